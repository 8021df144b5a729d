"""Third-party gymnasium environments through the factory and `thci train`."""

import json

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from test_cli import FAST, run_cli

from thci.envs.factory import make_vector_env
from thci.errors import ThciError


class _MissionOnly(gym.Env):
    """A Dict observation with nothing thci can learn from."""

    observation_space = spaces.Dict({"mission": spaces.Text(10)})
    action_space = spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return {"mission": "go"}, {}

    def step(self, action):
        return {"mission": "go"}, 0.0, True, False, {}


gym.register("ThciTest/MissionOnly-v0", entry_point=_MissionOnly)


def test_minigrid_dict_observations_keep_image_and_direction_and_drop_the_mission(capsys):
    envs = make_vector_env("minigrid:MiniGrid-Empty-5x5-v0", 2)
    try:
        assert envs.single_observation_space.shape == (7 * 7 * 3 + 4,)  # image + one-hot heading
        obs, _ = envs.reset(seed=0)
        assert obs.shape == (2, 151) and np.isfinite(obs).all()
    finally:
        envs.close()
    assert "['mission'] are ignored" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("env_id", "extra"),
    [
        ("minigrid:MiniGrid-Empty-5x5-v0", ["--method", "t-hci", "--ci-every", "256"]),
        (
            "minigrid:MiniGrid-Empty-5x5-v0",
            [
                *("--method", "t-hci", "--ci-every", "256"),
                *("--discretizer", "cell-set", "--cell-layout", "4", "49", "3"),
            ],
        ),
        ("CartPole-v1", ["--method", "gru", "--algo", "a2c"]),
    ],
)
def test_unmodified_third_party_envs_train_through_the_cli(tmp_path, env_id, extra):
    ci = ["--ci-min-episodes", "4", "--ci-min-rewarded-episodes", "1", "--ci-base-steps", "20"]
    ci += ["--ci-warm-steps", "10"]
    run = ["--env", env_id, "--run-dir", str(tmp_path / "run"), "--total-steps", "768"]
    code = run_cli(["train", *run, *FAST, "--num-envs", "4", "--num-minibatches", "4", *ci, *extra])
    assert code == 0
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["total_env_steps"] >= 768 and summary["episodes"] > 0
    assert np.isfinite(summary["mean_return_last100"])


def test_a_dict_space_without_usable_entries_is_refused_by_name():
    with pytest.raises(ThciError, match="no Box, Discrete, MultiDiscrete entry"):
        make_vector_env("ThciTest/MissionOnly-v0", 1)

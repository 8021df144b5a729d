"""Third-party gymnasium environments through the factory and `thci train`."""

import json

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from test_cli import FAST, run_cli

from thci.envs.factory import CELL_LAYOUT_KEY, make_vector_env
from thci.errors import ThciError
from thci.rl.encoders import observation_categories


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


def _minigrid(wrapper: str, **kwargs):
    """MiniGrid-Empty-5x5-v0 under one of minigrid's wrappers, or a bad image."""
    import minigrid.wrappers

    env = gym.make("MiniGrid-Empty-5x5-v0")
    if wrapper == "painted":  # declared like minigrid's image, holding values no cell has
        return gym.wrappers.TransformObservation(
            env,
            lambda obs: {**obs, "image": np.full_like(obs["image"], 200)},
            env.observation_space,
        )
    return getattr(minigrid.wrappers, wrapper)(env, **kwargs)


for _name in ("FullyObsWrapper", "RGBImgPartialObsWrapper", "painted"):
    gym.register(f"ThciTest/MiniGrid-{_name}-v0", entry_point=_minigrid, kwargs={"wrapper": _name})


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
    ("env_id", "layout", "cell_highs"),
    [
        ("minigrid:MiniGrid-Empty-5x5-v0", (4, 49, 3), [10, 5, 3]),  # heading first, 7x7 view
        ("ThciTest/MiniGrid-FullyObsWrapper-v0", (4, 25, 3), [10, 5, 3]),  # the whole 5x5 grid
        ("ThciTest/MiniGrid-RGBImgPartialObsWrapper-v0", None, [255, 255, 255]),  # pixels
    ],
)
def test_minigrid_cell_images_get_their_cells_bounds_and_layout(env_id, layout, cell_highs):
    envs = make_vector_env(env_id, 2)
    try:
        space = envs.single_observation_space
        assert envs.metadata.get(CELL_LAYOUT_KEY) == layout
        offset = 4 if layout is None else layout[0]
        assert space.high[offset : offset + 3].tolist() == cell_highs
        # Bounded cells are categories (one-hot, --encoder cells); pixels stay magnitudes.
        assert (observation_categories(space) is not None) == (layout is not None)
        obs, _ = envs.reset(seed=0)
        for _ in range(30):  # the agent's own cell (full view) holds its heading 0..3 as state
            obs, *_ = envs.step(envs.action_space.sample())
            assert np.all(obs <= space.high)
    finally:
        envs.close()


def test_a_minigrid_image_with_values_no_cell_has_is_refused():
    envs = make_vector_env("ThciTest/MiniGrid-painted-v0", 1)
    try:
        with pytest.raises(ThciError, match="not minigrid's cell encoding"):
            envs.reset(seed=0)
    finally:
        envs.close()


def test_cells_encoder_finds_a_minigrid_image_without_a_cell_layout(tmp_path):
    run = ["--env", "minigrid:MiniGrid-Empty-5x5-v0", "--run-dir", str(tmp_path / "run")]
    code = run_cli(["train", *run, *FAST, "--total-steps", "512", "--encoder", "cells"])
    assert code == 0
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["cell_layout"] == [4, 49, 3]


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

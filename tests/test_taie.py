"""TAIE over the expert's trajectories (the paper's τ ~ π*): the expert drives the episodes,
the scores have known answers, and environments without an expert are refused clearly."""

import json

import gymnasium as gym
import numpy as np
import pytest
import torch
from test_cli import assert_one_line_error, run_cli, train

from thci.causal.taie import measure_taie
from thci.config import TrainConfig
from thci.envs.factory import make_vector_env
from thci.errors import ThciError
from thci.rl.rollout import RolloutCollector
from thci.rl.trainer import build_agent

L1 = "thci/BabyAI-L1-v0"


def _agent(method: str, env_id: str = L1):
    torch.manual_seed(0)
    envs = make_vector_env(env_id, 1)
    agent = build_agent(TrainConfig(env=env_id, method=method), envs)
    envs.close()
    return agent


def test_expert_drives_the_collector_and_solves_every_episode():
    envs = make_vector_env(L1, 4)
    collector = RolloutCollector(envs, _agent("lstm"), num_steps=64, gamma=0.99, expert=True)
    collector.reset(seed=3)
    _, episodes = collector.collect()
    envs.close()
    # An untrained agent acting on its own almost never reaches the target ball in 64 steps.
    assert len(episodes) >= 8
    assert all(e.success for e in episodes)
    assert max(e.length for e in episodes) <= 21  # the expert's longest L1 episode (docs)


def _non_causal_fraction_of_expert_episodes(seed: int, episodes: int) -> float:
    """Mean over the first `episodes` expert episodes of one env of the share of steps whose
    observation is not labelled causal: the TAIE of a memory that keeps everything."""
    env = gym.make(L1)
    _, info = env.reset(seed=seed)
    fractions, labels = [], [info["causal"]]
    while len(fractions) < episodes:
        _, _, terminated, truncated, info = env.step(env.unwrapped.expert_action())
        if terminated or truncated:
            fractions.append(1.0 - float(np.mean(labels)))
            _, info = env.reset()
            labels = []
        labels.append(info["causal"])
    return float(np.mean(fractions))


def test_taie_over_expert_trajectories_has_known_answers():
    # measure_taie's first 4 complete episodes are the first 4 of environment 0 (seed 11).
    keeps_everything = measure_taie(_agent("lstm"), L1, episodes=4, seed=11, trajectories="expert")
    assert keeps_everything.trajectories == "expert"
    expected = _non_causal_fraction_of_expert_episodes(seed=11, episodes=4)
    assert 0.0 < expected < 1.0
    assert keeps_everything.value == pytest.approx(expected, abs=1e-6)
    oracle = measure_taie(_agent("oracle"), L1, episodes=4, seed=11)
    assert (oracle.value, oracle.trajectories) == (0.0, "expert")  # "auto" finds the expert


def test_expert_trajectories_need_an_expert():
    with pytest.raises(ThciError, match="expert_action"):
        measure_taie(_agent("oracle", "thci/PaperMaze-L1-v0"), "thci/PaperMaze-L1-v0",
                     episodes=4, trajectories="expert")  # fmt: skip


def test_taie_command_writes_taie_json_and_refuses_what_it_cannot_score(tmp_path, capsys):
    train(tmp_path, "oracle", "--env", L1, "--method", "oracle", "--total-steps", "512")
    assert run_cli(["taie", str(tmp_path / "oracle"), "--episodes", "8"]) == 0
    written = json.loads((tmp_path / "oracle" / "taie.json").read_text())
    assert (written["taie"], written["trajectories"], written["episodes"]) == (0.0, "expert", 8)

    train(tmp_path, "maze", "--method", "oracle", "--total-steps", "512")
    code = run_cli(["taie", str(tmp_path / "maze"), "--trajectories", "expert"])
    assert_one_line_error(capsys, code, "no expert", "expert_action")
    train(tmp_path, "lstm", "--method", "lstm", "--total-steps", "512")
    code = run_cli(["taie", str(tmp_path / "lstm")])
    assert_one_line_error(capsys, code, "--method lstm", "TAIE does not apply")

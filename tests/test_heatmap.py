"""`thci heatmap`: the episode it draws (greedy, or the expert's), per-head panels, bad input."""

import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from thci.cli import main
from thci.config import TrainConfig
from thci.envs import load_maze_level
from thci.experiments import heatmap as heatmap_module
from thci.experiments.heatmap import heatmap, play_trajectory
from thci.rl.trainer import train


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A tiny T-HCI run on Maze level 1 (its gate is not fitted yet: it keeps everything)."""
    path = tmp_path_factory.mktemp("heatmap") / "run"
    config = TrainConfig(
        method="t-hci", total_steps=256, num_envs=4, num_steps=32, num_minibatches=4,
        run_dir=path, progress=False,
    )  # fmt: skip
    train(config)
    return path


def png_width(path: Path) -> int:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">I", data[16:20])[0]


def test_trajectory_is_a_walk_through_the_maze_from_its_start(run_dir):
    config, trajectory = play_trajectory(run_dir)
    assert config.method == "t-hci" and trajectory.played_by == "greedy"  # the maze: no expert
    maze = load_maze_level(1)
    steps = len(trajectory.positions)
    assert 1 <= steps <= 30  # Maze episodes end after at most 30 steps
    np.testing.assert_array_equal(trajectory.positions[0], maze.start)
    moves = np.abs(np.diff(trajectory.positions, axis=0)).sum(axis=1)
    assert set(moves.tolist()) <= {0, 1}  # one cell at a time (0: bumped into a wall)
    assert trajectory.weights.shape == (steps, 1)
    assert np.all(trajectory.weights == 0.0)  # an unfitted gate: the memory starts empty
    assert trajectory.frame.shape[0] == pytest.approx(maze.shape[0] * trajectory.cell_pixels)


def test_one_panel_per_attention_head(run_dir, tmp_path, monkeypatch):
    single = heatmap(run_dir, tmp_path / "single.png")

    def four_heads(agent, obs):
        return torch.rand(obs.shape[0], obs.shape[1], 4)

    monkeypatch.setattr(heatmap_module, "observation_weights", four_heads)
    _, trajectory = play_trajectory(run_dir)
    assert trajectory.weights.shape[1] == 4
    heads = heatmap(run_dir, tmp_path / "heads.png")
    assert png_width(heads) > 2 * png_width(single)  # four panels side by side, not one


def test_heatmap_of_a_non_run_is_a_one_line_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["heatmap", str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1 and "config.json" in err


def test_babyai_heatmap_follows_the_expert_and_weighs_its_signpost_views(tmp_path):
    path = tmp_path / "oracle"
    config = TrainConfig(
        env="thci/BabyAI-L1-v0", method="oracle", total_steps=256, num_envs=4, num_steps=32,
        num_minibatches=4, run_dir=path, progress=False,
    )  # fmt: skip
    train(config)
    _, expert = play_trajectory(path, seed=5)
    assert expert.played_by == "expert"
    assert expert.reward > 0  # the expert reaches the target ball; the untrained agent would not
    # The oracle weighs by the labels: the expert looks at the signpost, then walks away from it.
    assert 0 < expert.weights.sum() < len(expert.weights)
    _, greedy = play_trajectory(path, seed=5, trajectories="greedy")
    assert greedy.played_by == "greedy"
    assert heatmap(path, tmp_path / "expert.png", seed=5).is_file()

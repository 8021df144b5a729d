"""`thci heatmap RUN_DIR`: the paper's Fig. 8, what a trained agent's memory weighs.

Along one episode, every visited grid cell is coloured by the
weight ν(o_t) the agent's memory put on the observation made there
(:func:`thci.causal.taie.observation_weights`, the same weights TAIE scores): the gate's keep
decision for T-HCI, HCI and Oracle, the attention weights for SAI (one panel per head) and HAI,
1 everywhere for memories that keep everything. The colours lie over a grey rendering of
the episode's first frame. A cell visited more than once shows its largest weight. The episode
is the environment's expert's when it has one (``expert_action()``: the π* whose trajectories
TAIE averages over, e.g. on the BabyAI levels), else the trained agent's greedy one.

Works for the built-in grid environments (Maze and BabyAI levels), which report
``info["agent_pos"]`` and render ``rgb_array`` frames.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import matplotlib
import numpy as np
import torch

import thci  # noqa: F401  (registers the environments for gym.make)
from thci.causal.taie import observation_weights
from thci.config import TrainConfig, Trajectories
from thci.errors import ThciError
from thci.experiments.report import env_label
from thci.experiments.run_dir import atomic_write_bytes
from thci.rl.evaluate import load_run
from thci.rl.rollout import RolloutCollector, plays_expert

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.patches import Rectangle

ROLLOUT_STEPS = 64  # steps collected at a time until the episode ends


@dataclass
class Trajectory:
    """One episode: where each observation was made and the memory's weight on it."""

    positions: np.ndarray
    """(T, 2) [row, col] of the cell where o_t was observed."""
    weights: np.ndarray
    """(T, K) ν(o_t); K = 1, or one column per attention head."""
    frame: np.ndarray
    """(H, W, 3) rendering of the episode's first step."""
    cell_pixels: float
    """Width of one grid cell in `frame`."""
    reward: float
    played_by: str
    """Who chose the actions: "expert" or "greedy" (the trained agent)."""


def play_trajectory(
    run_dir: Path, seed: int = 10_000, trajectories: Trajectories = "auto"
) -> tuple[TrainConfig, Trajectory]:
    """Play one episode and weigh its observations with the run's latest checkpoint.

    `trajectories`: "expert" (the environment's ``expert_action()``), "greedy" (the run's
    agent) or "auto" (expert when the environment has one). The episode is played by the same
    collector as training (so memories that read side inputs get them), then its actions are
    replayed in a rendering copy of the environment, seeded alike, to get the picture and the
    positions; the two must agree step by step.
    """
    config, envs, agent, _ = load_run(run_dir, 1, seed)
    try:
        _, start_info = envs.reset(seed=seed)
        if "agent_pos" not in start_info:
            raise ThciError(
                f"{config.env} reports no info['agent_pos']: a heatmap needs a grid environment "
                "such as the built-in Maze and BabyAI levels"
            )
        expert = plays_expert(envs, trajectories)
        collector = RolloutCollector(
            envs,
            agent,
            ROLLOUT_STEPS,
            config.gamma,
            greedy=True,
            info_keys=("agent_pos",),
            expert=expert,
        )
        collector.reset(seed)
        rollouts = []
        while not any(bool(r.dones.any()) for r in rollouts):
            rollouts.append(collector.collect()[0])
    finally:
        envs.close()
    inputs = torch.cat([r.inputs for r in rollouts])
    dones = torch.cat([r.dones for r in rollouts])[:, 0]
    length = int(dones.nonzero()[0]) + 1
    weights = observation_weights(agent, inputs[:length])  # one episode from t = 0
    weights = weights.reshape(length, -1).numpy()
    actions = torch.cat([r.actions for r in rollouts])[:length, 0].tolist()
    reached = np.concatenate([r.reached_info["agent_pos"] for r in rollouts])[:length, 0]
    reward = float(torch.cat([r.env_rewards for r in rollouts])[:length, 0].sum())
    positions, frame, cell = _replay(config.env, seed, actions, reached)
    played_by = "expert" if expert else "greedy"
    return config, Trajectory(positions, weights, frame, cell, reward, played_by)


def _replay(
    env_id: str, seed: int, actions: list[int], reached: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """Positions of the observations, first frame and cell width, from a rendering env."""
    env = gym.make(env_id, render_mode="rgb_array")
    try:
        _, info = env.reset(seed=seed)
        frame = np.asarray(env.render())
        positions = [np.asarray(info["agent_pos"])]
        for action in actions:
            _, _, _, _, info = env.step(action)
            positions.append(np.asarray(info["agent_pos"]))
        rows = _grid_rows(env)
    finally:
        env.close()
    if not np.array_equal(np.array(positions[1:]), reached):
        raise ThciError(
            f"{env_id} did not repeat the episode when replayed with the same seed; "
            "a heatmap needs an environment that is deterministic given its seed"
        )
    return np.array(positions[:-1]), frame, frame.shape[0] / rows


def _grid_rows(env: gym.Env) -> int:
    """Rows of the rendered grid: PaperMaze's maze shape, or minigrid's height."""
    unwrapped = env.unwrapped
    if hasattr(unwrapped, "maze"):
        return unwrapped.maze.shape[0]
    if hasattr(unwrapped, "height"):
        return int(unwrapped.height)
    raise ThciError(f"cannot tell the grid size of {env.spec.id if env.spec else env}")


def draw_heatmap(config: TrainConfig, trajectory: Trajectory, path: Path) -> None:
    """Fig. 8: one panel per weight column, the visited cells coloured by ν(o_t)."""
    heads = trajectory.weights.shape[1]
    figure, axes = plt.subplots(1, heads, figsize=(4.5 * heads, 4.5), squeeze=False)
    colours = plt.get_cmap("plasma")  # warmer (yellow) = larger weight, as in Fig. 8
    cell = trajectory.cell_pixels
    for head, ax in enumerate(axes[0]):
        ax.imshow(0.3 + 0.5 * trajectory.frame.mean(axis=2) / 255, cmap="gray", vmin=0, vmax=1)
        strongest: dict[tuple[int, int], float] = {}
        for (row, col), weight in zip(
            trajectory.positions, trajectory.weights[:, head], strict=True
        ):
            key = (int(row), int(col))
            strongest[key] = max(strongest.get(key, 0.0), float(weight))
        for (row, col), weight in strongest.items():
            ax.add_patch(
                Rectangle((col * cell, row * cell), cell, cell, color=colours(weight), alpha=0.75)
            )
        centres = (trajectory.positions[:, ::-1] + 0.5) * cell
        ax.plot(centres[:, 0], centres[:, 1], color="white", linewidth=1, alpha=0.8)
        ax.plot(*centres[0], "o", color="white", markersize=5)
        ax.set_axis_off()
        if heads > 1:
            ax.set_title(f"head {head + 1}")
    figure.colorbar(
        plt.cm.ScalarMappable(norm=plt.Normalize(0, 1), cmap=colours),
        ax=axes[0].tolist(),
        label="ν(o_t): weight on the observation",
        shrink=0.8,
    )
    figure.suptitle(
        f"{config.method} on {env_label(config.env)}: an {trajectory.played_by} episode of "
        f"{len(trajectory.positions)} steps, return {trajectory.reward:.2f}"
    )
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=120, bbox_inches="tight")
    plt.close(figure)
    atomic_write_bytes(path, buffer.getvalue())


def heatmap(
    run_dir: Path, out: Path | None = None, seed: int = 10_000, trajectories: Trajectories = "auto"
) -> Path:
    """Write the Fig. 8 heatmap of the run (default RUN_DIR/heatmap.png); returns its path."""
    config, trajectory = play_trajectory(run_dir, seed, trajectories)
    path = out or run_dir / "heatmap.png"
    draw_heatmap(config, trajectory, path)
    return path

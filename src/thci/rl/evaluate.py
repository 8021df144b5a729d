"""Evaluate a trained run: play N episodes with its latest checkpoint and report the results."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium.vector import VectorEnv

from thci.causal.taie import measure_taie
from thci.config import WEIGHING_METHODS, TrainConfig, Trajectories
from thci.envs.factory import make_vector_env
from thci.errors import ThciError
from thci.experiments.run_dir import RunDirectory, atomic_write_json
from thci.rl.agent import ActorCritic
from thci.rl.rollout import Episode, RolloutCollector
from thci.rl.trainer import build_agent, checkpoint_mismatch


def load_run(
    run_dir: Path, num_envs: int, seed: int
) -> tuple[TrainConfig, VectorEnv, ActorCritic, dict[str, Any]]:
    """A run's config, `num_envs` fresh environments, its trained agent and its checkpoint.

    Seeds torch with `seed` and uses the run's torch threads; every problem with the directory
    or the checkpoint is a one-line ThciError. The caller closes the environments.
    """
    run = RunDirectory(run_dir)
    if not run.config_path.is_file():
        raise ThciError(f"{run_dir} is not a thci run: config.json is missing")
    config = run.read_config()
    checkpoint = run.load_checkpoint()
    torch.set_num_threads(config.torch_threads)
    torch.manual_seed(seed)
    envs = make_vector_env(config.env, num_envs, config.vectorization)
    try:
        agent = build_agent(config, envs)
    except BaseException:
        envs.close()
        raise
    try:
        agent.load_state_dict(checkpoint["agent"])
    except (KeyError, RuntimeError) as exc:
        envs.close()
        raise ThciError(
            f"checkpoint does not match the run's config "
            f"({checkpoint_mismatch(checkpoint, agent, exc)})"
        ) from None
    return config, envs, agent, checkpoint


def evaluate(
    run_dir: Path, episodes: int, greedy: bool = False, seed: int = 10_000, num_envs: int = 16
) -> dict[str, Any]:
    """Play `episodes` episodes with the run's agent; write and return evaluation.json's content.

    Each of the parallel environments plays a fixed share of the episodes, so short episodes
    are not over-represented (the same scheme as SB3's ``evaluate_policy``).
    """
    if episodes <= 0:
        raise ThciError(f"--episodes must be a positive integer, got {episodes}")
    if not run_dir.is_dir():
        raise ThciError(f"run directory {run_dir} not found")
    num_envs = min(num_envs, episodes)
    config, envs, agent, checkpoint = load_run(run_dir, num_envs, seed)
    try:
        collector = RolloutCollector(
            envs,
            agent,
            num_steps=64,
            gamma=config.gamma,
            success_return=config.success_return,
            greedy=greedy,
            # the behaviour the agent trained with: DMC acts epsilon-greedily on its Q-values
            epsilon=config.dmc_epsilon if config.algo == "dmc" else None,
        )
        collector.reset(seed)
        quota = np.full(num_envs, episodes // num_envs) + (
            np.arange(num_envs) < episodes % num_envs
        )
        finished: list[Episode] = []
        counts = np.zeros(num_envs, dtype=np.int64)
        while (counts < quota).any():
            _, new = collector.collect()
            for episode in new:
                if counts[episode.env] < quota[episode.env]:
                    counts[episode.env] += 1
                    finished.append(episode)
    finally:
        envs.close()
    known = [e.success for e in finished if e.success is not None]
    result = {
        "env_id": config.env,
        "method": config.method,
        "algo": config.algo,
        "episodes": len(finished),
        "greedy": greedy,
        "success_rate": float(np.mean(known)) if known else None,
        "mean_return": float(np.mean([e.reward for e in finished])),
        "mean_length": float(np.mean([e.length for e in finished])),
        "checkpoint_update": checkpoint["update"],
    }
    atomic_write_json(run_dir / "evaluation.json", result)
    return result


def taie_of_run(
    run_dir: Path, episodes: int = 100, trajectories: Trajectories = "auto", seed: int = 20_000
) -> dict[str, Any]:
    """TAIE of a trained run's memory (:mod:`thci.causal.taie`); writes and returns taie.json's
    content. `trajectories`: "expert" (π*, as the paper defines TAIE; needs an environment with
    ``expert_action()``), "greedy" (the run's own policy) or "auto" (expert when available)."""
    if not run_dir.is_dir():
        raise ThciError(f"run directory {run_dir} not found")
    config, envs, agent, checkpoint = load_run(run_dir, 1, seed)
    envs.close()
    if config.method not in WEIGHING_METHODS:
        raise ThciError(f"--method {config.method} keeps every observation: TAIE does not apply")
    taie = measure_taie(agent, config.env, episodes, seed, config.vectorization, trajectories)
    if taie.value is None:
        raise ThciError(f"{config.env} gives no info['causal'] labels: TAIE needs them")
    result = {
        "env_id": config.env,
        "method": config.method,
        "taie": taie.rounded(),
        "trajectories": taie.trajectories,
        "episodes": taie.episodes,
        "checkpoint_update": checkpoint["update"],
    }
    atomic_write_json(run_dir / "taie.json", result)
    return result

"""Timely Averaged Inference Error (TAIE, the paper's Table 2).

TAIE = E_τ [ Σ_t |ν(o_t) − ν*(o_t)| / T_τ ] over trajectories τ of the trained policy, where
ν(o_t) is the method's weight on observation o_t (for the causal memory: 1 if the gate keeps it,
0 if it removes it) and ν*(o_t) is the human label (``info["causal"]``). A perfect gate scores
0, an inverted one 1.
"""

from __future__ import annotations

import numpy as np
import torch

from thci.envs.factory import make_vector_env
from thci.rl.agent import ActorCritic
from thci.rl.rollout import RolloutCollector
from thci.rl.sequences import cut_into_segments


def taie_of_rollout(
    weights: torch.Tensor,
    labels: torch.Tensor,
    episode_starts: torch.Tensor,
    dones: torch.Tensor,
) -> torch.Tensor:
    """Per-episode inference errors of the complete episodes in a (T, N) rollout.

    Args:
        weights: (T, N) ν(o_t) in [0, 1]. labels: (T, N) ν*(o_t) in {0, 1}.
        episode_starts, dones: (T, N) bool episode boundaries.

    Returns:
        (E,) Σ_t |ν − ν*| / T_τ for each episode that starts and ends inside the rollout.
    """
    segments = cut_into_segments(episode_starts)
    error = (weights.float() - labels.float()).abs()
    per_step = segments.gather(error) * segments.valid
    lengths = segments.lengths
    last = segments.gather(dones)[torch.arange(len(lengths)), lengths - 1]
    complete = ~segments.continues & last
    return (per_step.sum(dim=1) / lengths)[complete]


@torch.no_grad()
def observation_weights(agent: ActorCritic, obs: torch.Tensor) -> torch.Tensor:
    """ν(o_t): the weight the agent's memory puts on each observation of a (T, N, D) rollout.

    For the causal memory: 1 where the gate keeps the observation, 0 where it removes it; for
    a memory that keeps everything (LSTM, GRU, or a gate not yet fitted): 1 everywhere.

    Returns:
        (T, N) float weights in [0, 1].
    """
    keep = None if agent.gate is None else agent.gate.keep(obs)
    return torch.ones(obs.shape[:2]) if keep is None else keep.float()


@torch.no_grad()
def measure_taie(
    agent: ActorCritic,
    env_id: str,
    episodes: int = 100,
    seed: int = 20_000,
    vectorization: str = "auto",
    greedy: bool = True,
) -> float | None:
    """TAIE of the agent's gate over `episodes` greedy trajectories; None without labels."""
    envs = make_vector_env(env_id, min(16, episodes), vectorization)
    try:
        collector = RolloutCollector(envs, agent, num_steps=128, gamma=0.99, greedy=greedy)
        collector.reset(seed)
        errors: list[torch.Tensor] = []
        while sum(len(e) for e in errors) < episodes:
            rollout, _ = collector.collect()
            if rollout.causal is None:
                return None
            weights = observation_weights(agent, rollout.obs)
            errors.append(
                taie_of_rollout(weights, rollout.causal, rollout.episode_starts, rollout.dones)
            )
        return float(np.mean(torch.cat(errors)[:episodes].numpy()))
    finally:
        envs.close()

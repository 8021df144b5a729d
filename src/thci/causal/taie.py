"""Timely Averaged Inference Error (TAIE, the paper's Table 2).

TAIE = E_τ [ Σ_t |ν(o_t) − ν*(o_t)| / T_τ ], where ν(o_t) is the method's weight on
observation o_t and ν*(o_t) is the human label (``info["causal"]``). A perfect gate scores 0,
an inverted one 1. The paper takes τ ~ π*, the optimal policy: thci does so for environments
that offer an expert (``expert_action()``, e.g. the BabyAI levels), and otherwise uses the
trained policy's greedy trajectories, which are π*'s once the policy solves the task. The
difference matters for a policy that does not solve it: its own trajectories may never reach
the observations that decide success. ν is, per method:

* causal memory (t-hci, hci): 1 if the gate keeps o_t, 0 if it removes it;
* oracle: the label itself (TAIE 0 by construction, a check of the plumbing);
* hai: the binary selection z_t of hard attention;
* sai: per head, the attention that the episode's last step pays to o_t (each head's weights
  sum to 1 over the episode's last ``history_window`` steps), so TAIE is reported per head;
* every other memory: 1 everywhere (it keeps everything).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from thci.causal.gate import Gate
from thci.config import Trajectories
from thci.envs.factory import make_vector_env
from thci.errors import ThciError
from thci.rl.agent import ActorCritic
from thci.rl.rollout import Rollout, RolloutCollector, plays_expert
from thci.rl.sequences import cut_into_segments


def taie_of_rollout(
    weights: torch.Tensor,
    labels: torch.Tensor,
    episode_starts: torch.Tensor,
    dones: torch.Tensor,
) -> torch.Tensor:
    """Per-episode inference errors of the complete episodes in a (T, N) rollout.

    Args:
        weights: (T, N) or (T, N, K) ν(o_t) in [0, 1] (K: one column per attention head).
        labels: (T, N) ν*(o_t) in {0, 1}.
        episode_starts, dones: (T, N) bool episode boundaries.

    Returns:
        (E,) or (E, K) Σ_t |ν − ν*| / T_τ for each episode that starts and ends inside the
        rollout.
    """
    segments = cut_into_segments(episode_starts)
    per_head = weights.dim() == 3
    weights = weights.float() if per_head else weights.float().unsqueeze(-1)
    error = (weights - labels.float().unsqueeze(-1)).abs()
    per_step = segments.gather(error) * segments.valid.unsqueeze(-1)
    lengths = segments.lengths
    last = segments.gather(dones)[torch.arange(len(lengths)), lengths - 1]
    complete = ~segments.continues & last
    errors = (per_step.sum(dim=1) / lengths.unsqueeze(-1))[complete]
    return errors if per_head else errors.squeeze(-1)


@torch.no_grad()
def observation_weights(
    agent: ActorCritic,
    obs: torch.Tensor,
    episode_starts: torch.Tensor | None = None,
    gate: Gate | None = None,
) -> torch.Tensor:
    """ν(o_t): the weight the agent's memory puts on each observation of a (T, N) rollout.

    Args:
        obs: (T, N, D) the agent's inputs, ``Rollout.inputs`` (the observations followed by
            the memory's side inputs; the same as ``Rollout.obs`` for memories without any).
        episode_starts: (T, N) bool, where episodes start; attention weights are computed per
            episode. Default: each column is one episode from t = 0.
        gate: weigh by this gate instead of the agent's own (e.g. a CI round's gate that the
            policy never used); only for gated memories.

    Returns:
        (T, N) float weights in [0, 1] (the module docstring says which, per method), or
        (T, N, K) for a memory with K attention heads (SAI).
    """
    steps, envs = obs.shape[:2]
    features, _ = agent.memory_input(obs)
    if episode_starts is None:
        episode_starts = torch.zeros(steps, envs, dtype=torch.bool)
    segments = cut_into_segments(episode_starts)
    weights = agent.memory.observation_weights(segments.gather(features), segments.valid)
    if weights is not None:  # back from (segments, L, K) to the rollout's (T, N, K)
        result = torch.zeros(steps * envs, weights.shape[-1])
        result[segments.index[segments.valid]] = weights[segments.valid]
        result = result.view(steps, envs, -1)
        return result.squeeze(-1) if result.shape[-1] == 1 else result
    gate = gate if gate is not None else agent.gate
    keep = None if gate is None else gate.keep(obs[..., : agent.observation_size])
    return torch.ones(steps, envs) if keep is None else keep.float()


@torch.no_grad()
def kept_observations(agent: ActorCritic, rollout: Rollout) -> np.ndarray:
    """(T, N) bool: the observations of the rollout that the causal memory keeps (the gate's
    decisions, or the oracle's labels); all False while the gate is inactive, so that before
    the first CI round nothing counts as remembered."""
    if agent.gate is not None and not bool(agent.gate.active):
        return np.zeros(rollout.rewards.shape, dtype=bool)
    return (observation_weights(agent, rollout.inputs, rollout.episode_starts) >= 0.5).numpy()


@dataclass(frozen=True)
class Taie:
    """A TAIE measurement: `value` (one per attention head for SAI; None when the environment
    gives no labels) over `episodes` trajectories of `trajectories` ("expert" or "greedy")."""

    value: float | list[float] | None
    trajectories: str
    episodes: int

    def rounded(self, digits: int = 4) -> float | list[float] | None:
        """`value` rounded for summaries and tables."""
        if isinstance(self.value, list):
            return [round(v, digits) for v in self.value]
        return None if self.value is None else round(self.value, digits)


@torch.no_grad()
def measure_taie(
    agent: ActorCritic,
    env_id: str,
    episodes: int = 100,
    seed: int = 20_000,
    vectorization: str = "auto",
    trajectories: Trajectories = "auto",
    gate: Gate | None = None,
) -> Taie:
    """TAIE of the agent over `episodes` trajectories: the environment's expert's ("expert";
    "auto" picks it when the environment has one) or the agent's own greedy ones ("greedy").
    With `gate`, the agent's memory still runs as trained, and ν is that gate's."""
    if episodes <= 0:
        raise ThciError(f"TAIE needs a positive number of episodes, got {episodes}")
    if trajectories not in ("auto", "expert", "greedy"):
        raise ThciError(f"trajectories must be auto, expert or greedy, got {trajectories!r}")
    # The expert is read from each sub-environment: a native vector env has none.
    envs = make_vector_env(
        env_id, min(16, episodes), "sync" if trajectories == "expert" else vectorization
    )
    try:
        expert = plays_expert(envs, trajectories)
        # Only episodes that start and end inside one rollout count: 512 steps hold at least one
        # of every built-in level (BabyAI-L4 episodes last up to 250 steps), so this terminates.
        collector = RolloutCollector(
            envs, agent, num_steps=512, gamma=0.99, greedy=True, expert=expert
        )
        collector.reset(seed)
        errors: list[torch.Tensor] = []
        while sum(len(e) for e in errors) < episodes:
            rollout, _ = collector.collect()
            if rollout.causal is None:
                return Taie(None, "expert" if expert else "greedy", 0)
            weights = observation_weights(agent, rollout.inputs, rollout.episode_starts, gate)
            errors.append(
                taie_of_rollout(weights, rollout.causal, rollout.episode_starts, rollout.dones)
            )
        taie = torch.cat(errors)[:episodes].mean(dim=0)
        value = float(taie) if taie.dim() == 0 else taie.tolist()
        return Taie(value, "expert" if expert else "greedy", episodes)
    finally:
        envs.close()

"""Count-based exploration on discretized observations (#Exploration, Tang et al. 2017).

Every observation the agent reaches is mapped to a code by the same discretizers T-HCI uses
(exact codes for symbolic observations, SimHash for continuous ones), and the step that reached
it earns an intrinsic reward beta / sqrt(N(code)), N counting every visit so far. When the
observation is a poor proxy of the state (the maze's corridor codes repeat over many cells),
``count_key`` counts an info entry the environment reports instead (e.g. ``"agent_pos"``,
which every built-in environment provides); exploration then uses state information the agent's
policy never sees. Rarely seen
observations (the far goals of Maze levels 3-4) pay most, and the bonus fades as they become
familiar, leaving the task's own reward. It is an option for every method (``--exploration
count``), so baselines can be compared under the same exploration.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch

from thci.causal.discretize import Discretizer, discretizer_from_state, make_discretizer
from thci.rl.rollout import Rollout


class CountBonus:
    """Intrinsic reward beta / sqrt(N(code of the observation reached)).

    Args:
        observation_space: the flat single-env observation space.
        beta: scale of the bonus.
        kind: discretizer kind ("auto", "exact", "simhash").
        count_key: count this info entry of the reached observation instead (None: the
            observation itself).
    """

    def __init__(
        self,
        observation_space: gym.Space,
        beta: float,
        kind: str = "auto",
        count_key: str | None = None,
    ) -> None:
        self.observation_space, self.beta, self.kind = observation_space, beta, kind
        self.count_key = count_key
        self.discretizer: Discretizer | None = None
        self.counts = np.zeros(0, dtype=np.int64)

    def add_bonus(self, rollout: Rollout, next_obs: torch.Tensor) -> float:
        """Add the bonus to ``rollout.rewards`` in place; returns its mean per step.

        Args:
            rollout: a collected rollout (T, N).
            next_obs: (N, D) the observations after the rollout's last step.
        """
        if self.count_key is None:
            reached = torch.cat((rollout.obs[1:], next_obs.unsqueeze(0)))  # (T, N, D)
            reached = torch.where(rollout.dones.unsqueeze(-1), rollout.final_obs, reached)
            flat = reached.reshape(-1, reached.shape[-1]).numpy()
            space = self.observation_space
        else:
            info = rollout.reached_info[self.count_key]
            flat = info.reshape(info.shape[0] * info.shape[1], -1)
            space = gym.spaces.Box(-np.inf, np.inf, flat.shape[1:])
        if self.discretizer is None:
            self.discretizer = make_discretizer(self.kind, space, sample=flat)
        codes = self.discretizer.encode(flat)
        if self.discretizer.num_codes > len(self.counts):
            self.counts = np.pad(self.counts, (0, self.discretizer.num_codes - len(self.counts)))
        self.counts += np.bincount(codes, minlength=len(self.counts))
        bonus = self.beta / np.sqrt(self.counts[codes])
        rollout.rewards += torch.as_tensor(bonus, dtype=torch.float32).view_as(rollout.rewards)
        return float(bonus.mean())

    def state_dict(self) -> dict[str, Any]:
        return {
            "discretizer": None if self.discretizer is None else self.discretizer.state_dict(),
            "counts": torch.as_tensor(self.counts),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state["discretizer"] is not None:
            self.discretizer = discretizer_from_state(state["discretizer"])
        self.counts = state["counts"].numpy().copy()

"""Reassemble whole episodes from fixed-length rollouts.

Rollouts are (T, N) slices of N environments' step streams; an episode may begin in one
rollout and end several rollouts later. Both the replay pool of the CI loop (Fig. 3) and Deep
Monte Carlo (which regresses on the returns of *whole* episodes) need the episodes whole, so
this keeps each environment's unfinished part until its episode ends.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch


class EpisodeAssembler:
    """Cut (T, N) rollout arrays into finished episodes, carrying unfinished ones over.

    Args:
        num_envs: N.
    """

    def __init__(self, num_envs: int) -> None:
        self.pending: list[dict[str, np.ndarray] | None] = [None] * num_envs

    def add(
        self, steps: dict[str, np.ndarray], dones: np.ndarray
    ) -> list[tuple[int, int, dict[str, np.ndarray]]]:
        """Feed one rollout; return the episodes that ended in it, in order of environment.

        Args:
            steps: arrays (T, N, ...) of the same T and N (observations, actions, ...).
            dones: (T, N) bool, the episode ended with step t.

        Returns:
            (env n, step t of the episode's end in this rollout, {name: (length, ...)}) for
            each finished episode; a loop over environments and episodes, never over steps.
        """
        num_steps = dones.shape[0]
        finished = []
        for n in range(dones.shape[1]):
            begin = 0
            for end in np.flatnonzero(dones[:, n]):
                piece = self._take(n, {k: v[begin : end + 1, n] for k, v in steps.items()})
                finished.append((n, int(end), piece))
                begin = end + 1
            if begin < num_steps:
                self.pending[n] = self._take(n, {k: v[begin:, n] for k, v in steps.items()})
        return finished

    def _take(self, env: int, piece: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """`piece` prefixed by the unfinished part of env's episode from earlier rollouts."""
        before, self.pending[env] = self.pending[env], None
        if before is None:
            return piece
        return {k: np.concatenate([before[k], v]) for k, v in piece.items()}

    def state_dict(self) -> list[dict[str, torch.Tensor] | None]:
        return [
            None if p is None else {k: torch.as_tensor(v) for k, v in p.items()}
            for p in self.pending
        ]

    def load_state_dict(self, state: list[dict[str, Any] | None]) -> None:
        self.pending = [None if p is None else {k: v.numpy() for k, v in p.items()} for p in state]

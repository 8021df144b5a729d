"""The replay pool of whole episodes that counterfactual inference runs on (Fig. 3).

The RL loop appends every finished episode; the CI loop reads the pool as padded arrays. Each
episode keeps the discrete *code* of every observation (see :mod:`thci.causal.discretize`),
so interventions can name observation sub-spaces as sets of codes, and one representative
observation per code, so the gate can be trained on the observations themselves.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PoolEpisode:
    """One finished episode of L steps.

    Attributes:
        codes: (L + 1,) int64, codes of o_1 ... o_{L+1} (o_{L+1}: the observation after the last
            action, i.e. the final observation).
        actions: (L,) int64, a_1 ... a_L.
        rewards: (L,) float32, r_2 ... r_{L+1} (reward of each action).
        causal: (L + 1,) bool ground-truth labels of the observations, or None if unknown.
    """

    codes: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    causal: np.ndarray | None = None

    @property
    def length(self) -> int:
        return len(self.actions)


@dataclass(frozen=True)
class PoolArrays:
    """The pool as padded arrays (E episodes, padded to L steps).

    Attributes:
        codes: (E, L + 1) int64; padding -1.
        actions: (E, L) int64; padding 0.
        rewards: (E, L) float32; padding 0.
        lengths: (E,) int64, steps per episode.
        first_episode: the run's number of episode 0 (episode i is the run's episode
            first_episode + i), so that what is dealt per episode (the predictor's
            cross-fitting folds) stays with it as the pool slides.
    """

    codes: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    lengths: np.ndarray
    first_episode: int = 0

    @property
    def valid(self) -> np.ndarray:
        """(E, L) bool, True on real steps."""
        return np.arange(self.actions.shape[1])[None, :] < self.lengths[:, None]


def pad_episodes(episodes: list[PoolEpisode], first_episode: int = 0) -> PoolArrays:
    """Stack episodes (the run's episodes first_episode, first_episode + 1, …) into padded
    arrays."""
    lengths = np.array([e.length for e in episodes], dtype=np.int64)
    num, max_len = len(episodes), int(lengths.max()) if len(episodes) else 0
    codes = np.full((num, max_len + 1), -1, dtype=np.int64)
    actions = np.zeros((num, max_len), dtype=np.int64)
    rewards = np.zeros((num, max_len), dtype=np.float32)
    for i, e in enumerate(episodes):
        codes[i, : e.length + 1] = e.codes
        actions[i, : e.length] = e.actions
        rewards[i, : e.length] = e.rewards
    return PoolArrays(codes, actions, rewards, lengths, first_episode)


class ReplayPool:
    """Bounded FIFO pool of whole episodes plus a representative observation per code.

    Args:
        capacity: maximum number of episodes kept (the oldest are dropped first).
    """

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.episodes: deque[PoolEpisode] = deque(maxlen=capacity)
        self.observations: dict[int, np.ndarray] = {}
        self.num_rewarded = 0
        """Episodes in the pool with a non-zero reward somewhere."""
        self.num_added = 0
        """Episodes ever added (the pool holds the last len(self) of them)."""

    def __len__(self) -> int:
        return len(self.episodes)

    def add(self, episode: PoolEpisode, observations: np.ndarray | None = None) -> None:
        """Append an episode; `observations` (L + 1, D) supplies representatives of new codes."""
        if len(self.episodes) == self.capacity:  # the oldest episode is about to drop out
            self.num_rewarded -= bool(np.any(self.episodes[0].rewards != 0))
        self.num_rewarded += bool(np.any(episode.rewards != 0))
        self.episodes.append(episode)
        self.num_added += 1
        if observations is not None:
            # Only the episode's distinct codes are looked up, not every step.
            codes, first = np.unique(episode.codes, return_index=True)
            for code, index in zip(codes.tolist(), first.tolist(), strict=True):
                self.observations.setdefault(code, observations[index])

    def observed_codes(self) -> np.ndarray:
        """The observed space Ô: sorted distinct codes in the pool, (|Ô|,) int64."""
        if not self.episodes:
            return np.zeros(0, dtype=np.int64)
        return np.unique(np.concatenate([e.codes for e in self.episodes]))

    def arrays(self) -> PoolArrays:
        """The pool's episodes as padded arrays."""
        return pad_episodes(list(self.episodes), self.num_added - len(self.episodes))

"""Episode statistics and the paper's 'solved' criterion.

A run is *solved* when the success rate over the last `window` finished training episodes
first reaches `threshold` (0.9 over 100 episodes by default); `steps_to_solve` is the number
of environment steps taken by then, counted to the step on which the deciding episode ended.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from thci.rl.rollout import Episode


class SolveTracker:
    """Sliding window over finished episodes; remembers when the run was first solved."""

    def __init__(self, window: int, threshold: float) -> None:
        self.window, self.threshold = window, threshold
        self.successes: deque[bool] = deque(maxlen=window)
        self.rewards: deque[float] = deque(maxlen=window)
        self.lengths: deque[int] = deque(maxlen=window)
        self.episodes = 0
        self.success_known = False
        self.steps_to_solve: int | None = None

    def add(self, episodes: list[Episode], steps_before: int, num_envs: int) -> None:
        """Record the episodes of a rollout that began after `steps_before` env steps."""
        for episode in episodes:
            self.episodes += 1
            self.rewards.append(episode.reward)
            self.lengths.append(episode.length)
            if episode.success is None:
                continue
            self.success_known = True
            self.successes.append(episode.success)
            if (
                self.steps_to_solve is None
                and len(self.successes) == self.window
                and self.success_rate >= self.threshold
            ):
                self.steps_to_solve = steps_before + (episode.step + 1) * num_envs

    @property
    def solved(self) -> bool:
        return self.steps_to_solve is not None

    @property
    def success_rate(self) -> float:
        """Success rate over the window (NaN until an episode with known success ends)."""
        return float(np.mean(self.successes)) if self.successes else float("nan")

    @property
    def mean_reward(self) -> float:
        return float(np.mean(self.rewards)) if self.rewards else float("nan")

    @property
    def mean_length(self) -> float:
        return float(np.mean(self.lengths)) if self.lengths else float("nan")

    def state_dict(self) -> dict[str, Any]:
        return {
            "successes": [bool(s) for s in self.successes],
            "rewards": list(self.rewards),
            "lengths": list(self.lengths),
            "episodes": self.episodes,
            "success_known": self.success_known,
            "steps_to_solve": self.steps_to_solve,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.successes.extend(state["successes"])
        self.rewards.extend(state["rewards"])
        self.lengths.extend(state["lengths"])
        self.episodes = state["episodes"]
        self.success_known = state["success_known"]
        self.steps_to_solve = state["steps_to_solve"]

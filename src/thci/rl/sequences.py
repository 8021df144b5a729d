"""Cut rollouts at episode boundaries into whole, padded sequences for one RNN call each.

A rollout is time-major, (T, N): N environment columns of T steps, with episodes starting
anywhere inside a column. Recurrent training must reset the memory at every episode start,
which a single ``nn.LSTM`` call cannot do mid-sequence. So each column is cut at its episode
starts into *segments*; segments are padded to a common length L and run as one batch. A
segment that begins at t = 0 without an episode start continues the episode of the previous
rollout and starts from the memory state stored with the rollout; every other segment starts
from the zero state. All of it is vectorized: no Python loop over steps or environments.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Segments:
    """Episode segments of a (T, N) rollout.

    Attributes:
        index: (S, L) long, position of each segment step in the time-major flattened
            rollout (t * N + n); padding positions hold 0.
        valid: (S, L) bool, False on padding.
        column: (S,) long, environment column n of each segment.
        continues: (S,) bool, True when the segment continues an episode from the
            previous rollout (its initial memory state is the rollout's stored state).
    """

    index: torch.Tensor
    valid: torch.Tensor
    column: torch.Tensor
    continues: torch.Tensor

    @property
    def lengths(self) -> torch.Tensor:
        """(S,) number of real steps in each segment."""
        return self.valid.sum(dim=1)

    def gather(self, x: torch.Tensor) -> torch.Tensor:
        """Rearrange a time-major (T, N, ...) tensor into padded (S, L, ...) segments."""
        flat = x.reshape(-1, *x.shape[2:])
        return flat[self.index]

    def select(self, which: torch.Tensor) -> Segments:
        """The segments `which` (indices), cropped to their own longest length."""
        valid = self.valid[which]
        length = int(valid.sum(dim=1).max())
        return Segments(
            index=self.index[which, :length],
            valid=valid[:, :length],
            column=self.column[which],
            continues=self.continues[which],
        )

    def minibatches(self, num_minibatches: int, generator: torch.Generator | None = None):
        """Split the segments at random into `num_minibatches` groups of about equal step count.

        Returns:
            A list of index tensors into the segments, each non-empty.
        """
        order = torch.randperm(len(self.column), generator=generator)
        lengths = self.lengths[order]
        steps_before = torch.cumsum(lengths, 0) - lengths
        group = (steps_before * num_minibatches) // int(lengths.sum())
        return [order[group == g] for g in range(num_minibatches) if bool((group == g).any())]


def cut_into_segments(episode_starts: torch.Tensor) -> Segments:
    """Segments of a rollout whose step (t, n) starts an episode where `episode_starts` is True.

    Args:
        episode_starts: (T, N) bool; True where the observation at (t, n) is an episode's first.
    """
    num_steps, num_envs = episode_starts.shape
    starts = episode_starts.t().clone()  # column-major (N, T): a column's steps are contiguous
    starts[:, 0] = True
    flat_starts = starts.reshape(-1)
    segment_of_step = torch.cumsum(flat_starts.long(), 0) - 1
    segment_begin = torch.nonzero(flat_starts).squeeze(1)  # (S,) column-major positions
    steps = torch.arange(num_steps * num_envs)
    position = steps - segment_begin[segment_of_step]
    num_segments = len(segment_begin)
    max_length = int(position.max()) + 1

    column_of_step, time_of_step = steps // num_steps, steps % num_steps
    index = torch.zeros(num_segments, max_length, dtype=torch.long)
    valid = torch.zeros(num_segments, max_length, dtype=torch.bool)
    index[segment_of_step, position] = time_of_step * num_envs + column_of_step
    valid[segment_of_step, position] = True

    column = segment_begin // num_steps
    continues = (segment_begin % num_steps == 0) & ~episode_starts[0, column]
    return Segments(index=index, valid=valid, column=column, continues=continues)

"""Observation encoders: the first layer of the agent, chosen from the observation space.

A flat observation either holds real values (a linear layer reads them as they are) or small
integer codes such as minigrid's object / colour / state indices. Codes are categories, not
magnitudes: "key" (5) is not "between" "door" (4) and "ball" (6). A linear layer on the raw
indices has to untangle that; a linear layer on their one-hot expansion does not. So a Box of
integers with small bounds is encoded one-hot, computed as a sum of embeddings (the same
function as ``Linear(one_hot(obs))`` without building the one-hot tensor).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from gymnasium import spaces
from torch import nn

# One-hot encoding is used when every dimension has at most this many values and the
# expansion stays this small; past that (e.g. raw 0-255 pixels) the linear layer is kept.
MAX_VALUES_PER_DIM = 32
MAX_ONE_HOT_SIZE = 8192


def observation_categories(space: spaces.Space) -> list[int] | None:
    """Per-dimension number of values of a flat integer Box with small bounds, else None.

    Args:
        space: the single (flat) observation space of a vector env.

    Returns:
        ``[high_i + 1 for each dimension]`` when one-hot encoding applies (integer dtype,
        bounds 0 .. high_i, each at most ``MAX_VALUES_PER_DIM`` values, at most
        ``MAX_ONE_HOT_SIZE`` in total, and not already a 0/1 vector), else None.
    """
    if not isinstance(space, spaces.Box) or len(space.shape) != 1:
        return None
    if not np.issubdtype(space.dtype, np.integer):
        return None
    if not np.all(space.low == 0) or not np.all(np.isfinite(space.high)):
        return None  # codes 0 .. n-1 only: a shifted range is rare enough to read linearly
    values = space.high.astype(np.int64) + 1
    if values.max() > MAX_VALUES_PER_DIM or values.sum() > MAX_ONE_HOT_SIZE:
        return None
    if values.max() <= 2:  # binary already: one-hot would only double the input
        return None
    return values.tolist()


class OneHotLinear(nn.Module):
    """``Linear(one_hot(obs))`` for integer observations, as a sum of per-value embeddings.

    Args:
        categories: number of values n_i of each of the D dimensions (values 0 .. n_i - 1).
        out_size: E, the width of the features.
    """

    def __init__(self, categories: Sequence[int], out_size: int) -> None:
        super().__init__()
        sizes = torch.as_tensor(list(categories), dtype=torch.long)
        offsets = torch.cumsum(sizes, 0) - sizes
        self.register_buffer("offsets", offsets, persistent=False)
        self.register_buffer("last", sizes - 1, persistent=False)
        self.embedding = nn.Embedding(int(sizes.sum()), out_size)
        # Same scale as an orthogonally initialized Linear(sum(sizes), E) with gain sqrt(2).
        nn.init.orthogonal_(self.embedding.weight, np.sqrt(2))
        self.bias = nn.Parameter(torch.zeros(out_size))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """(..., D) integer-valued observations (any dtype) -> (..., E) features."""
        # Clamping keeps a masked (zeroed) or out-of-range value a valid index.
        index = torch.minimum(obs.long().clamp(min=0), self.last) + self.offsets
        return self.embedding(index).sum(dim=-2) + self.bias

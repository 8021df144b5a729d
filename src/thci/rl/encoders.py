"""Observation encoders: the first layer of the agent, chosen from the observation space.

A flat observation either holds real values (a linear layer reads them as they are) or small
integer codes such as minigrid's object / colour / state indices. Codes are categories, not
magnitudes: "key" (5) is not "between" "door" (4) and "ball" (6). A linear layer on the raw
indices has to untangle that; a linear layer on their one-hot expansion does not. So a Box of
integers with small bounds is encoded one-hot, computed as a sum of embeddings (the same
function as ``Linear(one_hot(obs))`` without building the one-hot tensor).

Images of categorical cells (minigrid's (object, colour, state) per cell) can also be read
*per cell* (``--encoder cells``): a per-dimension one-hot adds a "green" feature that is the
same for a green wall and a green door in the same place, so one linear layer cannot tell them
apart, while the cell's whole value as one category can; pooled over places, "a green wall
somewhere in view" becomes one feature (:class:`CellEncoder`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from gymnasium import spaces
from torch import nn

from thci.config import EncoderKind
from thci.errors import ThciError

# One-hot encoding is used when every dimension has at most this many values and the
# expansion stays this small; past that (e.g. raw 0-255 pixels) the linear layer is kept.
MAX_VALUES_PER_DIM = 32
MAX_ONE_HOT_SIZE = 8192
# ``--encoder cells``: rows of its table of whole cell values (198 for minigrid).
MAX_CELL_CATEGORIES = 65536


def orthogonal_linear(in_size: int, out_size: int, std: float) -> nn.Linear:
    """``nn.Linear`` with orthogonal weights of gain `std` and zero bias: the standard PPO
    recipe (CleanRL, SB3), with a small gain for the policy head."""
    linear = nn.Linear(in_size, out_size)
    nn.init.orthogonal_(linear.weight, std)
    nn.init.zeros_(linear.bias)
    return linear


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
        # One sum-mode bag per observation: an embedding followed by a sum built the
        # (..., D, E) rows first. On BabyAI views (151 entries, one thread) that was 1.5x
        # slower forward and backward on 512 views, 5x on 2048, and 68x on a 2048-view forward.
        lead = index.shape[:-1]
        summed = nn.functional.embedding_bag(
            index.reshape(-1, index.shape[-1]), self.embedding.weight, mode="sum"
        )
        return summed.view(*lead, -1) + self.bias


class CellLayout:
    """Where the cells of a flat observation lie (``--cell-layout``): ``offset`` entries before
    the first cell, ``num_cells`` cells of ``cell_size`` values, then the rest.

    Args:
        layout: (offset, num_cells, cell_size).
        observation_size: D of the flat observations the layout describes.
    """

    def __init__(self, layout: tuple[int, int, int], observation_size: int) -> None:
        self.offset, self.num_cells, self.cell_size = layout
        self.end = self.offset + self.num_cells * self.cell_size
        if self.end > observation_size:
            raise ThciError(
                f"--cell-layout {tuple(layout)} needs {self.end} entries, the observations "
                f"have {observation_size}"
            )

    def rest_size(self, observation_size: int) -> int:
        """Entries outside the cells."""
        return observation_size - (self.end - self.offset)

    def channel_categories(self, categories: Sequence[int]) -> list[int]:
        """Values of each cell channel (the largest over cells), for one table shared by all
        cells."""
        cells = torch.as_tensor(list(categories[self.offset : self.end]))
        return cells.view(self.num_cells, self.cell_size).max(dim=0).values.tolist()

    def split(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., D) -> cells (..., num_cells, cell_size) and the rest (..., D - cells)."""
        cells = obs[..., self.offset : self.end]
        cells = cells.reshape(*obs.shape[:-1], self.num_cells, self.cell_size)
        return cells, torch.cat((obs[..., : self.offset], obs[..., self.end :]), dim=-1)


class CellValues(nn.Module):
    """Each cell's whole value as one category: a cell of c channels with n_1 .. n_c values is
    one of n_1 * ... * n_c categories, numbered in mixed radix (the last channel varies
    fastest). Out-of-range channel values are clamped, as :class:`OneHotLinear` clamps them.

    Args:
        channels: n_1 .. n_c.
    """

    def __init__(self, channels: Sequence[int]) -> None:
        super().__init__()
        self.channels = list(channels)
        sizes = torch.as_tensor(self.channels)
        self.count = int(sizes.prod())
        after = torch.cat((sizes[1:], torch.ones(1, dtype=sizes.dtype)))
        self.register_buffer("strides", after.flip(0).cumprod(0).flip(0), persistent=False)
        self.register_buffer("last", sizes - 1, persistent=False)

    def forward(self, cells: torch.Tensor) -> torch.Tensor:
        """(..., c) cells (any dtype) -> (...) long categories."""
        values = torch.minimum(cells.long().clamp(min=0), self.last)
        return (values * self.strides).sum(dim=-1)

    def every_cell(self) -> torch.Tensor:
        """(count, c) long: the cell of each category, in category order."""
        return torch.arange(self.count).unsqueeze(1) // self.strides % (self.last + 1)


def max_over_cells(categories: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """max over cells of ``table[category]``: (..., n cells) long, (K, E) -> (..., E).

    A max-mode embedding bag per view: the same values and gradients as looking the rows up
    and taking the max, without building the (..., n cells, E) rows. On 512 BabyAI views (one
    thread) forward and backward took 19 ms against 73 ms.
    """
    pooled = nn.functional.embedding_bag(
        categories.reshape(-1, categories.shape[-1]), table, mode="max"
    )
    return pooled.view(*categories.shape[:-1], -1)


class CellEncoder(nn.Module):
    """The flat encoder plus each cell's whole value pooled over places (``--encoder cells``).

    A cell of c channels with n_1 .. n_c values is also one of n_1 * ... * n_c categories: for
    minigrid, "green wall" (object 2, colour 1, state 0) is its own category, not the sum of a
    "wall" and a "green" input shared with green doors, keys and balls. Two branches read the
    observation, and their sum is the output:

    * by place: the flat encoder (each entry one-hot, :class:`OneHotLinear`): *where* things
      are, with what is common to all colours of an object (a door ahead) learned once;
    * pooled: one embedding of the cell categories shared by all places, ReLU, max over the
      cells (as the gate's :class:`~thci.causal.gate.CellSetNet` and BabyAI's own models
      pool): *what* is in view, wherever it is, so "a green wall somewhere" is one feature
      learned from every view instead of once per place.

    Tested with a known answer (benchmarks/cell_recall.py, docs/babyai.md): the flat encoder
    alone does not reach 95% accuracy telling a green from a blue wall cell among 48 others
    within 100k views (it stays at ~0.90); with the pooled branch an LSTM-PPO agent also learns
    to remember it over a 12-step episode. An earlier by-place branch read whole cells too
    (49 x 198 rows for minigrid): it learned the recall as well but BabyAI's navigation far
    more slowly (each colour of a door learned apart; docs/babyai.md).

    Args:
        observation_size: D of a flat observation.
        cell_layout: (offset, n cells, c values per cell).
        categories: values per dimension of the observation.
        out_size: E.
    """

    def __init__(
        self,
        observation_size: int,
        cell_layout: tuple[int, int, int],
        categories: Sequence[int],
        out_size: int,
    ) -> None:
        super().__init__()
        self.layout = CellLayout(cell_layout, observation_size)
        self.values = CellValues(self.layout.channel_categories(categories))
        if self.values.count > MAX_CELL_CATEGORIES:
            raise ThciError(
                f"--encoder cells would embed {self.values.count} cell values (the product of "
                f"{self.values.channels}), more than {MAX_CELL_CATEGORIES}: use --encoder flat "
                "or grid"
            )
        self.by_place = OneHotLinear(categories, out_size)
        self.cell_embedding = nn.Embedding(self.values.count, out_size)
        self.pooled_out = nn.Linear(out_size, out_size)

    def cell_categories(self, obs: torch.Tensor) -> torch.Tensor:
        """(..., D) observations -> (..., n cells) long: each cell's category (mixed radix)."""
        cells, _ = self.layout.split(obs)
        return self.values(cells)

    def pooled(self, obs: torch.Tensor) -> torch.Tensor:
        """(..., D) -> (..., E): the position-free branch, before its output layer: the max
        over cells of ReLU(embedding of the cell's category)."""
        return max_over_cells(self.cell_categories(obs), torch.relu(self.cell_embedding.weight))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """(..., D) integer-valued observations -> (..., E) features."""
        return self.by_place(obs) + self.pooled_out(self.pooled(obs))


class GridEncoder(nn.Module):
    """A convolutional encoder for square images of categorical cells (``--encoder grid``).

    Each cell's values become one embedding (:class:`OneHotLinear` over the cell's channels,
    shared by all cells), two 3x3 convolutions read the grid, and a linear layer maps the result
    and the observation's other entries (e.g. minigrid's heading) to E features. A cell's
    meaning is the same wherever it is in view, which a flat one-hot layer has to learn once per
    position (the BabyAI models use such convolutions over cell embeddings).

    Args:
        observation_size: D of a flat observation.
        cell_layout: (offset, n cells, c values per cell); n must be a square (7x7 for minigrid).
        categories: values per dimension of the observation.
        out_size: E.
        channels: width of the cell embedding and of the convolutions.
    """

    def __init__(
        self,
        observation_size: int,
        cell_layout: tuple[int, int, int],
        categories: Sequence[int],
        out_size: int,
        channels: int = 16,
    ) -> None:
        super().__init__()
        self.layout = CellLayout(cell_layout, observation_size)
        num_cells = self.layout.num_cells
        self.side = math.isqrt(num_cells)
        if self.side * self.side != num_cells:
            raise ThciError(
                f"--encoder grid needs a square number of cells (--cell-layout), got {num_cells}"
            )
        self.cell = OneHotLinear(self.layout.channel_categories(categories), channels)
        self.conv = nn.Sequential(
            nn.ReLU(),
            nn.Conv2d(channels, 2 * channels, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(2 * channels, 2 * channels, 3, padding=1),
            nn.ReLU(),
            nn.Flatten(),
        )
        rest = self.layout.rest_size(observation_size)
        self.out = nn.Linear(2 * channels * num_cells + rest, out_size)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """(..., D) -> (..., E) features."""
        lead = obs.shape[:-1]
        cells, rest = self.layout.split(obs.reshape(-1, obs.shape[-1]))
        grid = self.cell(cells).view(len(cells), self.side, self.side, -1).permute(0, 3, 1, 2)
        return self.out(torch.cat((self.conv(grid), rest), dim=-1)).view(*lead, -1)


def make_encoder(
    kind: EncoderKind,
    observation_size: int,
    categories: Sequence[int] | None,
    cell_layout: tuple[int, int, int],
    out_size: int,
) -> nn.Module:
    """The agent's first layer (``--encoder``), without its activation.

    Args:
        kind: flat (one-hot per dimension for small integer codes, else linear), grid
            (:class:`GridEncoder`) or cells (:class:`CellEncoder`).
        observation_size: D. categories: values per dimension, or None for real values.
        cell_layout: (offset, n cells, c values per cell), for grid and cells.
        out_size: E.
    """
    if kind == "flat":
        if categories is None:
            return orthogonal_linear(observation_size, out_size, np.sqrt(2))
        return OneHotLinear(categories, out_size)
    if categories is None:
        raise ThciError(
            f"--encoder {kind} reads images of small integer cells (a Box of integers with "
            f"bounds 0..{MAX_VALUES_PER_DIM - 1}, as thci declares minigrid's images); these "
            f"observations are not: declare their bounds (README) or use --encoder flat"
        )
    if kind == "grid":
        return GridEncoder(observation_size, cell_layout, categories, out_size)
    return CellEncoder(observation_size, cell_layout, categories, out_size)

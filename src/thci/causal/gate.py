"""Gate_ϑ: which observations the causal memory removes (Eq. 10).

Gate_ϑ(o) ∈ [0, 1] approximates I(o ∈ O^w). It is a small network on the observation itself,
not a lookup table of codes, so it also decides for observations never seen in the pool. It is
fitted after each CI round on one representative observation per code of Ô with the L1 loss of
Eq. 10; an observation is removed from memory when Gate_ϑ(o) > 0.5. Until the first round the
gate is inactive, and the memory keeps nothing (the default, `--ci-initial-memory empty`) or
everything (`full`, the paper's O^w = ∅).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from thci.causal.flat_adam import FlatAdam
from thci.rl.encoders import CellLayout, CellValues, OneHotLinear, max_over_cells


@dataclass(frozen=True)
class GateFit:
    """How well the gate reproduces O^w on Ô after fitting."""

    loss: float
    accuracy: float
    steps: int


# Up to this many possible cell values (minigrid has 198), CellSetNet computes the features of
# every value once per call and max-pools rows of that table: on 512 BabyAI views the gate took
# 15 ms instead of 45 ms, with the same logits bit for bit. Past it, each cell is encoded apart.
MAX_TABLE_CELL_VALUES = 4096


class CellSetNet(nn.Module):
    """A function of the *set* of cell values in view and of the tail: max-pooled per-cell
    features (DeepSets). It has the invariance of
    :class:`~thci.causal.discretize.CellSetDiscretizer`, so a gate fitted on one observation
    per cell-set code decides every other view of that code alike (a plain MLP fitted on one
    view per code kept 48% of unseen BabyAI signpost views; this one all of them).

    Args:
        observation_size: D. cell_layout: (offset, n cells, c values per cell).
        categories: values per dimension (one-hot cells), or None (cells read linearly).
        hidden_size: H.
    """

    def __init__(
        self,
        observation_size: int,
        cell_layout: tuple[int, int, int],
        categories: Sequence[int] | None,
        hidden_size: int,
    ) -> None:
        super().__init__()
        self.layout = CellLayout(cell_layout, observation_size)
        self.values: CellValues | None = None
        if categories is None:
            self.cell: nn.Module = nn.Linear(self.layout.cell_size, hidden_size)
        else:
            channels = self.layout.channel_categories(categories)
            self.cell = OneHotLinear(channels, hidden_size)
            values = CellValues(channels)
            if values.count <= MAX_TABLE_CELL_VALUES:
                self.values = values
                # Every possible cell, built once: the table's rows are its features.
                self.register_buffer("every_cell", values.every_cell(), persistent=False)
        self.rest = nn.Linear(self.layout.rest_size(observation_size), hidden_size, bias=False)
        self.out = nn.Sequential(nn.ReLU(), nn.Linear(hidden_size, 1))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """(..., D) -> (..., 1) logits."""
        cells, rest = self.layout.split(obs)
        if self.values is None:
            pooled = torch.relu(self.cell(cells)).max(dim=-2).values  # (..., H)
        else:  # the same, from the features of every possible cell value (minigrid: 198)
            table = torch.relu(self.cell(self.every_cell))
            pooled = max_over_cells(self.values(cells), table)
        return self.out(pooled + self.rest(rest))


@dataclass(frozen=True)
class GateSpec:
    """How to build a gate (picklable, for CI worker processes).

    Attributes:
        observation_size: D of a flat observation.
        categories: values per dimension of an integer-coded observation
            (:func:`thci.rl.encoders.observation_categories`): the first layer then reads them
            one-hot, as the agent's encoder does. None: values are read linearly.
        cell_layout: (offset, cells, values per cell) when observations are coded by the set of cell
            values in view (``--discretizer cell-set``): the gate is then a :class:`CellSetNet`.
    """

    observation_size: int
    categories: list[int] | None = None
    cell_layout: tuple[int, int, int] | None = None

    def build(self, empty_before_fit: bool = False) -> Gate:
        return Gate(self, empty_before_fit=empty_before_fit)


class Gate(nn.Module):
    """Gate_ϑ(o) = sigmoid(net(o)), 1 = remove from memory.

    Before its first fit the gate is inactive: it keeps nothing (`empty_before_fit`, the causal
    memory starts empty) or everything.

    Args:
        spec: the network (:class:`GateSpec`), or just D for an MLP on values read linearly.
        hidden_size: width of the hidden layer.
        empty_before_fit: whether the inactive gate removes every observation.
    """

    def __init__(
        self, spec: GateSpec | int, hidden_size: int = 64, empty_before_fit: bool = False
    ) -> None:
        super().__init__()
        if isinstance(spec, int):
            spec = GateSpec(spec)
        self.spec, self.empty_before_fit = spec, empty_before_fit
        if spec.cell_layout is not None:
            self.net: nn.Module = CellSetNet(
                spec.observation_size, spec.cell_layout, spec.categories, hidden_size
            )
        else:
            first = (
                nn.Linear(spec.observation_size, hidden_size)
                if spec.categories is None
                else OneHotLinear(spec.categories, hidden_size)
            )
            self.net = nn.Sequential(first, nn.ReLU(), nn.Linear(hidden_size, 1))
        self.register_buffer("active", torch.tensor(False))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Gate_ϑ(o) for observations (..., D) -> (...)."""
        return torch.sigmoid(self.net(obs)).squeeze(-1)

    @torch.no_grad()
    def keep(self, obs: torch.Tensor) -> torch.Tensor | None:
        """(...) bool, False where the observation is removed; None (keep all) while inactive,
        unless `empty_before_fit`."""
        if not bool(self.active):
            if self.empty_before_fit:
                return torch.zeros(obs.shape[:-1], dtype=torch.bool, device=obs.device)
            return None
        return self(obs) <= 0.5

    def fit(
        self,
        observations: torch.Tensor,
        eliminated: torch.Tensor,
        max_steps: int = 3000,
        learning_rate: float = 1e-2,
        batch_size: int = 512,
    ) -> GateFit:
        """Fit Eq. 10 on Ô and activate the gate.

        Eq. 10's absolute error has a vanishing gradient where the sigmoid saturates, and the
        gate continues from round to round: a decision made confidently in earlier rounds could
        not be reversed (Maze L3 seed 5: CI put code 1 back, the gate kept removing it, 12 of 13
        right). The fit therefore minimizes the log-loss, whose minimizer on Ô is the same
        membership, and reports Eq. 10's loss.

        Up to `batch_size` observations every step takes all of them; beyond, a random
        minibatch of `batch_size` (seeded, so the same inputs give the same gate). Full batches
        of BabyAI-L2's 2,384 cell-set codes took 0.16 s a step and 488 s of a 594 s CI round
        (3000 steps, cProfile); minibatches of 512 took 0.03 s a step and left 9 codes wrong
        after 3000 steps, against 7 for full batches after 1000 (155 s).

        Args:
            observations: (|Ô|, D), one representative observation per observed code.
            eliminated: (|Ô|,) bool, I(o ∈ O^w).
        """
        target = eliminated.float()
        minibatches = len(observations) > batch_size
        generator = torch.Generator().manual_seed(0)
        # torch's Adam, bit for bit; constructing a torch.optim optimizer imports
        # torch._dynamo (~1.8 s), and this fit is all that would need it in the CI worker,
        # which the RL loop waits for when the first round comes before it is up.
        optimizer = FlatAdam(self.net.parameters(), lr=learning_rate)
        step = 0
        with torch.enable_grad():
            for step in range(1, max_steps + 1):
                if minibatches:
                    rows = torch.randint(len(observations), (batch_size,), generator=generator)
                    inputs, labels = observations[rows], target[rows]
                else:
                    inputs, labels = observations, target
                logits = self.net(inputs).squeeze(-1)
                loss = nn.functional.binary_cross_entropy_with_logits(logits, labels)
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                # Stop once every decision is right with a margin (on all of Ô).
                if step % 50 == 0:
                    with torch.no_grad():
                        all_logits = self.net(observations).squeeze(-1) if minibatches else logits
                    if bool(((torch.sigmoid(all_logits) - target).abs() < 0.25).all()):
                        break
        self.active.fill_(True)
        with torch.no_grad():
            prob = self(observations)
            accuracy = float(((prob > 0.5) == eliminated).float().mean())
            loss = float((prob - target).abs().mean())
        return GateFit(loss, accuracy, step)

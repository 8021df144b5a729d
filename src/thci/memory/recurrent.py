"""LSTM and GRU memories (the paper's gated-RNN baselines and the core of its causal memory).

Whole sequences go through one ``nn.LSTM`` / ``nn.GRU`` call; the trainer cuts rollouts at
episode boundaries beforehand (see :mod:`thci.rl.sequences`), so no per-step Python loop runs.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import nn

from thci.memory.base import Memory


class RecurrentMemory(Memory):
    """Single-layer LSTM or GRU with its state flattened to (B, state_size).

    The LSTM state is ``[h, c]`` concatenated (state_size = 2H); the GRU state is ``h`` (H).
    """

    def __init__(self, input_size: int, hidden_size: int, cell: Literal["lstm", "gru"]) -> None:
        super().__init__()
        rnn_class = {"lstm": nn.LSTM, "gru": nn.GRU}[cell]
        self.rnn = rnn_class(input_size, hidden_size, batch_first=True)
        self.cell = cell
        self.input_size = input_size
        self.output_size = hidden_size
        self.state_size = 2 * hidden_size if cell == "lstm" else hidden_size

    def forward(self, x: torch.Tensor, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """See :meth:`Memory.forward`; x (B, L, D), state (B, S) -> (B, L, H), (B, S)."""
        if self.cell == "lstm":
            h, c = state.unsqueeze(0).chunk(2, dim=-1)
            out, (h, c) = self.rnn(x, (h.contiguous(), c.contiguous()))
            return out, torch.cat((h, c), dim=-1).squeeze(0)
        out, h = self.rnn(x, state.unsqueeze(0).contiguous())
        return out, h.squeeze(0)

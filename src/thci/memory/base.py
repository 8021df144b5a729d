"""The interface every memory module implements, so agents and algorithms never special-case one.

A memory maps a sequence of per-step features to per-step outputs while carrying a state
between calls. The state is always one flat tensor of shape (B, state_size): rollouts can then
store it, zero it at episode starts and index it by environment the same way for an LSTM, a
GRU, or (in later modules) a causal memory, a Neural Map or a Working Memory Graph.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch
from torch import nn


class Memory(nn.Module, ABC):
    """Sequence model with a flat recurrent state.

    Attributes:
        input_size: feature size D of each step.
        output_size: size H of each step's output.
        state_size: size S of the flat state.
    """

    input_size: int
    output_size: int
    state_size: int

    def initial_state(self, batch_size: int, device: torch.device | None = None) -> torch.Tensor:
        """The state at an episode start: zeros of shape (batch_size, state_size)."""
        return torch.zeros(batch_size, self.state_size, device=device)

    @abstractmethod
    def forward(
        self, x: torch.Tensor, state: torch.Tensor, keep: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Run the memory over whole sequences.

        Args:
            x: features, shape (B, L, input_size).
            state: state before the first step, shape (B, state_size).
            keep: optional (B, L) bool, False where the gate removes the step's observation
                from memory (the causal memory); memories without a gate ignore it.

        Returns:
            outputs of shape (B, L, output_size) and the state after the last step, (B, state_size).
        """

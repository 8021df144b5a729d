"""The memoryless baseline: a policy that sees only the current observation.

It is the control that shows a task *needs* memory: on every built-in level it plateaus below
a recurrent policy (docs/babyai.md, the foundation notes for PaperMaze). The agent's heads
already receive the current observation's features, so this memory contributes nothing.
"""

from __future__ import annotations

import torch

from thci.memory.base import Memory


class NoMemory(Memory):
    """Outputs an empty feature vector, (B, L, 0), and carries a constant one-slot state."""

    def __init__(self, input_size: int) -> None:
        super().__init__()
        self.input_size = input_size
        self.output_size = 0
        # One slot, not zero: rollouts and checkpoints store states as (N, S) tensors.
        self.state_size = 1

    def forward(
        self, x: torch.Tensor, state: torch.Tensor, keep: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """See :meth:`Memory.forward`; x (B, L, D), state (B, 1) -> (B, L, 0), (B, 1)."""
        return x.new_zeros(x.shape[0], x.shape[1], 0), state

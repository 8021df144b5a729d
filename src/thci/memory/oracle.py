"""The Oracle ablation: the causal memory fed by the human labels instead of inference.

The paper's Oracle "leverages causal historical observations provided by experts" (Ablation
Study; Figs. 6, 9). Here it is T-HCI's causal memory (an LSTM whose state is not advanced on
removed observations, :class:`~thci.memory.recurrent.RecurrentMemory`) whose keep mask is the
environment's ground truth ``info["causal"]``, appended to each step by the rollout collector,
instead of the gate that the CI loop fits. No replay pool, no CI round: the gate is exact from
the first step and also for observations never seen before.
"""

from __future__ import annotations

import torch

from thci.memory.recurrent import RecurrentMemory


class OracleMemory(RecurrentMemory):
    """LSTM that keeps exactly the observations labelled causal (the last side input)."""

    side_inputs = (("causal", 1),)

    def __init__(self, input_size: int, hidden_size: int) -> None:
        super().__init__(input_size, hidden_size, "lstm")

    def _forward(
        self, x: torch.Tensor, state: torch.Tensor, keep: torch.Tensor | None, with_final: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """x (B, L, D+1) with the label last: the label is the keep mask (``forward`` and
        ``outputs`` both come here)."""
        return super()._forward(x[..., :-1], state, x[..., -1] > 0.5, with_final)

    def observation_weights(self, x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """The labels themselves: (B, L, 1), 1 where the observation is kept."""
        return (x[..., -1:] > 0.5).float()

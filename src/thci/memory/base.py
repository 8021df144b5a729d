"""The interface every memory module implements, so agents and algorithms never special-case one.

A memory maps a sequence of per-step inputs to per-step outputs while carrying a state between
calls. The state is always one flat tensor of shape (B, state_size): rollouts can then store it,
zero it at episode starts and index it by environment the same way for an LSTM, a GRU, the
causal memory, a Neural Map, a Working Memory Graph or an attention window.

Some memories read more than the observation: the Neural Map writes at the agent's position,
the Oracle reads the human labels, hard attention draws its selections from uniform noise.
A memory names these *side inputs* (:attr:`Memory.side_inputs`); the rollout collector appends
them, step by step, to the observation the agent receives, so they travel through rollouts,
minibatches and checkpoints exactly like the observation itself (see :mod:`thci.rl.rollout`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch
from torch import nn

NOISE = "noise"
"""Side-input name of a fresh U(0, 1) draw per step, made by the collector (not an info key)."""


class Memory(nn.Module, ABC):
    """Sequence model with a flat recurrent state.

    Attributes:
        input_size: size D of each step's features (before the side inputs).
        output_size: size H of each step's output.
        state_size: size S of the flat state.
        side_inputs: (name, width) of the values appended after the D features of each step:
            an ``info`` key of the environment (e.g. ``("agent_pos", 2)``) or :data:`NOISE`.
        reads_observation: True when the memory embeds the raw observation itself (WMG), so
            the agent gives it the observation instead of the encoder's features.
    """

    input_size: int
    output_size: int
    state_size: int
    side_inputs: tuple[tuple[str, int], ...] = ()
    reads_observation: bool = False

    @property
    def side_size(self) -> int:
        """Total width of the side inputs appended to each step."""
        return sum(width for _, width in self.side_inputs)

    def initial_state(self, batch_size: int, device: torch.device | None = None) -> torch.Tensor:
        """The state at an episode start: zeros of shape (batch_size, state_size)."""
        return torch.zeros(batch_size, self.state_size, device=device)

    @abstractmethod
    def forward(
        self, x: torch.Tensor, state: torch.Tensor, keep: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Run the memory over whole sequences.

        Args:
            x: features followed by the side inputs, shape (B, L, input_size + side_size).
            state: state before the first step, shape (B, state_size).
            keep: optional (B, L) bool, False where the gate removes the step's observation
                from memory (the causal memory); memories without a gate ignore it.

        Returns:
            outputs of shape (B, L, output_size) and the state after the last step, (B, state_size).
        """

    def outputs(
        self, x: torch.Tensor, state: torch.Tensor, keep: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The outputs of :meth:`forward` alone, (B, L, output_size), for training passes that
        discard the final state; a memory whose final state costs extra work skips it."""
        return self.forward(x, state, keep)[0]

    def observation_weights(self, x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor | None:
        """ν(o_t): the weight the memory puts on each step's observation, for TAIE and heatmaps.

        Args:
            x: (B, L, input_size + side_size) whole episodes (or their starts), each row from
                its episode's first step. valid: (B, L) bool, False on padding.

        Returns:
            (B, L, K) weights in [0, 1], K = 1 or one column per attention head; None for a
            memory that weighs every observation alike (the default).
        """
        return None

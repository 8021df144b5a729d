"""LSTM and GRU memories, and the causal memory of T-HCI (an LSTM that skips gated steps).

Whole sequences go through one ``nn.LSTM`` / ``nn.GRU`` call; the trainer cuts rollouts at
episode boundaries beforehand (see :mod:`thci.rl.sequences`), so no per-step Python loop runs.

With a ``keep`` mask the memory's state is *not advanced* on removed observations (the causal
memory ψ = φ_ϑ(h) of Eq. 10's section): that is the same as running the RNN on the kept steps
only. Each row's kept steps are moved to the front (a stable sort) and run as one sequence,
and every step then reads the output of the last kept step at or before it. The state after a
gated sequence carries no gradient for the LSTM (see :meth:`RecurrentMemory._final_state`).
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import nn
from torch.nn.utils.rnn import pack_padded_sequence, pad_packed_sequence

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

    def forward(
        self, x: torch.Tensor, state: torch.Tensor, keep: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """See :meth:`Memory.forward`; x (B, L, D), state (B, S) -> (B, L, H), (B, S)."""
        out, final = self._forward(x, state, keep, with_final=True)
        assert final is not None
        return out, final

    def outputs(
        self, x: torch.Tensor, state: torch.Tensor, keep: torch.Tensor | None = None
    ) -> torch.Tensor:
        """See :meth:`Memory.outputs`: a gated LSTM's final state needs a second, packed run
        (:meth:`_final_state`, ~a sixth of a training pass), which this skips."""
        return self._forward(x, state, keep, with_final=False)[0]

    def _forward(
        self, x: torch.Tensor, state: torch.Tensor, keep: torch.Tensor | None, with_final: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        if keep is None or bool(keep.all()):
            return self._run(x, state, None)
        _, steps, size = x.shape
        if steps == 1:  # acting: one step, advanced or not (packing would cost 2x the step)
            out, final = self._run(x, state, None)
            final = torch.where(keep, final, state)
            return torch.where(keep.unsqueeze(-1), out, state[:, None, : self.output_size]), final
        order = torch.argsort((~keep).to(torch.int8), dim=1, stable=True)  # kept steps first
        compact = x.gather(1, order.unsqueeze(-1).expand(-1, -1, size))
        kept = keep.sum(dim=1)
        # The RNN is causal, so the outputs of each row's kept prefix do not depend on the
        # padding after it: one plain call gives them (a packed sequence costs 2.8x on CPU).
        out, _ = self._run(compact, state, None)
        final = None
        if with_final:  # rows that kept nothing keep their state
            final = self._final_state(compact, state, kept, out)
            final = torch.where((kept > 0).unsqueeze(1), final, state)
        # Step t reads the last kept output <= t.
        last_kept = torch.cumsum(keep.long(), dim=1) - 1  # (B, L), -1 before the first kept
        read = out.gather(1, last_kept.clamp(min=0).unsqueeze(-1).expand(-1, -1, out.shape[-1]))
        initial = state[:, : self.output_size].unsqueeze(1).expand(-1, steps, -1)
        return torch.where((last_kept >= 0).unsqueeze(-1), read, initial), final

    def _final_state(
        self, compact: torch.Tensor, state: torch.Tensor, kept: torch.Tensor, out: torch.Tensor
    ) -> torch.Tensor:
        """(B, S) state after each row's `kept` first steps of `compact` (B, L, D).

        A GRU's state is its output at the last kept step. An LSTM's cell state is not an
        output, so a packed run (without gradient) computes it: training passes skip it
        (:meth:`outputs`) and acting runs one step at a time (see :meth:`_forward`), so no
        gradient ever flows through it.
        """
        if self.cell == "gru":
            return out[torch.arange(len(out)), (kept - 1).clamp(min=0)]
        with torch.no_grad():
            return self._run(compact, state, kept.clamp(min=1))[1]

    def _run(
        self, x: torch.Tensor, state: torch.Tensor, lengths: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The RNN over x (B, L, D) from `state`; with `lengths`, each row stops at its length."""
        if self.cell == "lstm":
            h, c = state.unsqueeze(0).chunk(2, dim=-1)
            hidden: torch.Tensor | tuple[torch.Tensor, torch.Tensor] = (
                h.contiguous(),
                c.contiguous(),
            )
        else:
            hidden = state.unsqueeze(0).contiguous()
        if lengths is None:
            out, hidden = self.rnn(x, hidden)
        else:
            packed = pack_padded_sequence(x, lengths.cpu(), batch_first=True, enforce_sorted=False)
            packed_out, hidden = self.rnn(packed, hidden)
            out, _ = pad_packed_sequence(packed_out, batch_first=True, total_length=x.shape[1])
        final = torch.cat(hidden, dim=-1) if isinstance(hidden, tuple) else hidden
        return out, final.squeeze(0)

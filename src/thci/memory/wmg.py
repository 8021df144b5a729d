"""Working Memory Graph (Loynd, Fernandez, Celikyilmaz, Swaminathan & Hausknecht, ICML 2020).

A Transformer runs over a small set of vectors each step:

* the **core**: a linear embedding of the current observation;
* **factors**: one embedding per entity of a factored observation. For BabyAI (the flat
  7×7×3 egocentric view of :mod:`thci.envs.babyai`) a factor is one visible object, a cell that
  is not unseen, empty or wall: one-hot object type (11), colour (6), state (3), view column (7)
  and row (7). The symbolic PaperMaze has none (its observation is one code);
* **Memos**: up to S earlier memos, each embedded with a one-hot of its age (0 = newest).

The core's output is the step's output; a new Memo = tanh(Linear(core output)) enters a FIFO of
S Memos and the oldest falls out. The Memo FIFO (newest first, so a Memo's slot *is* its age)
and a validity flag per slot are the flat state. Each Memo depends on the previous step's
Transformer, so the Transformer runs in a per-step loop; the core and factor embeddings of a
whole sequence are computed at once.

The Transformer layers are torch's post-norm ``TransformerEncoderLayer`` (ReLU, no dropout)
written out in a few fused ops (:class:`_EncoderLayer`), and the last layer computes the core
token alone, the only output WMG reads. In the per-step loop the cost is the number of ops,
not their size: one forward and backward of a 2-layer, 64-wide WMG over 9 tokens took 1.4 ms
against torch's 2.1 ms (one thread), the same outputs to 5e-7.

Defaults are WMG's factored-BabyAI settings (``specs/train_wmg_on_factored_babyai.py`` in
microsoft/wmg_agent): S = 8 Memos of size 32, 4 layers, 2 heads of size 128, feed-forward width
32. The actor-critic's 2048-unit hidden layer of that spec is not copied: every thci method
shares the same heads, so that only the memory differs between methods.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import nn
from torch.nn import functional as F

from thci.memory.base import Memory

MEMO_SIZE = 32
FEED_FORWARD_SIZE = 32

BABYAI_VIEW = 7
BABYAI_CELL_VALUES = (11, 6, 3)  # minigrid's object, colour and state index ranges
BABYAI_NON_FACTORS = (0, 1, 2)  # unseen, empty, wall
BABYAI_FACTOR_SIZE = sum(BABYAI_CELL_VALUES) + 2 * BABYAI_VIEW

# obs (..., D) -> factors (..., F, factor_size) and their validity (..., F)
Factorizer = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


def babyai_factors(obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Factors of flat BabyAI observations (..., 151): one per view cell, (..., 49, 34), valid
    where the cell holds an object (not unseen, empty or wall)."""
    cells = BABYAI_VIEW * BABYAI_VIEW
    view = obs[..., : 3 * cells].round().long().reshape(*obs.shape[:-1], cells, 3)
    column = torch.arange(cells) // BABYAI_VIEW  # minigrid flattens the image as (x, y, channel)
    row = torch.arange(cells) % BABYAI_VIEW
    parts = [F.one_hot(view[..., k], n) for k, n in enumerate(BABYAI_CELL_VALUES)]
    where = torch.stack((column, row), dim=-1).expand(*view.shape[:-1], 2)
    parts += [F.one_hot(where[..., k], BABYAI_VIEW) for k in range(2)]
    valid = ~torch.isin(view[..., 0], torch.tensor(BABYAI_NON_FACTORS))
    return torch.cat(parts, dim=-1).float(), valid


class _EncoderLayer(nn.Module):
    """torch's ``TransformerEncoderLayer`` (post-norm, ReLU, no dropout) in fewer ops.

    Args:
        width: token size. heads: attention heads (width divisible by them).
        feed_forward: hidden size of the feed-forward block.
    """

    def __init__(self, width: int, heads: int, feed_forward: int) -> None:
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(width, 3 * width)
        self.out = nn.Linear(width, width)
        self.ff_in, self.ff_out = nn.Linear(width, feed_forward), nn.Linear(feed_forward, width)
        self.norm_attention, self.norm_ff = nn.LayerNorm(width), nn.LayerNorm(width)
        nn.init.xavier_uniform_(self.qkv.weight)  # as nn.MultiheadAttention initializes
        nn.init.zeros_(self.qkv.bias)
        nn.init.zeros_(self.out.bias)

    def forward(self, x: torch.Tensor, key_bias: torch.Tensor, first_only: bool) -> torch.Tensor:
        """x (B, T, width), key_bias (B, 1, 1, T) 0 or -inf per key -> (B, T or 1, width);
        `first_only`: only token 0 is computed (it still attends to every token)."""
        batch, tokens, width = x.shape
        q, k, v = (
            self.qkv(x)
            .view(batch, tokens, 3, self.heads, width // self.heads)
            .permute(2, 0, 3, 1, 4)
        )  # each (B, heads, T, head_size)
        if first_only:
            q, x = q[:, :, :1], x[:, :1]
        attended = F.scaled_dot_product_attention(q, k, v, attn_mask=key_bias)
        x = self.norm_attention(x + self.out(attended.transpose(1, 2).reshape(batch, -1, width)))
        return self.norm_ff(x + self.ff_out(F.relu(self.ff_in(x))))


class WorkingMemoryGraph(Memory):
    """WMG over the core, the factors and up to `memos` Memos.

    Args:
        observation_size: D of a flat observation (WMG embeds the raw observation).
        memos: S, Memos kept. layers, heads, head_size: the Transformer.
        factorizer: splits an observation into factors, or None (no factors).
        factor_size: size of one factor vector (with a factorizer).
    """

    reads_observation = True

    def __init__(
        self,
        observation_size: int,
        memos: int,
        layers: int,
        heads: int,
        head_size: int,
        factorizer: Factorizer | None = None,
        factor_size: int = 0,
    ) -> None:
        super().__init__()
        width = heads * head_size
        self.input_size, self.output_size, self.memos = observation_size, width, memos
        self.state_size = memos * (MEMO_SIZE + 1)
        self.factorizer = factorizer
        self.core = nn.Linear(observation_size, width)
        self.factor = nn.Linear(factor_size, width) if factorizer is not None else None
        self.memo = nn.Linear(MEMO_SIZE + memos, width)
        self.layers = nn.ModuleList(
            _EncoderLayer(width, heads, FEED_FORWARD_SIZE) for _ in range(layers)
        )
        self.write = nn.Linear(width, MEMO_SIZE)
        self.register_buffer("ages", torch.eye(memos), persistent=False)  # slot k has age k

    def split(self, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Flat state (B, S·(M+1)) -> Memos (B, S, M), newest first, and validity (B, S) bool."""
        slots = state.view(state.shape[0], self.memos, MEMO_SIZE + 1)
        return slots[..., :-1], slots[..., -1] > 0.5

    def forward(
        self, x: torch.Tensor, state: torch.Tensor, keep: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """See :meth:`Memory.forward`; x (B, L, D) observations, state (B, S·(M+1)) ->
        (B, L, heads·head_size), (B, S·(M+1))."""
        batch, steps, _ = x.shape
        core = self.core(x).unsqueeze(2)  # (B, L, 1, width)
        if self.factorizer is not None and self.factor is not None:
            factors, factor_valid = self.factorizer(x)
            tokens = torch.cat((core, self.factor(factors)), dim=2)
            token_valid = torch.cat((factor_valid.new_ones(batch, steps, 1), factor_valid), -1)
        else:
            tokens, token_valid = core, torch.ones(batch, steps, 1, dtype=torch.bool)
        memos, memo_valid = self.split(state)
        # Slot k holds, at step t, the Memo written at step t-1-k (k < t) or the state's Memo
        # in slot k-t: the validity of every step's slots (and after the last, t = L) is known
        # before the loop.
        shift = torch.arange(self.memos) - torch.arange(steps + 1).unsqueeze(1)  # (L+1, S)
        slot_valid = (shift < 0) | memo_valid[:, shift.clamp(min=0)]  # (B, L+1, S)
        valid = torch.cat((token_valid, slot_valid[:, :-1]), dim=-1)  # (B, L, T)
        key_bias = torch.zeros(valid.shape).masked_fill(~valid, -math.inf)[:, :, None, None]
        # Linear([memo, one-hot age]) = W_memo · memo + (W_age[:, k] + b) for slot k: each
        # Memo is projected once, when written, and the age terms once per call.
        memo_weight, age_weight = self.memo.weight.split((MEMO_SIZE, self.memos), dim=1)
        age_terms = F.linear(self.ages, age_weight, self.memo.bias)  # (S, width)
        projected = F.linear(memos, memo_weight)  # (B, S, width), newest first
        outputs, written = [], []
        for t in range(steps):
            out = torch.cat((tokens[:, t], projected + age_terms), dim=1)
            for depth, layer in enumerate(self.layers):
                out = layer(out, key_bias[:, t], first_only=depth == len(self.layers) - 1)
            out = out[:, 0]  # the core token's output
            outputs.append(out)
            new = torch.tanh(self.write(out)).unsqueeze(1)  # FIFO: push newest, drop oldest
            written.append(new)
            projected = torch.cat((F.linear(new, memo_weight), projected[:, :-1]), dim=1)
        kept = min(steps, self.memos)
        memos = torch.cat((*written[::-1][:kept], memos[:, : self.memos - kept]), dim=1)
        state = torch.cat((memos, slot_valid[:, -1].unsqueeze(-1).to(memos.dtype)), dim=-1)
        return torch.stack(outputs, dim=1), state.reshape(batch, -1)

"""Attention over the episode's history instead of CI: the SAI and HAI ablations of the paper.

The paper's Ablation Study compares T-HCI with two variants that pick the informative past
observations by attention instead of counterfactual inference (Table 2, Figs. 8-9):

* **SAI** (:class:`SoftAttentionMemory`): soft attention (Vaswani et al. 2017), one Transformer
  layer with four heads whose query is the current step and whose keys and values are the past
  observations. Its per-head attention weights are the ν of TAIE and of the heatmaps.
* **HAI** (:class:`HardAttentionMemory`): hard attention (Xu et al. 2015): each observation is
  *selected* (z_t = 1) or not (z_t = 0) by a stochastic binary choice, and the memory reads the
  element-wise max of the selected observations' values (a mean diluted a selected cue among
  the other selected steps: on Maze L2 a policy that selected 86% of its steps, every cue
  included, stayed at the guess in 2 of 3 seeds; docs/baselines.md). Training uses the
  relaxed estimator, the straight-through Gumbel-sigmoid (binary Concrete; Maddison et al.
  2017, Jang et al. 2017): the forward pass uses the hard z_t = 1[ℓ_t + g_t > 0], the gradient
  flows through σ((ℓ_t + g_t) / τ), with ℓ_t the selection logit and g_t = log u_t −
  log(1 − u_t) logistic noise. The uniform u_t is a side input drawn by the rollout collector
  (:data:`~thci.memory.base.NOISE`), so the update replays exactly the selections the rollout
  made and PPO's ratios stay exact.

"The replay buffer" of the paper is, for both, the window of the last ``window`` observations
of the current episode (the observations a CI round would see of it). Both memories share the
window: a FIFO of the last W steps' features, each with a weight (1 for SAI, z for HAI, 0 for an
empty slot), stored in the flat state as (B, W·(D+1)). A whole sequence is one call: the window
and the new steps are concatenated and each step's query sees a band of W steps ending at
itself, so no Python loop runs over time.
"""

from __future__ import annotations

import torch
from torch import nn

from thci.errors import ThciError
from thci.memory.base import NOISE, Memory

SAI_HEADS = 4
"""Attention heads of SAI (the paper's Ablation Study: four heads, one Transformer layer)."""
HAI_TEMPERATURE = 1.0
"""τ of HAI's relaxed selection (only the gradient sees it; the forward pass is hard)."""


class WindowMemory(Memory):
    """Shared part of SAI and HAI: the FIFO window of the last W steps in the flat state.

    Args:
        input_size: D, feature size of a step (also the output size).
        window: W, how many past steps (the current one included) a step can attend to.
    """

    def __init__(self, input_size: int, window: int) -> None:
        super().__init__()
        self.input_size, self.output_size, self.window = input_size, input_size, window
        self.state_size = window * (input_size + 1)

    def split(self, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Flat state (B, S) -> window features (B, W, D) and slot weights (B, W)."""
        slots = state.view(state.shape[0], self.window, self.input_size + 1)
        return slots[..., :-1], slots[..., -1]

    def extend(
        self, state: torch.Tensor, features: torch.Tensor, weights: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The window followed by L new steps, the band each step sees, and the next state.

        Args:
            state: (B, S). features: (B, L, D) of the new steps. weights: (B, L) their weights.

        Returns:
            keys (B, W+L, D), key weights (B, W+L), band (L, W+L) bool (step l sees keys
            l+1 .. l+W, i.e. the W most recent steps up to itself), next state (B, S).
        """
        past, past_weights = self.split(state)
        keys = torch.cat((past, features), dim=1)
        key_weights = torch.cat((past_weights, weights), dim=1)
        steps = features.shape[1]
        query = torch.arange(steps).unsqueeze(1)
        key = torch.arange(self.window + steps).unsqueeze(0)
        band = (key > query) & (key <= query + self.window)
        last = torch.cat((keys, key_weights.unsqueeze(-1)), dim=-1)[:, -self.window :]
        return keys, key_weights, band, last.reshape(state.shape[0], -1)


class SoftAttentionMemory(WindowMemory):
    """SAI: one post-norm Transformer layer, four heads, queries = steps, keys = the window.

    Args:
        input_size: D (divisible by 4). hidden_size: width of the feed-forward block.
        window: W.
    """

    def __init__(self, input_size: int, hidden_size: int, window: int) -> None:
        super().__init__(input_size, window)
        self.attention = nn.MultiheadAttention(input_size, SAI_HEADS, batch_first=True)
        self.norm1, self.norm2 = nn.LayerNorm(input_size), nn.LayerNorm(input_size)
        self.feed_forward = nn.Sequential(
            nn.Linear(input_size, hidden_size), nn.ReLU(), nn.Linear(hidden_size, input_size)
        )

    def forward(
        self, x: torch.Tensor, state: torch.Tensor, keep: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """See :meth:`Memory.forward`; x (B, L, D), state (B, S) -> (B, L, D), (B, S)."""
        out, state, _ = self.attend(x, state)
        return out, state

    def attend(
        self, x: torch.Tensor, state: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The layer's outputs (B, L, D), next state (B, S) and attention (B, heads, L, W+L)."""
        batch, steps, _ = x.shape
        keys, key_weights, band, state = self.extend(state, x, x.new_ones(batch, steps))
        allowed = band.unsqueeze(0) & (key_weights > 0).unsqueeze(1)  # empty slots excluded
        mask = torch.zeros(allowed.shape).masked_fill(~allowed, float("-inf"))
        mask = mask.repeat_interleave(SAI_HEADS, dim=0)  # (B * heads, L, W+L), batch-major
        read, weights = self.attention(
            x, keys, keys, attn_mask=mask, need_weights=True, average_attn_weights=False
        )
        out = self.norm1(x + read)
        return self.norm2(out + self.feed_forward(out)), state, weights

    @torch.no_grad()
    def observation_weights(self, x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """Per head, the attention that each row's *last* step (the decision the episode ends
        with) pays to every observation of the row: (B, L, 4), each head summing to 1 over the
        row's last W steps."""
        _, _, weights = self.attend(x, self.initial_state(x.shape[0]))
        last = valid.sum(dim=1) - 1
        rows = torch.arange(x.shape[0])
        return weights[rows, :, last, self.window :].transpose(1, 2)


class HardAttentionMemory(WindowMemory):
    """HAI: a stochastic binary selection per observation and the max of the selected values.

    The last side input is the uniform noise u_t of the selection (:data:`NOISE`).

    Args:
        input_size: D. hidden_size: width of the selector's hidden layer. window: W.
        read: "max" of the selected values, or their "mean" (runs before 2026-12-06).
    """

    side_inputs = ((NOISE, 1),)

    def __init__(self, input_size: int, hidden_size: int, window: int, read: str = "max") -> None:
        super().__init__(input_size, window)
        if read not in ("max", "mean"):
            raise ThciError(f"--hai-read must be max or mean, got {read!r}")
        self.read = read
        self.selector = nn.Sequential(
            nn.Linear(input_size, hidden_size), nn.ReLU(), nn.Linear(hidden_size, 1)
        )
        self.value = nn.Sequential(nn.Linear(input_size, input_size), nn.ReLU())

    def select(self, x: torch.Tensor) -> torch.Tensor:
        """z_t in {0, 1} of each step, (B, L), with the straight-through relaxed gradient."""
        features, noise = x[..., : self.input_size], x[..., self.input_size]
        noise = noise.clamp(1e-6, 1 - 1e-6)
        perturbed = self.selector(features).squeeze(-1) + torch.log(noise) - torch.log1p(-noise)
        soft = torch.sigmoid(perturbed / HAI_TEMPERATURE)
        hard = (perturbed > 0).to(soft.dtype)
        return hard + (soft - soft.detach())  # exactly hard in value, soft's gradient

    def forward(
        self, x: torch.Tensor, state: torch.Tensor, keep: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """See :meth:`Memory.forward`; x (B, L, D+1), state (B, S) -> (B, L, D), (B, S)."""
        features = x[..., : self.input_size]
        keys, key_weights, band, state = self.extend(state, features, self.select(x))
        values = self.value(keys)  # (B, W+L, D), >= 0: an unselected step reads as 0
        if self.read == "mean":
            attention = band.unsqueeze(0) * key_weights.unsqueeze(1)  # (B, L, W+L), hard 0/1
            read = attention @ values
            return read / attention.sum(dim=-1, keepdim=True).clamp(min=1.0), state
        # z (hard in value) scales each value, so the max's gradient reaches the selection.
        # Step l's band is keys l+1 .. l+W: a sliding window (B, L, D, W) over the scaled values,
        # not a (B, L, W+L, D) product masked by the band (10x slower forward and backward
        # with L = 128, W = 32; the band's zeros never win a max of values >= 0).
        selected = key_weights.unsqueeze(-1) * values  # (B, W+L, D)
        return selected.unfold(1, self.window, 1)[:, 1:].amax(dim=-1), state

    @torch.no_grad()
    def observation_weights(self, x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """z_t, the binary selection of each step's observation: (B, L, 1)."""
        return self.select(x).unsqueeze(-1)

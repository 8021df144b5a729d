"""Neural Map (Parisotto & Salakhutdinov, "Neural Map: Structured Memory for Deep Reinforcement
Learning", ICLR 2018): a C×H×W memory laid out like the environment's grid.

At each step t, with s_t the observation's features and (x_t, y_t) the agent's position:

* global read  r_t = read(M_t): a small CNN over the whole map, flattened to C values;
* context read c_t = Σ_xy α_xy M_t^(xy), α = softmax_xy(q_t · M_t^(xy)), q_t = W[s_t, r_t];
* local write  w_t = GRU-gated write of Sec. 3.1's "GRU-based local write" at (x_t, y_t):
  u = σ(W_u[s, r, c, m]), g = σ(W_g[s, r, c, m]), ĥ = tanh(W_h[s, r, c] + U_h(g ⊙ m)),
  w = (1 − u) ⊙ m + u ⊙ ĥ, with m = M_t^(x_t y_t); M_{t+1} is M_t with w written there;
* output       o_t = [r_t, c_t, w_t] (the policy's input, as in the paper).

Positions come from the environment's ``info["agent_pos"]`` ([row, col]); the rollout collector
appends them to every step as this memory's side input. Each write depends on the previous
step's map, so the steps of a sequence run in a Python loop (inherently sequential, as for an
RNN cell); everything inside a step is batched.
"""

from __future__ import annotations

import torch
from torch import nn

from thci.errors import ThciError
from thci.memory.base import Memory


class NeuralMap(Memory):
    """Neural Map with global read, context read and GRU-gated local write.

    Args:
        input_size: D, feature size of a step.
        map_size: the map is map_size × map_size; positions must lie inside it.
        channels: C, the feature size of one map cell.
    """

    side_inputs = (("agent_pos", 2),)

    def __init__(self, input_size: int, map_size: int, channels: int) -> None:
        super().__init__()
        self.input_size, self.map_size, self.channels = input_size, map_size, channels
        self.output_size = 3 * channels
        self.state_size = channels * map_size * map_size
        reduced = (map_size + 1) // 2
        self.global_read = nn.Sequential(
            nn.Conv2d(channels, 8, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(8, 8, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Flatten(),
            nn.Linear(8 * reduced * reduced, channels),
        )
        self.query = nn.Linear(input_size + channels, channels)
        self.gates = nn.Linear(input_size + 3 * channels, 2 * channels)
        self.candidate = nn.Linear(input_size + 2 * channels, channels)
        self.candidate_memory = nn.Linear(channels, channels, bias=False)

    def cells(self, x: torch.Tensor) -> torch.Tensor:
        """Flat map cell index row * map_size + col of each step, (B, L) long."""
        position = x[..., self.input_size : self.input_size + 2].round().long()
        outside = ((position < 0) | (position >= self.map_size)).any(dim=-1)
        if bool(outside.any()):
            raise ThciError(
                f"agent position {position[outside][0].tolist()} lies outside the Neural Map "
                f"of {self.map_size}x{self.map_size} cells: raise --nm-map-size"
            )
        return position[..., 0] * self.map_size + position[..., 1]

    def forward(
        self, x: torch.Tensor, state: torch.Tensor, keep: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """See :meth:`Memory.forward`; x (B, L, D+2), state (B, C·H·W) -> (B, L, 3C), (B, S)."""
        batch, size = x.shape[0], self.map_size
        features, cells = x[..., : self.input_size], self.cells(x)
        memory = state.view(batch, self.channels, size * size)
        outputs = []
        for t in range(x.shape[1]):
            s = features[:, t]
            read = self.global_read(memory.view(batch, self.channels, size, size))
            query = self.query(torch.cat((s, read), dim=-1))
            attention = torch.softmax(torch.einsum("bc,bcn->bn", query, memory), dim=-1)
            context = torch.einsum("bn,bcn->bc", attention, memory)
            where = cells[:, t].view(batch, 1, 1).expand(-1, self.channels, 1)
            old = memory.gather(2, where).squeeze(2)
            update, reset = torch.sigmoid(
                self.gates(torch.cat((s, read, context, old), dim=-1))
            ).chunk(2, dim=-1)
            candidate = torch.tanh(
                self.candidate(torch.cat((s, read, context), dim=-1))
                + self.candidate_memory(reset * old)
            )
            written = (1 - update) * old + update * candidate
            memory = memory.scatter(2, where, written.unsqueeze(2))  # out of place: autograd
            outputs.append(torch.cat((read, context, written), dim=-1))
        return torch.stack(outputs, dim=1), memory.reshape(batch, -1)

"""The actor-critic agent: observation encoder -> pluggable memory -> policy and value heads.

The same agent serves rollouts (one step for N environments at a time, :meth:`step`) and
updates (whole padded sequences, :meth:`forward`). Which memory it uses is the ``--method``.

The agent's *input* is the flat observation followed by the memory's side inputs (agent
positions for the Neural Map, labels for the Oracle, noise for hard attention; none for most
memories), which the rollout collector appends (:attr:`thci.memory.Memory.side_inputs`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import nn

from thci.causal.gate import Gate
from thci.config import EncoderKind
from thci.memory import Memory
from thci.rl.encoders import make_encoder, orthogonal_linear


class ActorCritic(nn.Module):
    """pi_theta(a_t | memory(h_t)) and V(memory(h_t)) over flat observations.

    Args:
        observation_size: size D_obs of a flat observation.
        num_actions: number A of discrete actions.
        memory: the memory module; its input_size must equal `encoder_size`.
        encoder_size: width of the observation encoder and of the heads' hidden layer.
        gate: for the causal memory, the gate that decides which observations the memory keeps
            (fitted by the CI loop, never by the RL loss).
        categories: for observations of small integer codes, the number of values of each
            dimension (:func:`thci.rl.encoders.observation_categories`): the encoder then reads
            them one-hot. None: a linear encoder on the values as they are.
        encoder: the first layer (:func:`thci.rl.encoders.make_encoder`): flat, or for images
            of categorical cells (needs `categories`) grid or cells.
        cell_layout: (offset, cells, values per cell) of those images.
    """

    def __init__(
        self,
        observation_size: int,
        num_actions: int,
        memory: Memory,
        encoder_size: int,
        gate: Gate | None = None,
        categories: list[int] | None = None,
        encoder: EncoderKind = "flat",
        cell_layout: tuple[int, int, int] = (0, 49, 3),
    ) -> None:
        super().__init__()
        self.gate = gate
        self.observation_size = observation_size
        self.encoder_size = encoder_size
        if categories is not None and len(categories) != observation_size:
            raise ValueError(f"{len(categories)} categories for {observation_size} dimensions")
        first = make_encoder(encoder, observation_size, categories, cell_layout, encoder_size)
        self.encoder = nn.Sequential(first, nn.ReLU())
        self.memory = memory
        # A hidden layer between memory and outputs (as in SB3's RecurrentPPO): with linear
        # heads, LSTM-PPO barely learns to condition on small-scale inputs such as CartPole's.
        # The heads see the memory output and the current observation's features: a memory
        # that skips observations (the causal memory) must never hide the present one.
        head_input = memory.output_size + encoder_size
        self.actor = self._head(head_input, encoder_size, num_actions, 0.01)
        self.critic = self._head(head_input, encoder_size, 1, 1.0)

    @staticmethod
    def _head(in_size: int, hidden: int, out_size: int, std: float) -> nn.Sequential:
        return nn.Sequential(
            orthogonal_linear(in_size, hidden, np.sqrt(2)),
            nn.Tanh(),
            orthogonal_linear(hidden, out_size, std),
        )

    def policy_parameters(self) -> list[nn.Parameter]:
        """Parameters the RL loss trains: everything but the gate."""
        return [p for name, p in self.named_parameters() if not name.startswith("gate.")]

    def initial_state(self, batch_size: int) -> torch.Tensor:
        """Zero memory state, (batch_size, memory.state_size)."""
        return self.memory.initial_state(batch_size)

    @property
    def input_size(self) -> int:
        """D_obs + the memory's side inputs: the width of what :meth:`forward` takes per step."""
        return self.observation_size + self.memory.side_size

    def memory_input(
        self, inputs: torch.Tensor, valid: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The memory's input (..., D + side) and the encoder's features (..., E) of agent
        inputs (..., D_obs + side). With `valid` (the leading dims' bool mask of real steps),
        padding steps get zero features and cost no encoder time: a DMC step on 32 BabyAI
        episodes (one of 80 steps, 31 of 20) took 0.201 s without the mask, 0.058 s with it."""
        obs = inputs[..., : self.observation_size]
        features = _on_valid_steps(self.encoder, obs, valid)
        side = inputs[..., self.observation_size :]
        own = obs if self.memory.reads_observation else features
        return torch.cat((own, side), dim=-1), features

    def forward(
        self, inputs: torch.Tensor, state: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Run whole sequences.

        Args:
            inputs: (B, L, D_obs + side) observations and side inputs (:attr:`input_size`).
            state: (B, S) memory state before the first step.

        Returns:
            logits (B, L, A), values (B, L) and the final state (B, S).
        """
        memory_input, features, keep = self._memory_args(inputs)
        out, state = self.memory(memory_input, state, keep)
        return *self._heads(out, features), state

    def evaluate(
        self, inputs: torch.Tensor, state: torch.Tensor, valid: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`forward` without the final state, for training passes: logits (B, L, A) and
        values (B, L). `valid` (B, L): the real steps of right-padded sequences; the outputs at
        the others are meaningless (padding skips the encoder)."""
        memory_input, features, keep = self._memory_args(inputs, valid)
        return self._heads(self.memory.outputs(memory_input, state, keep), features)

    def _memory_args(
        self, inputs: torch.Tensor, valid: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The memory's input, the encoder's features and the gate's keep mask (B, L).
        Padding steps cost no gate time either: the gate was 40% of a T-HCI-DMC run's time
        on BabyAI-L1 (py-spy), most of it on the padding of 32-episode batches."""
        memory_input, features = self.memory_input(inputs, valid)
        if self.gate is None:
            return memory_input, features, None
        obs = inputs[..., : self.observation_size]
        return memory_input, features, _on_valid_steps(self.gate.keep, obs, valid)

    def _heads(
        self, out: torch.Tensor, features: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Logits and values from the memory's outputs and the encoder's features."""
        out = torch.cat((out, features), dim=-1)
        return self.actor(out), self.critic(out).squeeze(-1)

    def step(
        self, obs: torch.Tensor, state: torch.Tensor, episode_start: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One step for N environments, zeroing the state where an episode starts.

        Args:
            obs: (N, D_obs + side) agent inputs; state: (N, S); episode_start: (N,) bool.

        Returns:
            logits (N, A), values (N,), new state (N, S).
        """
        state = state * (~episode_start).unsqueeze(1).to(state.dtype)
        logits, values, state = self(obs.unsqueeze(1), state)
        return logits.squeeze(1), values.squeeze(1), state


def _on_valid_steps(
    function: Callable[[torch.Tensor], torch.Tensor | None],
    obs: torch.Tensor,
    valid: torch.Tensor | None,
) -> torch.Tensor | None:
    """`function` of (..., D) observations -> (..., *out), evaluated on the real steps only
    (`valid`: the leading dims' bool mask; None: all real); padding gets zeros (False). A
    None result (e.g. an inactive gate: keep everything) is passed on."""
    if valid is None or bool(valid.all()):
        return function(obs)
    real = function(obs[valid])
    if real is None:
        return None
    out = real.new_zeros(*valid.shape, *real.shape[1:])
    out[valid] = real
    return out

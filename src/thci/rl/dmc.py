"""Deep Monte Carlo (DMC): Q(h, a) regressed on the Monte-Carlo returns of whole episodes.

DMC (Sutton & Barto 2018, ch. 5; at scale in DouZero, Zha et al. 2021) is one of the paper's
three RL algorithms. The agent's policy head outputs Q(h_t, ·), one value per action (its value
head is unused); the collector acts epsilon-greedily on it (``--dmc-epsilon``) and adds no
truncation bootstrap. The episodes that *finished* in a rollout — whole, however many rollouts
they spanned (:class:`thci.rl.episodes.EpisodeAssembler`) — join a FIFO buffer of the last
``--dmc-buffer-episodes`` episodes with their returns, as DouZero's learner samples the episodes
its actors leave in shared buffers. Each update takes ``--dmc-gradient-steps`` gradient
steps, each on ``--dmc-batch-episodes`` episodes drawn from the buffer without replacement,
runs the memory over each from its first step and a zero state, and minimizes

    L = mean over steps of ½ (Q(h_t, a_t) − G_t)²,   G_t = Σ_{k≥0} γ^k r_{t+k},

the return to the episode's end (intrinsic rewards included when exploration adds them).
With ``--dmc-n-step N`` > 0 the target is bootstrapped N steps on instead (:func:`n_step_targets`),
an option that leaves Monte Carlo: on BabyAI-L1 Q must read the signpost at the one choice step,
and the Monte-Carlo targets of the ~97% of steps before it carry the choice's outcome, a guess
no Q can predict there, which drowns that step's gradient (docs/babyai.md). The bootstrap
comes from the network being fitted, or with ``--dmc-target-every K`` from a copy of it
refreshed every K gradient steps (DQN's target network), so the targets hold still between
refreshes.

Why a buffer: regressing on only the ~25 episodes of one rollout (BabyAI-L1, 16 envs × 128
steps), Q overrated whatever the greedy action was (returns ×100 in that diagnostic: `right`
rated 1.18 against its mean return 0.38, while `forward` returned 1.11), the greedy policy
turned in place and success fell from random play's 0.06 to 0 (mlp memory, 150k steps; lower
learning rates, Adam's eps, dueling heads, epsilon and gamma changed nothing). Fitted offline
on 96 such episodes, the same network ranked the actions as their returns do (forward 1.10,
the others 0.38-0.41). With a 256-episode buffer, success rose to the memoryless optimum
(0.45) within 75k steps (docs/babyai.md, "DMC with an episode buffer").

Epsilon starts at ``--dmc-epsilon-start`` (1: uniformly random) and falls linearly to
``--dmc-epsilon`` over ``--dmc-epsilon-decay`` env steps (:func:`epsilon_at`), as in DQN. A
fixed small epsilon does not work with sparse rewards: before the first reward every Q-value
regresses to 0, the greedy action is an arbitrary constant (walking into a wall), and on Maze
L1 no goal was reached in 120k steps at epsilon 0.1.
"""

from __future__ import annotations

import copy
from collections import deque

import numpy as np
import torch
from torch import nn

from thci.config import TrainConfig
from thci.errors import ThciError
from thci.rl.agent import ActorCritic
from thci.rl.episodes import EpisodeAssembler
from thci.rl.rollout import Rollout


def monte_carlo_returns(rewards: torch.Tensor, valid: torch.Tensor, gamma: float) -> torch.Tensor:
    """Discounted returns to the end of each episode.

    Args:
        rewards: (E, L) rewards of E whole episodes, padded after their end.
        valid: (E, L) bool, False on padding.
        gamma: discount.

    Returns:
        (E, L) G_t (0 on padding).
    """
    returns = torch.zeros_like(rewards)
    running = torch.zeros(rewards.shape[0])
    rewards = rewards * valid
    for t in reversed(range(rewards.shape[1])):  # a scan over time, vectorized over episodes
        running = rewards[:, t] + gamma * running
        returns[:, t] = running
    return returns


def n_step_targets(
    returns: torch.Tensor, q_taken: torch.Tensor, valid: torch.Tensor, gamma: float, n: int
) -> torch.Tensor:
    """Targets bootstrapped `n` steps on: G_t − γ^n G_{t+n} + γ^n Q(h_{t+n}, a_{t+n}), i.e. the
    n rewards from t and then Q of the action taken n steps later (SARSA-style: the buffer's own
    actions); G_t itself where the episode ends within n steps. n = 0 gives G_t (Monte Carlo).

    Args:
        returns: (E, L) Monte-Carlo returns G_t of E episodes, 0 on padding.
        q_taken: (E, L) Q(h_t, a_t); gradients do not flow into the bootstrap.
        valid: (E, L) bool, False on padding.
        gamma: discount.
        n: bootstrap horizon in steps (>= 0).

    Returns:
        (E, L) targets.
    """
    if n == 0:
        return returns
    later_returns = torch.zeros_like(returns)
    later_q = torch.zeros_like(returns)
    later_valid = torch.zeros_like(valid)
    later_returns[:, :-n] = returns[:, n:]
    later_q[:, :-n] = q_taken.detach()[:, n:]
    later_valid[:, :-n] = valid[:, n:]
    discount = gamma**n
    return torch.where(later_valid, returns - discount * (later_returns - later_q), returns)


def epsilon_at(config: TrainConfig, global_step: int) -> float:
    """DMC's exploration rate after `global_step` env steps (linear decay, then constant)."""
    if global_step >= config.dmc_epsilon_decay:
        return config.dmc_epsilon
    fraction = global_step / config.dmc_epsilon_decay
    return config.dmc_epsilon_start + fraction * (config.dmc_epsilon - config.dmc_epsilon_start)


class DMC:
    """Monte-Carlo Q regression on whole episodes for a recurrent :class:`ActorCritic`.

    Args:
        config: dmc_gradient_steps per update, each on dmc_batch_episodes episodes of the
            dmc_buffer_episodes kept; gamma, max_grad_norm.
        num_envs: N, the rollouts' width.
    """

    def __init__(self, config: TrainConfig, num_envs: int) -> None:
        self.config = config
        self.assembler = EpisodeAssembler(num_envs)
        # Each episode: obs (L, D), actions (L,), returns (L,) — returns fixed when it ends.
        self.buffer: deque[dict[str, torch.Tensor]] = deque(maxlen=config.dmc_buffer_episodes)
        self.gradient_steps = 0  # taken so far: when to refresh the target network
        self.target: ActorCritic | None = None  # --dmc-target-every's copy of the agent
        self._target_weights: dict[str, torch.Tensor] | None = None  # from a checkpoint

    def add(self, rollout: Rollout) -> int:
        """Move the episodes that ended in `rollout` into the buffer; returns how many ended."""
        steps = {
            "obs": rollout.inputs.numpy(),  # with the memory's side inputs (rl/rollout.py)
            "actions": rollout.actions.numpy(),
            "rewards": rollout.rewards.numpy(),
        }
        episodes = [piece for _, _, piece in self.assembler.add(steps, rollout.dones.numpy())]
        if episodes:
            rewards, valid = _padded([torch.as_tensor(e["rewards"]) for e in episodes])
            returns = monte_carlo_returns(rewards, valid, self.config.gamma)
            for episode, episode_returns, mask in zip(episodes, returns, valid, strict=True):
                # Copies: a view would pin (and checkpoint) its whole rollout.
                self.buffer.append(
                    {
                        "obs": torch.tensor(episode["obs"]),
                        "actions": torch.tensor(episode["actions"]),
                        "returns": episode_returns[mask],
                    }
                )
        return len(episodes)

    def update(
        self, agent: ActorCritic, optimizer: torch.optim.Optimizer, rollout: Rollout
    ) -> dict[str, float]:
        """Add the rollout's finished episodes to the buffer, then take the gradient steps."""
        self.add(rollout)
        return self._fit(agent, optimizer, self.config.dmc_gradient_steps)

    def refit(self, agent: ActorCritic, optimizer: torch.optim.Optimizer) -> dict[str, float]:
        """``--dmc-refit-steps`` gradient steps on the buffer alone, when the memory has just
        changed under Q (a new T-HCI gate): the greedy policy must not act on a Q fitted to
        the old memory."""
        self.target = self._target_weights = None  # the bootstrap must read the new memory too
        return self._fit(agent, optimizer, self.config.dmc_refit_steps)

    def _fit(
        self, agent: ActorCritic, optimizer: torch.optim.Optimizer, steps: int
    ) -> dict[str, float]:
        """`steps` gradient steps, each on dmc_batch_episodes episodes from the buffer."""
        cfg = self.config
        if not self.buffer or steps == 0:  # nothing to regress on yet
            return {"q_loss": float("nan"), "q_mean": float("nan")}
        batch_size = min(cfg.dmc_batch_episodes, len(self.buffer))
        losses, q_means = [], []
        for _ in range(steps):
            which = torch.randperm(len(self.buffer))[:batch_size].tolist()
            batch = [self.buffer[i] for i in which]
            obs, valid = _padded([e["obs"] for e in batch])
            actions, _ = _padded([e["actions"] for e in batch])
            returns, _ = _padded([e["returns"] for e in batch])
            q_values, _ = agent.evaluate(obs, agent.initial_state(batch_size), valid)
            q_taken = q_values.gather(-1, actions.unsqueeze(-1)).squeeze(-1)
            bootstrap = self._bootstrap_q(agent, obs, actions, valid, q_taken)
            targets = n_step_targets(returns, bootstrap, valid, cfg.gamma, cfg.dmc_n_step)
            q = q_taken[valid]
            loss = 0.5 * (q - targets[valid]).pow(2).mean()
            if not torch.isfinite(loss):
                raise ThciError(
                    "DMC loss became NaN/inf: lower --learning-rate or --max-grad-norm, "
                    "or check the environment's rewards and observations"
                )
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(agent.parameters(), cfg.max_grad_norm)
            optimizer.step()
            self.gradient_steps += 1
            losses.append(loss.item())
            q_means.append(q.mean().item())
        return {"q_loss": float(np.mean(losses)), "q_mean": float(np.mean(q_means))}

    def _bootstrap_q(
        self,
        agent: ActorCritic,
        obs: torch.Tensor,
        actions: torch.Tensor,
        valid: torch.Tensor,
        q_taken: torch.Tensor,
    ) -> torch.Tensor:
        """Q(h_t, a_t) for the n-step targets, (E, L): the fitted network's own `q_taken`, or
        with --dmc-target-every K the target network's, refreshed from `agent` every K steps."""
        every = self.config.dmc_target_every
        if not every:
            return q_taken
        if self.target is None:  # built once (and after a new gate); refreshes copy weights
            self.target = copy.deepcopy(agent).requires_grad_(False)
        if self.gradient_steps % every == 0:
            self.target.load_state_dict(agent.state_dict())
        elif self._target_weights is not None:  # resumed between refreshes
            self.target.load_state_dict(self._target_weights)
        self._target_weights = None
        with torch.no_grad():
            q_values, _ = self.target.evaluate(obs, self.target.initial_state(len(obs)), valid)
        return q_values.gather(-1, actions.unsqueeze(-1)).squeeze(-1)

    def state_dict(self) -> dict:
        target = self._target_weights
        if self.target is not None:  # a snapshot: refreshes copy into the target's tensors
            target = {name: value.clone() for name, value in self.target.state_dict().items()}
        return {
            "pending": self.assembler.state_dict(),
            "buffer": list(self.buffer),
            "gradient_steps": self.gradient_steps,
            "target": target,
        }

    def load_state_dict(self, state: dict) -> None:
        self.assembler.load_state_dict(state["pending"])
        self.buffer.clear()
        self.buffer.extend(state.get("buffer", []))  # checkpoints from before the buffer
        self.gradient_steps = state.get("gradient_steps", 0)
        self.target, self._target_weights = None, state.get("target")


def _padded(sequences: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Sequences of lengths L_i (each (L_i, ...)) as one zero-padded (E, max L_i, ...) tensor,
    and the (E, max L_i) bool mask of real steps."""
    lengths = torch.tensor([len(s) for s in sequences])
    valid = torch.arange(int(lengths.max())).unsqueeze(0) < lengths.unsqueeze(1)
    return nn.utils.rnn.pad_sequence(sequences, batch_first=True), valid

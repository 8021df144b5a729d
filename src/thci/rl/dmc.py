"""Deep Monte Carlo (DMC): Q(h, a) regressed on the Monte-Carlo returns of whole episodes.

DMC (Sutton & Barto 2018, ch. 5; at scale in DouZero, Zha et al. 2021) is one of the paper's
three RL algorithms. The agent's policy head outputs Q(h_t, ·), one value per action (its value
head is unused); the collector acts epsilon-greedily on it (``--dmc-epsilon``) and adds no
truncation bootstrap. Each update takes the episodes that *finished* in the rollout — whole,
however many rollouts they spanned (:class:`thci.rl.episodes.EpisodeAssembler`) — runs the
memory over each from its first step and a zero state, and minimizes

    L = mean over steps of ½ (Q(h_t, a_t) − G_t)²,   G_t = Σ_{k≥0} γ^k r_{t+k},

the return to the episode's end (intrinsic rewards included when exploration adds them).

Epsilon starts at ``--dmc-epsilon-start`` (1: uniformly random) and falls linearly to
``--dmc-epsilon`` over ``--dmc-epsilon-decay`` env steps (:func:`epsilon_at`), as in DQN. A
fixed small epsilon does not work with sparse rewards: before the first reward every Q-value
regresses to 0, the greedy action is an arbitrary constant (walking into a wall), and on Maze
L1 no goal was reached in 120k steps at epsilon 0.1.
"""

from __future__ import annotations

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


def epsilon_at(config: TrainConfig, global_step: int) -> float:
    """DMC's exploration rate after `global_step` env steps (linear decay, then constant)."""
    if global_step >= config.dmc_epsilon_decay:
        return config.dmc_epsilon
    fraction = global_step / config.dmc_epsilon_decay
    return config.dmc_epsilon_start + fraction * (config.dmc_epsilon - config.dmc_epsilon_start)


class DMC:
    """Monte-Carlo Q regression on whole episodes for a recurrent :class:`ActorCritic`.

    Args:
        config: update_epochs, num_minibatches, gamma, max_grad_norm.
        num_envs: N, the rollouts' width.
    """

    def __init__(self, config: TrainConfig, num_envs: int) -> None:
        self.config = config
        self.assembler = EpisodeAssembler(num_envs)

    def update(
        self, agent: ActorCritic, optimizer: torch.optim.Optimizer, rollout: Rollout
    ) -> dict[str, float]:
        """Several epochs of minibatch updates on the episodes that ended in `rollout`."""
        cfg = self.config
        steps = {
            "obs": rollout.inputs.numpy(),  # with the memory's side inputs (rl/rollout.py)
            "actions": rollout.actions.numpy(),
            "rewards": rollout.rewards.numpy(),
        }
        episodes = [piece for _, _, piece in self.assembler.add(steps, rollout.dones.numpy())]
        if not episodes:  # every episode is still running: nothing to regress on yet
            return {"q_loss": float("nan"), "q_mean": float("nan")}
        obs, actions, rewards, valid = _pad(episodes)
        returns = monte_carlo_returns(rewards, valid, cfg.gamma)

        losses, q_means = [], []
        for _ in range(cfg.update_epochs):
            order = torch.randperm(len(episodes))
            for which in order.tensor_split(min(cfg.num_minibatches, len(episodes))):
                mask = valid[which]
                length = int(mask.sum(dim=1).max())
                mask = mask[:, :length]
                q_values, _ = agent.evaluate(obs[which, :length], agent.initial_state(len(which)))
                q = q_values.gather(-1, actions[which, :length].unsqueeze(-1)).squeeze(-1)[mask]
                loss = 0.5 * (q - returns[which, :length][mask]).pow(2).mean()
                if not torch.isfinite(loss):
                    raise ThciError(
                        "DMC loss became NaN/inf: lower --learning-rate or --max-grad-norm, "
                        "or check the environment's rewards and observations"
                    )
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), cfg.max_grad_norm)
                optimizer.step()
                losses.append(loss.item())
                q_means.append(q.mean().item())
        return {"q_loss": float(np.mean(losses)), "q_mean": float(np.mean(q_means))}

    def state_dict(self) -> dict:
        return {"pending": self.assembler.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.assembler.load_state_dict(state["pending"])


def _pad(
    episodes: list[dict[str, np.ndarray]],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Whole episodes as padded tensors: obs (E, L, D), actions (E, L), rewards (E, L), valid."""
    lengths = np.array([len(e["actions"]) for e in episodes])
    num, length = len(episodes), int(lengths.max())
    obs = np.zeros((num, length, *episodes[0]["obs"].shape[1:]), dtype=np.float32)
    actions = np.zeros((num, length), dtype=np.int64)
    rewards = np.zeros((num, length), dtype=np.float32)
    for i, episode in enumerate(episodes):  # a loop over episodes, each a block copy
        obs[i, : lengths[i]] = episode["obs"]
        actions[i, : lengths[i]] = episode["actions"]
        rewards[i, : lengths[i]] = episode["rewards"]
    valid = torch.arange(length).unsqueeze(0) < torch.as_tensor(lengths).unsqueeze(1)
    return torch.as_tensor(obs), torch.as_tensor(actions), torch.as_tensor(rewards), valid

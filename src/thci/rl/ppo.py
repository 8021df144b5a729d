"""Recurrent PPO (Schulman et al. 2017) and A2C (Mnih et al. 2016) on episode segments, with GAE.

Each update cuts the rollout into whole episode segments (:mod:`thci.rl.sequences`), runs the
agent once per minibatch of segments, and minimizes a policy loss plus the value and entropy
losses over the real (unpadded) steps. PPO: the clipped surrogate, several epochs of
minibatches. A2C: the plain policy gradient -A·log pi, one step on the whole rollout.
"""

from __future__ import annotations

import torch
from torch import nn

from thci.config import TrainConfig
from thci.errors import ThciError
from thci.rl.agent import ActorCritic
from thci.rl.rollout import Rollout
from thci.rl.sequences import cut_into_segments


def compute_gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    dones: torch.Tensor,
    last_value: torch.Tensor,
    gamma: float,
    gae_lambda: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalized advantage estimation over a (T, N) rollout.

    Args:
        rewards, values: (T, N). dones: (T, N) bool, episode ended with step t.
        last_value: (N,) value after the last step.

    Returns:
        advantages and returns (= advantages + values), both (T, N).
    """
    num_steps = rewards.shape[0]
    advantages = torch.zeros_like(rewards)
    next_value, next_advantage = last_value, torch.zeros_like(last_value)
    not_done = (~dones).to(rewards.dtype)
    for t in reversed(range(num_steps)):  # a scan over time, vectorized over environments
        delta = rewards[t] + gamma * next_value * not_done[t] - values[t]
        next_advantage = delta + gamma * gae_lambda * not_done[t] * next_advantage
        advantages[t] = next_advantage
        next_value = values[t]
    return advantages, advantages + values


class PPO:
    """Clipped-surrogate PPO update for a recurrent :class:`ActorCritic`."""

    def __init__(self, config: TrainConfig) -> None:
        self.config = config
        self.epochs, self.num_minibatches = config.update_epochs, config.num_minibatches

    def policy_loss(
        self, logprob: torch.Tensor, old_logprob: torch.Tensor, adv: torch.Tensor
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The clipped surrogate over n steps (all (n,)), and statistics to log."""
        clip = self.config.clip_coef
        log_ratio = logprob - old_logprob
        ratio = log_ratio.exp()
        loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - clip, 1 + clip)).mean()
        with torch.no_grad():
            stats = {
                "approx_kl": ((ratio - 1) - log_ratio).mean(),
                "clipfrac": ((ratio - 1).abs() > clip).float().mean(),
            }
        return loss, stats

    def update(
        self, agent: ActorCritic, optimizer: torch.optim.Optimizer, rollout: Rollout
    ) -> dict[str, float]:
        """Several epochs of minibatch updates on one rollout; returns mean losses and stats."""
        cfg = self.config
        advantages, returns = compute_gae(
            rollout.rewards,
            rollout.values,
            rollout.dones,
            rollout.last_value,
            cfg.gamma,
            cfg.gae_lambda,
        )
        segments = cut_into_segments(rollout.episode_starts)
        inputs = rollout.inputs  # observations and the memory's side inputs (rl/rollout.py)
        stats: dict[str, list[float]] = {}
        for _ in range(self.epochs):
            for which in segments.minibatches(self.num_minibatches):
                batch = segments.select(which)
                state = torch.where(
                    batch.continues.unsqueeze(1),
                    rollout.initial_state[batch.column],
                    agent.initial_state(len(batch.column)),
                )
                mask = batch.valid
                logits, values = agent.evaluate(batch.gather(inputs), state, mask)
                dist = torch.distributions.Categorical(logits=logits[mask])
                logprob = dist.log_prob(batch.gather(rollout.actions)[mask])
                adv = batch.gather(advantages)[mask]
                if cfg.norm_adv and adv.numel() > 1:
                    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
                policy_loss, policy_stats = self.policy_loss(
                    logprob, batch.gather(rollout.logprobs)[mask], adv
                )
                value_loss = 0.5 * (values[mask] - batch.gather(returns)[mask]).pow(2).mean()
                entropy = dist.entropy().mean()
                loss = policy_loss + cfg.vf_coef * value_loss - cfg.ent_coef * entropy
                if not torch.isfinite(loss):
                    raise ThciError(
                        f"{type(self).__name__} loss became NaN/inf: lower --learning-rate or "
                        "--max-grad-norm, or check the environment's rewards and observations"
                    )

                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), cfg.max_grad_norm)
                optimizer.step()

                for name, value in (
                    ("policy_loss", policy_loss),
                    ("value_loss", value_loss),
                    ("entropy", entropy),
                    *policy_stats.items(),
                ):
                    stats.setdefault(name, []).append(value.item())
        result = {name: sum(v) / len(v) for name, v in stats.items()}
        variance = returns.var()
        result["explained_variance"] = float(
            1 - (returns - rollout.values).var() / variance if variance > 0 else float("nan")
        )
        return result

    def state_dict(self) -> dict:
        """Nothing carries over between rollouts (DMC's episodes do)."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


class A2C(PPO):
    """Synchronous advantage actor-critic: one gradient step per rollout on all of it."""

    def __init__(self, config: TrainConfig) -> None:
        super().__init__(config)
        self.epochs, self.num_minibatches = 1, 1

    def policy_loss(
        self, logprob: torch.Tensor, old_logprob: torch.Tensor, adv: torch.Tensor
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """-A · log pi(a|h), averaged over the n steps."""
        return -(adv * logprob).mean(), {}

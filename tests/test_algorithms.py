"""A2C and DMC against hand computation; whole episodes across rollouts; epsilon-greedy."""

import copy

import numpy as np
import pytest
import torch

from thci.config import TrainConfig
from thci.errors import ThciError
from thci.memory import make_memory
from thci.rl.agent import ActorCritic
from thci.rl.dmc import DMC, epsilon_at, monte_carlo_returns, n_step_targets
from thci.rl.episodes import EpisodeAssembler
from thci.rl.ppo import A2C
from thci.rl.rollout import Rollout


def test_monte_carlo_returns_match_hand_computation():
    rewards = torch.tensor([[1.0, 0.0, 2.0], [0.0, 5.0, 9.0]])
    valid = torch.tensor([[True, True, True], [True, True, False]])  # 9.0 is padding
    got = monte_carlo_returns(rewards, valid, gamma=0.5)
    expected = torch.tensor([[1 + 0.5 * (0 + 0.5 * 2), 0 + 0.5 * 2, 2], [2.5, 5, 0]])
    assert torch.allclose(got, expected)


def test_assembler_joins_episodes_across_rollouts_and_restores():
    assembler = EpisodeAssembler(num_envs=2)
    steps = {"x": np.arange(6).reshape(3, 2)}  # (T=3, N=2): env 0 gets 0, 2, 4; env 1: 1, 3, 5
    dones = np.array([[False, True], [False, False], [False, False]])
    finished = assembler.add(steps, dones)
    assert [(n, t, p["x"].tolist()) for n, t, p in finished] == [(1, 0, [1])]
    restored = EpisodeAssembler(num_envs=2)
    restored.load_state_dict(assembler.state_dict())
    dones = np.array([[True, False], [False, False], [False, True]])
    finished = restored.add({"x": 10 + np.arange(6).reshape(3, 2)}, dones)
    assert [(n, t, p["x"].tolist()) for n, t, p in finished] == [
        (0, 0, [0, 2, 4, 10]),  # began in the first rollout
        (1, 2, [3, 5, 11, 13, 15]),
    ]


def _rollout(obs, actions, rewards, dones) -> Rollout:
    """A (T, N) rollout with the fields the updates read; the rest zeros."""
    T, N = actions.shape
    zeros = torch.zeros(T, N)
    starts = torch.zeros(T, N, dtype=torch.bool)
    starts[0] = True
    starts[1:] = dones[:-1]
    return Rollout(
        obs=obs,
        actions=actions,
        logprobs=zeros,
        values=zeros,
        rewards=rewards,
        dones=dones,
        episode_starts=starts,
        initial_state=torch.zeros(N, 2 * 8),
        last_value=torch.zeros(N),
        env_rewards=rewards,
        final_obs=torch.zeros_like(obs),
        causal=None,
        final_causal=None,
        reached_info={},
    )


def _agent() -> ActorCritic:
    torch.manual_seed(0)
    return ActorCritic(3, 2, make_memory("lstm", 4, 8), 4)


@pytest.mark.parametrize("n_step", [0, 1])
def test_dmc_regresses_q_of_taken_actions_on_whole_episode_returns(n_step: int):
    agent = _agent()
    config = TrainConfig(gamma=0.5, dmc_gradient_steps=1, max_grad_norm=1e9, dmc_n_step=n_step)
    dmc = DMC(config, num_envs=1)
    obs = torch.randn(4, 1, 3)
    actions = torch.tensor([[1], [0], [1], [1]])
    rewards = torch.tensor([[0.0], [1.0], [3.0], [7.0]])
    # first rollout: the episode (steps 0-1 here, 2 of the next rollout) is unfinished
    first = _rollout(obs[:2], actions[:2], rewards[:2], torch.zeros(2, 1, dtype=torch.bool))
    optimizer = torch.optim.SGD(agent.parameters(), lr=0.0)  # lr 0: the loss is all we read
    assert np.isnan(dmc.update(agent, optimizer, first)["q_loss"])
    dones = torch.tensor([[True], [False]])  # ends with step 0 of the second rollout
    second = _rollout(obs[2:], actions[2:], rewards[2:], dones)
    losses = dmc.update(agent, optimizer, second)
    # by hand: Q over the whole episode (obs 0..2) from a zero state, G = [0+.5*1+.25*3, 1+.5*3, 3]
    q, _, _ = agent(obs[:3, 0].unsqueeze(0), agent.initial_state(1))
    taken = q[0, torch.arange(3), actions[:3, 0]]
    returns = torch.tensor([1.25, 2.5, 3.0])
    if n_step == 1:  # --dmc-n-step 1: r_t + γ Q(h_{t+1}, a_{t+1}), the last step's G
        returns = torch.stack([0 + 0.5 * taken[1], 1 + 0.5 * taken[2], torch.tensor(3.0)])
    assert losses["q_loss"] == pytest.approx(0.5 * (taken - returns).pow(2).mean().item(), rel=1e-5)


def test_dmc_target_network_holds_the_bootstrap_between_refreshes_and_resumes():
    """--dmc-target-every 3: steps 0-2 bootstrap from the agent as it was before step 0, step 3
    from the agent as it is then; a DMC restored from a checkpoint bootstraps the same way."""
    config = TrainConfig(
        gamma=0.5, dmc_gradient_steps=1, max_grad_norm=1e9, dmc_n_step=1, dmc_target_every=3
    )
    obs = torch.randn(3, 1, 3)
    actions = torch.tensor([[1], [0], [1]])
    rewards = torch.tensor([[0.0], [1.0], [3.0]])
    episode = _rollout(obs, actions, rewards, torch.tensor([[False], [False], [True]]))
    nothing_new = _rollout(obs[:1], actions[:1], rewards[:1], torch.tensor([[False]]))

    def expected_loss(agent: ActorCritic, target: ActorCritic) -> float:
        def taken(net: ActorCritic) -> torch.Tensor:
            q, _, _ = net(obs[:, 0].unsqueeze(0), net.initial_state(1))
            return q[0, torch.arange(3), actions[:, 0]]

        online, frozen = taken(agent), taken(target).detach()
        targets = torch.stack([0 + 0.5 * frozen[1], 1 + 0.5 * frozen[2], torch.tensor(3.0)])
        return 0.5 * (online - targets).pow(2).mean().item()

    agent = _agent()
    optimizer = torch.optim.SGD(agent.parameters(), lr=0.5)
    dmc = DMC(config, num_envs=1)
    dmc.add(episode)  # one finished episode: every step fits it
    snapshot = copy.deepcopy(agent)
    for step in range(4):
        if step == 3:  # refreshed: the agent after three steps
            snapshot = copy.deepcopy(agent)
        want = expected_loss(agent, snapshot)
        got = dmc.update(agent, optimizer, nothing_new)["q_loss"]
        assert got == pytest.approx(want, rel=1e-5), step
        if step == 1:  # the online network has moved, so the two bootstraps now differ
            assert want != pytest.approx(expected_loss(agent, agent), rel=1e-3)
            resumed = DMC(config, num_envs=1)
            resumed.load_state_dict(dmc.state_dict())
            twin, twin_optimizer = copy.deepcopy(agent), copy.deepcopy(optimizer.state_dict())
    # the restored DMC, two steps behind, follows the same schedule from the same target
    twin_opt = torch.optim.SGD(twin.parameters(), lr=0.5)
    twin_opt.load_state_dict(twin_optimizer)
    for _ in range(2):
        resumed.update(twin, twin_opt, nothing_new)
    for a, b in zip(twin.parameters(), agent.parameters(), strict=True):
        assert torch.allclose(a, b, atol=1e-6)


def test_n_step_targets_bootstrap_from_q_of_the_action_taken_n_steps_later():
    # rewards [0, 1, 3] with gamma 0.5 give G = [1.25, 2.5, 3]; a second episode of one step
    returns = torch.tensor([[1.25, 2.5, 3.0], [4.0, 0.0, 0.0]])
    valid = torch.tensor([[True, True, True], [True, False, False]])
    q = torch.tensor([[10.0, 20.0, 30.0], [40.0, 0.0, 0.0]], requires_grad=True)
    one = n_step_targets(returns, q, valid, 0.5, 1)
    # by hand: r_0 + γ Q_1 = 0 + 10, r_1 + γ Q_2 = 1 + 15, then the episodes' last steps: G
    assert one.tolist() == [[10.0, 16.0, 3.0], [4.0, 0.0, 0.0]]
    two = n_step_targets(returns, q, valid, 0.5, 2)
    assert two[0].tolist() == [0 + 0.5 * 1 + 0.25 * 30, 2.5, 3.0]
    assert not one.requires_grad  # the bootstrap is a target, not a path for gradients
    for monte_carlo in (0, 3, 10):  # no bootstrap, or none within the episode
        assert torch.equal(n_step_targets(returns, q, valid, 0.5, monte_carlo), returns)


def _one_step_episodes(rewards: list[float], first: int = 0) -> Rollout:
    """A rollout of len(rewards) one-step episodes in one environment; each episode's
    observation holds its number (first, first + 1, ...)."""
    T = len(rewards)
    numbers = torch.arange(first, first + T, dtype=torch.float32)
    obs = numbers.view(T, 1, 1).expand(T, 1, 3).contiguous()
    actions = torch.zeros(T, 1, dtype=torch.long)
    dones = torch.ones(T, 1, dtype=torch.bool)
    return _rollout(obs, actions, torch.tensor(rewards).view(T, 1), dones)


def test_dmc_buffer_keeps_the_last_episodes_and_restores():
    config = TrainConfig(dmc_buffer_episodes=3)
    dmc = DMC(config, num_envs=1)
    assert dmc.add(_one_step_episodes([1.0, 2.0])) == 2
    assert dmc.add(_one_step_episodes([3.0, 4.0])) == 2
    # FIFO of 3: the first episode (return 1) was evicted
    assert [e["returns"].tolist() for e in dmc.buffer] == [[2.0], [3.0], [4.0]]
    restored = DMC(config, num_envs=1)
    restored.load_state_dict(dmc.state_dict())
    assert [e["returns"].tolist() for e in restored.buffer] == [[2.0], [3.0], [4.0]]


def test_dmc_buffer_copies_episodes_out_of_the_rollout():
    dmc = DMC(TrainConfig(), num_envs=2)
    T, N = 4, 2
    dones = torch.zeros(T, N, dtype=torch.bool)
    dones[1] = True  # each environment's first episode ends with step 1
    obs = torch.randn(T, N, 3)
    dmc.add(_rollout(obs, torch.zeros(T, N, dtype=torch.long), torch.zeros(T, N), dones))
    for n, episode in enumerate(dmc.buffer):
        assert torch.equal(episode["obs"], obs[:2, n])
        # its own storage: a view into the (T, N, D) rollout would keep (and checkpoint) it all
        assert episode["obs"].untyped_storage().nbytes() == episode["obs"].nbytes


def test_dmc_steps_on_distinct_buffered_episodes():
    agent = _agent()
    config = TrainConfig(dmc_gradient_steps=6, dmc_batch_episodes=4, dmc_refit_steps=3)
    dmc = DMC(config, num_envs=1)
    dmc.add(_one_step_episodes([0.0, 1.0, 2.0, 3.0, 4.0]))  # a first rollout's episodes
    seen: list[list[float]] = []
    evaluate = agent.evaluate

    def recording(inputs: torch.Tensor, state: torch.Tensor, valid: torch.Tensor):
        seen.append(inputs[:, 0, 0].tolist())  # each episode's obs holds its number
        return evaluate(inputs, state, valid)

    agent.evaluate = recording
    optimizer = torch.optim.SGD(agent.parameters(), lr=0.0)
    dmc.update(agent, optimizer, _one_step_episodes([5.0, 6.0], first=5))
    assert len(seen) == 6  # --dmc-gradient-steps
    for batch in seen:
        assert len(batch) == len(set(batch)) == 4  # without replacement
    # the batches come from the whole buffer: an earlier rollout's episodes and the new ones
    drawn = set().union(*map(set, seen))
    assert drawn <= set(range(7)) and drawn & {0, 1, 2, 3, 4} and drawn & {5, 6}
    dmc.refit(agent, optimizer)  # after a new gate: steps on the buffer, no new episodes
    assert len(seen) == 6 + 3 and len(dmc.buffer) == 7


def test_a2c_takes_one_policy_gradient_step_on_the_whole_rollout():
    agent = _agent()
    config = TrainConfig(gamma=0.9, gae_lambda=1.0, norm_adv=False, ent_coef=0.0, vf_coef=0.0)
    a2c = A2C(config)
    obs = torch.randn(3, 2, 3)
    actions = torch.tensor([[0, 1], [1, 1], [0, 0]])
    rewards = torch.tensor([[0.0, 1.0], [0.0, 0.0], [2.0, 0.0]])
    dones = torch.tensor([[False, True], [False, False], [True, False]])
    rollout = _rollout(obs, actions, rewards, dones)
    optimizer = torch.optim.SGD(agent.parameters(), lr=0.0)
    steps = []
    optimizer.register_step_post_hook(lambda *_: steps.append(1))
    losses = a2c.update(agent, optimizer, rollout)
    assert len(steps) == 1
    # values are 0 in the rollout, so the advantages are the discounted returns (GAE, lambda 1)
    adv = torch.tensor([[0.81 * 2, 1.0], [0.9 * 2, 0.0], [2.0, 0.0]])
    logits_0, _, _ = agent(obs[:, 0].unsqueeze(0), agent.initial_state(1))
    logits_1a, _, _ = agent(obs[:1, 1].unsqueeze(0), agent.initial_state(1))
    logits_1b, _, _ = agent(obs[1:, 1].unsqueeze(0), agent.initial_state(1))
    logp = torch.cat(
        (
            logits_0[0].log_softmax(-1)[torch.arange(3), actions[:, 0]],
            logits_1a[0].log_softmax(-1)[0, actions[0, 1]].view(1),
            logits_1b[0].log_softmax(-1)[torch.arange(2), actions[1:, 1]],
        )
    )
    flat_adv = torch.cat((adv[:, 0], adv[:1, 1], adv[1:, 1]))
    assert losses["policy_loss"] == pytest.approx(-(flat_adv * logp).mean().item(), rel=1e-5)
    assert len(losses) >= 3 and "clipfrac" not in losses  # no PPO statistics


def test_dmc_epsilon_decays_linearly_then_stays():
    config = TrainConfig(algo="dmc", dmc_epsilon_start=1.0, dmc_epsilon=0.1, dmc_epsilon_decay=1000)
    assert epsilon_at(config, 0) == 1.0
    assert epsilon_at(config, 500) == pytest.approx(0.55)
    assert epsilon_at(config, 1000) == pytest.approx(0.1)
    assert epsilon_at(config, 10**6) == pytest.approx(0.1)
    assert epsilon_at(TrainConfig(algo="dmc", dmc_epsilon_decay=0), 0) == 0.1  # no decay


def test_only_ppo_needs_a_minibatch_per_environment():
    """PPO splits a rollout's sequences into --num-minibatches groups, so it needs at least as
    many environments; A2C (one batch) and DMC (its own episode batches) do not."""
    with pytest.raises(ThciError, match="--num-minibatches \\(8\\) cannot exceed --num-envs"):
        TrainConfig(algo="ppo", num_envs=4, num_minibatches=8).validate()
    for algo in ("a2c", "dmc"):
        TrainConfig(algo=algo, num_envs=4, num_minibatches=8).validate()

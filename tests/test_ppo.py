"""GAE against hand computation; memories: sequence calls equal step-by-step calls."""

import pytest
import torch

from thci.memory import make_memory
from thci.rl.agent import ActorCritic
from thci.rl.ppo import compute_gae


def test_gae_matches_hand_computation():
    gamma, lam = 0.9, 0.5
    rewards = torch.tensor([[1.0], [0.0], [2.0]])
    values = torch.tensor([[0.5], [1.0], [1.5]])
    dones = torch.tensor([[False], [True], [False]])
    last_value = torch.tensor([3.0])
    advantages, returns = compute_gae(rewards, values, dones, last_value, gamma, lam)
    d2 = 2.0 + gamma * 3.0 - 1.5
    d1 = 0.0 - 1.0  # episode ended: no bootstrap
    d0 = 1.0 + gamma * 1.0 - 0.5
    expected = torch.tensor([[d0 + gamma * lam * d1], [d1], [d2]])
    assert torch.allclose(advantages, expected)
    assert torch.allclose(returns, expected + values)


@pytest.mark.parametrize("method", ["lstm", "gru"])
def test_sequence_call_equals_step_loop_with_resets(method):
    torch.manual_seed(0)
    agent = ActorCritic(6, 3, make_memory(method, 8, 16), 8)
    obs = torch.randn(4, 9, 6)
    starts = torch.zeros(4, 9, dtype=torch.bool)
    starts[:, 0] = True
    starts[1, 5] = True
    state = agent.initial_state(4)
    step_logits = []
    for t in range(9):
        logits, _, state = agent.step(obs[:, t], state, starts[:, t])
        step_logits.append(logits)
    step_logits = torch.stack(step_logits, 1)
    # The same sequences cut at the episode start of env 1 give the same outputs.
    seq_logits, _, _ = agent(obs, agent.initial_state(4))
    assert torch.allclose(seq_logits[[0, 2, 3]], step_logits[[0, 2, 3]], atol=1e-6)
    assert torch.allclose(seq_logits[1, :5], step_logits[1, :5], atol=1e-6)
    tail, _, _ = agent(obs[1:2, 5:], agent.initial_state(1))
    assert torch.allclose(tail[0], step_logits[1, 5:], atol=1e-6)
    assert not torch.allclose(seq_logits[1, 5:], step_logits[1, 5:], atol=1e-4)
    # training passes (no final state) see exactly what a sequence call sees
    seq_logits, seq_values, _ = agent(obs, agent.initial_state(4))
    train_logits, train_values = agent.evaluate(obs, agent.initial_state(4))
    assert torch.equal(train_logits, seq_logits) and torch.equal(train_values, seq_values)


def test_episode_start_zeroes_state():
    torch.manual_seed(0)
    agent = ActorCritic(4, 2, make_memory("lstm", 8, 8), 8)
    obs = torch.randn(2, 4)
    busy = torch.randn(2, agent.memory.state_size)
    fresh_logits, _, _ = agent.step(obs, agent.initial_state(2), torch.ones(2, dtype=torch.bool))
    reset_logits, _, _ = agent.step(obs, busy, torch.ones(2, dtype=torch.bool))
    kept_logits, _, _ = agent.step(obs, busy, torch.zeros(2, dtype=torch.bool))
    assert torch.allclose(fresh_logits, reset_logits)
    assert not torch.allclose(fresh_logits, kept_logits)


def test_memoryless_policy_ignores_the_past():
    torch.manual_seed(0)
    agent = ActorCritic(4, 3, make_memory("mlp", 8, 8), 8)
    obs = torch.randn(2, 5, 4)
    other_past = obs.clone()
    other_past[:, :4] = torch.randn(2, 4, 4)
    logits, _, _ = agent(obs, agent.initial_state(2))
    other, _, _ = agent(other_past, agent.initial_state(2))
    assert torch.allclose(logits[:, 4], other[:, 4])
    assert not torch.allclose(logits[:, 3], other[:, 3])  # the present still matters

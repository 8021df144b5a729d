"""The rollout collector: truncation bootstrap, success reporting, generic gymnasium envs."""

import gymnasium as gym
import numpy as np
import pytest
import torch

from thci.envs.factory import make_vector_env
from thci.memory import make_memory
from thci.rl.agent import ActorCritic
from thci.rl.rollout import RolloutCollector


class ConstantEnv(gym.Env):
    """Observation always c; truncates after `horizon` steps, or terminates on action 1."""

    observation_space = gym.spaces.Box(-1, 1, (3,), np.float32)
    action_space = gym.spaces.Discrete(2)

    def __init__(self, horizon: int = 3):
        self.horizon, self.t = horizon, 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.array([0.5, -0.5, 0.25], np.float32), {}

    def step(self, action):
        self.t += 1
        terminated = int(action) == 1
        reward = 2.0 if terminated else 0.0
        obs = np.array([0.5, -0.5, 0.25], np.float32)
        return obs, reward, terminated, self.t >= self.horizon and not terminated, {}


gym.register("ThciTest/Constant-v0", entry_point=ConstantEnv)


def test_truncated_steps_are_bootstrapped_and_terminated_ones_are_not():
    torch.manual_seed(0)
    envs = make_vector_env("ThciTest/Constant-v0", 4)
    agent = ActorCritic(3, 2, make_memory("lstm", 8, 8), 8)
    collector = RolloutCollector(envs, agent, num_steps=12, gamma=0.9)
    collector.reset(seed=0)
    rollout, episodes = collector.collect()
    c = torch.tensor([0.5, -0.5, 0.25])
    checked = 0
    for t in range(12):
        for n in range(4):
            if not rollout.dones[t, n]:
                assert rollout.rewards[t, n] == 0
            elif rollout.actions[t, n] == 1:  # terminated: the raw reward only
                assert rollout.rewards[t, n] == 2.0
            else:  # truncated after 3 steps: + gamma * V(4th observation of the episode)
                with torch.no_grad():
                    _, values, _ = agent(c.expand(1, 4, 3), agent.initial_state(1))
                assert rollout.rewards[t, n] == pytest.approx(0.9 * float(values[0, 3]), abs=1e-5)
                checked += 1
    assert checked > 0
    assert all(e.success is None for e in episodes)
    envs.close()


def test_success_return_defines_success_for_envs_without_the_info_key():
    envs = make_vector_env("ThciTest/Constant-v0", 2)
    agent = ActorCritic(3, 2, make_memory("gru", 8, 8), 8)
    collector = RolloutCollector(envs, agent, num_steps=300, gamma=0.9, success_return=1.0)
    collector.reset(seed=1)
    _, episodes = collector.collect()
    assert {e.success for e in episodes} == {True, False}
    assert all(e.success == (e.reward >= 1.0) for e in episodes)
    envs.close()


def test_maze_episodes_report_success_from_info():
    envs = make_vector_env("thci/PaperMaze-L1-v0", 8)
    agent = ActorCritic(15, 4, make_memory("lstm", 8, 8), 8)
    collector = RolloutCollector(envs, agent, num_steps=200, gamma=0.99)
    collector.reset(seed=0)
    _, episodes = collector.collect()
    assert episodes and all(e.success is not None for e in episodes)
    # The maze rewards 1 exactly on success.
    assert all(e.success == (e.reward == 1.0) for e in episodes)
    assert all(1 <= e.length <= 30 for e in episodes)
    envs.close()

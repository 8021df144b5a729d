"""Intrinsic rewards against hand-computed cases."""

from types import SimpleNamespace

import numpy as np
import torch
from gymnasium import spaces

from thci.rl.exploration import (
    CountBonus,
    EpisodicCountBonus,
    EpisodicNoveltyBonus,
    MemoryContent,
)

SPACE = spaces.Box(0, 1, (3,))


def test_episodic_bonus_pays_first_visits_and_forgets_at_episode_end():
    bonus = EpisodicNoveltyBonus(SPACE, 0.5, num_envs=2)
    codes = np.array([[1, 5], [2, 5], [1, 5], [3, 6]])  # (T, N)
    dones = np.array([[0, 0], [0, 0], [1, 0], [0, 0]], dtype=bool)  # env 0 ends at t=2
    got = bonus.bonus(codes, dones)
    # env 0: 1 new, 2 new, 1 seen (then the episode ends), 3 new; env 1: 5 new, 5, 5, 6 new
    np.testing.assert_allclose(got, 0.5 * np.array([[1, 1], [1, 0], [0, 0], [1, 1]]))
    # the episode of env 1 continues into the next rollout; env 0's new episode has seen only 3
    got = bonus.bonus(np.array([[5, 5], [3, 6]]), np.zeros((2, 2), dtype=bool))
    np.testing.assert_allclose(got, 0.5 * np.array([[1, 0], [0, 0]]))


def test_episodic_bonus_state_round_trips():
    bonus = EpisodicNoveltyBonus(SPACE, 1.0, num_envs=1)
    bonus.bonus(np.array([[4]]), np.zeros((1, 1), dtype=bool))
    state = {
        k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in bonus.state_dict().items()
    }
    restored = EpisodicNoveltyBonus(SPACE, 1.0, num_envs=1)
    restored.load_state_dict(state)
    assert restored.bonus(np.array([[4]]), np.zeros((1, 1), dtype=bool))[0, 0] == 0.0


def test_count_bonus_is_beta_over_root_of_visits_so_far():
    bonus = CountBonus(SPACE, 1.0)
    got = bonus.bonus(np.array([[0, 1], [0, 0]]), np.zeros((2, 2), dtype=bool))
    # a rollout's visits are counted before paying: code 0 is reached 3 times, code 1 once
    np.testing.assert_allclose(got, [[1 / np.sqrt(3), 1.0], [1 / np.sqrt(3), 1 / np.sqrt(3)]])
    np.testing.assert_allclose(
        bonus.bonus(np.array([[1]]), np.zeros((1, 1), dtype=bool)), [[1 / np.sqrt(2)]]
    )


def test_episodic_count_bonus_pays_first_visits_by_run_wide_rarity():
    bonus = EpisodicCountBonus(SPACE, 1.0, num_envs=2)
    codes = np.array([[1, 5], [2, 5], [1, 5]])  # (T, N)
    dones = np.array([[0, 0], [0, 0], [0, 0]], dtype=bool)
    got = bonus.bonus(codes, dones)
    # every visit counts toward N (code 1: 2, code 2: 1, code 5: 3), only first visits pay
    np.testing.assert_allclose(got, [[1 / np.sqrt(2), 1 / np.sqrt(3)], [1.0, 0.0], [0.0, 0.0]])
    # env 1's episode continues (5 already visited); env 0 ends, and code 1 is new again
    got = bonus.bonus(np.array([[5, 5], [1, 7]]), np.array([[1, 0], [0, 0]], dtype=bool))
    np.testing.assert_allclose(got, [[1 / np.sqrt(5), 0.0], [1 / np.sqrt(3), 1.0]])
    state = bonus.state_dict()
    assert set(state) == {"discretizer", "memory", "counts", "visited"}


def _digests(memory, codes, kept, starts):
    """Digests of MemoryContent for (T, N) integer codes given as one-hot observations."""
    obs = torch.nn.functional.one_hot(torch.as_tensor(codes), 3).float()
    return memory.digests(obs, np.array(kept, dtype=bool), np.array(starts, dtype=bool))


def test_memory_content_identifies_the_set_kept_so_far_in_the_episode():
    memory = MemoryContent(SPACE, "auto", num_envs=2)
    # env 0 keeps code 0, then code 1, then code 0 again; env 1 keeps code 1, drops code 0,
    # then keeps code 0 (the same set as env 0's at t=1, reached in another order)
    codes = [[0, 1], [1, 0], [0, 0]]
    kept = [[1, 1], [1, 0], [1, 1]]
    starts = [[1, 1], [0, 0], [0, 0]]
    got = _digests(memory, codes, kept, starts)
    assert got[1, 0] != got[0, 0] != 0  # the set grew
    assert got[2, 0] == got[1, 0]  # code 0 was already held
    assert got[1, 1] == got[0, 1]  # a removed observation leaves the memory as it was
    assert got[2, 1] == got[1, 0]  # {0, 1} in either order
    # env 0 starts a new episode: its memory holds only what it keeps from then on ({1}, as
    # env 1's at t=0)
    assert _digests(memory, [[1, 2]], [[1, 0]], [[1, 0]])[0, 0] == got[0, 1]


def test_count_memory_counts_a_place_again_when_reached_remembering_something_new():
    bonus = EpisodicCountBonus(SPACE, 1.0, num_envs=1, memory=MemoryContent(SPACE, "auto", 1))
    rollout = SimpleNamespace(
        obs=torch.nn.functional.one_hot(torch.tensor([[0], [2], [1], [2]]), 3).float(),
        episode_starts=torch.tensor([[1], [0], [1], [0]], dtype=torch.bool),
        dones=torch.tensor([[0], [1], [0], [1]], dtype=torch.bool),
        final_obs=torch.nn.functional.one_hot(torch.tensor([[0], [2], [0], [2]]), 3).float(),
        rewards=torch.zeros(4, 1),
    )
    next_obs = torch.nn.functional.one_hot(torch.tensor([0]), 3).float()
    kept = np.array([[1], [0], [1], [0]], dtype=bool)  # the indicators 0 and 1 are kept
    # Both episodes reach the place 2 twice (every visit counts, only first visits in an
    # episode pay). Without the memory it is one code, reached 4 times; with it the second
    # episode reaches 2 remembering 1 instead of 0: another code, each reached twice.
    plain = EpisodicCountBonus(SPACE, 1.0, num_envs=1)
    plain_rollout = SimpleNamespace(**{**vars(rollout), "rewards": torch.zeros(4, 1)})
    plain.add_bonus(plain_rollout, next_obs)
    np.testing.assert_allclose(plain_rollout.rewards[:, 0].numpy(), [0.5, 0, 0.5, 0])
    bonus.add_bonus(rollout, next_obs, kept)
    np.testing.assert_allclose(rollout.rewards[:, 0].numpy(), [2**-0.5, 0, 2**-0.5, 0])


def test_each_gate_has_its_own_counts_of_memory_contents():
    """An empty memory before the first gate says nothing; under a gate that keeps {0} it says
    'not 0'. The same (place, empty memory) pair must pay again under the new gate, and a gate
    seen before resumes its counts."""
    bonus = EpisodicCountBonus(SPACE, 1.0, num_envs=1, memory=MemoryContent(SPACE, "auto", 1))
    obs = torch.nn.functional.one_hot(torch.tensor([[1], [2]]), 3).float()
    rollout = SimpleNamespace(
        obs=obs,
        episode_starts=torch.tensor([[1], [0]], dtype=torch.bool),
        dones=torch.tensor([[0], [1]], dtype=torch.bool),
        final_obs=obs,
        rewards=torch.zeros(2, 1),
    )
    next_obs = torch.nn.functional.one_hot(torch.tensor([1]), 3).float()
    kept = np.zeros((2, 1), dtype=bool)  # code 1 is never kept: the memory stays empty

    def first_visit_bonus() -> float:
        rollout.rewards = torch.zeros(2, 1)
        bonus.add_bonus(rollout, next_obs, kept)
        return float(rollout.rewards[0, 0])

    # place 2 is reached twice per rollout (at t=0 and at the episode's end); the first pays
    counts = [first_visit_bonus() ** -2 for _ in range(3)]
    np.testing.assert_allclose(counts, [2, 4, 6], rtol=1e-5)
    bonus.memory.set_gate(np.array([0]))
    np.testing.assert_allclose(first_visit_bonus() ** -2, 2, rtol=1e-5)  # new again
    bonus.memory.set_gate(np.array([4, 0]))
    np.testing.assert_allclose(first_visit_bonus() ** -2, 2, rtol=1e-5)
    bonus.memory.set_gate(np.array([0]))
    np.testing.assert_allclose(first_visit_bonus() ** -2, 4, rtol=1e-5)  # {0}'s count goes on
    bonus.memory.set_gate(np.array([], dtype=np.int64))
    np.testing.assert_allclose(first_visit_bonus() ** -2, 8, rtol=1e-5)  # as before any gate
    memory = MemoryContent(SPACE, "auto", 1)
    memory.load_state_dict(bonus.memory.state_dict())
    assert memory.gate_key == bonus.memory.gate_key

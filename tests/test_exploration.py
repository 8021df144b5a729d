"""Intrinsic rewards against hand-computed cases."""

import numpy as np
import torch
from gymnasium import spaces

from thci.rl.exploration import CountBonus, EpisodicCountBonus, EpisodicNoveltyBonus

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
    assert set(state) == {"discretizer", "counts", "visited"}

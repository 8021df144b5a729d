"""Planted-cause synthetic histories: structure, confounding strengths, reward, coverage."""

import time

import numpy as np
import pytest

from thci.causal.replay import pad_episodes
from thci.causal.synthetic import generate_planted_episodes, planted_reward
from thci.errors import ThciError


@pytest.fixture(scope="module")
def data():
    return generate_planted_episodes(
        num_codes=300,
        num_causal=3,
        num_episodes=4000,
        episode_length=12,
        confounders_per_cause=2,
        seed=7,
    )


def test_shapes_and_dtypes(data):
    assert len(data.episodes) == 4000
    for episode in data.episodes[:50]:
        assert episode.codes.shape == (13,) and episode.codes.dtype == np.int64
        assert episode.actions.shape == (12,) and episode.actions.dtype == np.int64
        assert episode.rewards.shape == (12,) and episode.rewards.dtype == np.float32
        assert episode.causal.shape == (13,) and episode.causal.dtype == np.bool_
        assert episode.length == 12
    arrays = pad_episodes(data.episodes)
    assert arrays.codes.min() >= 0 and arrays.codes.max() < data.num_codes
    assert set(np.unique(arrays.actions).tolist()) == {0, 1, 2, 3}
    assert data.causal_codes.shape == (3,) and data.confounder_codes.shape == (3, 2)
    assert data.on.shape == (4000, 3) and data.on.dtype == np.bool_


def test_causes_and_confounders_distinct_and_labels_match(data):
    planted = np.concatenate([data.causal_codes, data.confounder_codes.ravel()])
    assert len(set(planted.tolist())) == 9
    assert len(data.distractor_codes) == data.num_codes - 9
    arrays = pad_episodes(data.episodes)
    labels = np.stack([e.causal for e in data.episodes])
    assert (labels == np.isin(arrays.codes, data.causal_codes)).all()


def test_planted_steps_causes_early_and_before_their_confounders(data):
    codes = pad_episodes(data.episodes).codes  # (E, L + 1)
    for i, cause in enumerate(data.causal_codes):
        seen = codes == cause
        assert (seen.sum(1) == data.on[:, i]).all(), "observed exactly once iff on"
        assert not seen[:, 10:].any(), "only at steps 1..L-2"
        cause_step = np.where(data.on[:, i], seen.argmax(1), -1)
        for f in data.confounder_codes[i]:
            f_seen = codes == f
            assert f_seen.sum(1).max() <= 1 and not f_seen[:, 10:].any()
            both = data.on[:, i] & f_seen.any(1)
            assert (f_seen.argmax(1)[both] > cause_step[both]).all()


def test_confounders_follow_their_cause_with_0_9_and_0_1(data):
    codes = pad_episodes(data.episodes).codes
    for i in range(3):
        on = data.on[:, i]
        for f in data.confounder_codes[i]:
            f_seen = (codes == f).any(1)
            assert f_seen[on].mean() == pytest.approx(0.9, abs=0.03)
            assert f_seen[~on].mean() == pytest.approx(0.1, abs=0.03)


def test_last_reward_counts_the_observed_causes(data):
    arrays = pad_episodes(data.episodes)
    observed = np.stack([(arrays.codes == c).any(1) for c in data.causal_codes], axis=1)
    assert (observed == data.on).all()
    assert np.array_equal(arrays.rewards[:, -1], observed.sum(1).astype(np.float32))
    assert (arrays.rewards[:, :-1] == 0).all()
    # every cause matters: k + 1 distinct reward values
    assert sorted(np.unique(arrays.rewards[:, -1]).tolist()) == [0, 1, 2, 3]
    assert planted_reward(np.zeros((4, 0), bool)).tolist() == [0, 0, 0, 0]


def test_equal_seeds_equal_data_other_seed_differs():
    a = generate_planted_episodes(50, num_episodes=30, seed=1)
    b = generate_planted_episodes(50, num_episodes=30, seed=1)
    c = generate_planted_episodes(50, num_episodes=30, seed=2)
    assert (a.causal_codes == b.causal_codes).all()
    for x, y in zip(a.episodes, b.episodes, strict=True):
        assert (x.codes == y.codes).all() and (x.actions == y.actions).all()
        assert (x.rewards == y.rewards).all()
    assert not all((x.codes == z.codes).all() for x, z in zip(a.episodes, c.episodes, strict=True))


def test_coverage_grows_with_episodes():
    def coverage(num_episodes):
        d = generate_planted_episodes(2000, num_episodes=num_episodes, seed=3)
        return len(np.unique(pad_episodes(d.episodes).codes)) / d.num_codes

    small, medium, large = coverage(50), coverage(300), coverage(1500)
    assert small < medium < large
    # ≈ 1 - exp(-N / D) with N = E * (L + 1) draws
    assert small == pytest.approx(1 - np.exp(-50 * 13 / 2000), abs=0.05)
    assert large > 0.99


def test_large_generation_is_fast():
    start = time.perf_counter()
    d = generate_planted_episodes(100_000, num_causal=4, num_episodes=20_000, seed=0)
    assert time.perf_counter() - start < 2.0
    assert len(d.episodes) == 20_000


def test_impossible_sizes_are_one_line_errors():
    with pytest.raises(ThciError, match="distractor"):
        generate_planted_episodes(4, num_causal=2, confounders_per_cause=1)
    with pytest.raises(ThciError, match="too short"):
        generate_planted_episodes(100, num_causal=3, confounders_per_cause=3, episode_length=12)
    with pytest.raises(ThciError):
        generate_planted_episodes(100, num_causal=-1)

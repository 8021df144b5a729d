"""Tests for the Fig. 1 key-to-door env and the naive vs backdoor (Eq. 1) estimators."""

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import thci
from thci.causal.backdoor import (
    ConfoundingReport,
    backdoor_adjusted,
    confounding_report,
    naive_conditional,
)
from thci.causal.replay import PoolEpisode
from thci.envs import KeyDoorTVEnv
from thci.envs.key_door_tv import (
    BALL,
    CORRIDOR,
    DOOR_CLOSED,
    DOOR_OPEN,
    HALLWAY,
    KEY,
    NUM_CODES,
    TV,
    confounded_sampling_policy,
    sample_episodes,
)
from thci.errors import ThciError


def _play(env: KeyDoorTVEnv, start: int | None, first_action: int, seed: int | None = None):
    """One whole episode; returns the list of (code, reward, terminated, truncated, info)."""
    options = None if start is None else {"start_code": start}
    obs, info = env.reset(seed=seed, options=options)
    trace = [(int(np.argmax(obs)), 0.0, False, False, info)]
    for action in (first_action, 1, 1):
        obs, reward, terminated, truncated, info = env.step(action)
        assert obs.dtype == np.float32 and obs.shape == (NUM_CODES,) and obs.sum() == 1.0
        trace.append((int(np.argmax(obs)), reward, terminated, truncated, info))
        if terminated or truncated:
            break
    return trace


@pytest.mark.parametrize("first_action", [0, 1])
@pytest.mark.parametrize(
    ("start", "door", "reward"), [(KEY, DOOR_OPEN, 1.0), (BALL, DOOR_CLOSED, 0.0)]
)
def test_only_the_start_decides_the_door(start, door, reward, first_action):
    trace = _play(KeyDoorTVEnv(), start, first_action)
    codes = [t[0] for t in trace]
    assert codes == [start, TV if first_action == 0 else CORRIDOR, HALLWAY, door]
    # Exactly 3 steps: only the third (at the door) terminates the episode.
    assert [t[2] for t in trace[1:]] == [False, False, True]
    assert not any(t[3] for t in trace)
    assert [t[1] for t in trace[1:]] == [0.0, 0.0, reward]
    assert [t[4]["success"] for t in trace] == [False, False, False, reward == 1.0]
    assert [t[4]["code"] for t in trace] == codes


def test_random_starts_are_balanced_and_rewarded_by_the_key():
    env = KeyDoorTVEnv()
    starts = []
    for seed in range(400):
        trace = _play(env, None, first_action=seed % 2, seed=seed)
        starts.append(trace[0][0])
        assert trace[-1][1] == (1.0 if trace[0][0] == KEY else 0.0)
        assert len(trace) == 4
    assert set(starts) == {KEY, BALL}
    assert abs(np.mean(np.array(starts) == KEY) - 0.5) < 0.1


def test_causal_label_exactly_at_key_and_ball():
    env = KeyDoorTVEnv()
    seen: dict[int, set[bool]] = {}
    for start in (KEY, BALL):
        for first_action in (0, 1):
            for code, _, _, _, info in _play(env, start, first_action):
                seen.setdefault(code, set()).add(info["causal"])
                assert info["agent_pos"].dtype == np.int64 and info["agent_pos"].shape == (2,)
    assert seen == {
        KEY: {True},
        BALL: {True},
        TV: {False},
        CORRIDOR: {False},
        HALLWAY: {False},
        DOOR_OPEN: {False},
        DOOR_CLOSED: {False},
    }


def test_step_after_the_door_needs_reset_and_render_is_text():
    env = KeyDoorTVEnv(render_mode="ansi")
    _play(env, KEY, 0)
    assert "DOOR_OPEN" in env.render()
    with pytest.raises(gym.error.ResetNeeded):
        env.step(0)


def test_check_env_and_registration():
    assert thci.__version__  # `import thci` registered the id
    env = gym.make("thci/KeyDoorTV-v0")
    with warnings.catch_warnings():
        # Any checker complaint (not just a failed assertion) counts as a failure.
        warnings.simplefilter("error")
        check_env(env.unwrapped)
    obs, _ = env.reset(seed=3)
    assert obs.shape == (NUM_CODES,)
    for _ in range(2):
        _, _, terminated, _, _ = env.step(0)
        assert not terminated
    _, _, terminated, _, _ = env.step(0)
    assert terminated
    env.close()


def test_sampling_policy_biases_toward_tv_after_key():
    rng = np.random.default_rng(0)
    tv_after_key = np.mean([confounded_sampling_policy(KEY, rng) == 0 for _ in range(2000)])
    tv_after_ball = np.mean([confounded_sampling_policy(BALL, rng) == 0 for _ in range(2000)])
    assert abs(tv_after_key - 0.88) < 0.03
    assert abs(tv_after_ball - 0.12) < 0.03
    with pytest.raises(ThciError):
        confounded_sampling_policy(TV, rng)


def test_sample_episodes_format_and_seeding():
    episodes = sample_episodes(50, seed=7)
    assert len(episodes) == 50
    for e in episodes:
        assert e.codes.dtype == np.int64 and e.codes.shape == (4,)
        assert e.actions.dtype == np.int64 and e.actions.shape == (3,)
        assert e.rewards.dtype == np.float32 and e.rewards.shape == (3,)
        assert e.causal.tolist() == [True, False, False, False]
        assert e.codes[1] == (TV if e.actions[0] == 0 else CORRIDOR)
        assert e.codes[2] == HALLWAY
        assert e.rewards.tolist() == [0.0, 0.0, 1.0 if e.codes[0] == KEY else 0.0]
    again = sample_episodes(50, seed=7)
    assert all(np.array_equal(a.codes, b.codes) for a, b in zip(episodes, again, strict=True))


def test_confounding_report_matches_fig1():
    report = confounding_report(20_000, seed=0)
    assert isinstance(report, ConfoundingReport)
    assert report.num_episodes == 20_000
    assert abs(report.naive_p_open_given_tv - 0.88) < 0.03
    assert abs(report.adjusted_p_open_do_tv - 0.5) < 0.03


def _episode(*codes: int) -> PoolEpisode:
    length = len(codes) - 1
    return PoolEpisode(
        codes=np.array(codes, dtype=np.int64),
        actions=np.zeros(length, dtype=np.int64),
        rewards=np.zeros(length, dtype=np.float32),
    )


def test_estimators_on_hand_made_episodes():
    episodes = [
        # Key stratum, p(z) = 3/5: treated episodes open 1 of 2 -> p(Open | TV, KEY) = 1/2.
        _episode(KEY, TV, DOOR_OPEN),
        _episode(KEY, TV, DOOR_CLOSED),
        _episode(KEY, DOOR_OPEN),  # shorter episode, untreated: exercises the flattening
        # Ball stratum, p(z) = 2/5: the one treated episode stays closed -> 0.
        _episode(BALL, TV, DOOR_CLOSED),
        _episode(BALL, CORRIDOR, DOOR_OPEN),
    ]
    # Naive: TV episodes are #1, #2, #4, of which only #1 opens.
    assert naive_conditional(episodes, DOOR_OPEN, TV) == pytest.approx(1 / 3, abs=1e-12)
    # Eq. 1: 1/2 * 3/5 + 0 * 2/5.
    assert backdoor_adjusted(episodes, DOOR_OPEN, TV, [KEY, BALL]) == pytest.approx(0.3, abs=1e-12)
    # With no backdoor code there is a single stratum: the adjustment is the naive estimate.
    assert backdoor_adjusted(episodes, DOOR_OPEN, TV, []) == pytest.approx(1 / 3, abs=1e-12)


def test_unidentifiable_adjustment_raises():
    episodes = [_episode(KEY, TV, DOOR_OPEN), _episode(BALL, CORRIDOR, DOOR_CLOSED)]
    assert naive_conditional(episodes, DOOR_OPEN, TV) == 1.0
    with pytest.raises(ThciError, match="not identifiable"):
        backdoor_adjusted(episodes, DOOR_OPEN, TV, [KEY, BALL])
    # The same on sampled data whose policy never passes the TV after a ball start.
    sampled = sample_episodes(200, seed=1, p_tv_given_ball=0.0)
    with pytest.raises(ThciError, match="not identifiable"):
        backdoor_adjusted(sampled, DOOR_OPEN, TV, [KEY, BALL])


def test_estimator_input_errors():
    episodes = [_episode(KEY, CORRIDOR, DOOR_OPEN)]
    with pytest.raises(ThciError):
        naive_conditional(episodes, DOOR_OPEN, TV)
    with pytest.raises(ThciError):
        naive_conditional([], DOOR_OPEN, TV)
    with pytest.raises(ThciError):
        backdoor_adjusted(episodes, DOOR_OPEN, TV, [KEY, TV])

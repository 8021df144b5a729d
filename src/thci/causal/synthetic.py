"""Synthetic history data with planted causal observations.

Ground truth for counterfactual inference: episodes over an observation space of
``num_codes`` codes in which a few codes are planted *causes* of the final reward and a few
others are planted *confounders*, observations strongly correlated with a cause (and therefore
with the reward) that have no effect of their own. This is the confounding the paper's CI
adjusts for ("Counterfactual Inference on Observations" / "on Sub-Spaces", Thm. 2, Prop. 2):
a correlation-based method gives confounders high belief, while intervening on them changes
nothing once the causes are kept. The generator serves the tests of the CI engine and the
scaling benchmark of App. J (interventions / run time of T-HCI as |O| grows), so it is
vectorized over episodes: 100k codes × 20k episodes take well under a second.

The data are codes, as stored in the replay pool (:class:`thci.causal.replay.PoolEpisode`);
no observation vectors are involved.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from thci.causal.replay import PoolEpisode
from thci.errors import ThciError

NUM_ACTIONS = 4
"""Actions are uniform random in {0, 1, 2, 3} and have no effect on anything."""

P_CONFOUNDER_IF_ON = 0.9
P_CONFOUNDER_IF_OFF = 0.1


@dataclass(frozen=True)
class PlantedData:
    """Episodes with planted causes and confounders.

    Attributes:
        episodes: E episodes of L steps (codes (L + 1,), actions (L,), rewards (L,), causal
            labels (L + 1,): True exactly where the code is a planted cause).
        causal_codes: (k,) int64, the planted causes c_1 .. c_k.
        confounder_codes: (k, m) int64; row i holds the confounders of cause i.
        num_codes: size of the observation space; codes are 0 .. num_codes - 1.
        on: (E, k) bool, whether cause i was on (hence observed) in each episode.
    """

    episodes: list[PoolEpisode]
    causal_codes: np.ndarray
    confounder_codes: np.ndarray
    num_codes: int
    on: np.ndarray

    @property
    def distractor_codes(self) -> np.ndarray:
        """(num_codes - k(1 + m),) int64, sorted: codes that are neither causes nor confounders."""
        planted = np.concatenate([self.causal_codes, self.confounder_codes.ravel()])
        return np.setdiff1d(np.arange(self.num_codes, dtype=np.int64), planted)


def planted_reward(on: np.ndarray) -> np.ndarray:
    """Reward of the last action given which causes were on: how many were.

    r = sum_i on_i: every cause changes the reward by 1, and no proper subset of causes
    determines it. Each cause weighs the same: the effect predictor scales rewards by their
    largest value (k), so masking one cause (and its confounder) costs a held-out error of
    2 * (1/k)**2 / 4 = 1/(2 k**2) per rewarded transition, 0.125 for two causes against the
    default threshold xi = 0.1. (The earlier binary weighting, r = sum_i 2**i on_i / (2**k - 1),
    gave the lighter of two causes 2 * (1/3)**2 / 4 = 0.056, below xi: a cause the threshold
    defines away.)

    Args:
        on: (..., k) bool.

    Returns:
        (...,) float32; 0 when k = 0.
    """
    return on.sum(axis=-1).astype(np.float32)


def generate_planted_episodes(
    num_codes: int,
    num_causal: int = 2,
    num_episodes: int = 2000,
    episode_length: int = 12,
    confounders_per_cause: int = 1,
    seed: int = 0,
) -> PlantedData:
    """Generate episodes whose final reward depends on planted causal observations only.

    Design (k = ``num_causal``, m = ``confounders_per_cause``, L = ``episode_length``; steps are
    1-based, step t observes o_t, and o_{L+1} is the observation after the last action):

    * Codes. k causes and k·m confounders, all distinct, are drawn from 0..num_codes-1 by a
      seeded RNG; the remaining D = num_codes - k(1 + m) codes are *distractors*.
    * Causes. In each episode cause i is "on" independently with probability 1/2; if on, c_i
      is observed once, at a random step among 1..L-2 (so it is history, not the current
      observation, when the last action is rewarded).
    * Confounders. Each confounder f of cause i is observed once, with probability 0.9 if c_i
      is on and 0.1 if off: strongly correlated with c_i and with the reward, never causal.
      Its step is random but always *after* c_i's (slot drawn even when c_i is off), also
      within 1..L-2. Why after: if f could precede c_i, f would genuinely predict the later
      observation c_i, i.e. f would have an effect on the next observation and a forward
      model (which predicts (o_{t+1}, r_{t+1}), Eq. 9) would rightly call it causal. With c_i
      first, once c_i is known nothing about the future depends on f. All planted
      observations of an episode get distinct steps (a random permutation of 1..L-2; this
      needs k(1 + m) <= L - 2). The only, negligible, leak: a planted observation at step s
      tells that s is not another planted item's step.
    * Distractors. Every other step, o_{L-1}, o_L and the final o_{L+1} included, observes a
      distractor drawn uniformly at random, independently of everything. Uniform maximizes
      coverage: with N ≈ num_episodes · (L + 1) distractor draws, the expected fraction of
      distractor codes seen at least once is 1 - (1 - 1/D)**N ≈ 1 - exp(-N / D), so
      N ≈ 3·D covers ~95% of the space and N ≈ 5·D ~99%.
    * Actions are uniform in {0, 1, 2, 3} and affect nothing. Rewards are 0 except for the
      last action, whose reward is :func:`planted_reward` of the causes that were on. Next
      observations are independent of the actions and of the causes (except a confounder's
      probability, which depends on its own cause only).

    Hence exact recovery is possible: each cause is the only observation that reveals its term
    of the reward (its confounder is a 90%-accurate proxy, not a substitute), and intervening
    on any set of confounders and distractors while the causes are kept changes nothing.

    Args:
        num_codes: size of the observation space; needs at least one distractor.
        num_causal: k >= 0 causes (k = 0: all rewards 0, a null benchmark).
        num_episodes: E.
        episode_length: L steps per episode.
        confounders_per_cause: m >= 0.
        seed: seed of the whole draw (equal seeds give equal data).

    Raises:
        ThciError: sizes that make the design impossible.
    """
    k, m, length = num_causal, confounders_per_cause, episode_length
    if k < 0 or m < 0 or num_episodes < 0:
        raise ThciError(
            "num_causal, confounders_per_cause and num_episodes must be >= 0, got "
            f"{k}, {m}, {num_episodes}"
        )
    num_planted = k * (1 + m)
    if num_codes <= num_planted:
        raise ThciError(
            f"num_codes={num_codes} leaves no distractor codes: it must exceed "
            f"num_causal * (1 + confounders_per_cause) = {num_planted}"
        )
    if length < 3 or num_planted > length - 2:
        raise ThciError(
            f"episode_length={length} is too short: planted observations need distinct steps "
            f"in 1..L-2, so L must be >= max(3, {num_planted} + 2)"
        )
    rng = np.random.default_rng(seed)
    num_ep = num_episodes

    planted = rng.choice(num_codes, size=num_planted, replace=False).astype(np.int64)
    causal_codes, confounder_codes = planted[:k], planted[k:].reshape(k, m)
    distractors = np.setdiff1d(np.arange(num_codes, dtype=np.int64), planted)

    # (E, L + 1) codes of o_1 .. o_{L+1}: distractors everywhere, then the planted ones.
    codes = distractors[rng.integers(0, len(distractors), size=(num_ep, length + 1))]

    on = rng.random((num_ep, k)) < 0.5
    p_conf = np.where(on, P_CONFOUNDER_IF_ON, P_CONFOUNDER_IF_OFF)[:, :, None]  # (E, k, 1)
    conf_seen = rng.random((num_ep, k, m)) < p_conf  # (E, k, m)

    # Distinct steps for all planted items: the first k(1+m) entries of a random permutation
    # of the slots 0..L-3 (steps 1..L-2), grouped per cause; the earliest slot of each group
    # goes to the cause so that its confounders come after it.
    slots = np.argsort(rng.random((num_ep, length - 2)), axis=1)[:, :num_planted]
    slots = np.sort(slots.reshape(num_ep, k, 1 + m), axis=2)  # (E, k, 1 + m)
    cause_slot, conf_slot = slots[:, :, 0], slots[:, :, 1:]

    ep, cause = np.nonzero(on)
    codes[ep, cause_slot[ep, cause]] = causal_codes[cause]
    ep, cause, j = np.nonzero(conf_seen)
    codes[ep, conf_slot[ep, cause, j]] = confounder_codes[cause, j]

    actions = rng.integers(0, NUM_ACTIONS, size=(num_ep, length), dtype=np.int64)
    rewards = np.zeros((num_ep, length), dtype=np.float32)
    rewards[:, -1] = planted_reward(on)
    causal = np.isin(codes, causal_codes)

    episodes = [
        PoolEpisode(codes=codes[e], actions=actions[e], rewards=rewards[e], causal=causal[e])
        for e in range(num_ep)
    ]
    return PlantedData(
        episodes=episodes,
        causal_codes=causal_codes,
        confounder_codes=confounder_codes,
        num_codes=num_codes,
        on=on,
    )

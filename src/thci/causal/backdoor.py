"""Naive vs backdoor-adjusted effect estimates on replay-pool episodes (paper Eq. 1, Fig. 1).

The T-HCI paper motivates counterfactual inference with the key-to-door example of Fig. 1: a
sampling policy that passes the TV mostly after collecting the key makes the TV correlate with
the open door, p(Open | TV) = 0.88, although only the key opens it. The backdoor formula (Eq. 1)

    p(Y | do(X = x)) = Σ_z p(Y | X = x, Z = z) p(Z = z)

with the backdoor variable Z = the start (KEY vs BALL) removes that confounding and gives
p(Open | do(TV)) = 0.5. This module computes both quantities on a list of
:class:`~thci.causal.replay.PoolEpisode` and reports them for the KeyDoorTV environment
(:mod:`thci.envs.key_door_tv`), as a check that the data really is confounded the way the
paper describes.

All variables are episode-level indicators: "the episode contains code c" among its
observations o_1 ... o_{L+1}. That matches Fig. 1, where start, path and door each occur at a
fixed time; the estimators do not look at when a code was seen.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from thci.causal.replay import PoolEpisode
from thci.errors import ThciError

__all__ = [
    "ConfoundingReport",
    "backdoor_adjusted",
    "confounding_report",
    "naive_conditional",
]


def _contains(episodes: Sequence[PoolEpisode], codes: Sequence[int]) -> np.ndarray:
    """(E, K) bool: whether episode e contains code ``codes[k]`` anywhere in o_1 ... o_{L+1}.

    The episodes are flattened once into one code array plus the episode index of each entry,
    so the membership test is a single numpy pass over all observations.
    """
    if len(episodes) == 0:
        raise ThciError("no episodes given: the probabilities need at least one episode")
    flat = np.concatenate([np.asarray(e.codes, dtype=np.int64) for e in episodes])
    lengths = np.array([len(e.codes) for e in episodes], dtype=np.int64)
    episode_of = np.repeat(np.arange(len(episodes)), lengths)
    query = np.asarray(codes, dtype=np.int64)
    hits = flat[:, None] == query[None, :]  # (N observations, K)
    out = np.zeros((len(episodes), len(query)), dtype=bool)
    rows, cols = np.nonzero(hits)
    out[episode_of[rows], cols] = True
    return out


def naive_conditional(
    episodes: Sequence[PoolEpisode], outcome_code: int, treatment_code: int
) -> float:
    """Empirical p(outcome | treatment): the confounded correlation of Fig. 1.

    Args:
        episodes: replay-pool episodes.
        outcome_code: the response Y, e.g. DOOR_OPEN.
        treatment_code: the conditioned observation X, e.g. TV.

    Returns:
        Fraction of the episodes containing ``treatment_code`` that also contain
        ``outcome_code``.

    Raises:
        ThciError: if there are no episodes or none contains ``treatment_code``.
    """
    has = _contains(episodes, [outcome_code, treatment_code])
    outcome, treated = has[:, 0], has[:, 1]
    num_treated = int(treated.sum())
    if num_treated == 0:
        raise ThciError(
            f"no episode contains treatment code {treatment_code}: "
            "p(outcome | treatment) is undefined; collect episodes that observe it"
        )
    return float((outcome & treated).sum() / num_treated)


def backdoor_adjusted(
    episodes: Sequence[PoolEpisode],
    outcome_code: int,
    treatment_code: int,
    backdoor_codes: Sequence[int],
) -> float:
    """Backdoor-adjusted p(outcome | do(treatment)) by Eq. 1 of the paper.

    The backdoor variable Z is the pattern of which ``backdoor_codes`` an episode contains
    (for KeyDoorTV with ``[KEY, BALL]``: the start, KEY or BALL). Each stratum z observed in
    the data contributes p(outcome | treatment, z) · p(z), both estimated by counting.

    Args:
        episodes: replay-pool episodes.
        outcome_code: the response Y, e.g. DOOR_OPEN.
        treatment_code: the intervened observation X, e.g. TV.
        backdoor_codes: codes whose presence forms Z; they must precede X causally (no
            descendant of X) and block every backdoor path from X to Y.

    Returns:
        Σ_z p(outcome | treatment, z) p(z).

    Raises:
        ThciError: if there are no episodes, if ``backdoor_codes`` contains the treatment or the
            outcome, or if some stratum z with p(z) > 0 has no treated episode (then
            p(outcome | treatment, z) and so the adjustment are not identifiable from the data).
    """
    backdoor = [int(c) for c in backdoor_codes]
    if treatment_code in backdoor or outcome_code in backdoor:
        raise ThciError(
            f"backdoor_codes {backdoor} contain the treatment ({treatment_code}) or the outcome "
            f"({outcome_code}): pass only confounders that precede the treatment"
        )
    has = _contains(episodes, [outcome_code, treatment_code, *backdoor])
    outcome, treated, z_bits = has[:, 0], has[:, 1], has[:, 2:]
    # Strata = distinct presence patterns of the backdoor codes; reshape guards against the
    # inverse's shape, which changed across numpy 2.x releases for axis=0.
    patterns, stratum = np.unique(z_bits, axis=0, return_inverse=True)
    stratum = stratum.reshape(-1)
    num_strata = len(patterns)
    size = np.bincount(stratum, minlength=num_strata)
    num_treated = np.bincount(stratum, weights=treated, minlength=num_strata)
    num_treated_outcome = np.bincount(stratum, weights=outcome & treated, minlength=num_strata)
    missing = np.flatnonzero(num_treated == 0)
    if missing.size:
        present = [c for c, bit in zip(backdoor, patterns[missing[0]], strict=True) if bit]
        raise ThciError(
            f"p(outcome | do(treatment)) is not identifiable: no episode with backdoor codes "
            f"{present} contains treatment code {treatment_code}; collect data where it occurs"
        )
    p_z = size / len(episodes)
    return float(np.sum(num_treated_outcome / num_treated * p_z))


@dataclass(frozen=True)
class ConfoundingReport:
    """Naive vs adjusted probability of the open door given the TV on KeyDoorTV data (Fig. 1).

    Attributes:
        naive_p_open_given_tv: p(Open | TV), inflated by the sampling policy (≈ 0.88).
        adjusted_p_open_do_tv: p(Open | do(TV)) by Eq. 1 with Z = the start (≈ 0.5).
        num_episodes: episodes the estimates were computed on.
    """

    naive_p_open_given_tv: float
    adjusted_p_open_do_tv: float
    num_episodes: int


def confounding_report(num_episodes: int = 20_000, seed: int = 0) -> ConfoundingReport:
    """Sample KeyDoorTV with the confounded policy and estimate the TV's effect both ways.

    Args:
        num_episodes: episodes to sample.
        seed: seed of :func:`thci.envs.key_door_tv.sample_episodes`.

    Returns:
        The naive and the backdoor-adjusted probabilities of the open door given the TV.
    """
    # Imported here, not at module level: thci.envs imports thci.causal.replay, so a package
    # __init__ importing this module must not pull thci.envs in before it is initialized.
    from thci.envs.key_door_tv import BALL, DOOR_OPEN, KEY, TV, sample_episodes

    episodes = sample_episodes(num_episodes, seed)
    return ConfoundingReport(
        naive_p_open_given_tv=naive_conditional(episodes, DOOR_OPEN, TV),
        adjusted_p_open_do_tv=backdoor_adjusted(episodes, DOOR_OPEN, TV, [KEY, BALL]),
        num_episodes=len(episodes),
    )

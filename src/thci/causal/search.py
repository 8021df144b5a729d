"""Which observations have a causal effect: HCI, T-HCI and fine-grained CI on a replay pool.

* :func:`t_hci` — coarse-to-fine CI (Prop. 3): split the candidates into Z even parts, test
  each part together with the eliminated set O^w, eliminate the parts whose ATE ≤ ξ and recurse
  into each remaining part until it holds fewer than Z observations, which are then tested one
  by one. About Z·log_Z|Ô|·|O^Ca| interventions.
* :func:`hci` — CI on single observations (Thm. 2): |Ô| interventions, then the singles it
  could not decide are eliminated together where their union shows no effect
  (:meth:`_Search.settle_undecided`).
* :func:`fine_grained_ci` — one intervention per observation and history step (Prop. 1):
  |Ô|·T interventions, for small problems.

Eliminating is sequential in meaning: a part is tested with everything eliminated *before* it
masked. If parts were only tested side by side, two complementary causes (say the indicator
codes 0 and 1 of Maze level 1, each of which the other's absence reveals) would both look
removable. Tests run side by side for speed, and every batch that would eliminate several
parts first checks their union in one more intervention; only when that union has an effect
are the parts resolved in order (the gate's current choices last, then by ascending ATE, so
that of a cause and its proxy the cause stays): the longest leading run of them whose union
has no effect is eliminated (found by binary search on union checks) and the rest are tested
again. Causal
verdicts never need re-checking: masking more can only lose information (the ATE is monotone
in the masked set).

A test has three outcomes, by where the ATE's confidence interval lies against the band
[−ξ, ξ]:

* no higher than ξ: no effect, the set is eliminated (an equivalence test; a true ATE is never
  negative, so an interval that reaches below −ξ but no higher than ξ still confines it to
  [0, ξ]: on App. J's data the codes seen in ~20 held-out episodes had such intervals, e.g.
  [−0.19, 0.10], and were kept as undecided before, three false positives at |O| = 1000);
* above it, and significantly positive (estimate > ξ, lower bound > 0): a *confirmed* effect.
  A confirmed single observation is causal for good: the CI loop does not test it again
  (`keep` in later rounds), because once the policy acts on a cause, the path it takes tells
  the outcome too and a later pool shows the cause as redundant. (Requiring the whole interval
  above ξ confirmed too little: tested alone, Maze L1's two complementary indicators had ATEs
  of 0.11-0.31 with lower bounds of 0.03-0.15 in 9 of 10 first-round tests (five runs), so an
  early round left them undecided, and the next round, on the pool of the policy that had
  learned to use them, eliminated both: success fell to ~0.5.)
* anything else: undecided. The set is kept (a wrongly eliminated cause is gone from the
  agent's memory, a wrongly kept set only costs compression) and tested again in the next
  round on a larger pool. This covers a confidently negative estimate too (the whole
  interval below 0 and reaching below −ξ): a true ATE is never negative, so it means p_ζ is
  unreliable for that set (see the predictor's module doc).

Only confirmed observations are final, so what an early, noisy pool keeps by doubt does not
stay in the causal memory for the rest of the run.

Substitutes. Sequential elimination returns a *sufficient* set: of two values of one hidden
variable (Maze's indicator cell shows code 0 or code 1, never both in an episode) it keeps one,
since the other's absence tells it. Both searches then admit back each eliminated observation
that stands in for a confirmed cause it never shares an episode with
(:meth:`_Search.admit_substitutes`), so the memory holds every value of the variable instead of
asking the policy to read one from an absence (`substitutes=False` returns the sufficient set).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from thci.causal.predictor import EffectEstimator, Intervention

DEFAULT_XI = 0.1
"""ξ: with the ATE's confidence interval inside [−ξ, ξ] a set has no effect. Measured by
benchmarks/xi_calibration.py with the dynamics target (before cross-fitting,
results/xi_calibration_dynamics.json): 0.1 kept the causes on all six maze pools (0.05 kept up
to seven other codes beside them, 0.2 lost a cause on three). With the reward target
(results/xi_calibration_reward.json) 0.05 keeps exactly the labels on five early Maze L3-L4
pools and 0.1 on four of them."""

DEFAULT_Z = 4
"""Z: parts each candidate set is split into (Prop. 3)."""

DEFAULT_MIN_SUPPORT = 10
"""T-HCI splits a part that has an effect only while it occurs in at least this many held-out
episodes. Below that its pieces' confidence intervals are too wide to eliminate anything, so
splitting would only spend interventions: on a BabyAI-L1 pool (4039 codes, most seen in one
or two episodes) the unbounded tree ran thousands of interventions and kept nearly all. The
maze's codes occur in most episodes, so there this never applies."""


EXCLUSIVE_EXPECTED = 3.0
"""A cause and an eliminated observation count as exclusive (values of one variable, for
:meth:`_Search.admit_substitutes`) when no held-out episode holds both although independence
would put both in at least this many (P(0 | Poisson(3)) = 0.05)."""


@dataclass(frozen=True)
class InterventionRecord:
    """One intervention: the observation codes intervened on (with O^w also masked), the
    history step for fine-grained CI, its ATE with confidence bounds, and the seconds of the
    batch it ran in."""

    codes: tuple[int, ...]
    ate: float
    seconds: float
    step: int | None = None
    kind: str = "test"  # "test", "union-check", "cause-check" or "substitute"
    ate_lower: float = 0.0
    ate_upper: float = 0.0


@dataclass
class CIResult:
    """Outcome of a search over the observed space Ô (all in original codes): `causal` is
    everything not eliminated, `confirmed` the part of it with a confirmed effect (see the
    module doc)."""

    algorithm: str
    observed: np.ndarray
    eliminated: np.ndarray
    causal: np.ndarray
    confirmed: np.ndarray
    interventions: list[InterventionRecord] = field(default_factory=list)
    seconds: float = 0.0
    units: CIResult | None = None
    """With ``--ci-units cells``: the search's own result over cell values, from which this
    one over codes follows (thci.causal.units.codes_result)."""

    @property
    def num_interventions(self) -> int:
        return len(self.interventions)


class _Search:
    """Shared machinery: batched tests with sequential-meaning elimination (see module doc)."""

    def __init__(
        self,
        estimator: EffectEstimator,
        xi: float,
        confirmed: np.ndarray | None = None,
        prefer: np.ndarray | None = None,
    ) -> None:
        self.estimator, self.xi = estimator, xi
        self.prefer = np.zeros(0, dtype=np.int64) if prefer is None else prefer
        self.eliminated = np.zeros(0, dtype=np.int64)  # dense ids
        self.confirmed = np.zeros(0, dtype=np.int64) if confirmed is None else confirmed
        self.records: list[InterventionRecord] = []

    def _run(
        self, sets: list[np.ndarray], kind: str = "test", given: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Whether masking each set (with O^w) may have, and has for sure, an effect, and its
        estimated ATE; see :meth:`run_interventions`."""
        return self.run_interventions([Intervention(s) for s in sets], kind, given)

    def run_interventions(
        self,
        interventions: list[Intervention],
        kind: str = "test",
        given: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One batched ATE estimate of `interventions` given O^w (or the masked set `given`,
        dense ids, instead), every one logged. Returns
        three (K,) arrays: which may have an effect (bool: all but those whose confidence
        interval lies within [−ξ, ξ] or, the true ATE being ≥ 0, reaches no higher than ξ
        without being confidently negative), which have a confirmed one (bool: estimate above
        ξ, lower bound above 0), and the estimates; see the module doc."""
        started = time.perf_counter()
        given = self.eliminated if given is None else given
        estimate = self.estimator.ate(interventions, given)
        seconds = time.perf_counter() - started
        observed = self.estimator.data.observed
        for k, intervention in enumerate(interventions):
            codes = tuple(int(c) for c in observed[intervention.codes])
            self.records.append(
                InterventionRecord(
                    codes,
                    float(estimate.ate[k]),
                    seconds,
                    intervention.step,
                    kind,
                    float(estimate.lower[k]),
                    float(estimate.upper[k]),
                )
            )
        misfit = self._misfit(estimate.lower, estimate.upper)
        effect = (estimate.upper > self.xi) | misfit
        return effect, (estimate.ate > self.xi) & (estimate.lower > 0), estimate.ate

    def _misfit(self, lower, upper):
        """Confidently negative (the whole interval below 0, reaching below −ξ): p_ζ is
        unreliable for that set, which stays undecided (module doc)."""
        return (upper < 0) & (lower < -self.xi)

    def _elimination_order(self, drops: list[tuple[np.ndarray, float]]) -> list[np.ndarray]:
        """Parts (with their estimated ATEs) in the order they are offered for elimination:
        those without a code the current gate keeps first, then by ascending ATE."""
        ordered = sorted(drops, key=lambda d: (bool(np.isin(d[0], self.prefer).any()), d[1]))
        return [part for part, _ in ordered]

    def resolve(self, parts: list[np.ndarray]) -> list[np.ndarray]:
        """Test `parts` given O^w; eliminate those without effect; return those with effect
        (a single observation with a confirmed effect is also recorded as confirmed)."""
        kept: list[np.ndarray] = []
        while parts:
            effect, confirmed, ate = self._run(parts)
            kept += [p for p, e in zip(parts, effect, strict=True) if e]
            singles = [p for p, c in zip(parts, confirmed, strict=True) if c and len(p) == 1]
            self.confirmed = np.concatenate([self.confirmed, *singles])
            drops = [(p, a) for p, e, a in zip(parts, effect, ate, strict=True) if not e]
            if len(drops) <= 1 or not self._union_has_effect([p for p, _ in drops]):
                self._eliminate([p for p, _ in drops])
                return kept
            # Interchangeable causes among the drops: the first one is truly removable (it was
            # tested with the current O^w), and so is the longest run of drops after it whose
            # union has no effect either; the rest must be tested again without them. Which
            # drops go first decides which of two interchangeable sets stays. First the one the
            # current gate keeps stays (drops without a preferred code go first), so that the
            # agent's memory does not swap one for the other from round to round; then the one
            # with the larger effect: a proxy of a cause (a confounder that shows it 90% of the
            # time) has an ATE of ~0 beside the cause, the cause ~0.09 beside the proxy (App. J
            # data), so in id order whichever came first was eliminated, the cause included.
            ordered = self._elimination_order(drops)
            removable = self._removable_prefix(ordered, low=1)
            self._eliminate(ordered[:removable])
            parts = ordered[removable:]
        return kept

    def _removable_prefix(self, drops: list[np.ndarray], low: int) -> int:
        """The largest m such that masking drops[:m] together (with O^w) has no effect, given
        that drops[:low] has none and all of them together have one. Binary search: the ATE is
        monotone in the masked set, so about log2(len(drops)) union checks. Re-testing the
        rest one elimination at a time instead cost a quadratic number of tests on a BabyAI
        pool (37,303 interventions on 6158 codes, the same 6-code part tested up to 191 times)."""
        high = len(drops)  # drops[:low] has no effect, drops[:high] has one
        while high - low > 1:
            middle = (low + high) // 2
            if self._union_has_effect(drops[:middle]):
                high = middle
            else:
                low = middle
        return low

    def settle_undecided(self) -> None:
        """Eliminate together what single tests could not decide, where their union can be.

        A single observation seen in few held-out episodes gets an interval too wide to
        decide (App. J at |O| = 1000: distractors in ~26 episodes each, intervals like
        [−0.06, 0.11]), so HCI kept 47 of them. Their union has the support that each lacks.
        Sorted by estimated ATE, the longest leading run whose union has no effect given O^w
        is eliminated (binary search on union checks; the ATE is monotone in the masked set),
        so a cause, whose estimate is high, is the last to be considered and stays unless it
        too has no effect beside the others."""
        undecided = np.setdiff1d(
            np.arange(self.estimator.data.num_codes),
            np.concatenate([self.eliminated, self.confirmed]),
        )
        dense = {int(c): d for d, c in enumerate(self.estimator.data.observed)}
        latest = {  # each undecided single's last test (later records overwrite earlier ones)
            dense[r.codes[0]]: r for r in self.records if len(r.codes) == 1 and r.kind == "test"
        }
        drops = [
            (np.array([c]), latest[c].ate if c in latest else math.inf)
            for c in undecided.tolist()
            if c not in latest or not self._misfit(latest[c].ate_lower, latest[c].ate_upper)
        ]
        if not drops:
            return
        ordered = self._elimination_order(drops)
        if not self._union_has_effect(ordered):
            self._eliminate(ordered)
        else:
            self._eliminate(ordered[: self._removable_prefix(ordered, low=0)])

    def admit_substitutes(self, min_support: int) -> None:
        """Keep the eliminated observations that stand in for a cause: the other values of
        its variable.

        Of two observations that never occur in one episode and each tell the other's
        absence (Maze L3's indicator cell shows code 0 or code 1), sequential elimination keeps
        one: the second has no effect beside the first. The kept set is sufficient, but the
        policy must then read the other value from an *absence* in its memory, and that is
        slow to learn: T-HCI on Maze L3 solved in 144k steps with the gate [0, 1, 2] (the
        labels) and in 560k-1.97M with [0, 2] or [1, 2] (seeds 1-5, docs/experiments.md).
        An eliminated c (seen in at least `min_support` held-out episodes) is admitted when a
        confirmed cause k that never shares a held-out episode with it (significantly, see
        EXCLUSIVE_EXPECTED) loses its effect once c
        is visible: ATE(k | O^w without c) has no effect while ATE(k | O^w) has a confirmed
        one (checked on this pool first, one batched "cause-check" pass over the causes), i.e.
        eliminating k instead of c would have been as valid.
        Each candidate is tested against the search's own O^w (not one with earlier admissions
        removed), so an unrelated code exclusive of k is not admitted because some other
        substitute already tells k. Candidates are found from the held-out episodes'
        (episode, code) pairs and tested in groups per cause (:meth:`_substitutes_of`)."""
        causes = np.setdiff1d(self.confirmed, self.eliminated)
        if len(causes) == 0 or len(self.eliminated) == 0:
            return
        pairs = self.estimator.history_pairs
        eliminated = self.eliminated
        counts = pairs.counts()
        candidates = eliminated[(counts[eliminated] >= min_support).numpy()]
        if len(candidates) == 0:
            return
        together = pairs.together(causes, candidates)  # (causes, candidates)
        # Never together where independence would put them together in EXCLUSIVE_EXPECTED or
        # more episodes (a one-sided 5% test): a rare cause is "exclusive" of most codes by
        # chance, and testing each of them cost 1,720 passes on App. J's |O| = 1000 data.
        expected = counts[causes].unsqueeze(1) * counts[candidates].unsqueeze(0)
        expected = expected / pairs.num_episodes
        exclusive = (together == 0) & (expected >= EXCLUSIVE_EXPECTED)
        # Only a cause this pool confirms given the whole O^w can have substitutes. A cause
        # kept from an earlier round (`keep`) was confirmed on another pool and may be redundant
        # on this one; then every code exclusive of it passed the test below, joined `keep`
        # and brought its own exclusive codes in the next round (BabyAI-L1, A2C: 143-1262
        # substitute tests in rounds 4-8, the kept set growing to 129 of 208 codes).
        with_partners = exclusive.any(dim=1).numpy()
        if not with_partners.any():
            return
        checked = causes[with_partners]
        _, confirmed_now, _ = self._run([np.array([k]) for k in checked], "cause-check")
        exclusive[with_partners] &= torch.as_tensor(confirmed_now).unsqueeze(1)
        admitted: set[int] = set()
        for i, cause in enumerate(causes.tolist()):
            admitted.update(self._substitutes_of(cause, candidates[exclusive[i].numpy()]))
        self.eliminated = np.setdiff1d(eliminated, sorted(admitted))
        self.confirmed = np.union1d(self.confirmed, sorted(admitted)).astype(np.int64)

    def _substitutes_of(self, cause: int, group: np.ndarray) -> list[int]:
        """The codes of `group` each of which, visible on its own, takes away the effect of
        `cause`: ATE(cause | O^w without c) has none. Group testing, one pass per test: when
        the cause keeps an effect with the whole group visible, it keeps one with any single
        code of it visible (the ATE is monotone in the masked set), so one test clears the
        group; otherwise the group is halved. Testing each candidate on its own took 195-982
        substitute tests a round (a pass each) on BabyAI-L1 pools that admitted almost none."""
        if len(group) == 0:
            return []
        masked = np.setdiff1d(self.eliminated, group)  # O^w with the group visible
        effect, _, _ = self._run([np.array([cause])], "substitute", masked)
        if effect[0]:
            return []
        if len(group) == 1:
            return [int(group[0])]
        half = len(group) // 2
        return self._substitutes_of(cause, group[:half]) + self._substitutes_of(cause, group[half:])

    def _union_has_effect(self, parts: list[np.ndarray]) -> bool:
        """Whether masking all `parts` together (with O^w) may have an effect."""
        effect, _, _ = self._run([np.concatenate(parts)], "union-check")
        return bool(effect[0])

    def _eliminate(self, parts: list[np.ndarray]) -> None:
        if parts:
            self.eliminated = np.concatenate([self.eliminated, *parts])

    def result(self, algorithm: str, started: float) -> CIResult:
        observed = self.estimator.data.observed
        is_eliminated = np.zeros(len(observed), dtype=bool)
        is_eliminated[self.eliminated] = True
        return CIResult(
            algorithm,
            observed.copy(),
            observed[is_eliminated],
            observed[~is_eliminated],
            np.sort(observed[self.confirmed]),
            self.records,
            time.perf_counter() - started,
        )


def t_hci(
    estimator: EffectEstimator,
    z: int = DEFAULT_Z,
    xi: float = DEFAULT_XI,
    keep: np.ndarray | None = None,
    min_support: int = DEFAULT_MIN_SUPPORT,
    prefer: np.ndarray | None = None,
    substitutes: bool = True,
) -> CIResult:
    """Tree-based History Counterfactual Inference (Prop. 3) over Ô.

    Args:
        estimator: a fitted :class:`EffectEstimator` on the replay pool.
        z: Z, the number of parts each candidate set is split into (≥ 2).
        xi: ξ, the ATE threshold at or below which a part has no causal effect.
        keep: dense ids confirmed causal already (in an earlier round): not tested.
        min_support: a part with an effect is split further only while it occurs in at least
            this many held-out episodes; rarer parts are kept whole (see DEFAULT_MIN_SUPPORT).
        prefer: dense ids the current gate keeps; of interchangeable causes (each of which the
            other's absence reveals), these are the ones kept.
        substitutes: then admit the eliminated observations that stand in for a cause
            (:meth:`_Search.admit_substitutes`): the other values of its variable.
    """
    if z < 2:
        raise ValueError(f"Z must be at least 2, got {z}")
    started = time.perf_counter()
    search = _Search(estimator, xi, keep, prefer)
    branches = [_candidates(estimator, keep)]  # every candidate is tested at least once
    while branches:
        large = [b for b in branches if len(b) >= z]
        small = [b for b in branches if len(b) < z]
        # All branches of a tree level are split and tested in one batch.
        parts = [p for b in large for p in np.array_split(b, z)]
        kept = search.resolve(parts)
        # Branches with fewer than Z observations: test them one by one.
        singles = [np.array([c]) for b in small for c in b]
        search.resolve(singles)
        # A kept part of one observation is causal: nothing left to split. A part with an
        # effect too rare to test its pieces is kept whole, as an uncertain test would keep it.
        branches = [p for p in kept if len(p) > 1 and estimator.support(p) >= min_support]
    if substitutes:
        search.admit_substitutes(min_support)
    return search.result("t-hci", started)


def hci(
    estimator: EffectEstimator,
    xi: float = DEFAULT_XI,
    batch_size: int = 16,
    keep: np.ndarray | None = None,
    prefer: np.ndarray | None = None,
    substitutes: bool = True,
    min_support: int = DEFAULT_MIN_SUPPORT,
) -> CIResult:
    """History Counterfactual Inference on single observations (Thm. 2): |Ô| interventions,
    run `batch_size` at a time; `keep`, `prefer`, `substitutes` and `min_support` (of a
    substitute) as in :func:`t_hci`."""
    started = time.perf_counter()
    search = _Search(estimator, xi, keep, prefer)
    codes = _candidates(estimator, keep)
    for begin in range(0, len(codes), batch_size):
        search.resolve([np.array([c]) for c in codes[begin : begin + batch_size]])
    search.settle_undecided()
    if substitutes:
        search.admit_substitutes(min_support)
    return search.result("hci", started)


def _candidates(estimator: EffectEstimator, keep: np.ndarray | None) -> np.ndarray:
    """Dense ids of Ô to test: all but `keep`."""
    codes = np.arange(estimator.data.num_codes)
    return codes if keep is None else np.setdiff1d(codes, keep)


def fine_grained_ci(
    estimator: EffectEstimator, xi: float = DEFAULT_XI, batch_size: int = 64
) -> CIResult:
    """Fine-grained CI (Prop. 1): intervene on each observation at each history step alone.

    An observation is causal when any of its time-specific interventions has ATE > ξ.
    """
    started = time.perf_counter()
    data = estimator.data
    search = _Search(estimator, xi)
    valid_positions = data.valid.any(dim=0).nonzero().flatten().tolist()
    pairs = [(c, t) for c in range(data.num_codes) for t in valid_positions[:-1]]
    causal = set()
    for begin in range(0, len(pairs), batch_size):
        chunk = pairs[begin : begin + batch_size]
        effect, _, _ = search.run_interventions([Intervention(np.array([c]), t) for c, t in chunk])
        causal.update(c for (c, _), e in zip(chunk, effect, strict=True) if e)
    search.eliminated = np.array(sorted(set(range(data.num_codes)) - causal), dtype=np.int64)
    return search.result("fine-grained", started)

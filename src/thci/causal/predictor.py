"""The effect predictor p_ζ and the ATE of an intervention (Eqs. 3, 8, 9).

An *intervention* replaces, in every history h_{t-1}, the observations whose code lies in a set
S ∪ O^w by zero vectors (Eq. 3); the current observation o_t is never masked. p_ζ is fitted on
the masked histories and its held-out prediction error is compared with that of a
control arm (see the estimator below).

Predictor. Each code has a learned embedding (zero-initialized, so a code the predictor never
learned to use behaves like a masked one). The history h_{t-1} is summarized by the running
max of the embeddings of the *kept* observations among o_1 … o_{t-1} (a masked one leaves no
trace, not even its slot). This order-free summary matches the method's assumption that causal
effects do not depend on the time step, and needs no loop over time (a GRU over the history, the
way to let past *actions* tell where the agent is, was 1.6-5.6x slower per fitting step in a
quick measurement: 49-168 ms against ~30 ms). A
two-layer MLP maps [history, embedding of o_t, a_t, embedding of t, embedding of the
intervened set] to

* ``dynamics`` (Eq. 9): a distribution over the next observation's code (codes beyond
  `max_classes` are hashed into that many buckets, a coarsening that can only hide effects,
  never invent them) and the reward; or
* ``reward``: the reward alone, given the transition it pays for: p(r_t | h, o_t, a_t,
  o_{t+1}). This is the second factor of Eq. 9's joint prediction, p(o_{t+1}, r_t | ·) =
  p(o_{t+1} | ·) · p(r_t | ·, o_{t+1}): the first factor asks where the history says the agent
  goes, this one what it is paid for getting there. In a maze whose cells repeat codes the
  history tells *where* the agent is, so every corridor code predicts the next observation
  (the dynamics target kept 10 of 13 codes on a Maze-L3 pool, TAIE 0.91); once the goal
  reached is an input, only what decides whether that goal pays is left to predict, which is
  what the paper's labels call causal (a Maze-L3 pool: [0, 2], a sufficient set of the labels
  0, 1, 2). What acts on the reward only *through* an observation is invisible to it: in
  ``thci/KeyDoorTV-v0`` the key opens the door, and the open door (o_{t+1}) pays, so the key's
  effect is a dynamics effect. Where nothing but such effects exist, no decision of the agent
  depends on memory either.
* ``inverse``: a distribution over a_t, from [history, o_t, o_{t+1}].

One network for every intervention. Eq. 9 minimizes over ζ separately for each intervention.
Here one predictor (an ensemble of M, see Confidence) is fitted once per CI round under
*random* interventions (each episode
of a minibatch has whole codes removed at a rate drawn from U[0, 1]) and is told which codes
its intervention masks (the sum of learned embeddings of the masked codes, never whether they
occurred in the episode). It therefore represents the family of per-intervention minimizers,
p_ζ(· | h^{masked by S}, S), and every ATE of the search is a forward pass on held-out
episodes: no per-intervention fitting, and no fitting noise that differs between arms. Telling
the set matters: without it "c is absent" (not observed) and "c is masked" look alike and the
effect of a cause masked in an otherwise rich history is underestimated. Per-intervention
fine-tuning from this network remains available (`finetune_steps`, continuing the fit's Adam
moments) but is off by default: short fine-tunes add arm-to-arm noise of the size of the
effects sought.

Estimator. The per-transition error is the L1 distance of Eq. 9 between the predicted
distribution and the observed outcome, 2·(1 − p(observed)) / 2 = 1 − p(observed), and the
Brier score 2·(r̂ − r)² for the reward (rewards divided by max|r|; the head is fitted on the
squared error). It equals the absolute error |r̂ − r| where a binary reward is a coin flip to
the predictor (r̂ = 1/2), so the effect of losing what decides a reward is the same, but it
stays ~0 where the absolute error does not: most transitions pay nothing and are predicted to
within ~0.004, which an absolute error sums over an episode's ~25 such steps into ~0.1 of noise
per episode, more than the effect of what decides the reward at the one step it is paid
(measured on a Maze-L3 pool). For an intervention S with eliminated set O^w:

    D_e(S) = Σ_t  1[h_{t-1} contains an observation in S] · (err_{S∪O^w}(t) − err_{O^w}(t))
    ATE(S) = mean of D_e(S) over the n held-out episodes whose history contains S

i.e. the extra prediction error per episode (Eq. 4 sums over t) that the intervention causes
where it applies (Prop. 2 integrates over histories that contain O^i). The two parts of the
dynamics error are measured separately: the next-observation part as is, the reward part (and
the reward target's error) divided by the mean reward per episode (at least
REWARD_SCALE_FLOOR), so that what decides a sparse reward is not diluted below ξ by the many
unrewarded episodes. The control arm masks O^w only, so the ATE is the effect of S *given*
the eliminated set, which is what the sequential elimination of the search needs; the
environment's own noise, and whatever masking O^w costs, hit the control and the intervened
arm alike and cancel.

Explained transitions (reward target). Where the transition itself fixes the reward, no
history can change its prediction. A transition is explained when at least
`explained_min_count` *other* pool transitions share its step, or its step and next
observation, or its step and (o_t, a_t, o_{t+1}), and all of them have one reward (a step into
a corridor cell; in App. J's data, any step before an episode's last); it is left out of the
fit and of every ATE (its D_e term is 0; the episodes an ATE averages over are still all those
whose history holds S). The test reads the other transitions of the context only: judged with
its own reward too, a rare paying step among many unpaid ones in its context would be kept
exactly when it paid, and the predictor would see a sample selected on the outcome. For a
perfect p_ζ leaving explained transitions out changes no ATE; for ours it removes the noise of
~98% of the transitions (a Maze-L1 pool: 185 of 12,130 are predicted), and every fitting step
spends its batch on the transitions that decide the reward. A context seen fewer times says
nothing, so rare contexts are predicted. The test looks at transitions and their rewards, never
at the history, so it favours no history observation over another.

Confidence and cross-fitting. p_ζ is an ensemble of M independently initialized predictors
(`ensemble`, fitted side by side in one batched pass, each with its own random
interventions). The pool's episodes are dealt into M folds (by the run's episode number, so an
episode stays in its fold in later rounds, whose warm-started members must not be measured on
what they were fitted on) and member m is fitted without fold m and measured on it, so every
episode is held out once: four times the held-out data of a
25% split at the same cost, which matters on early pools where few episodes show the reward.
The ATE is the mean D_e over all episodes, and its confidence interval mean ± z·SE
(`confidence_z`) takes the larger of two variance estimates: the spread of D_e over episodes,
and the spread of the folds' means, which also holds how each member happened to be fitted (on
hard pools this dominated: single fits with different seeds kept the causes in one and dropped
all of them in the other). The search eliminates a set only when the whole interval lies within
[−ξ, ξ] (:mod:`thci.causal.search`).

Negative estimates. Masking can only remove information, so for a perfect p_ζ no ATE is
negative. Ours can be: on a Maze-L3 pool of a weak policy, masking the indicator code 2 made
p_ζ's error on (7 → 7) corridor transitions *fall* from 0.102 to 0.075, on training episodes
as much as on held-out ones (ATE −0.25 per episode) — a misfit of the control arm (the
order-free history summary, see above), not overfitting. An interval below −ξ says nothing
about whether S matters, so such a set is kept (undecided, tested again next round). Before
these rules T-HCI eliminated the indicators of Maze L3 on such pools, and the policy, blind to
them, never improved.

Warm starts. Rounds after the first continue the previous round's predictor on the grown
pool for `warm_steps` instead of fitting `base_steps` from scratch
(:meth:`BatchedPredictor.warm_start` carries each code's embedding and output class over).

Known limits (see the issues): with coarse parts, the per-episode ATE is averaged over almost
every episode, which dilutes a rare cause's effect; and an observation that the *policy* makes
informative (a path a trained policy takes only in one variant) shows an effect like a cause.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch
from torch import nn

from thci.causal.flat_adam import FlatAdam
from thci.causal.replay import PoolArrays

Target = Literal["dynamics", "reward", "inverse"]
REWARD_PART = {"dynamics": 1, "reward": 0}
"""Which error component is the reward's, for the targets that predict one."""
REWARD_SCALE_FLOOR = 0.1
"""Smallest reward per episode (in units of max |r|) the reward part of an ATE is divided by."""
FEW_PER_EPISODE = 4
"""A batch with at most this many transitions to predict per episode (on average) sums each
transition's history on its own (:meth:`BatchedPredictor.bag_max`); one with more takes a
running max along each episode."""


@dataclass(frozen=True)
class PredictorConfig:
    """Hyperparameters of p_ζ and its fitting."""

    target: Target = "dynamics"
    embed_dim: int = 16
    hidden_size: int = 64
    base_steps: int = 1000
    """Adam steps of the base predictor fit (once per CI round)."""
    warm_steps: int = 300
    """Adam steps of the fit when it continues an earlier round's predictor (`warm_start`)."""
    ensemble: int = 4
    """M independently initialized predictors fitted side by side (one batched pass); an
    ATE's uncertainty includes how much they disagree (see the module doc)."""
    finetune_steps: int = 0
    """Adam steps of per-intervention fine-tuning (0: the shared network answers directly)."""
    arms_per_pass: int = 16
    """Interventions whose ATEs are evaluated side by side in one pass (bounds memory)."""
    batch_episodes: int = 128
    """Episodes per Adam step, at most; fewer when they are long (`batch_transitions`)."""
    batch_transitions: int = 2048
    """Transitions per Adam step, about: long episodes (BabyAI's ~76 steps against the
    maze's ~20) make smaller batches, so a step costs the same on every task. 2048 fitted two
    Maze-L3 pools in 4.6-4.9 s where 4096 took 8.1 s (400 steps, one thread), and kept the
    same sets."""
    learning_rate: float = 3e-3
    whole_batch_steps: int = 0
    """A fit from scratch whose training set holds at most `batch_transitions` predicted
    transitions takes the whole set at every step, for this many steps, from Adam rate
    `whole_batch_learning_rate` decayed linearly towards 0 (0: minibatches of
    `batch_episodes` for `base_steps` at `learning_rate`, as every other fit). On such small
    sets a step costs about what a minibatch step does (its cost is per-operation overhead),
    and without sampling noise fewer steps fit as well: the first CI round of a run, which the
    RL loop may wait for, is one. On the 10 first-round Maze L1-L2 pools of seeds 1-5, 250
    steps from 1e-2 kept exactly what 400 minibatch steps at 3e-3 keep, in 0.31-0.48 s
    against 0.47-0.56 s; 200 steps kept corridor codes on one (docs/experiments.md)."""
    whole_batch_learning_rate: float = 1e-2
    code_dropout: float = 1.0
    """Largest rate at which the base fit removes codes from an episode's history (see
    :meth:`EffectEstimator._random_code_dropout`)."""
    holdout_fraction: float = 0.25
    """With a single predictor (`ensemble` 1), the share of episodes held out of its fit. An
    ensemble of M ≥ 2 cross-fits instead: member m is fitted without fold m of M and measured on
    it, so every episode is held out once (see Cross-fitting in the module doc)."""
    confidence_z: float = 1.645
    """The ATE's interval is mean ± confidence_z · standard error over held-out episodes. The
    search's tests are one-sided (a true ATE is ≥ 0: no effect when the upper bound is ≤ ξ, a
    confirmed one when the lower bound is > 0), so 1.645 makes each a 5% test, as in the
    two-one-sided-tests equivalence procedure. With 2.0, on 2026-12-03's machine, T-HCI kept
    a distractor at App. J's |O| = 1000 (code 266: −0.047 [−0.208, 0.114], 21 held-out
    episodes); with 1.645 it is exact at 100, 1000 and 10^4 and on Maze L1-L4 solved 20 of
    20 runs, L1-L2 step for step as before, L3 in 386k steps on average against 446k
    (docs/experiments.md). HCI at 1000 then confirms more single distractors (13 codes kept
    against 4)."""
    min_code_episodes: int = 10
    """A code seen in fewer episodes of the pool is *rare*: as the current or next observation
    it shares one embedding with the other rare codes, and in the history p_ζ does not see it
    at all (as if always masked; nor does an intervened set tell it). With an embedding of its
    own, a code that occurs in one or two episodes lets the predictor memorize those episodes'
    outcomes instead of learning them from the observations that recur: on synthetic data with
    10^4 codes (App. J) the planted causes' ATE fell from the expected 0.125 to 0.03, and T-HCI
    eliminated them. With the shared row in the history (and a mask embedding per rare code),
    whether *some* rare code was left in a heavily masked history moved the predictions: masking
    4045 distractors "had" an ATE of 0.26, and single rare codes 0.07-0.22 with intervals too
    wide to decide, so they were kept. Unseen in the history, a rare set's ATE is exactly 0: it
    is eliminated, and tested again in a later round once the pool holds it often enough."""
    explained_min_count: int = 10
    """Reward target: a transition is explained without history when at least this many other
    pool transitions share its step (or its step and next observation, or its step and
    (o_t, a_t, o_{t+1})) and all have one reward; it is left out of the fit and of every ATE
    (see Explained transitions in the module doc). 0: every transition is predicted."""
    max_classes: int = 128
    """Classes of the next-observation head; more codes than this are hashed into them. The
    head's width sets the cost of a round (0.07 s per step at 128, 0.48 s at 1024 on a
    4000-code BabyAI pool, one thread)."""
    seed: int = 0


@dataclass(frozen=True)
class PredictedTransitions:
    """A pool's predicted transitions laid out once for the fit's minibatches
    (:meth:`BatchedPredictor.transition_loss`): a fitting step gathers its batch's transitions
    with one indexing instead of cutting them out of (B, L) episode tensors, and their
    histories come ready as their distinct codes, latest occurrence first
    (:meth:`BatchedPredictor.bag_max`, :func:`_latest_distinct`). Built where transitions per
    episode are few (the reward target): it holds W ≤ L codes per transition.

    Attributes:
        slots: (E, P) the transitions of each episode (rows of the tensors below) in step
            order, -1 after its last.
        count: (E,) predicted transitions of each episode. length: (E,) real ones.
        integers: (N, 2W + 5) per transition: the dense ids of the distinct codes among
            o_1 … o_{t-1}, latest occurrence first (where masks are looked up), their
            embedding rows (-1 after the last, and rare codes are left out), then step,
            current, following and action as in :class:`Transitions`, and the class of
            o_{t+1} (see :meth:`gather`).
        reward: (N,) r_t (divided by max |r|).
    """

    slots: torch.Tensor
    count: torch.Tensor
    length: torch.Tensor
    integers: torch.Tensor
    reward: torch.Tensor

    def gather(self, chosen: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """history codes (n, W), history rows (n, W), step, current, following, action and
        next class (n,) of transitions `chosen` (n,)."""
        positions = (self.integers.shape[1] - 5) // 2
        codes, rows, rest = self.integers[chosen].split([positions, positions, 5], dim=1)
        return codes, rows, *rest.unbind(1)


class CodeData:
    """A pool's episodes as tensors with codes mapped to dense ids 0 … |Ô|-1.

    Attributes:
        observed: (|Ô|,) the observed codes; dense id i stands for observed[i].
        ids: (E, L+1) long dense ids, padding 0 (masked out by `valid`).
        embed_ids: (E, L+1) long, the embedding row of each observation: its dense id, or
            |Ô| (the shared row) for a code seen in fewer than `min_code_episodes` episodes.
        frequent: (|Ô|,) bool, the codes that are not rare (seen in that many episodes).
        actions: (E, L) long. rewards: (E, L) float, divided by max |r|.
        valid: (E, L) bool, real transitions.
        next_class: (E, L) long, class of o_{t+1} (dense id, hashed above max_classes).
        fold: (E,) long, the ensemble member each episode is held out for (-1: for none).
        predicted: (E, L) bool, the transitions p_ζ predicts (the others are explained
            without history: `PredictorConfig.explained_min_count`).
        fit_episodes: the training episodes with a predicted transition.
    """

    def __init__(self, pool: PoolArrays, config: PredictorConfig, num_actions: int) -> None:
        self.observed = np.unique(pool.codes[pool.codes >= 0])
        dense = np.searchsorted(self.observed, np.maximum(pool.codes, 0))
        self.ids = torch.as_tensor(dense, dtype=torch.long)
        self.actions = torch.as_tensor(pool.actions, dtype=torch.long)
        scale = float(np.abs(pool.rewards).max()) or 1.0
        self.rewards = torch.as_tensor(pool.rewards / scale, dtype=torch.float32)
        self.valid = torch.as_tensor(pool.valid)
        # Weight the reward's squared error like a unit-variance Gaussian log-likelihood, so a
        # sparse reward is not drowned by the next-observation cross-entropy.
        self.reward_weight = 1.0 / max(float(self.rewards[self.valid].var()), 1e-3)
        self.num_codes = len(self.observed)
        self.num_classes = min(self.num_codes, config.max_classes)
        self.frequent = self._episodes_with_code() >= config.min_code_episodes
        self.embed_ids = torch.where(self.frequent[self.ids], self.ids, self.num_codes)
        self.next_class = self.ids[:, 1:] % self.num_classes

        self.num_actions = num_actions
        # Folds are dealt by the run's episode number, not the position in this pool: a later
        # round warm-starts member m, which must not then be measured on episodes it was
        # fitted on in an earlier round.
        numbers = np.arange(len(self.ids), dtype=np.int64) + pool.first_episode
        everyone = torch.arange(len(self.ids))
        if config.ensemble >= 2:
            self.fold = torch.as_tensor(deal_folds(numbers, config.ensemble, config.seed))
            self.train = everyone  # every episode is fitted on by all members but one
        else:
            held = _episode_uniforms(numbers, config.seed) < config.holdout_fraction
            if not held.any():  # a tiny pool: hold out one episode all the same
                held[np.argmin(_episode_uniforms(numbers, config.seed))] = True
            self.fold = torch.where(torch.as_tensor(held), 0, -1)
            self.train = everyone[self.fold < 0] if not held.all() else everyone
        self.test = (self.fold >= 0).nonzero().flatten()  # held out for some member
        self.predicted = self._needs_history(config)
        # the fit draws its episodes among those with a transition to predict
        self.fit_episodes = self.train[self.predicted[self.train].any(dim=1)]

    def _needs_history(self, config: PredictorConfig) -> torch.Tensor:
        """(E, L) bool: the transitions p_ζ predicts (module doc, Explained transitions): for
        the reward target, the real transitions whose reward is not fixed by their step, or
        their step and next observation, or their step and (o_t, a_t, o_{t+1}) (judged on the
        *other* transitions of that context, so that whether a transition is predicted does
        not depend on its own reward); for the other targets, every real transition."""
        valid, minimum = self.valid, config.explained_min_count
        if config.target != "reward" or minimum <= 0:
            return valid
        rewards = self.rewards[valid]
        now, following = self.ids[:, :-1][valid], self.ids[:, 1:][valid]
        steps = torch.arange(valid.shape[1]).expand_as(valid)[valid]
        transition = (now * self.num_actions + self.actions[valid]) * self.num_codes + following
        explained = torch.zeros(len(rewards), dtype=torch.bool)
        for context in (steps, torch.stack((steps, following)), torch.stack((steps, transition))):
            explained |= _others_agree(context, rewards, minimum)
        predicted = torch.zeros_like(valid)
        predicted[valid] = ~explained
        return predicted

    def _episodes_with_code(self) -> torch.Tensor:
        """(|Ô|,) long: in how many episodes each code occurs (o_1 … o_{L+1}). Counts distinct
        (episode, code) pairs, so memory stays O(E·L) however large Ô is."""
        lengths = self.valid.sum(dim=1)
        real = torch.arange(self.ids.shape[1]).unsqueeze(0) <= lengths.unsqueeze(1)
        episode = torch.arange(len(self.ids)).unsqueeze(1).expand_as(self.ids)
        pairs = torch.unique(episode[real] * self.num_codes + self.ids[real])
        return torch.bincount(pairs % self.num_codes, minlength=self.num_codes)

    def predicted_transitions(self) -> PredictedTransitions:
        """The predicted transitions of every episode, laid out for the fit's minibatches."""
        episodes, steps = self.predicted.nonzero(as_tuple=True)  # episode by episode
        counts = self.predicted.sum(dim=1)
        slots = torch.full((len(counts), max(int(counts.max()), 1)), -1, dtype=torch.long)
        first = (torch.cumsum(counts, 0) - counts)[episodes]
        slots[episodes, torch.arange(len(episodes)) - first] = torch.arange(len(episodes))
        positions = self.ids.shape[1] - 1  # o_1 … o_L
        codes = self.ids[episodes, :positions].flip(1)  # latest first
        rows = self.embed_ids[episodes, :positions].flip(1)
        later = torch.arange(positions - 1, -1, -1).unsqueeze(0) >= steps.unsqueeze(1)
        unread = later | (rows == self.num_codes)  # o_t and after, and rare codes
        codes, rows = _latest_distinct(codes, rows.masked_fill(unread, -1))
        per_step = (
            steps,
            self.embed_ids[episodes, steps],  # o_t
            self.embed_ids[episodes, steps + 1],  # o_{t+1}
            self.actions[episodes, steps],
            self.next_class[episodes, steps],
        )
        return PredictedTransitions(
            slots=slots,
            count=counts,
            length=self.valid.sum(dim=1),
            integers=torch.cat((codes, rows, torch.stack(per_step, dim=1)), 1),
            reward=self.rewards[episodes, steps],
        )

    def held_out(self, member: int) -> torch.Tensor:
        """Index tensor of the episodes member `member` is measured on (not fitted on)."""
        return (self.fold == member).nonzero().flatten()

    def fit_weights(self, episodes: torch.Tensor, members: torch.Tensor) -> torch.Tensor:
        """(K, B) 1.0 where model k (standing for ensemble member `members[k]`) is fitted on
        the episode, 0.0 where the episode is held out for it."""
        return (self.fold[episodes].unsqueeze(0) != members.unsqueeze(1)).float()

    def dense_ids(self, codes: np.ndarray) -> np.ndarray:
        """Dense ids of `codes` that are in Ô (others are dropped)."""
        codes = np.asarray(codes, dtype=np.int64)
        inside = np.isin(codes, self.observed)
        return np.searchsorted(self.observed, codes[inside])


def _episode_keys(numbers: np.ndarray, seed: int) -> np.ndarray:
    """(N,) uint64 pseudo-random keys of episode numbers (SplitMix64 of number and seed)."""
    with np.errstate(over="ignore"):  # the mixing wraps around 2^64 by design
        z = numbers.astype(np.uint64) + np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return z ^ (z >> np.uint64(31))


def _episode_uniforms(numbers: np.ndarray, seed: int) -> np.ndarray:
    """(N,) float64 in [0, 1), a fixed pseudo-random draw per episode number."""
    return (_episode_keys(numbers, seed) >> np.uint64(11)).astype(np.float64) / 2.0**53


def deal_folds(numbers: np.ndarray, members: int, seed: int) -> np.ndarray:
    """(N,) int64 fold in 0 … members-1 of each episode number: numbers are cut into blocks of
    `members` consecutive episodes and each block is dealt one per fold in a pseudo-random
    order, so an episode keeps its fold in every pool that holds it and the folds of a run of
    consecutive episodes differ in size by at most 2."""
    if len(numbers) == 0:
        return numbers.copy()
    start = numbers.min() // members * members
    blocks = (numbers.max() - start) // members + 1
    keys = _episode_keys(start + np.arange(blocks * members), seed).reshape(blocks, members)
    folds = np.argsort(np.argsort(keys, axis=1), axis=1).reshape(-1)  # rank within the block
    return folds[numbers - start]


@dataclass(frozen=True)
class PredictorState:
    """A fitted (ensemble) predictor, kept to warm-start the next CI round's fit.

    Attributes:
        observed: (|Ô|,) the codes its embedding rows (and output classes, unless hashed)
            stand for.
        parameters: its parameters by name (leading dimension M, the ensemble members).
    """

    observed: np.ndarray
    parameters: dict[str, torch.Tensor]


@dataclass(frozen=True)
class Transitions:
    """The n transitions (o_t, a_t) -> (o_{t+1}, r_t) that a pass predicts, flat.

    Attributes:
        episode: (n,) the row of each transition's episode in the batch.
        step: (n,) t - 1, its 0-based index in the episode.
        current, following: (n,) embedding rows of o_t and o_{t+1}.
        action: (n,) a_t.
        steps: rows of the step table: the longest episode of the batch.
    """

    episode: torch.Tensor
    step: torch.Tensor
    current: torch.Tensor
    following: torch.Tensor
    action: torch.Tensor
    steps: int


class BatchedPredictor(nn.Module):
    """K independent predictors p_ζ evaluated in one pass (parameters lead with K).

    Args:
        num_models: K.
        num_codes: |Ô| (embedding rows: one per code and one shared by the rare codes).
        num_actions: A.
        num_classes: classes of the next-observation head (dynamics target).
        config: sizes and target.
    """

    def __init__(
        self,
        num_models: int,
        num_codes: int,
        num_actions: int,
        num_classes: int,
        config: PredictorConfig,
        max_steps: int = 1,
    ) -> None:
        super().__init__()
        d, h = config.embed_dim, config.hidden_size
        self.target, self.num_actions = config.target, num_actions
        # Inputs beside the history and o_t, and categories of the classification head:
        # dynamics classifies o_{t+1}, inverse classifies a_t, reward has no categorical head.
        # The first layer's inputs, in the order of its weight rows (w1): the history summary
        # and o_t, then what the target adds (a_t for the outcome of an action, o_{t+1} for the
        # reward it pays or the action that led there), the step and the intervened set.
        extra = {
            "dynamics": ("action",),
            "reward": ("action", "following"),
            "inverse": ("following",),
        }
        self.inputs = ("history", "current", *extra[config.target], "when", "intervened")
        self.input_widths = [num_actions if name == "action" else d for name in self.inputs]
        categories = {"dynamics": num_classes, "reward": 0, "inverse": num_actions}[config.target]
        # The categorical head is padded to a multiple of 16 logits, the padding pinned at
        # -1e4 (probability exactly 0 in float32): torch's CPU log-softmax is ~10x slower on a
        # width like 15 than on 16, and it was the largest cost of a CI round.
        self.num_logits = -(-categories // 16) * 16
        offset = torch.zeros(self.num_logits)
        offset[categories:] = -1e4
        self.register_buffer("logit_offset", offset)
        out = self.num_logits + (1 if config.target in REWARD_PART else 0)
        self.embed = nn.Parameter(torch.zeros(num_models, num_codes + 1, d))  # + rare codes' row
        self.mask_embed = nn.Parameter(torch.zeros(num_models, num_codes, d))
        self.step_embed = nn.Parameter(torch.zeros(num_models, max_steps, d))
        self.w1 = nn.Parameter(_uniform(num_models, sum(self.input_widths), h))
        self.b1 = nn.Parameter(torch.zeros(num_models, 1, h))
        self.w2 = nn.Parameter(_uniform(num_models, h, out))
        self.b2 = nn.Parameter(torch.zeros(num_models, 1, out))

    def state(self, observed: np.ndarray) -> PredictorState:
        """The models' parameters, their rows standing for the codes `observed`."""
        return PredictorState(
            observed.copy(), {n: p.detach().clone() for n, p in self.named_parameters()}
        )

    def warm_start(
        self, state: PredictorState, observed: np.ndarray, classes_are_codes: bool
    ) -> None:
        """Start from an earlier round's predictor fitted on codes `state.observed`.

        The pool has moved on: codes seen in both rounds keep their embeddings, and their
        output class if `classes_are_codes` (no hashing of classes in either round); new codes
        start at zero like in a fresh fit, codes that left the pool are dropped.
        """
        old = state.parameters
        _, new_rows, old_rows = np.intersect1d(observed, state.observed, return_indices=True)
        new_rows, old_rows = torch.as_tensor(new_rows), torch.as_tensor(old_rows)
        with torch.no_grad():
            for name in ("embed", "mask_embed"):
                getattr(self, name)[:, new_rows] = old[name][:, old_rows]
            self.embed[:, -1] = old["embed"][:, -1]  # the rare codes' shared row
            steps = min(self.step_embed.shape[1], old["step_embed"].shape[1])
            self.step_embed[:, :steps] = old["step_embed"][:, :steps]
            self.w1.copy_(old["w1"])
            self.b1.copy_(old["b1"])
            if self.target != "dynamics":  # the outputs are the actions or the reward alone
                self.w2.copy_(old["w2"])
                self.b2.copy_(old["b2"])
                return
            # dynamics: the reward output is the last column; class c is dense id c
            self.w2[..., -1], self.b2[..., -1] = old["w2"][..., -1], old["b2"][..., -1]
            if classes_are_codes:
                self.w2[..., new_rows] = old["w2"][..., old_rows]
                self.b2[..., new_rows] = old["b2"][..., old_rows]

    def replicate(
        self,
        copies: int,
        member: int | None = None,
        shared: bool = False,
        members: list[int] | None = None,
    ) -> BatchedPredictor:
        """A (M·copies)-model predictor: `copies` consecutive copies of each of the M models;
        with `member`, `copies` copies of that model alone (with `members`, of those models).
        `shared` (needs `member`): the copies are views of that model's parameters, for
        evaluation only. Copying the embeddings of every arm cost more than the evaluation
        itself on large Ô (App. J with 10^5 codes: 17 arms x 2 x 10^5 x 16 floats per fold
        and pass)."""
        if shared and member is None:
            raise ValueError("shared replicas are views of one member: pass member")
        clone = BatchedPredictor.__new__(BatchedPredictor)
        nn.Module.__init__(clone)
        clone.target, clone.num_actions = self.target, self.num_actions
        clone.inputs, clone.input_widths = self.inputs, self.input_widths
        clone.num_logits = self.num_logits
        clone.register_buffer("logit_offset", self.logit_offset)
        chosen: slice | list[int] = slice(None) if member is None else slice(member, member + 1)
        if members is not None:
            chosen = members
        for name in ("embed", "mask_embed", "step_embed", "w1", "b1", "w2", "b2"):
            value = getattr(self, name).detach()[chosen]
            if shared:
                value = value.expand(copies, *value.shape[1:])
            else:
                value = value.repeat_interleave(copies, dim=0)
            setattr(clone, name, nn.Parameter(value, requires_grad=not shared))
        return clone

    def select(self, members: list[int]) -> BatchedPredictor:
        """A predictor of models `members` alone (their parameters copied), for a split fit."""
        return self.replicate(1, members=members)

    def forward(
        self,
        ids: torch.Tensor,
        masked: torch.Tensor,
        masked_codes: torch.Tensor,
        actions: torch.Tensor,
        valid: torch.Tensor,
    ) -> torch.Tensor:
        """Predictions for the real transitions.

        Args:
            ids: (B, L+1) embedding rows of o_1 … o_{L+1} (`CodeData.embed_ids`).
            masked: (K, B, L+1) bool, True where the history observation is replaced by 0.
            masked_codes: (K, 1 or B, |Ô|) bool, the intervened set: codes masked wherever
                they occur (the same for every episode of an arm, or drawn per episode).
            actions: (B, L).
            valid: (B, L) bool, the real (unpadded) transitions; n of them.

        Returns:
            (K, n, out) outputs for the transitions (o_t, a_t) -> (o_{t+1}, r_t) where valid.
        """
        steps = actions.shape[1]
        # Only the n real transitions are gathered into the first layer's input (K, n, ·).
        rows, cols = valid.nonzero(as_tuple=True)
        history = self._history(ids[:, :steps], masked[:, :, :steps], rows, cols)  # (K, n, d)
        transitions = Transitions(
            rows, cols, ids[rows, cols], ids[rows, cols + 1], actions[rows, cols], steps
        )
        return self.predict(history, transitions, masked_codes)

    def predict(
        self, history: torch.Tensor, transitions: Transitions, masked_codes: torch.Tensor
    ) -> torch.Tensor:
        """(K, n, out) outputs for `transitions` given their history summaries (K, n, d) and
        the intervened set `masked_codes` (K, 1 or B, |Ô|) (see :meth:`forward`)."""
        weights = self._w1
        others = self._table_inputs(weights, transitions, masked_codes)  # (K, n, h)
        hidden = torch.relu(torch.baddbmm(others, history, weights["history"]))
        if self.w2.shape[-1] == 1:
            # the reward target's single output: a batched matrix-vector product through bmm
            # cost ~7x this product-sum (forward and backward, 4 x 2048 x 64 on one thread)
            return (hidden * self.w2.transpose(1, 2)).sum(-1, keepdim=True) + self.b2
        return torch.baddbmm(self.b2, hidden, self.w2)

    def _history(
        self, ids: torch.Tensor, masked: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor
    ) -> torch.Tensor:
        """The history summary h_{t-1} of transitions (rows, cols), (K, n, d): the max of the
        embeddings of the kept observations o_1 … o_{t-1} (the zero vector when none is kept).

        Eq. 3: intervened observations are replaced by zero vectors. The max runs over the
        *kept* history only: a removed observation leaves no trace, not even its slot (a zero
        placeholder would reveal that a masked code was there).

        Args:
            ids: (B, L) embedding rows of o_1 … o_L. masked: (K, B, L) bool, removed.
            rows, cols: (n,) episode and step t - 1 (0-based) of each transition.
        """
        num_models, num_rows, d = self.embed.shape
        if not _few(len(rows), len(ids)):
            # Many transitions per episode: one running max along each episode, read one step
            # back (h_{t-1} excludes o_t). Laid out (K, d, B, L) so that it runs along the
            # contiguous last dimension (~1.4x faster than along L in (K, B, L, d)). F.embedding's
            # backward is far cheaper than that of an indexing with repeated rows.
            table = self.embed.transpose(0, 1).reshape(num_rows, num_models * d)
            hist = nn.functional.embedding(ids, table).view(*ids.shape, num_models, d)
            hist = hist.permute(2, 3, 0, 1).masked_fill(masked.unsqueeze(1), -math.inf)
            seen = torch.cummax(hist, dim=-1).values  # (K, d, B, L): max over o_1 … o_t
            history = seen[:, :, rows, (cols - 1).clamp(min=0)].transpose(1, 2)  # (K, n, d)
            history = history.masked_fill((cols == 0).view(1, -1, 1), -math.inf)
        else:
            # A few transitions per episode (the reward target's predicted ones, ~1.4 per
            # episode on Maze pools): the max over each transition's own history, without a
            # running max (400 steps on a Maze-L1 pool: 3.1 s, against 6.8 s with it).
            after = torch.arange(ids.shape[1]).unsqueeze(0) >= cols.unsqueeze(1)  # (n, L)
            rows_of = ids[rows].masked_fill(after, -1).flip(1)  # -1: a later position
            return self.bag_max(rows_of, masked[:, rows].flip(2))
        return history.masked_fill(torch.isinf(history), 0.0)

    def bag_max(self, rows_of: torch.Tensor, masked: torch.Tensor) -> torch.Tensor:
        """History summaries (K, n, d) of n transitions from their positions, latest first:
        the max of the embedding rows `rows_of` (n, L) (-1: no observation there) that are not
        `masked` (K, n, L), the zero vector when none is left.

        One max-mode embedding_bag per (model, transition): a removed position reads the
        padding row, which the bag skips (an empty bag is the zero vector), and the backward
        pass adds each gradient to the row of its maximum only, never touching the (K, n, L, d)
        embeddings that a gather-then-max builds (its max over L was the costliest op of a
        fitting step; same values and gradients, 0.4 ms against 0.8 ms per step on a Maze-L1
        batch). The bag keeps the first of tied maxima, and positions come latest first, so
        that a tie credits the same (latest) position as the running max (cummax) does.
        """
        return bag_max(self.embed, rows_of, masked)

    @property
    def _w1(self) -> dict[str, torch.Tensor]:
        """The first layer's weights (K, width, h) by input."""
        return dict(zip(self.inputs, self.w1.split(self.input_widths, dim=1), strict=True))

    def _table_inputs(
        self, weights: dict[str, torch.Tensor], transitions: Transitions, masked_codes: torch.Tensor
    ) -> torch.Tensor:
        """b1 + the first layer (`weights`, :attr:`_w1`) applied to every input but the
        history, (K, n, h).

        The first layer is linear, W1·[history, o_t, …] = W_history·history + Σ_i W_i·input_i,
        and every input but the history is a row of a small table: the embeddings of the codes
        in the batch, the actions, the steps, the intervened sets. W_i is applied once per
        table row instead of once per transition, and each transition's rows are summed by one
        embedding_bag. The product with the concatenated input was the largest cost of a
        fitting step; with this and F.embedding for the history, a first-round CI job on
        eleven Maze pools (1000 steps, one thread) took 13.0-16.4 s instead of 16.5-19.7 s.
        """
        # o_t (current) and o_{t+1} (following) are never masked; only the codes of this batch
        # are projected, which keeps the cost bounded on pools of thousands of codes.
        used, which = torch.unique(
            torch.stack((transitions.current, transitions.following)), return_inverse=True
        )
        codes = self.embed[:, used]  # (K, U, d)
        # The model is told *which* codes the intervention masks (not whether they occurred in
        # this episode): one network then stands for the per-intervention minimizers of Eq. 9,
        # and "c is absent" (c was not observed) stays distinct from "c is masked".
        intervened = torch.bmm(
            torch.bmm(masked_codes.to(codes.dtype), self.mask_embed), weights["intervened"]
        )  # (K, 1|B, h)
        # The step embedding lets the predictor know *when* an outcome arrives (e.g. a reward
        # at the horizon); b1 and an intervened set shared by every episode ride along with it.
        when = torch.bmm(self.step_embed[:, : transitions.steps], weights["when"]) + self.b1
        if intervened.shape[1] == 1:
            when = when + intervened
        # (table (K, rows, h), row of each transition (n,)) of each input but the history
        tables = {
            "current": lambda: (torch.bmm(codes, weights["current"]), which[0]),
            "following": lambda: (torch.bmm(codes, weights["following"]), which[1]),
            "action": lambda: (weights["action"], transitions.action),
            "when": lambda: (when, transitions.step),
            "intervened": lambda: (intervened, transitions.episode),
        }
        chosen = [tables[name]() for name in self.inputs[1:]]
        if intervened.shape[1] == 1:
            chosen.pop()  # already in `when`
        table = torch.cat([part for part, _ in chosen], dim=1)  # (K, T, h)
        offsets = np.cumsum([0] + [part.shape[1] for part, _ in chosen[:-1]])
        index = torch.stack(
            [i + int(o) for (_, i), o in zip(chosen, offsets, strict=True)], dim=1
        )  # (n, P)
        # The rows a transition sums are the same for every model: one bag per transition over
        # (T, K·h) rows, 4x fewer indices than a bag per (model, transition).
        num_models, size, h = table.shape
        summed = nn.functional.embedding_bag(
            index, table.transpose(0, 1).reshape(size, num_models * h), mode="sum"
        )  # (n, K·h)
        return summed.view(-1, num_models, h).transpose(0, 1)

    def errors(
        self,
        data: CodeData,
        episodes: torch.Tensor,
        masked: torch.Tensor,
        masked_codes: torch.Tensor,
        transitions: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Per-transition errors (C, K, B, L') (module doc, Estimator; 0 on padding). L' is the
        longest episode among `episodes` (the batch is cropped to it). C = 2 error components
        for dynamics (next observation, reward), else 1. `transitions` (B, L'), if given,
        limits the predictions to those transitions (errors are 0 elsewhere): the history
        summary still runs over every step."""
        flat_errors, _, valid = self._terms(data, episodes, masked, masked_codes, transitions)
        errors = flat_errors.new_zeros(*flat_errors.shape[:2], *valid.shape)
        errors[:, :, valid] = flat_errors
        return errors

    def loss(
        self,
        data: CodeData,
        episodes: torch.Tensor,
        masked: torch.Tensor,
        masked_codes: torch.Tensor,
        weights: torch.Tensor,
    ) -> torch.Tensor:
        """The training loss of each model (K,): the mean over its predicted transitions of the
        negative log-likelihood (squared error for the reward), episodes weighed by `weights`
        (K, B) (cross-fitting gives a member's held-out fold weight 0)."""
        _, per_step, valid = self._terms(
            data, episodes, masked, masked_codes, data.predicted[episodes]
        )
        step_weights = weights.unsqueeze(-1).expand(-1, -1, valid.shape[1])[:, valid]
        return _weighted_mean(per_step, step_weights)

    def transition_loss(
        self,
        data: CodeData,
        table: PredictedTransitions,
        episodes: torch.Tensor,
        masked_codes: torch.Tensor,
        weights: torch.Tensor,
    ) -> torch.Tensor:
        """:meth:`loss` where the masks are whole codes `masked_codes` (K, B, |Ô|), with the
        batch's transitions gathered from `table` (:meth:`CodeData.predicted_transitions`):
        the same loss, bit for bit, in fewer operations. Only for batches of few transitions
        per episode (`FEW_PER_EPISODE`, the history bag's regime)."""
        slots = table.slots[episodes]  # (B, P)
        present = slots >= 0
        chosen = slots[present]  # (n,) the batch's transitions, episode by episode
        episode = present.nonzero(as_tuple=True)[0]
        codes, rows, step, current, following, action, next_class = table.gather(chosen)
        masked = masked_codes[:, episode].gather(2, codes.expand(len(masked_codes), -1, -1))
        history = self.bag_max(rows, masked)  # masked: (K, n, L) positions of masked codes
        steps = int(table.length[episodes].max())
        transitions = Transitions(episode, step, current, following, action, steps)
        out = self.predict(history, transitions, masked_codes & data.frequent)
        targets = {"dynamics": next_class, "inverse": action, "reward": None}[self.target]
        _, per_step = self._outcome_terms(out, table.reward[chosen], targets, data.reward_weight)
        return _weighted_mean(per_step, weights[:, episode])

    def _terms(
        self,
        data: CodeData,
        episodes: torch.Tensor,
        masked: torch.Tensor,
        masked_codes: torch.Tensor,
        transitions: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Errors (C, K, n) and loss terms (K, n) of the n predicted transitions, and where
        they are (B, L')."""
        valid = data.valid[episodes]
        steps = int(valid.sum(dim=1).max())
        valid = valid[:, :steps]
        if transitions is not None:
            valid = valid & transitions[:, :steps]
        ids, actions = data.embed_ids[episodes, : steps + 1], data.actions[episodes, :steps]
        # Rare codes are not seen in the history, nor told as intervened (CodeData.frequent).
        hidden = masked[:, :, : steps + 1] | (ids == data.num_codes)
        masked_codes = masked_codes & data.frequent
        out = self(ids, hidden, masked_codes, actions, valid)  # (K, n, out)
        reward = data.rewards[episodes, :steps][valid]
        targets = {
            "dynamics": lambda: data.next_class[episodes, :steps][valid],
            "inverse": lambda: actions[valid],
            "reward": lambda: None,
        }[self.target]()
        return (*self._outcome_terms(out, reward, targets, data.reward_weight), valid)

    def _outcome_terms(
        self,
        out: torch.Tensor,
        reward: torch.Tensor,
        targets: torch.Tensor | None,
        reward_weight: float,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Errors (C, K, n) and loss terms (K, n) of outputs `out` (K, n, out) for transitions
        with rewards `reward` (n,) and categorical `targets` (n,): the next observation's class
        (dynamics) or the action (inverse); None for the reward target."""
        num_models = out.shape[0]
        true_reward = reward.unsqueeze(0)
        if self.target == "dynamics":
            logits, predicted = out[..., :-1] + self.logit_offset, out[..., -1]
            nll = nn.functional.cross_entropy(
                logits.flatten(0, 1), targets.expand(num_models, -1).flatten(), reduction="none"
            ).view_as(predicted)
            squared = (predicted - true_reward).pow(2)
            return torch.stack((1 - torch.exp(-nll), 2 * squared)), nll + reward_weight * squared
        if self.target == "reward":
            squared = (out[..., -1] - true_reward).pow(2)
            return 2 * squared.unsqueeze(0), reward_weight * squared
        nll = nn.functional.cross_entropy(
            (out + self.logit_offset).flatten(0, 1),
            targets.expand(num_models, -1).flatten(),
            reduction="none",
        ).view(num_models, -1)
        return (1 - torch.exp(-nll)).unsqueeze(0), nll


def effect_bounds(
    folds: list[tuple[torch.Tensor, torch.Tensor]], data: CodeData, config: PredictorConfig
) -> EffectEstimate:
    """The ATE of K interventions and its bounds, from each fold's D_e (C, K, E_m) and where
    the interventions apply (K, E_m) (module doc, Estimator and Confidence)."""
    if config.target in REWARD_PART:
        # The reward part is measured against how much reward there is to predict: a sparse
        # reward (2% of maze episodes early on) would otherwise dilute the effect of what
        # decides it below any threshold, next to observations that matter every step. The
        # floor keeps a nearly reward-free pool from amplifying noise without bound.
        reward_scale = float(data.rewards[data.test].abs().sum(dim=1).mean())
        for fold_extra, _ in folds:
            fold_extra[REWARD_PART[config.target]] /= max(reward_scale, REWARD_SCALE_FLOOR)
    extra = torch.cat([f[0] for f in folds], dim=-1)  # (C, K, E): D_e of each episode
    hit = torch.cat([f[1] for f in folds], dim=-1)  # (K, E): episodes S applies to
    count = hit.sum(dim=1).clamp(min=2)
    mean = extra.sum(dim=-1) / count  # (C, K): the ATE
    # Two estimates of the ATE's variance; the larger counts. Over episodes: the spread of
    # D_e. Over folds: the spread of the members' means, which also holds how each member
    # happened to be fitted (on hard pools this dominated: single fits with different seeds
    # kept the causes of a Maze-L3 pool in one and dropped all of them in the other).
    episode_var = ((extra - mean.unsqueeze(-1)) * hit).pow(2).sum(dim=-1) / (count - 1)
    variance = episode_var / count
    if len(folds) > 1:
        fold_means = torch.stack(
            [f[0].sum(dim=-1) / f[1].sum(dim=-1).clamp(min=1) for f in folds], dim=1
        )  # (C, folds, K)
        variance = torch.maximum(variance, fold_means.var(dim=1) / len(folds))
    margin = config.confidence_z * variance.sqrt()
    return EffectEstimate(
        mean.max(dim=0).values.numpy(),
        (mean - margin).min(dim=0).values.numpy(),
        (mean + margin).max(dim=0).values.numpy(),
    )


def bag_max(embed: torch.Tensor, rows_of: torch.Tensor, masked: torch.Tensor) -> torch.Tensor:
    """(K, n, d): for K models (embedding tables `embed` (K, R, d)) and n bags, the max of
    the rows `rows_of` (n, W) (-1: none) that are not `masked` (K, n, W); the zero vector
    for an empty bag (see :meth:`BatchedPredictor.bag_max`)."""
    num_models, num_rows, d = embed.shape
    padding = num_models * num_rows
    table = torch.cat((embed.reshape(padding, d), embed.new_zeros(1, d)))
    index = rows_of + (torch.arange(num_models) * num_rows).view(-1, 1, 1)  # (K, n, W)
    index = index.masked_fill(masked | (rows_of < 0), padding)
    out = nn.functional.embedding_bag(
        index.view(-1, index.shape[-1]), table, mode="max", padding_idx=padding
    )
    return out.view(num_models, -1, d)


def _latest_distinct(codes: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each history's distinct codes, at their latest occurrence: `codes` and embedding `rows`
    (n, L), latest first, rows -1 where nothing is read, cut to (n, W), W the most distinct
    codes any history holds (rows -1 after them). The history max over these reads the same
    rows in the same order of first occurrence, so it has the values and gradients of the max
    over all L positions; a Maze history of ~20 steps holds ~8 distinct codes, and the max's
    cost goes with the positions it reads."""
    n, positions = codes.shape
    read = rows >= 0
    # one key per (transition, code); a stable sort puts each key's latest position first
    largest = int(codes.max()) if codes.numel() else 0
    key = torch.arange(n).unsqueeze(1) * (largest + 1) + codes
    # a position not read gets a key of its own: it never hides an earlier one of its code
    key = torch.where(read, key, -1 - torch.arange(n * positions).view(n, positions)).flatten()
    ranked = torch.argsort(key, stable=True)
    first = torch.ones(len(ranked), dtype=torch.bool)
    first[1:] = key[ranked[1:]] != key[ranked[:-1]]
    keep = torch.zeros(n * positions, dtype=torch.bool)
    keep[ranked[first]] = True
    keep = keep.view(n, positions) & read
    slot = torch.cumsum(keep, dim=1) - 1
    width = max(int(keep.sum(dim=1).max()) if n else 0, 1)
    out_codes = torch.zeros(n, width, dtype=codes.dtype)
    out_rows = torch.full((n, width), -1, dtype=rows.dtype)
    which, where = keep.nonzero(as_tuple=True)
    out_codes[which, slot[which, where]] = codes[which, where]
    out_rows[which, slot[which, where]] = rows[which, where]
    return out_codes, out_rows


def _few(transitions: int, episodes: int) -> bool:
    """Whether a batch of `episodes` with `transitions` to predict is in the history bag's
    regime (`FEW_PER_EPISODE`)."""
    return transitions <= FEW_PER_EPISODE * episodes


def _weighted_mean(terms: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """(K,) the mean of each model's terms (K, n) weighed by `weights` (K, n)."""
    return (terms * weights).sum(dim=1) / weights.sum(dim=1).clamp(min=1)


def _others_agree(context: torch.Tensor, rewards: torch.Tensor, minimum: int) -> torch.Tensor:
    """(n,) bool: whether at least `minimum` *other* transitions share each transition's
    context (a column of `context`, (n,) or (k, n)) and all of them have one reward. Leaving
    the transition itself out keeps the test blind to its own reward: a rare varying case in
    a context that is otherwise constant is left out whatever it paid, never because of it."""
    group = _group_ids(context)
    groups = int(group.max()) + 1 if len(group) else 0
    low = rewards.new_full((groups,), math.inf).scatter_reduce(0, group, rewards, "amin")
    high = rewards.new_full((groups,), -math.inf).scatter_reduce(0, group, rewards, "amax")
    count = torch.bincount(group, minlength=groups)
    at_low = torch.bincount(group, weights=(rewards == low[group]).double(), minlength=groups)
    at_high = torch.bincount(group, weights=(rewards == high[group]).double(), minlength=groups)
    two_values = (at_low + at_high >= count)[group]  # every reward is the low or the high one
    alone = ((rewards == low[group]) & (at_low[group] == 1)) | (
        (rewards == high[group]) & (at_high[group] == 1)
    )  # the only one with its reward: the others share the other value
    constant = (low == high)[group]
    return (count[group] - 1 >= minimum) & (constant | (two_values & alone))


def _group_ids(context: torch.Tensor) -> torch.Tensor:
    """(n,) long: one id per distinct column of `context` ((n,) or (k, n) integers), the same
    ids as ``torch.unique(context, dim=-1, return_inverse=True)`` gives. Rows are folded in one
    at a time, each fold a 1-D unique of (group so far, next row) packed into one integer. The
    ids are the ranks of the columns in lexicographic order, as unique's are; but unique over
    columns compares them one by one in Python-level loops, which cost ~0.25 s of a Maze-L1
    round's 2.7 s (three contexts of ~12k transitions)."""
    rows = context if context.dim() > 1 else context.unsqueeze(0)
    group = torch.zeros(rows.shape[1], dtype=torch.long)
    if rows.shape[1] == 0:
        return group
    for row in rows:
        _, row = torch.unique(row, return_inverse=True)
        _, group = torch.unique(group * (int(row.max()) + 1) + row, return_inverse=True)
    return group


def fit_members(
    pool: PoolArrays,
    num_actions: int,
    config: PredictorConfig,
    members: list[int],
    warm_start: PredictorState | None = None,
) -> dict[str, torch.Tensor]:
    """The parameters (leading dimension len(members)) that fitting the whole ensemble gives
    members `members`: one part of a split fit (:class:`EffectEstimator`)."""
    estimator = EffectEstimator(pool, num_actions, config, warm_start, members=members)
    return {name: p.detach() for name, p in estimator.base.named_parameters()}


def join_members(parts: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """The parameters of the whole ensemble from its parts, in member order."""
    return {name: torch.cat([part[name] for part in parts]) for name in parts[0]}


def _replicate_state(state: dict[str, Any], copies: int, member: int) -> dict[str, Any]:
    """The Adam state_dict of a BatchedPredictor for its
    :meth:`BatchedPredictor.replicate` (`copies`, `member`)."""
    per_param = {
        index: {
            key: value[member : member + 1].repeat_interleave(copies, dim=0)
            if value.dim() > 0
            else value
            for key, value in entry.items()
        }
        for index, entry in state["state"].items()
    }
    return {"state": per_param, "param_groups": state["param_groups"]}


def _uniform(num_models: int, fan_in: int, fan_out: int) -> torch.Tensor:
    bound = 1 / math.sqrt(fan_in)
    return torch.empty(num_models, fan_in, fan_out).uniform_(-bound, bound)


@dataclass(frozen=True)
class HistoryPairs:
    """Which codes the held-out episodes' histories hold, as (episode, code) pairs, each once:
    sparse, as a dense (episodes × |Ô|) matrix would be 2.1 GB on App. J's 10^5 codes
    (23,077 episodes), and summing it took most of a 60 s search.

    Attributes:
        episodes: (P,) long, held-out episode rows 0 … num_episodes-1.
        codes: (P,) long, dense code ids 0 … num_codes-1.
        num_episodes: E_test, the held-out episodes. num_codes: |Ô|.
    """

    episodes: torch.Tensor
    codes: torch.Tensor
    num_episodes: int
    num_codes: int

    def counts(self) -> torch.Tensor:
        """(|Ô|,) long: held-out episodes holding each code."""
        return torch.bincount(self.codes, minlength=self.num_codes)

    def support(self, codes: np.ndarray) -> int:
        """Held-out episodes holding any of `codes`."""
        hit = torch.isin(self.codes, torch.as_tensor(codes, dtype=torch.long))
        return int(torch.unique(self.episodes[hit]).numel())

    def together(self, rows: np.ndarray, columns: np.ndarray) -> torch.Tensor:
        """(len(rows), len(columns)) long: held-out episodes holding both codes."""
        row, column = self._position(rows), self._position(columns)
        holds = torch.zeros(len(rows), self.num_episodes, dtype=torch.bool)
        in_rows = row >= 0
        holds[row[in_rows], self.episodes[in_rows]] = True
        in_columns = column >= 0
        out = torch.zeros(len(rows), len(columns), dtype=torch.long)
        return out.index_add_(1, column[in_columns], holds[:, self.episodes[in_columns]].long())

    def _position(self, chosen: np.ndarray) -> torch.Tensor:
        """(P,) long: each pair's code's position in `chosen` (distinct dense ids), -1 if not
        there."""
        position = torch.full((self.num_codes,), -1, dtype=torch.long)
        position[torch.as_tensor(chosen, dtype=torch.long)] = torch.arange(len(chosen))
        return position[self.codes]


@dataclass(frozen=True)
class EffectEstimate:
    """The ATEs of K interventions and their confidence bounds (see the module doc).

    Attributes:
        ate: (K,) the ensemble's mean D_e, the largest over the error parts.
        lower: (K,) the smallest over the error parts of mean − z·SE.
        upper: (K,) the largest over the error parts of mean + z·SE.
    """

    ate: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    @staticmethod
    def in_passes(
        one_pass: Callable[[list[Intervention], np.ndarray], EffectEstimate],
        interventions: list[Intervention],
        eliminated: np.ndarray,
        arms_per_pass: int,
    ) -> EffectEstimate:
        """`one_pass` on `arms_per_pass` interventions at a time (each pass with its own
        control arm), joined: memory stays bounded when a tree level tests hundreds of parts."""
        pieces = [
            one_pass(interventions[begin : begin + arms_per_pass], eliminated)
            for begin in range(0, len(interventions), arms_per_pass)
        ]
        if not pieces:
            return EffectEstimate(np.zeros(0), np.zeros(0), np.zeros(0))
        return EffectEstimate(
            *(np.concatenate([getattr(p, f) for p in pieces]) for f in ("ate", "lower", "upper"))
        )


@dataclass(frozen=True)
class Intervention:
    """A set of observations to mask in histories: codes `codes` (dense ids), or, for the
    fine-grained CI of Prop. 1, only the occurrence of those codes at history step `step`."""

    codes: np.ndarray
    step: int | None = None


class EffectEstimator:
    """Fits p_ζ on a pool once, then estimates ATEs of batches of interventions.

    Args:
        pool: the replay pool's arrays.
        num_actions: A.
        config: predictor settings.
        warm_start: an earlier round's predictor to continue (`config.warm_steps` Adam steps
            instead of `config.base_steps` from scratch).
        members: fit only these ensemble members (one part of a split fit, see
            :func:`fit_members`); the estimator then answers no ATEs.
        fitted: every member's fitted parameters (the parts of a split fit joined): skips the
            fit. Not with per-intervention fine-tuning, which continues the fit's Adam state.

    The members are independent (their own initialization, random interventions and held-out
    fold; only the minibatch order is shared), so a fit of some members gives them exactly the
    parameters the whole ensemble's fit does, and two processes can fit half each.
    """

    def __init__(
        self,
        pool: PoolArrays,
        num_actions: int,
        config: PredictorConfig,
        warm_start: PredictorState | None = None,
        members: list[int] | None = None,
        fitted: dict[str, torch.Tensor] | None = None,
    ) -> None:
        if fitted is not None and config.finetune_steps > 0:
            raise ValueError("fine-tuning continues the fit's Adam state: fit in one piece")
        self.config = config
        self.data = CodeData(pool, config, num_actions)
        torch.manual_seed(config.seed)
        self._dropout_generator = torch.Generator().manual_seed(config.seed + 2)
        self._history_pairs: HistoryPairs | None = None  # built by `history_pairs`
        self.base = BatchedPredictor(
            config.ensemble,
            self.data.num_codes,
            num_actions,
            self.data.num_classes,
            config,
            max_steps=self.data.actions.shape[1],
        )
        self._base_optimizer: FlatAdam | None = None
        if fitted is not None:
            with torch.no_grad():
                for name, parameter in self.base.named_parameters():
                    parameter.copy_(fitted[name])
            return
        steps, whole = config.base_steps, False
        if warm_start is not None:
            largest = max(self.data.num_codes, len(warm_start.observed))
            self.base.warm_start(
                warm_start, self.data.observed, classes_are_codes=largest <= config.max_classes
            )
            steps = config.warm_steps
        elif config.whole_batch_steps > 0:
            predicted = int(self.data.predicted[self.data.fit_episodes].sum())
            if predicted <= config.batch_transitions:
                steps, whole = config.whole_batch_steps, True
        masks = self._random_code_dropout
        if members is not None:
            self.base = self.base.select(list(members))
            masks = self._dropout_of(list(members))
        fitted_members = torch.arange(config.ensemble) if members is None else torch.tensor(members)
        self._base_optimizer = self._fit(self.base, fitted_members, masks, steps, whole=whole)

    @property
    def history_pairs(self) -> HistoryPairs:
        """Which codes lie in the history (before the last transition) of each held-out
        episode, the episodes ATEs are estimated from (:class:`HistoryPairs`)."""
        if self._history_pairs is None:
            ids, valid = self.data.ids[self.data.test], self.data.valid[self.data.test]
            # o_j is in the history of transition t > j: of a real transition when j + 1 is one
            in_history = torch.zeros_like(ids, dtype=torch.bool)
            in_history[:, : valid.shape[1] - 1] = valid[:, 1:]
            rows = torch.arange(len(ids)).unsqueeze(1).expand_as(ids)
            pairs = torch.unique(rows[in_history] * self.data.num_codes + ids[in_history])
            num_codes = self.data.num_codes
            self._history_pairs = HistoryPairs(
                pairs // num_codes, pairs % num_codes, len(ids), num_codes
            )
        return self._history_pairs

    def support(self, codes: np.ndarray) -> int:
        """Held-out episodes whose history holds any of `codes` (dense ids): the episodes an
        ATE of that set is estimated from."""
        return self.history_pairs.support(codes)

    def state(self) -> PredictorState:
        """The fitted base predictor, to warm-start the next round."""
        return self.base.state(self.data.observed)

    def _optimizer(self) -> FlatAdam:
        assert self._base_optimizer is not None, "fitted elsewhere: no Adam state to continue"
        return self._base_optimizer

    def _random_code_dropout(self, episodes: torch.Tensor) -> tuple[None, torch.Tensor]:
        """Random interventions: whole codes removed from each episode's history at a rate
        drawn per episode uniformly from [0, 1]. Returns None for the masked positions (whole
        codes are masked wherever they occur, see :meth:`_fit`) and the masked codes
        (M, B, |Ô|), drawn independently for each of the M members.

        Training the base predictor under random interventions of every size keeps it from
        leaning on any one frequent observation and makes heavily masked histories familiar,
        so every warm-started intervention adapts in a few steps instead of paying a spurious
        're-learning' cost that would look like a causal effect.
        """
        generator, members = self._dropout_generator, self.config.ensemble
        shape = (members, len(episodes))
        rate = torch.rand(*shape, 1, generator=generator) * self.config.code_dropout
        return None, torch.rand(*shape, self.data.num_codes, generator=generator) < rate

    def _dropout_of(self, members: list[int]):
        """:meth:`_random_code_dropout` for some members: drawn for all of them and sliced, so
        each member's draws are those of the whole ensemble's fit."""

        def draw(episodes: torch.Tensor) -> tuple[None, torch.Tensor]:
            return None, self._random_code_dropout(episodes)[1][members]

        return draw

    def _fit(
        self,
        model: BatchedPredictor,
        members: torch.Tensor,
        masks,
        steps: int,
        optimizer_state: dict[str, Any] | None = None,
        whole: bool = False,
    ) -> FlatAdam:
        """Adam on minibatches of training episodes; the minibatch order depends only on the
        seed, so every model fine-tuned for the same number of steps sees the same batches.
        With `whole`, every step takes all training episodes, and the rate falls linearly from
        `whole_batch_learning_rate` (`PredictorConfig.whole_batch_steps`).
        Model k stands for ensemble member `members[k]` and skips the episodes held out for it.
        `masks` maps a batch of episodes to (masked positions (K, B, L+1), masked codes
        (K, 1 or B, |Ô|)), the positions None where whole codes are masked wherever they occur.
        `optimizer_state` continues an earlier fit's Adam moments."""
        optimizer = FlatAdam(model.parameters(), lr=self.config.learning_rate)
        if optimizer_state is not None:
            optimizer.load_state_dict(optimizer_state)
        generator = torch.Generator().manual_seed(self.config.seed + 1)
        train = self.data.fit_episodes
        if len(train) == 0:  # nothing needs the history: every ATE is 0
            return optimizer
        mean_length = float(self.data.predicted[train].sum(dim=1).float().mean())
        by_length = max(1, round(self.config.batch_transitions / max(mean_length, 1.0)))
        size = min(self.config.batch_episodes, by_length, len(train))
        # Few transitions per episode (the reward target): gather each batch's from a table
        # laid out once (BatchedPredictor.transition_loss, the same loss in fewer operations).
        table = self.data.predicted_transitions() if mean_length <= FEW_PER_EPISODE else None
        if whole:
            episodes, weights = train, self.data.fit_weights(train, members)
        for step in range(steps):
            if whole:
                optimizer.lr = self.config.whole_batch_learning_rate * (1 - step / steps)
            else:
                episodes = train[torch.randint(len(train), (size,), generator=generator)]
                weights = self.data.fit_weights(episodes, members)
            masked, masked_codes = masks(episodes)
            if (
                masked is None
                and table is not None
                and _few(int(table.count[episodes].sum()), len(episodes))
            ):
                loss = model.transition_loss(self.data, table, episodes, masked_codes, weights)
            else:
                if masked is None:  # whole codes, wherever they occur in the episodes
                    ids = self.data.ids[episodes].expand(len(masked_codes), -1, -1)
                    masked = masked_codes.gather(2, ids)
                loss = model.loss(self.data, episodes, masked, masked_codes, weights)
            optimizer.zero_grad()
            loss.sum().backward()
            optimizer.step()
        return optimizer

    def _mask_builder(self, interventions: list[Intervention], eliminated: np.ndarray):
        """A function of a minibatch of episodes returning (masked, masked_codes, tested):
        positions replaced by zero vectors (K, B, L+1), the masked codes (K, 1, |Ô|), and the
        positions holding the tested observations (K, B, L+1)."""
        num_codes, positions = self.data.num_codes, self.data.ids.shape[1]
        member = torch.zeros(len(interventions), num_codes, dtype=torch.bool)
        at_step = torch.ones(len(interventions), positions, dtype=torch.bool)
        for k, intervention in enumerate(interventions):
            member[k, torch.as_tensor(intervention.codes, dtype=torch.long)] = True
            if intervention.step is not None:
                at_step[k] = False
                at_step[k, intervention.step] = True
        in_eliminated = torch.zeros(num_codes, dtype=torch.bool)
        in_eliminated[torch.as_tensor(eliminated, dtype=torch.long)] = True

        masked_codes = (member | in_eliminated).unsqueeze(1)

        def build(episodes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            ids = self.data.ids[episodes]
            tested = member[:, ids] & at_step.unsqueeze(1)
            return tested | in_eliminated[ids].unsqueeze(0), masked_codes, tested

        return build

    def ate(self, interventions: list[Intervention], eliminated: np.ndarray) -> EffectEstimate:
        """ATE bounds of each intervention given the eliminated set O^w (dense ids),
        `arms_per_pass` interventions at a time."""
        return EffectEstimate.in_passes(
            self._ate_pass, interventions, eliminated, self.config.arms_per_pass
        )

    def _ate_pass(
        self, interventions: list[Intervention], eliminated: np.ndarray
    ) -> EffectEstimate:
        """:meth:`ate` for interventions evaluated side by side in one pass."""
        # Arm 0 is the control: O^w masked, nothing else (fine-tuned on the same batches when
        # fine-tuning), so what masking O^w costs cancels out of every ATE.
        control = Intervention(np.zeros(0, dtype=np.int64))
        masks = self._mask_builder([control, *interventions], eliminated)
        # Each member is measured on the fold it was not fitted on (cross-fitting).
        folds = [
            self._fold_effects(member, held_out, masks, len(interventions))
            for member in range(self.config.ensemble)
            if len(held_out := self.data.held_out(member)) > 0
        ]
        return effect_bounds(folds, self.data, self.config)

    def _fold_effects(
        self, member: int, episodes: torch.Tensor, masks, num_interventions: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """D_e of each intervention on the episodes held out for `member` (C, K, E_m) and
        where it applies (K, E_m): the member's extra error with S ∪ O^w masked over O^w
        masked, summed over the transitions whose history holds an observation of S."""
        arms = num_interventions + 1
        components = 2 if self.config.target == "dynamics" else 1
        masked, masked_codes, tested = masks(episodes)
        steps = int(self.data.valid[episodes].sum(dim=1).max())
        # transition t counts when a tested observation lies in h_{t-1} (positions < t)
        seen = torch.cummax(tested[1:, :, :steps].int(), dim=2).values.bool()
        applies = torch.cat((torch.zeros_like(seen[:, :, :1]), seen[:, :, :-1]), dim=2)
        applies &= self.data.valid[episodes, :steps].unsqueeze(0)
        hit = applies.any(dim=2)  # (K, E_m)
        extra = torch.zeros(components, num_interventions, len(episodes))
        # Only the transitions some intervention applies to enter an ATE, so only they are
        # predicted: a rare observation's intervention touches a few episodes, and on BabyAI
        # pools (thousands of codes) this is most of the search's cost.
        needed = applies.any(dim=0) & self.data.predicted[episodes, :steps]  # (E_m, L')
        hit_any = needed.any(dim=1)
        if not hit_any.any():
            return extra, hit
        tuned = self.config.finetune_steps > 0  # fine-tuned arms need parameters of their own
        model = self.base.replicate(arms, member=member, shared=not tuned)
        if tuned:
            # Fine-tuning continues the base fit's Adam moments: a fresh Adam's first steps
            # move every weight by about the learning rate whatever its gradient, noise that
            # would differ between arms and read as (negative or positive) effects.
            self._fit(
                model,
                torch.full((arms,), member),
                lambda batch: masks(batch)[:2],
                self.config.finetune_steps,
                _replicate_state(self._optimizer().state_dict(), arms, member),
            )
        with torch.no_grad():
            errors = model.errors(
                self.data,
                episodes[hit_any],
                masked[:, hit_any],
                masked_codes,
                transitions=needed[hit_any],
            )  # (C, arms, E_hit, L'')
        applies = applies[:, hit_any, : errors.shape[-1]]
        extra[:, :, hit_any] = ((errors[:, 1:] - errors[:, :1]) * applies).sum(dim=-1)
        return extra, hit

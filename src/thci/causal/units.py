"""Cell-value interventions: counterfactual inference whose units are the values of cells.

The search of :mod:`thci.causal.search` tests sets of *units*; by default a unit is an
observation code (:mod:`thci.causal.discretize`), and an intervention removes whole observations
from the histories (Eq. 3). On images of categorical cells (minigrid's (object, colour, state)
views) that unit is too fine: on a BabyAI-L2 pool of 2,000 episodes 947 of ~3,850 cell-set codes
show the signpost, each too rarely to be decided, and no threshold ξ gave a usable gate
(docs/babyai.md). With ``--ci-units cells`` a unit is one *cell value* instead (a red wall, a
grey door that is open), wherever it appears in a view: there are a few dozen of them, each seen
in hundreds of episodes.

An intervention Do(S) on a set S of cell values removes those values from every view of the
history h_{t-1}; the rest of each view stays (the intervention of Eq. 3 applied to the factors
of the observation instead of the whole). The effect predictor p_ζ is the reward target's
(:mod:`thci.causal.predictor`, p(r_t | h, o_t, a_t, o_{t+1})) over these factors:

* a view's embedding is the max of the learned embeddings of its cell values (o_t and o_{t+1},
  never masked);
* the history summary is the max of the embeddings of the cell values seen in o_1 … o_{t-1}
  that are not masked (order-free, as the code predictor's);
* the intervened set is told by the sum of learned embeddings of its units.

Everything else is the code predictor's and shared with it: the transitions it predicts (those
the transition itself does not explain), cross-fitting over an ensemble with random
interventions (units removed at a rate drawn from U[0, 1] per episode), and the ATE with its
confidence bounds (:func:`thci.causal.predictor.effect_bounds`): D_e(S) sums, over the
transitions whose history holds a unit of S, the extra error that masking S beside O^w causes.

The search returns the units without effect (O^w). A *view* then has no causal effect when
every cell value in it is in O^w: :func:`codes_result` turns the units' result into the codes'
one, which the gate (Eq. 10) and the causal memory use unchanged: a view stays in memory iff it
shows a kept cell value. Units are cell values encoded as integers
(:func:`cell_units`), so they mean the same in every round and across resumed runs.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from thci.causal.flat_adam import FlatAdam
from thci.causal.predictor import (
    CodeData,
    EffectEstimate,
    HistoryPairs,
    Intervention,
    PredictorConfig,
    PredictorState,
    _others_agree,
    bag_max,
    effect_bounds,
)
from thci.causal.replay import PoolArrays
from thci.causal.search import CIResult
from thci.errors import ThciError

UNIT_RADIX = 256
"""Cell values are integers in [0, UNIT_RADIX); a cell's unit id is its values in this radix."""
UNIT_EMBED_DIM = 32
UNIT_HIDDEN_SIZE = 128
"""Widths of the unit predictor (the code predictor's 16 / 64 gave the signpost of a level-2
pool an ATE of 0.15 [0.10, 0.19] where these give 0.22 [0.17, 0.28], 1000 steps)."""
MAX_CELL_SIZE = 7
"""Values per cell a unit id can hold in an int64 (256**7 < 2**63)."""


def cell_units(observation: np.ndarray, layout: tuple[int, int, int]) -> np.ndarray:
    """The sorted distinct unit ids (int64) of the cells of one flat observation (D,).

    `layout` is (offset, cells, values per cell) (``--cell-layout``); the entries outside the
    cells (e.g. minigrid's heading) are not units.
    """
    offset, num_cells, cell_size = layout
    if cell_size > MAX_CELL_SIZE:
        raise ThciError(
            f"--ci-units cells codes a cell of up to {MAX_CELL_SIZE} values, the layout has "
            f"{cell_size}; use --ci-units observations"
        )
    cells = np.asarray(observation[offset : offset + num_cells * cell_size], dtype=np.float64)
    values = np.rint(cells).astype(np.int64)
    if (
        len(values) < num_cells * cell_size
        or np.any(values != cells)
        or values.min() < 0
        or values.max() >= UNIT_RADIX
    ):
        raise ThciError(
            f"--ci-units cells needs {num_cells} cells of {cell_size} integer values in "
            f"[0, {UNIT_RADIX}) after {offset} entries (--cell-layout), such as minigrid's "
            "(object, colour, state); use --ci-units observations"
        )
    weights = UNIT_RADIX ** np.arange(cell_size, dtype=np.int64)
    return np.unique(values.reshape(num_cells, cell_size) @ weights)


def unit_value(unit: int, cell_size: int) -> list[int]:
    """The cell values a unit id stands for (inverse of :func:`cell_units`' coding)."""
    return [int(unit) // UNIT_RADIX**i % UNIT_RADIX for i in range(cell_size)]


def codes_result(units: CIResult, units_of_code: dict[int, np.ndarray]) -> CIResult:
    """The codes' result of a search over units: a code is causal iff its view holds a causal
    unit, confirmed iff it holds a confirmed one, eliminated otherwise. The interventions stay
    those of the search (over units); ``units`` keeps the units' result."""
    observed = np.array(sorted(units_of_code), dtype=np.int64)
    holds = [np.isin(units_of_code[int(c)], units.causal).any() for c in observed]
    confirmed = [np.isin(units_of_code[int(c)], units.confirmed).any() for c in observed]
    causal = np.asarray(holds, dtype=bool)
    return CIResult(
        units.algorithm,
        observed,
        observed[~causal],
        observed[causal],
        observed[np.asarray(confirmed, dtype=bool)],
        units.interventions,
        units.seconds,
        units=units,
    )


class UnitData:
    """A pool's episodes for cell-value interventions.

    Attributes:
        codes: the pool as :class:`CodeData` (transitions to predict, folds, rewards).
        observed: (U,) the unit ids in the pool; dense unit i stands for observed[i] (the
            space the search splits).
        num_codes: U (named as CodeData's: the search reads it).
        frequent: (U,) bool, units seen in at least `min_code_episodes` episodes; the others
            are left out of every view (too rare to learn or to decide).
        first: (E, U) long, the first position (0 … L) of each unit in each episode, L + 2 if
            it never occurs.
        code_units: (|Ô|, W) dense frequent units of each code's view, -1 after them.
        episode, step: (n,) the episode and 0-based step of each predicted transition.
        predicted: (E, L) bool, the transitions p_ζ predicts: the code predictor's
            (:attr:`CodeData.predicted`) less those :func:`_explained_by_ending` explains.
        fit_episodes: the training episodes with a predicted transition.
        slots: (E, P) the predicted transitions of each episode (indices into those), -1 after.
    """

    def __init__(
        self,
        pool: PoolArrays,
        config: PredictorConfig,
        num_actions: int,
        units_of_code: dict[int, np.ndarray],
    ) -> None:
        if config.target != "reward":
            raise ThciError(
                f"--ci-units cells predicts the reward (--ci-target reward), got "
                f"--ci-target {config.target}"
            )
        self.codes = codes = CodeData(pool, config, num_actions)
        missing = [int(c) for c in codes.observed if int(c) not in units_of_code]
        if missing:
            raise ValueError(f"no units for codes {missing[:5]}")
        self.observed = np.unique(np.concatenate([units_of_code[int(c)] for c in codes.observed]))
        self.num_codes = num_units = len(self.observed)
        per_code = [np.searchsorted(self.observed, units_of_code[int(c)]) for c in codes.observed]
        width = max(len(u) for u in per_code)
        all_units = torch.full((codes.num_codes, width), -1, dtype=torch.long)
        for row, units in enumerate(per_code):
            all_units[row, : len(units)] = torch.as_tensor(units)

        # first position of each unit in each episode (scatter-min over the views' units)
        num_episodes, positions = codes.ids.shape
        lengths = codes.valid.sum(dim=1)
        real = torch.arange(positions).unsqueeze(0) <= lengths.unsqueeze(1)  # o_1 … o_{L+1}
        units = all_units[codes.ids].masked_fill(~real.unsqueeze(-1), -1)  # (E, L+1, W)
        never = positions + 1
        first = torch.full((num_episodes, num_units + 1), never, dtype=torch.long)
        where = torch.arange(positions).view(1, -1, 1).expand_as(units)
        first.scatter_reduce_(
            1, units.masked_fill(units < 0, num_units).flatten(1), where.flatten(1), "amin"
        )
        self.first = first[:, :num_units]
        counts = (self.first < never).sum(dim=0)
        self.frequent = counts >= config.min_code_episodes
        self.code_units = torch.where(
            (all_units >= 0) & self.frequent[all_units.clamp(min=0)], all_units, -1
        )

        self.predicted = codes.predicted & ~_explained_by_ending(codes, config)
        self.fit_episodes = codes.train[self.predicted[codes.train].any(dim=1)]
        self.episode, self.step = self.predicted.nonzero(as_tuple=True)  # episode by episode
        per_episode = self.predicted.sum(dim=1)
        self.slots = torch.full((num_episodes, max(int(per_episode.max()), 1)), -1)
        start = (torch.cumsum(per_episode, 0) - per_episode)[self.episode]
        self.slots[self.episode, torch.arange(len(self.episode)) - start] = torch.arange(
            len(self.episode)
        )

    def history(self, transitions: torch.Tensor) -> torch.Tensor:
        """(n, W) the dense frequent units in the history o_1 … o_{t-1} of `transitions`
        (indices of predicted transitions), -1 after them; W the most any of them holds."""
        episode, step = self.episode[transitions], self.step[transitions]
        present = (self.first[episode] < step.unsqueeze(1)) & self.frequent
        width = max(int(present.sum(dim=1).max()) if len(present) else 0, 1)
        order = torch.argsort((~present).to(torch.uint8), dim=1, stable=True)[:, :width]
        return torch.where(present.gather(1, order), order, -1)

    def transitions_of(self, episodes: torch.Tensor) -> torch.Tensor:
        """(n,) the predicted transitions of `episodes`, episode by episode."""
        slots = self.slots[episodes]
        return slots[slots >= 0]

    def in_history(self, episodes: torch.Tensor) -> torch.Tensor:
        """(B, U) bool: whether each unit lies in the history of some transition of each
        episode (positions 0 … L-2), i.e. whether an intervention on it applies there."""
        lengths = self.codes.valid[episodes].sum(dim=1)
        return self.first[episodes] <= (lengths - 2).unsqueeze(1)

    def dense_ids(self, units: np.ndarray) -> np.ndarray:
        """Dense ids of the unit ids `units` that are in the pool (others are dropped)."""
        units = np.asarray(units, dtype=np.int64)
        return np.searchsorted(self.observed, units[np.isin(units, self.observed)])


def _explained_by_ending(codes: CodeData, config: PredictorConfig) -> torch.Tensor:
    """(E, L) bool: transitions whose reward is fixed by whether they end their episode.

    The code predictor explains a transition by other transitions of its step and next view
    (:meth:`CodeData._needs_history`); on BabyAI nearly every view is rare, so it explained
    almost nothing (a level-2 pool: 33 predicted transitions per episode, 2.6% of them the
    episode's last, the only ones that pay) and the fit spent its batches on rewards of 0.
    Whether a transition ends the episode is part of the transition: where every transition
    that does not end one pays the same (minigrid pays only at the end), they are explained,
    judged as the code predictor does, on the *other* transitions of the context."""
    valid = codes.valid
    lengths = valid.sum(dim=1, keepdim=True)
    ending = (torch.arange(valid.shape[1]).unsqueeze(0) == lengths - 1)[valid].long()
    explained = torch.zeros_like(valid)
    explained[valid] = _others_agree(ending, codes.rewards[valid], config.explained_min_count)
    return explained


class UnitPredictor(nn.Module):
    """K independent reward predictors over cell-value units, evaluated in one pass.

    Unlike the code predictor it is not told the step t: the final transitions it predicts
    on BabyAI are one per episode, and a learned embedding per step let it memorize rewards by
    episode length (a level-2 pool, 1000 steps: held-out squared error 0.203 with the step,
    0.117 without; the signpost's ATE 0.12 and 0.22).

    Args:
        num_models: K. num_units: U. num_actions: A.
    """

    def __init__(self, num_models: int, num_units: int, num_actions: int) -> None:
        super().__init__()
        d, h = UNIT_EMBED_DIM, UNIT_HIDDEN_SIZE
        self.num_actions = num_actions
        # Small random unit embeddings: a view's embedding is a max over ~10 of them, and with
        # equal (zero) rows only the first unit of each view would get a gradient.
        self.embed = nn.Parameter(torch.randn(num_models, num_units, d) * 0.1)
        self.mask_embed = nn.Parameter(torch.zeros(num_models, num_units, d))
        fan_in = 4 * d + num_actions  # history, o_t, o_{t+1}, intervened set; a_t
        bound = 1 / fan_in**0.5
        self.w1 = nn.Parameter(torch.empty(num_models, fan_in, h).uniform_(-bound, bound))
        self.b1 = nn.Parameter(torch.zeros(num_models, 1, h))
        self.w2 = nn.Parameter(torch.empty(num_models, h, 1).uniform_(-(h**-0.5), h**-0.5))
        self.b2 = nn.Parameter(torch.zeros(num_models, 1, 1))

    def forward(
        self,
        data: UnitData,
        transitions: torch.Tensor,
        history: torch.Tensor,
        masked: torch.Tensor,
    ) -> torch.Tensor:
        """Predicted rewards (K, n) of predicted `transitions` (n,) with history units
        `history` (n, W) (:meth:`UnitData.history`) and the masked units `masked` (K, n or 1,
        U) (removed from the history, and told)."""
        num_models = self.embed.shape[0]
        n = len(transitions)
        masked_history = masked.expand(num_models, n, -1).gather(
            2, history.clamp(min=0).expand(num_models, -1, -1)
        )
        episode, step = data.episode[transitions], data.step[transitions]
        ids = data.codes.ids
        never = torch.zeros(num_models, n, data.code_units.shape[1], dtype=torch.bool)
        inputs = [
            bag_max(self.embed, history, masked_history),
            bag_max(self.embed, data.code_units[ids[episode, step]], never),  # o_t
            bag_max(self.embed, data.code_units[ids[episode, step + 1]], never),  # o_{t+1}
            torch.bmm((masked & data.frequent).float(), self.mask_embed).expand(-1, n, -1),
            nn.functional.one_hot(data.codes.actions[episode, step], self.num_actions)
            .float()
            .expand(num_models, -1, -1),
        ]
        hidden = torch.relu(torch.baddbmm(self.b1, torch.cat(inputs, dim=-1), self.w1))
        return torch.baddbmm(self.b2, hidden, self.w2).squeeze(-1)

    def member(self, member: int, copies: int) -> UnitPredictor:
        """`copies` views of model `member`'s parameters (evaluation only)."""
        clone = UnitPredictor.__new__(UnitPredictor)
        nn.Module.__init__(clone)
        clone.num_actions = self.num_actions
        for name, parameter in self.named_parameters():
            value = parameter.detach()[member : member + 1].expand(copies, *parameter.shape[1:])
            setattr(clone, name, nn.Parameter(value, requires_grad=False))
        return clone


class UnitEffectEstimator:
    """Fits the unit predictor on a pool once, then estimates ATEs of sets of units; the
    interface :func:`thci.causal.search.t_hci` and :func:`~thci.causal.search.hci` use
    (``data.observed``, ``data.num_codes``, :meth:`ate`, :meth:`support`,
    :attr:`history_pairs`), with units in place of codes.

    Args:
        pool: the replay pool's arrays. num_actions: A. config: predictor settings.
        units_of_code: every code of the pool -> its view's unit ids (:func:`cell_units`).
        warm_start: an earlier round's unit predictor to continue for `config.warm_steps`.
    """

    def __init__(
        self,
        pool: PoolArrays,
        num_actions: int,
        config: PredictorConfig,
        units_of_code: dict[int, np.ndarray],
        warm_start: PredictorState | None = None,
    ) -> None:
        self.config = config
        self.data = UnitData(pool, config, num_actions, units_of_code)
        torch.manual_seed(config.seed)
        self.model = UnitPredictor(config.ensemble, self.data.num_codes, num_actions)
        steps = config.base_steps
        if warm_start is not None:
            self._warm_start(warm_start)
            steps = config.warm_steps
        self._history_pairs: HistoryPairs | None = None
        self._fit(steps)

    def _warm_start(self, state: PredictorState) -> None:
        """Units seen in both rounds keep their embeddings; new units start fresh."""
        old = state.parameters
        _, new_rows, old_rows = np.intersect1d(
            self.data.observed, state.observed, return_indices=True
        )
        new_rows, old_rows = torch.as_tensor(new_rows), torch.as_tensor(old_rows)
        with torch.no_grad():
            for name in ("embed", "mask_embed"):
                getattr(self.model, name)[:, new_rows] = old[name][:, old_rows]
            for name in ("w1", "b1", "w2", "b2"):
                getattr(self.model, name).copy_(old[name])

    def state(self) -> PredictorState:
        """The fitted predictor, to warm-start the next round."""
        return PredictorState(
            self.data.observed.copy(),
            {n: p.detach().clone() for n, p in self.model.named_parameters()},
        )

    def _fit(self, steps: int) -> None:
        """Adam on minibatches of training episodes under random unit interventions (each
        member its own, at a rate drawn per episode from U[0, `code_dropout`]); member m skips
        the episodes held out for it."""
        data, cfg = self.data, self.config
        train = data.fit_episodes
        if len(train) == 0:  # nothing needs the history: every ATE is 0
            return
        optimizer = FlatAdam(self.model.parameters(), lr=cfg.learning_rate)
        order = torch.Generator().manual_seed(cfg.seed + 1)
        dropout = torch.Generator().manual_seed(cfg.seed + 2)
        members = torch.arange(cfg.ensemble)
        mean_length = float(data.predicted[train].sum(dim=1).float().mean())
        size = min(cfg.batch_episodes, max(1, round(cfg.batch_transitions / mean_length)))
        size = min(size, len(train))
        for _ in range(steps):
            episodes = train[torch.randint(len(train), (size,), generator=order)]
            rate = torch.rand(cfg.ensemble, size, 1, generator=dropout) * cfg.code_dropout
            drop = torch.rand(cfg.ensemble, size, data.num_codes, generator=dropout) < rate
            transitions = data.transitions_of(episodes)
            row = torch.repeat_interleave(
                torch.arange(size), data.predicted[episodes].sum(dim=1)
            )  # each transition's episode in the batch
            predicted = self.model(data, transitions, data.history(transitions), drop[:, row])
            target = data.codes.rewards[data.episode[transitions], data.step[transitions]]
            weights = data.codes.fit_weights(episodes, members)[:, row]
            squared = (predicted - target).pow(2) * data.codes.reward_weight
            loss = (squared * weights).sum(dim=1) / weights.sum(dim=1).clamp(min=1)
            optimizer.zero_grad()
            loss.sum().backward()
            optimizer.step()

    @property
    def history_pairs(self) -> HistoryPairs:
        """Which units lie in the history of each held-out episode (:class:`HistoryPairs`)."""
        if self._history_pairs is None:
            test = self.data.codes.test
            rows, units = self.data.in_history(test).nonzero(as_tuple=True)
            self._history_pairs = HistoryPairs(rows, units, len(test), self.data.num_codes)
        return self._history_pairs

    def support(self, units: np.ndarray) -> int:
        """Held-out episodes whose history holds any of `units` (dense ids)."""
        return self.history_pairs.support(units)

    def ate(self, interventions: list[Intervention], eliminated: np.ndarray) -> EffectEstimate:
        """ATE bounds of each intervention (a set of dense unit ids) given the eliminated
        units O^w, `arms_per_pass` interventions at a time."""
        if any(i.step is not None for i in interventions):
            raise ThciError(
                "fine-grained CI (one history step at a time) needs --ci-units observations"
            )
        return EffectEstimate.in_passes(
            self._ate_pass, interventions, eliminated, self.config.arms_per_pass
        )

    def _ate_pass(
        self, interventions: list[Intervention], eliminated: np.ndarray
    ) -> EffectEstimate:
        """:meth:`ate` for interventions side by side; arm 0 is the control (O^w alone)."""
        tested = torch.zeros(len(interventions) + 1, self.data.num_codes, dtype=torch.bool)
        for k, intervention in enumerate(interventions, start=1):
            tested[k, torch.as_tensor(intervention.codes, dtype=torch.long)] = True
        in_eliminated = torch.zeros(self.data.num_codes, dtype=torch.bool)
        in_eliminated[torch.as_tensor(eliminated, dtype=torch.long)] = True
        masked = tested | in_eliminated
        folds = [
            self._fold_effects(member, held_out, tested[1:], masked)
            for member in range(self.config.ensemble)
            if len(held_out := self.data.codes.held_out(member)) > 0
        ]
        return effect_bounds(folds, self.data.codes, self.config)

    def _fold_effects(
        self, member: int, episodes: torch.Tensor, tested: torch.Tensor, masked: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """D_e (1, K, E_m) of the K interventions `tested` (K, U) on the episodes held out for
        `member`, and where they apply (K, E_m); `masked` (K + 1, U) are the arms' masks."""
        data = self.data
        hit = (data.in_history(episodes).unsqueeze(0) & tested.unsqueeze(1)).any(dim=-1)
        extra = torch.zeros(1, len(tested), len(episodes))
        transitions = data.transitions_of(episodes)
        if len(transitions) == 0:
            return extra, hit
        history = data.history(transitions)
        holds = torch.zeros(len(transitions), data.num_codes + 1, dtype=torch.bool)
        holds.scatter_(1, history.masked_fill(history < 0, data.num_codes), True)
        applies = (holds[:, :-1].unsqueeze(0) & tested.unsqueeze(1)).any(dim=-1)  # (K, n)
        needed = applies.any(dim=0)
        if not needed.any():
            return extra, hit
        transitions, history, applies = transitions[needed], history[needed], applies[:, needed]
        model = self.model.member(member, len(masked))
        with torch.no_grad():
            predicted = model(data, transitions, history, masked.unsqueeze(1))  # (K+1, n)
        target = data.codes.rewards[data.episode[transitions], data.step[transitions]]
        errors = 2 * (predicted - target).pow(2)
        # the row of each transition's episode among `episodes`
        position = torch.full((len(data.codes.ids),), -1, dtype=torch.long)
        position[episodes] = torch.arange(len(episodes))
        row = position[data.episode[transitions]]
        effect = (errors[1:] - errors[:1]) * applies
        extra[0].index_add_(1, row, effect)
        return extra, hit

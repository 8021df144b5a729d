"""The CI loop of Fig. 3: replay pool -> HCI / T-HCI -> gate, alternating with the RL loop.

After every rollout the loop discretizes the observations, cuts the rollout into whole
episodes and adds them to the replay pool. On its schedule it starts a CI round on a snapshot
of the pool: fit the effect predictor, search the observed space Ô for the observations
without causal effect (O^w), and fit the gate to O^w (Eq. 10). The round's gate takes effect
``ci_lag`` env steps after the round started (``ci_first_lag`` for the first round), from which
moment the agent's causal memory drops those observations. Until then the memory holds nothing
(``ci_initial_memory``: the policy starts memoryless, so the first pool shows what history
decides instead of hiding it behind a policy that already uses it). Rounds stop once two in a
row agree (or after ``ci_max_rounds`` rounds that keep something): each later pool comes from a
policy that acts on its memory more, and such a pool hides causes rather than revealing them
(see ``_more_rounds``).

As in Fig. 3, the two loops run side by side: with ``ci_async`` a round runs in a worker
process while the RL loop goes on, and the RL loop waits only if the round is not finished when
its gate is due. The gate takes effect at the same step whether or not the round ran in a
worker, so a run's results do not depend on the machine's speed, and a checkpoint taken while a
round is in flight holds the round's inputs, so a resumed run recomputes the same round.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from multiprocessing.pool import Pool
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
import torch

from thci.causal.discretize import Discretizer, discretizer_from_state, make_discretizer
from thci.causal.gate import Gate, GateSpec
from thci.causal.predictor import (
    EffectEstimator,
    PredictorConfig,
    PredictorState,
    fit_members,
    join_members,
)
from thci.causal.replay import PoolArrays, PoolEpisode, ReplayPool, pad_episodes
from thci.causal.search import DEFAULT_MIN_SUPPORT, DEFAULT_XI, DEFAULT_Z, CIResult, hci, t_hci
from thci.causal.synthetic import generate_planted_episodes
from thci.causal.units import UnitEffectEstimator, cell_units, codes_result, unit_value
from thci.config import DEFAULT_CELL_LAYOUT, TrainConfig
from thci.rl.episodes import EpisodeAssembler
from thci.rl.rollout import Rollout
from thci.workers import die_with_parent


@dataclass(frozen=True)
class CIRound:
    """What one CI round did (a row of ci_rounds.csv): started on the pool at `global_step`,
    took `seconds` of compute, its gate took effect at `applied_step`, and the RL loop waited
    `blocking_seconds` for it (all of `seconds` when the round runs in the RL process)."""

    round: int
    global_step: int
    pool_episodes: int
    observed: int
    interventions: int
    eliminated: int
    causal: int
    seconds: float
    gate_accuracy: float
    applied_step: int
    blocking_seconds: float


@dataclass(frozen=True)
class CIJob:
    """Everything one CI round needs, picklable so that it can run in a worker process.

    Attributes:
        pool: the replay pool's episodes when the round started.
        observations: code -> one observation of that code (D,), for the gate fit.
        gate_state: the gate's parameters when the round started (the fit continues them).
        gate: the gate's network (:class:`GateSpec`). num_actions: A.
        method: "hci" or "t-hci". z, xi: the search's Z and ξ.
        predictor: settings of the effect predictor p_ζ.
        threads: torch threads of the round.
        warm_start: the previous round's p_ζ, continued on this pool (None: fit from scratch).
        keep: codes confirmed causal in earlier rounds (`ci_cumulative`): kept untested.
        prefer: codes the current gate keeps: of two interchangeable causes, these stay.
        min_support: T-HCI splits a part only while it occurs in this many held-out episodes
            (and admits a substitute of a cause seen in as many).
        substitutes: admit the observations that stand in for a cause (search.t_hci).
        units: with ``--ci-units cells``, code -> the cell values of its view
            (thci.causal.units); the search then tests cell values, and `keep` and `prefer`
            hold cell values too.
    """

    pool: PoolArrays
    observations: dict[int, np.ndarray]
    gate_state: dict[str, torch.Tensor]
    gate: GateSpec
    num_actions: int
    method: str
    z: int
    xi: float
    predictor: PredictorConfig
    threads: int
    warm_start: PredictorState | None = None
    keep: np.ndarray | None = None
    prefer: np.ndarray | None = None
    min_support: int = DEFAULT_MIN_SUPPORT
    substitutes: bool = True
    units: dict[int, np.ndarray] | None = None


@dataclass(frozen=True)
class CIOutcome:
    """A finished CI round: the search's result, the fitted gate, the fitted effect predictor
    (for the next round's warm start) and the round's compute time."""

    result: CIResult
    gate_state: dict[str, torch.Tensor]
    gate_accuracy: float
    seconds: float
    predictor: PredictorState


@dataclass(frozen=True)
class FittedPart:
    """Some ensemble members of a CI round's effect predictor, fitted in one process (a round
    the RL loop waits for is fitted half here, half in the worker): their parameters and the
    seconds the fit took."""

    parameters: dict[str, torch.Tensor]
    seconds: float


@contextmanager
def _round_context(job: CIJob) -> Iterator[None]:
    """The round's torch threads; CI must not shift the RL loop's random stream."""
    threads = torch.get_num_threads()
    torch.set_num_threads(job.threads)
    try:
        with torch.random.fork_rng():
            yield
    finally:
        torch.set_num_threads(threads)


def fit_ci_part(job: CIJob, members: list[int]) -> FittedPart:
    """Fit ensemble members `members` of the round's effect predictor (one part of
    :func:`run_ci_job`'s fit, with the same result for them)."""
    started = time.perf_counter()
    with _round_context(job):
        parameters = fit_members(job.pool, job.num_actions, job.predictor, members, job.warm_start)
    return FittedPart(parameters, time.perf_counter() - started)


def run_ci_job(job: CIJob, parts: list[FittedPart] | None = None) -> CIOutcome:
    """One CI round: effect predictor, search, gate fit. Runs in the RL process or a worker.
    With `parts` (every member's, in order), the predictor is already fitted; the round's
    seconds then include the parts' fits."""
    started = time.perf_counter()
    with _round_context(job):
        estimator: EffectEstimator | UnitEffectEstimator
        if job.units is not None:
            estimator = UnitEffectEstimator(
                job.pool, job.num_actions, job.predictor, job.units, warm_start=job.warm_start
            )
        else:
            estimator = EffectEstimator(
                job.pool,
                job.num_actions,
                job.predictor,
                warm_start=job.warm_start,
                fitted=None if parts is None else join_members([p.parameters for p in parts]),
            )
        keep = None if job.keep is None else estimator.data.dense_ids(job.keep)
        prefer = None if job.prefer is None else estimator.data.dense_ids(job.prefer)
        if job.method == "hci":
            result = hci(
                estimator,
                xi=job.xi,
                keep=keep,
                prefer=prefer,
                substitutes=job.substitutes,
                min_support=job.min_support,
            )
        else:
            result = t_hci(
                estimator,
                z=job.z,
                xi=job.xi,
                keep=keep,
                min_support=job.min_support,
                prefer=prefer,
                substitutes=job.substitutes,
            )
        if job.units is not None:
            result = codes_result(result, job.units)
        gate = job.gate.build()
        gate.load_state_dict(job.gate_state)
        observations = torch.as_tensor(
            np.stack([job.observations[int(c)] for c in result.observed]),
            dtype=torch.float32,
        )
        fit = gate.fit(observations, torch.as_tensor(np.isin(result.observed, result.eliminated)))
    seconds = time.perf_counter() - started + sum(p.seconds for p in parts or [])
    return CIOutcome(result, gate.state_dict(), fit.accuracy, seconds, estimator.state())


@dataclass(frozen=True)
class CIWorker:
    """The CI worker process (:func:`start_ci_worker`) and an event set once it has started
    up."""

    pool: Pool
    ready: Any  # multiprocessing Event

    def close(self) -> None:
        """Stop the worker (a round in flight is dropped)."""
        # CPython gh-78178: Pool.terminate can find its result-handler thread already gone
        # while a dropped round is still listed, and raise (seen once in 363 tests, the worker
        # process already stopped); the pool is in its TERMINATE state either way.
        with contextlib.suppress(AssertionError):
            self.pool.terminate()
        self.pool.join()


def run_ci_job_on_two_cores(job: CIJob, worker: CIWorker) -> CIOutcome:
    """:func:`run_ci_job` with its fit split: the worker fits half of the ensemble's members,
    this process the other half (the same predictor as one process fitting all), then the
    search runs here. For a round the RL loop waits for whole (the final round), whose core is
    idle meanwhile. Maze
    L1-L3 first-round pools, 400 steps: 2.5-3.8 s in one process, 2.3-2.8 s in two. A single
    predictor, or one fine-tuned per intervention (which continues the fit's Adam state), or
    one over cell values (`--ci-units cells`), is fitted in one piece, and so is a round that
    comes while the worker is still starting up:
    waiting for it (a fresh interpreter importing torch and warming up, ~6 s at the time,
    longer than Maze L1 takes to fill its first pool) made the RL loop wait 6.2 s for a 2.6 s
    round."""
    members = job.predictor.ensemble
    split = members >= 2 and job.predictor.finetune_steps == 0 and job.units is None
    if not split or not worker.ready.is_set():
        return run_ci_job(job)
    half = members // 2
    first = worker.pool.apply_async(fit_ci_part, (job, list(range(half))))
    second = fit_ci_part(job, list(range(half, members)))
    return run_ci_job(job, [first.get(), second])


class _Outcome(Protocol):
    def get(self) -> CIOutcome: ...


@dataclass(frozen=True)
class _Computed:
    """An outcome computed in the RL process (same interface as a worker's AsyncResult)."""

    outcome: CIOutcome

    def get(self) -> CIOutcome:
        return self.outcome


@dataclass(frozen=True)
class _WorkerOrHere:
    """A round given to a worker that was still starting up: if by the time the gate is
    needed the worker has not started on it (it is still not ready), the round is computed
    here instead, the same round with the same result. The worker still computes its queued
    copy once up, and its result is dropped: one round's compute on the other core, against
    the RL loop waiting for the whole round at its start."""

    queued: Any  # the worker's AsyncResult
    worker: CIWorker
    job: CIJob

    def get(self) -> CIOutcome:
        if self.queued.ready() or self.worker.ready.is_set():
            return self.queued.get()
        return run_ci_job(self.job)


@dataclass
class _PendingRound:
    """A started round: its inputs (kept for checkpoints), when its gate takes effect, and
    its outcome (still being computed while a worker has it)."""

    job: CIJob
    started_step: int
    apply_step: int
    outcome: _Outcome
    blocking_seconds: float = 0.0


class CausalInferenceLoop:
    """Replay pool, discretizer, search and gate of one training run.

    Args:
        config: the run's config (method "hci" or "t-hci", ci_* settings).
        observation_space: the flat single-env observation space.
        num_actions: A.
        num_envs: N, the rollouts' width.
        gate: the agent's gate, fitted here after each round.
        worker: a CI worker started earlier (:func:`start_ci_worker`), so that its start-up
            overlaps the run's own; with `ci_async` and none given, the loop starts one with
            the first rollout. The loop closes it (:meth:`close`).
    """

    def __init__(
        self,
        config: TrainConfig,
        observation_space: gym.Space,
        num_actions: int,
        num_envs: int,
        gate: Gate,
        worker: CIWorker | None = None,
    ) -> None:
        self.config, self.observation_space = config, observation_space
        self.num_actions, self.gate = num_actions, gate
        self.pool = ReplayPool(config.ci_pool_episodes)
        self.discretizer: Discretizer | None = None
        self.assembler = EpisodeAssembler(num_envs)
        self.rounds: list[CIRound] = []
        self.intervention_log: list[dict[str, Any]] = []
        self.last_result: CIResult | None = None
        self.stable_rounds = 0
        self.next_round_step = 0  # the first round runs once the pool is ready (see due)
        self.pending: _PendingRound | None = None
        self.predictor_state: PredictorState | None = None  # the last applied round's p_ζ
        self.causal_so_far: set[int] = set()  # codes confirmed causal by any applied round
        self._worker = worker

    # ------------------------------------------------------------------ the RL loop's side
    def observe(self, rollout: Rollout) -> None:
        """Add the episodes that ended in `rollout` to the pool (unfinished ones carry over)."""
        if self.config.ci_async and self._worker is None:
            self._worker = start_ci_worker()
        T, N = rollout.dones.shape
        obs = rollout.obs.numpy()
        if self.discretizer is None:  # chosen from the first data, e.g. one-hot -> exact codes
            self.discretizer = make_discretizer(
                self.config.discretizer,
                self.observation_space,
                sample=obs.reshape(T * N, -1),
                cell_layout=self.config.cell_layout,
            )
        codes = self.discretizer.encode(obs.reshape(T * N, -1)).reshape(T, N)
        dones = rollout.dones.numpy()
        final_obs = rollout.final_obs.numpy()
        final_codes = np.full((T, N), -1, dtype=np.int64)
        if dones.any():
            final_codes[dones] = self.discretizer.encode(final_obs[dones])
        steps = {
            "codes": codes,
            "obs": obs,
            "actions": rollout.actions.numpy(),
            "rewards": rollout.env_rewards.numpy(),
        }
        labelled = rollout.causal is not None and rollout.final_causal is not None
        if labelled:
            steps["causal"] = rollout.causal.numpy()
        for n, end, piece in self.assembler.add(steps, dones):
            episode = PoolEpisode(
                codes=np.append(piece["codes"], final_codes[end, n]),
                actions=piece["actions"],
                rewards=piece["rewards"].astype(np.float32),
                causal=np.append(piece["causal"], rollout.final_causal[end, n].item())
                if labelled
                else None,
            )
            self.pool.add(episode, np.concatenate([piece["obs"], final_obs[end, n][None]]))

    # ------------------------------------------------------------------ the CI loop's side
    def start_if_due(self, global_step: int, solved: bool = False) -> None:
        """Called once a rollout is pooled, before the RL update that trains on it: starts a
        round that is due (:meth:`due`), so that it runs beside that update. The pool and the
        gate are the same before and after the update (the RL loss never trains the gate), so
        the round is the one :meth:`step` would start after it, begun one update's training
        earlier."""
        if self.due(global_step, solved):
            self._start(global_step)

    def step(self, global_step: int, solved: bool = False) -> CIRound | None:
        """Called after every RL update: applies the pending round once its step has come
        (waiting for it if need be), then starts the next round when one is due (never once
        the run has `solved` the task, see :meth:`due`)."""
        record = None
        pending = self.pending
        # A gate takes effect at an update after the one its round started at, even with
        # lag 0: a round started before this update's training is the round that, started
        # after it, would have been applied at the next update.
        if (
            pending is not None
            and global_step > pending.started_step
            and global_step >= pending.apply_step
        ):
            record = self._apply(global_step)
        self.start_if_due(global_step, solved)
        return record

    def due(self, global_step: int, solved: bool = False) -> bool:
        """Whether a CI round should start now. None starts once the run has `solved` the
        task: its pool then comes from a policy that acts on what its memory keeps, and there
        a cause shows no effect (the reward follows from where the policy goes, which the
        predictor sees). On Maze L1 (seed 2, commit cb73f35) the two rounds after the solve
        eliminated the last indicator the gate kept, and success fell from 0.9 to 0.43. A
        round already in flight still applies: its pool was collected before the solve."""
        return (
            not solved
            and self.pending is None
            and global_step >= self.next_round_step
            and len(self.pool) >= self.config.ci_min_episodes
            and self.pool.num_rewarded >= self.config.ci_min_rewarded_episodes
            and self._more_rounds()
        )

    def _more_rounds(self) -> bool:
        """Rounds go on until two in a row agree, or until ``ci_max_rounds`` rounds have kept
        something (``ci_max_empty_rounds`` bounds those that keep nothing), even if some code
        they keep was never confirmed. Going on until every kept code was confirmed left the
        decision to later pools, which come from a policy that acts on the memory: on Maze L4
        (seed 2, 1000-step fits) two rounds kept the labels {0, 1, 2} with the complementary
        indicators 0 and 1 undecided (each is redundant given the other, so neither shows an
        effect alone), and the fourth round found the pair's effect 0.06 [0.04, 0.08] and
        eliminated both: success 0.56 at 1M steps.

        Rounds that keep nothing never count as agreeing. Early pools can show no effect at
        all: on BabyAI-L1 (seed 1) the first two rounds ran on the pool of a policy that
        wandered until the time limit and reached a ball in ~1 of 4 episodes; both kept
        nothing, rounds stopped, and the policy stayed memoryless (0.48 success at 1.5M steps).
        A round on the same run's pool at 520k steps (a memoryless policy that reaches a ball
        in most episodes) found the signpost codes (ATE 0.42 [0.39, 0.44] for the first part).
        For the same reason empty rounds do not use up ``ci_max_rounds``."""
        kept_something = sum(1 for r in self.rounds if r.causal > 0)
        empty = len(self.rounds) - kept_something
        return (
            self.stable_rounds < 2
            and kept_something < self.config.ci_max_rounds
            and empty < self.config.ci_max_empty_rounds
        )

    def make_job(self, pool: PoolArrays) -> CIJob:
        """The CI round of the next round's index on `pool` (episodes of this run's pool)."""
        cfg = self.config
        codes = np.unique(pool.codes[pool.codes >= 0]).tolist()
        units = None
        if cfg.ci_units == "cells":
            layout = cfg.cell_layout or DEFAULT_CELL_LAYOUT
            units = {c: cell_units(self.pool.observations[c], layout) for c in codes}
        z = cfg.ci_z or DEFAULT_Z
        if cfg.ci_z is None and units:  # cell values: each tested alone first
            z = max(2, len(np.unique(np.concatenate(list(units.values())))))
        return CIJob(
            pool=pool,
            observations={c: self.pool.observations[c] for c in codes},
            gate_state={k: v.clone() for k, v in self.gate.state_dict().items()},
            gate=self.gate.spec,
            num_actions=self.num_actions,
            method=cfg.method,
            z=z,
            xi=cfg.ci_xi,
            predictor=PredictorConfig(
                target=cfg.ci_target,
                base_steps=cfg.ci_base_steps if units is None else cfg.ci_unit_steps,
                warm_steps=cfg.ci_warm_steps,
                whole_batch_steps=cfg.ci_whole_batch_steps,
                finetune_steps=cfg.ci_finetune_steps,
                ensemble=cfg.ci_ensemble,
                seed=cfg.seed + len(self.rounds),
            ),
            threads=cfg.ci_threads,
            warm_start=self.predictor_state if cfg.ci_warm_steps > 0 else None,
            keep=np.array(sorted(self.causal_so_far), dtype=np.int64)
            if cfg.ci_cumulative
            else None,
            prefer=self._kept_units() if units is not None else self._kept_codes(),
            min_support=cfg.ci_min_support,
            substitutes=cfg.ci_substitutes,
            units=units,
        )

    def _kept_codes(self) -> np.ndarray | None:
        return None if self.last_result is None else self.last_result.causal

    def _kept_units(self) -> np.ndarray | None:
        units = None if self.last_result is None else self.last_result.units
        return None if units is None else units.causal

    def _start(self, global_step: int) -> None:
        job = self.make_job(self.pool.arrays())
        lag = self.config.ci_first_lag if not self.rounds else self.config.ci_lag
        self._submit(job, global_step, global_step + lag)

    def _submit(self, job: CIJob, started_step: int, apply_step: int) -> None:
        blocking = 0.0
        outcome: _Outcome
        if self.config.ci_async and self._worker is None:  # a round resumed before a rollout
            self._worker = start_ci_worker()
        # A gate is loaded at an update after the one its round started at, so even a round
        # due at once (lag 0) runs in the worker beside that update's training and the next
        # rollout: the same gate at the same step, with their time off the wait. A worker
        # still starting up (a fresh interpreter importing torch) gets it queued, and the RL
        # loop computes it itself when the gate is due if the worker has not started on it by
        # then. Computing it here at once made the RL loop wait for the whole round in 2 of 10
        # Maze L1-L2 runs (2.2 and 1.6 s, with a first fit since reverted; docs/experiments.md).
        if self._worker is not None:
            outcome = self._worker.pool.apply_async(run_ci_job, (job,))
            if not self._worker.ready.is_set():
                outcome = _WorkerOrHere(outcome, self._worker, job)
        else:  # no worker (--no-ci-async): compute the round now
            started = time.perf_counter()
            outcome = _Computed(self._compute_now(job))
            blocking = time.perf_counter() - started
        self.pending = _PendingRound(job, started_step, apply_step, outcome, blocking)

    def _compute_now(self, job: CIJob) -> CIOutcome:
        """A round the RL loop waits for: on both cores when the worker is there."""
        if self._worker is None:
            return run_ci_job(job)
        return run_ci_job_on_two_cores(job, self._worker)

    def _apply(self, global_step: int) -> CIRound:
        """Wait for the pending round, load its gate, and record it."""
        pending, self.pending = self.pending, None
        assert pending is not None
        waited = time.perf_counter()
        outcome = pending.outcome.get()
        blocking = pending.blocking_seconds + (time.perf_counter() - waited)
        self.gate.load_state_dict(outcome.gate_state)
        self.predictor_state = outcome.predictor
        result = outcome.result
        confirmed = result.confirmed if result.units is None else result.units.confirmed
        self.causal_so_far.update(int(c) for c in confirmed)
        # Two empty results do not settle anything: the memory stays empty, so the policy
        # stays memoryless and later pools stay as informative (see _more_rounds).
        same = (
            self.last_result is not None
            and len(result.causal) > 0
            and np.array_equal(self.last_result.causal, result.causal)
        )
        self.stable_rounds = self.stable_rounds + 1 if same else 1
        self.last_result = result
        self.next_round_step = pending.started_step + self.config.ci_every
        record = CIRound(
            round=len(self.rounds) + 1,
            global_step=pending.started_step,
            pool_episodes=len(pending.job.pool.lengths),
            observed=len(result.observed),
            interventions=result.num_interventions,
            eliminated=len(result.eliminated),
            causal=len(result.causal),
            seconds=outcome.seconds,
            gate_accuracy=outcome.gate_accuracy,
            applied_step=global_step,
            blocking_seconds=blocking,
        )
        self.rounds.append(record)
        for item in result.interventions:
            self.intervention_log.append(
                {
                    "round": record.round,
                    "observations": self.describe_tested(item.codes),
                    "ate": round(item.ate, 5),
                    "ate_lower": round(item.ate_lower, 5),
                    "ate_upper": round(item.ate_upper, 5),
                    "kind": item.kind,
                    "batch_seconds": round(item.seconds, 4),
                }
            )
        return record

    def final_inference(self) -> tuple[dict[str, Any], Gate, float] | None:
        """One more CI round on the whole pool, run here (on both cores when the worker is
        idle) and not applied to the agent: the fields of summary.json's ``final_ci``, the
        round's gate and its seconds. None when the pool is too small for a round
        (``ci_min_episodes``, ``ci_min_rewarded_episodes``)."""
        cfg = self.config
        if len(self.pool) < cfg.ci_min_episodes or (
            self.pool.num_rewarded < cfg.ci_min_rewarded_episodes
        ):
            return None
        if self.pending is not None:  # the worker is busy with a round the run will not use
            self.close()
        job = self.make_job(self.pool.arrays())
        outcome = self._compute_now(job)
        gate = job.gate.build()
        gate.load_state_dict(outcome.gate_state)
        fields = {
            "pool_episodes": len(job.pool.lengths),
            "observation_space_size": len(outcome.result.observed),
            "interventions": outcome.result.num_interventions,
            "causal_observations": self.describe(outcome.result.causal),
        }
        return fields, gate, outcome.seconds

    def close(self) -> None:
        """Stop the worker process (a round in flight is dropped; checkpoints hold its inputs)."""
        if self._worker is not None:
            self._worker.close()
            self._worker = None

    def describe_causal(self) -> list[int]:
        """The causal observations of the last round, as the index of the one-hot entry when
        observations are one-hot (e.g. the maze's cell codes), else as discretizer codes."""
        return [] if self.last_result is None else self.describe(self.last_result.causal)

    def describe_tested(self, tested) -> list:
        """What an intervention masked: codes (:meth:`describe`), or with ``--ci-units
        cells`` the cell values, each as its list of values (e.g. [object, colour, state])."""
        if self.config.ci_units != "cells":
            return self.describe(tested)
        size = (self.config.cell_layout or DEFAULT_CELL_LAYOUT)[2]
        return sorted(unit_value(u, size) for u in tested)

    def describe(self, codes) -> list[int]:
        """Codes as the index of the one-hot entry when observations are one-hot, else as is."""
        described = []
        for code in codes:
            obs = self.pool.observations[int(code)]
            one_hot = obs.ndim == 1 and np.isin(obs, (0, 1)).all() and obs.sum() == 1
            described.append(int(obs.argmax()) if one_hot else int(code))
        return sorted(described)

    def summary(self) -> dict[str, Any]:
        """The CI fields of summary.json."""
        return {
            "ci_rounds": len(self.rounds),
            "interventions": sum(r.interventions for r in self.rounds),
            "interventions_per_round": [r.interventions for r in self.rounds],
            "observation_space_size": self.rounds[-1].observed if self.rounds else None,
            "causal_observations": self.describe_causal(),
            **(
                {"causal_cell_values": self.describe_tested(_or_empty(self._kept_units()))}
                if self.config.ci_units == "cells"
                else {}
            ),
            "ci_wall_clock_s": round(sum(r.seconds for r in self.rounds), 3),
            "ci_round_seconds": [round(r.seconds, 3) for r in self.rounds],
            "ci_blocking_s": round(sum(r.blocking_seconds for r in self.rounds), 3),
        }

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Pool, pending episodes, discretizer and schedule (tensors and plain values only)."""
        episodes = list(self.pool.episodes)
        arrays = self.pool.arrays() if episodes else None
        labelled = bool(episodes) and episodes[0].causal is not None
        return {
            "pool": None
            if arrays is None
            else {
                **_arrays_to_tensors(arrays),
                "causal": [torch.as_tensor(e.causal) for e in episodes] if labelled else None,
            },
            "observations": {int(c): torch.as_tensor(o) for c, o in self.pool.observations.items()},
            "pending": self.assembler.state_dict(),
            "discretizer": None if self.discretizer is None else self.discretizer.state_dict(),
            "rounds": [asdict(r) for r in self.rounds],
            "intervention_log": self.intervention_log,
            "last_causal": None
            if self.last_result is None
            else torch.as_tensor(self.last_result.causal),
            "last_eliminated": None
            if self.last_result is None
            else torch.as_tensor(self.last_result.eliminated),
            "last_observed": None
            if self.last_result is None
            else torch.as_tensor(self.last_result.observed),
            "last_units_causal": None
            if self._kept_units() is None
            else torch.as_tensor(self._kept_units()),
            "stable_rounds": self.stable_rounds,
            "next_round_step": self.next_round_step,
            "causal_so_far": sorted(self.causal_so_far),
            "predictor": None
            if self.predictor_state is None
            else {
                "observed": torch.as_tensor(self.predictor_state.observed),
                "parameters": self.predictor_state.parameters,
            },
            # a round in flight is saved as its inputs; the resumed run computes it again
            "round_in_flight": None
            if self.pending is None
            else {
                "started_step": self.pending.started_step,
                "apply_step": self.pending.apply_step,
                "pool": _arrays_to_tensors(self.pending.job.pool),
            },
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Inverse of :meth:`state_dict`."""
        self.pool = ReplayPool(self.config.ci_pool_episodes)
        pool = state["pool"]
        if pool is not None:
            self.pool.num_added = int(pool.get("first_episode", 0))
            for i, length in enumerate(pool["lengths"].tolist()):
                self.pool.add(
                    PoolEpisode(
                        codes=pool["codes"][i, : length + 1].numpy(),
                        actions=pool["actions"][i, :length].numpy(),
                        rewards=pool["rewards"][i, :length].numpy(),
                        causal=None if pool["causal"] is None else pool["causal"][i].numpy(),
                    )
                )
        self.pool.observations = {c: o.numpy() for c, o in state["observations"].items()}
        self.assembler.load_state_dict(state["pending"])
        if state["discretizer"] is not None:
            self.discretizer = discretizer_from_state(state["discretizer"])
        self.rounds = [CIRound(**r) for r in state["rounds"]]
        self.intervention_log = state["intervention_log"]
        if state["last_causal"] is not None:
            confirmed = np.array(sorted(state.get("causal_so_far", [])), dtype=np.int64)
            units = state.get("last_units_causal")
            self.last_result = CIResult(
                "restored",
                state["last_observed"].numpy(),
                state["last_eliminated"].numpy(),
                state["last_causal"].numpy(),
                confirmed,
                units=None
                if units is None
                else CIResult(
                    "restored", units.numpy(), np.zeros(0, np.int64), units.numpy(), confirmed
                ),
            )
        self.stable_rounds = state["stable_rounds"]
        self.next_round_step = state["next_round_step"]
        self.causal_so_far = set(state.get("causal_so_far", []))
        predictor = state.get("predictor")
        if predictor is not None:
            self.predictor_state = PredictorState(
                predictor["observed"].numpy(), predictor["parameters"]
            )
        pending = state["round_in_flight"]
        if pending is not None:
            pool = _arrays_from_tensors(pending["pool"])
            self._submit(self.make_job(pool), pending["started_step"], pending["apply_step"])


def _or_empty(codes: np.ndarray | None) -> np.ndarray:
    return np.zeros(0, np.int64) if codes is None else codes


def _restored_units(causal: np.ndarray, confirmed: np.ndarray) -> CIResult:
    """The part of a checkpointed round's units result later rounds read (causal, confirmed)."""
    return CIResult("restored", causal, np.zeros(0, np.int64), causal, confirmed)


def start_ci_worker() -> CIWorker:
    """The CI worker process, started with the run: spawned (a fresh interpreter, safe with
    torch threads), it imports torch and this module while the RL loop fills the pool, instead
    of while the RL loop waits for the first round (~2 s of each run's waiting)."""
    context = multiprocessing.get_context("spawn")
    ready = context.Event()
    return CIWorker(context.Pool(1, initializer=_init_worker, initargs=(ready,)), ready)


def _init_worker(ready: Any) -> None:
    """Worker initializer; unpickling it imports this module (torch, the predictor). It then
    warms torch up on a tiny synthetic pool: the first fit in a fresh process paid ~1-2 s of
    one-time set-up. (No torch.optim optimizer is built in a round, which would import
    torch._dynamo, ~1.8 s: both fits use FlatAdam.) Sets `ready` when done, ~1.3 s after the
    start on an idle machine."""
    die_with_parent()
    run_ci_job(planted_ci_job(16, num_episodes=64, episode_length=8, base_steps=5))
    ready.set()


def planted_ci_job(
    num_codes: int, num_episodes: int, episode_length: int, base_steps: int, seed: int = 0
) -> CIJob:
    """A T-HCI round's job on synthetic episodes with planted causes (one-hot observations,
    :func:`~thci.causal.synthetic.generate_planted_episodes`), with the search's defaults."""
    data = generate_planted_episodes(
        num_codes, num_episodes=num_episodes, episode_length=episode_length, seed=seed
    )
    return CIJob(
        pool=pad_episodes(data.episodes),
        observations={c: np.eye(num_codes, dtype=np.float32)[c] for c in range(num_codes)},
        gate_state=Gate(num_codes).state_dict(),
        gate=GateSpec(num_codes),
        num_actions=4,
        method="t-hci",
        z=DEFAULT_Z,
        xi=DEFAULT_XI,
        predictor=PredictorConfig(base_steps=base_steps),
        threads=1,
    )


def _arrays_to_tensors(arrays: PoolArrays) -> dict[str, Any]:
    return {
        "codes": torch.as_tensor(arrays.codes),
        "actions": torch.as_tensor(arrays.actions),
        "rewards": torch.as_tensor(arrays.rewards),
        "lengths": torch.as_tensor(arrays.lengths),
        "first_episode": arrays.first_episode,
    }


def _arrays_from_tensors(tensors: dict[str, Any]) -> PoolArrays:
    """Inverse of :func:`_arrays_to_tensors` (checkpoints from before first_episode: 0)."""
    return PoolArrays(
        **{k: tensors[k].numpy() for k in ("codes", "actions", "rewards", "lengths")},
        first_episode=int(tensors.get("first_episode", 0)),
    )

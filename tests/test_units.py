"""Cell-value interventions (--ci-units cells): unit coding, the estimator on a pool whose
cause is a known cell value, the codes' result, the round and the loop's bookkeeping."""

from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest
import torch

from thci.causal.gate import Gate, GateSpec
from thci.causal.loop import (
    CausalInferenceLoop,
    CIJob,
    CIOutcome,
    _Computed,
    _PendingRound,
    run_ci_job,
)
from thci.causal.predictor import Intervention, PredictorConfig
from thci.causal.replay import PoolEpisode, pad_episodes
from thci.causal.search import CIResult, t_hci
from thci.causal.units import UnitEffectEstimator, cell_units, codes_result, unit_value
from thci.config import TrainConfig
from thci.errors import ThciError

LAYOUT = (0, 4, 3)  # four cells of (object, colour, state), then a heading entry
FLOOR, CUE_A, CUE_B, BALL_A, BALL_B = (1, 0, 0), (2, 0, 0), (2, 1, 0), (6, 0, 0), (6, 1, 0)
NOISE = [(5, c, 0) for c in range(4)]  # distractor keys, seen at random


def view(*cells: tuple[int, int, int]) -> np.ndarray:
    """A flat observation of four cells (padded with floor) and a heading entry."""
    padded = list(cells) + [FLOOR] * (4 - len(cells))
    return np.array([v for cell in padded for v in cell] + [3], dtype=np.float32)


def unit(cell: tuple[int, int, int]) -> int:
    return int(cell_units(view(cell, cell, cell, cell), LAYOUT)[0])


def test_cell_units_code_each_distinct_cell_value_once_and_decode_back():
    units = cell_units(view(CUE_A, FLOOR, CUE_A, (10, 5, 2)), LAYOUT)
    assert len(units) == 3  # the heading entry is not a unit
    assert sorted(unit_value(u, 3) for u in units) == sorted([[2, 0, 0], [1, 0, 0], [10, 5, 2]])
    assert unit(CUE_A) != unit(CUE_B)  # the colour tells them apart
    with pytest.raises(ThciError, match="integer values in"):
        cell_units(view(CUE_A) + 0.5, LAYOUT)
    with pytest.raises(ThciError, match="integer values in"):
        cell_units(view((300, 0, 0)), LAYOUT)


def cue_pool(num_episodes: int, seed: int = 0) -> tuple[list, dict[int, np.ndarray], dict]:
    """Episodes whose reward is decided by a cue cell value seen at the first step only.

    o_1 shows cue A or B (and a random distractor key), o_2 a distractor, o_3 both balls; the
    action at o_3 faces ball A (0) or B (1), and pays 1 iff its colour is the cue's. Ground
    truth: the cue values are the causes; floor, keys and balls have no effect from history.
    """
    rng = np.random.default_rng(seed)
    codes: dict[bytes, int] = {}
    observations: dict[int, np.ndarray] = {}

    def code(obs: np.ndarray) -> int:
        key = obs.tobytes()
        if key not in codes:
            codes[key] = len(codes)
            observations[codes[key]] = obs
        return codes[key]

    episodes = []
    for _ in range(num_episodes):
        cue = int(rng.integers(2))
        noise = [NOISE[i] for i in rng.integers(len(NOISE), size=2)]
        choice = int(rng.integers(2))
        obs = [
            view((CUE_A, CUE_B)[cue], noise[0]),
            view(noise[1], BALL_A),
            view(BALL_A, BALL_B),
            view((BALL_A, BALL_B)[choice]),
        ]
        episodes.append(
            PoolEpisode(
                codes=np.array([code(o) for o in obs]),
                actions=np.array([2, 2, choice]),
                rewards=np.array([0.0, 0.0, float(choice == cue)], dtype=np.float32),
                causal=np.array([True, False, False, False]),
            )
        )
    units = {c: cell_units(o, LAYOUT) for c, o in observations.items()}
    return episodes, units, observations


def test_unit_estimator_finds_the_cue_values_and_only_them():
    episodes, units, _ = cue_pool(600)
    config = PredictorConfig(target="reward", seed=0, base_steps=1000)
    estimator = UnitEffectEstimator(pad_episodes(episodes), 3, config, units)
    data = estimator.data
    cues = data.dense_ids(np.array([unit(CUE_A), unit(CUE_B)]))
    others = np.setdiff1d(np.arange(data.num_codes), cues)
    # only the last transition of each episode pays: the others are explained by ending
    assert bool((data.step == 2).all()) and len(data.step) == 600
    effect = estimator.ate([Intervention(cues), Intervention(others)], np.zeros(0, np.int64))
    assert effect.lower[0] > 0.1  # masking the cue loses what decides the reward
    assert effect.lower[1] > -0.1 and effect.upper[1] < 0.1  # the rest decides nothing
    result = t_hci(estimator, z=data.num_codes, xi=0.1)
    assert sorted(unit_value(u, 3) for u in result.causal) == [list(CUE_A), list(CUE_B)]


def test_codes_result_keeps_exactly_the_views_that_show_a_kept_value():
    units = {
        10: np.array([unit(FLOOR), unit(CUE_A)]),
        11: np.array([unit(FLOOR)]),
        12: np.array([unit(CUE_B), unit(BALL_A)]),
    }
    kept, confirmed = np.array([unit(CUE_A), unit(CUE_B)]), np.array([unit(CUE_B)])
    observed = np.array(sorted({u for v in units.values() for u in v.tolist()}))
    search = CIResult("t-hci", observed, np.setdiff1d(observed, kept), kept, confirmed, seconds=1.5)
    result = codes_result(search, units)
    assert result.observed.tolist() == [10, 11, 12]
    assert result.causal.tolist() == [10, 12] and result.eliminated.tolist() == [11]
    assert result.confirmed.tolist() == [12]
    assert result.units is search and result.seconds == 1.5


@pytest.mark.parametrize("method", ["t-hci", "hci"])
def test_a_unit_round_fits_the_gate_on_the_views_that_show_the_cue(method: str):
    episodes, units, observations = cue_pool(600)
    job = CIJob(
        pool=pad_episodes(episodes),
        observations=observations,
        gate_state=GateSpec(13).build().state_dict(),
        gate=GateSpec(13),
        num_actions=3,
        method=method,
        z=32,
        xi=0.1,
        predictor=PredictorConfig(target="reward", seed=0, base_steps=1000),
        threads=1,
        units=units,
    )
    outcome = run_ci_job(job)
    shows_cue = {c for c, u in units.items() if np.isin([unit(CUE_A), unit(CUE_B)], u).any()}
    assert set(outcome.result.causal.tolist()) == shows_cue
    assert outcome.gate_accuracy == 1.0
    gate = GateSpec(13).build()
    gate.load_state_dict(outcome.gate_state)
    views = torch.as_tensor(np.stack([observations[c] for c in sorted(observations)]))
    keeps = gate.keep(views).tolist()
    assert {c for c, k in zip(sorted(observations), keeps, strict=True) if k} == shows_cue
    # a later round warm-starts from this one's predictor, rows matched by unit id
    assert outcome.predictor.observed.tolist() == sorted(
        {int(u) for v in units.values() for u in v}
    )


def test_the_loop_keeps_cell_values_across_rounds_and_checkpoints():
    """With --ci-units cells the next round is told the confirmed cell values (not codes) as
    `keep` and last round's kept values as `prefer`, also after a checkpoint round trip."""
    config = TrainConfig(
        method="t-hci",
        ci_units="cells",
        cell_layout=LAYOUT,
        ci_min_episodes=0,
        ci_min_rewarded_episodes=0,
    )
    space = gym.spaces.Box(0, 300, (13,))
    loop = CausalInferenceLoop(config, space, 3, 1, Gate(13))
    episodes, units, observations = cue_pool(20)
    for episode in episodes:
        loop.pool.add(episode)
    loop.pool.observations = dict(observations)
    kept = np.array([unit(CUE_A), unit(CUE_B)])
    search = CIResult("t-hci", kept, np.zeros(0, np.int64), kept, kept[:1])
    outcome = CIOutcome(codes_result(search, units), Gate(13).state_dict(), 1.0, 0.1, None)
    job = SimpleNamespace(pool=SimpleNamespace(lengths=np.ones(5)))
    loop.pending = _PendingRound(job, 0, 0, _Computed(outcome))
    loop.step(1)
    assert loop.causal_so_far == {unit(CUE_A)}
    assert loop.intervention_log == []  # none in this hand-made round
    restored = CausalInferenceLoop(config, space, 3, 1, Gate(13))
    restored.load_state_dict(loop.state_dict())
    for each in (loop, restored):
        job = each.make_job(each.pool.arrays())
        assert job.keep.tolist() == [unit(CUE_A)]
        assert job.prefer.tolist() == kept.tolist()
        assert all(np.array_equal(job.units[c], units[c]) for c in units)
        assert job.predictor.base_steps == config.ci_unit_steps
    assert restored.summary()["causal_cell_values"] == [list(CUE_A), list(CUE_B)]


@pytest.mark.parametrize(
    ("units", "ci_z", "expected"),
    [("cells", None, 9), ("cells", 3, 3), ("observations", None, 4), ("observations", 6, 6)],
)
def test_z_defaults_to_testing_each_cell_value_alone(units: str, ci_z, expected: int):
    """Without --ci-z, a cell-value round splits into as many parts as the pool has values
    (floor, two cues, two balls, four keys: 9), an observation round into the paper's 4."""
    config = TrainConfig(method="t-hci", ci_units=units, cell_layout=LAYOUT, ci_z=ci_z)
    loop = CausalInferenceLoop(config, gym.spaces.Box(0, 300, (13,)), 3, 1, Gate(13))
    episodes, _, observations = cue_pool(20)
    for episode in episodes:
        loop.pool.add(episode)
    loop.pool.observations = dict(observations)
    assert loop.make_job(loop.pool.arrays()).z == expected


def test_cell_units_need_the_reward_target():
    with pytest.raises(ThciError, match="--ci-units cells predicts the reward"):
        TrainConfig(ci_units="cells", ci_target="dynamics").validate()

"""Observation discretizers: consistent dense codes, exact vs locality-sensitive, auto choice."""

import io

import gymnasium as gym
import numpy as np
import pytest
import torch

from thci.causal.discretize import (
    CellSetDiscretizer,
    Discretizer,
    ExactDiscretizer,
    SimHashDiscretizer,
    make_discretizer,
)
from thci.errors import ThciError


def test_exact_codes_are_dense_first_seen_and_consistent_across_batches():
    disc = ExactDiscretizer()
    first = disc.encode(np.array([[5, 1], [2, 2], [5, 1], [0, 0]], dtype=np.int64))
    assert first.dtype == np.int64
    assert first.tolist() == [0, 1, 0, 2], "first-seen order, not sorted order"
    second = disc.encode(np.array([[0, 0], [9, 9], [5, 1]], dtype=np.int64))
    assert second.tolist() == [2, 3, 0]
    assert disc.num_codes == 4
    assert isinstance(disc, Discretizer)


def test_exact_is_injective_on_distinct_rows():
    rng = np.random.default_rng(0)
    obs = rng.integers(0, 3, size=(500, 3, 4)).astype(np.uint8)  # images with repeats
    disc = ExactDiscretizer()
    codes = np.concatenate([disc.encode(obs[:200]), disc.encode(obs[200:])])
    _, groups = np.unique(obs.reshape(500, -1), axis=0, return_inverse=True)
    # codes and exact-row groups induce the same partition of the batch
    pairs = set(zip(codes.tolist(), groups.ravel().tolist(), strict=True))
    assert len(pairs) == len(set(codes.tolist())) == len(set(groups.ravel().tolist()))
    assert sorted(set(codes.tolist())) == list(range(disc.num_codes))


def test_exact_equal_float_values_get_equal_codes():
    disc = ExactDiscretizer()
    codes = disc.encode(np.array([[0.0, 1.0], [-0.0, 1.0], [np.nan, 1.0], [-np.nan, 1.0]]))
    assert codes[0] == codes[1]
    assert codes[2] == codes[3]
    # a lossless cast of another dtype finds the same codes; a lossy one is refused
    assert disc.encode(np.array([[0, 1]], dtype=np.float32)).tolist() == [codes[0]]
    ints = ExactDiscretizer()
    ints.encode(np.array([[0, 1]], dtype=np.int8))
    assert ints.encode(np.array([[0.0, 1.0]])).tolist() == [0]
    with pytest.raises(ThciError, match="losslessly"):
        ints.encode(np.array([[0.5, 1.0]]))


def test_simhash_identical_same_code_near_usually_same_far_usually_different():
    rng = np.random.default_rng(1)
    dim = 32
    disc = SimHashDiscretizer(dim, bits=16, seed=0)
    base = rng.standard_normal((400, dim))
    near = base + 1e-3 * rng.standard_normal((400, dim))
    far = rng.standard_normal((400, dim))
    c_base = disc.encode(base)
    assert (disc.encode(base[::-1].copy())[::-1] == c_base).all(), "identical → same code"
    assert np.mean(disc.encode(near) == c_base) > 0.9
    assert np.mean(disc.encode(far) == c_base) < 0.05
    assert sorted(set(disc.encode(base).tolist())) == list(range(len(set(c_base.tolist()))))
    codes_all = disc.encode(np.concatenate([base, near, far]))
    assert codes_all.max() == disc.num_codes - 1, "dense ids"


def test_simhash_centre_separates_data_far_from_the_origin():
    # Positive data far from the origin: without a centre every projection has the same sign.
    rng = np.random.default_rng(2)
    obs = 100.0 + rng.standard_normal((300, 8))
    space = gym.spaces.Box(-np.inf, np.inf, shape=(8,), dtype=np.float32)
    centred = make_discretizer("simhash", space, sample=obs, bits=8)
    uncentred = SimHashDiscretizer(8, bits=8)
    centred.encode(obs)
    uncentred.encode(obs)
    assert centred.num_codes > 10 * uncentred.num_codes


def test_auto_picks_exact_for_symbolic_and_simhash_for_continuous():
    rng = np.random.default_rng(3)
    onehot = np.eye(5, dtype=np.float32)[rng.integers(0, 5, size=64)]
    float_box = gym.spaces.Box(0.0, 1.0, shape=(5,), dtype=np.float32)
    assert isinstance(make_discretizer("auto", float_box, sample=onehot), ExactDiscretizer)
    assert isinstance(make_discretizer("auto", gym.spaces.Discrete(7)), ExactDiscretizer)
    assert isinstance(make_discretizer("auto", gym.spaces.MultiDiscrete([3, 4])), ExactDiscretizer)
    image_box = gym.spaces.Box(0, 255, shape=(7, 7, 3), dtype=np.uint8)
    assert isinstance(make_discretizer("auto", image_box), ExactDiscretizer)
    continuous = rng.random((64, 5)).astype(np.float32)
    disc = make_discretizer("auto", float_box, sample=continuous)
    assert isinstance(disc, SimHashDiscretizer)
    assert isinstance(make_discretizer("auto", float_box), SimHashDiscretizer)
    # Discrete observations arrive as (B,) ints
    exact = make_discretizer("auto", gym.spaces.Discrete(7))
    assert exact.encode(np.array([3, 3, 6])).tolist() == [0, 0, 1]


def _round_trip(state):
    buffer = io.BytesIO()
    torch.save(state, buffer)
    buffer.seek(0)
    return torch.load(buffer, weights_only=True)


@pytest.mark.parametrize("kind", ["exact", "simhash", "cell-set"])
def test_state_dict_round_trip_keeps_codes(kind):
    rng = np.random.default_rng(4)
    space = gym.spaces.Box(-1.0, 1.0, shape=(2, 3), dtype=np.float32)
    obs = rng.random((50, 2, 3)).astype(np.float32)
    obs[25:] = obs[:25]
    disc = make_discretizer(kind, space, sample=obs, bits=12, seed=5)
    codes = disc.encode(obs)
    restored = make_discretizer(kind, space, bits=12, seed=99)  # other centre / seed
    restored.load_state_dict(_round_trip(disc.state_dict()))
    assert restored.num_codes == disc.num_codes
    assert (restored.encode(obs[::-1].copy())[::-1] == codes).all()
    new = rng.random((5, 2, 3)).astype(np.float32) + 3.0
    assert (restored.encode(new) == disc.encode(new)).all(), "new codes continue identically"


def test_empty_state_round_trips_and_wrong_kind_is_refused():
    exact = ExactDiscretizer()
    fresh = ExactDiscretizer()
    fresh.load_state_dict(_round_trip(exact.state_dict()))
    assert fresh.num_codes == 0
    assert fresh.encode(np.zeros((2, 3))).tolist() == [0, 0]
    with pytest.raises(ThciError, match="simhash"):
        exact.load_state_dict(SimHashDiscretizer(3).state_dict())


def test_bad_kind_lists_valid_kinds():
    with pytest.raises(ThciError, match="exact, simhash, cell-set, auto") as info:
        make_discretizer("md5", gym.spaces.Discrete(3))
    assert "\n" not in str(info.value)


def test_misuse_is_a_one_line_error():
    disc = ExactDiscretizer()
    disc.encode(np.zeros((2, 4)))
    with pytest.raises(ThciError):
        disc.encode(np.zeros((2, 5)))
    with pytest.raises(ThciError):
        SimHashDiscretizer(4).encode(np.zeros((2, 5)))
    with pytest.raises(ThciError):
        SimHashDiscretizer(4, bits=64)
    with pytest.raises(ThciError, match="FlattenObservation"):
        make_discretizer("auto", gym.spaces.Dict({"a": gym.spaces.Discrete(2)}))


def test_discretizer_from_state_rebuilds_both_kinds():
    from thci.causal.discretize import (
        ExactDiscretizer,
        SimHashDiscretizer,
        discretizer_from_state,
    )

    rng = np.random.default_rng(0)
    data = rng.normal(size=(50, 5))
    for original in (ExactDiscretizer(), SimHashDiscretizer(5, bits=8, seed=3)):
        codes = original.encode(data)
        rebuilt = discretizer_from_state(original.state_dict())
        assert type(rebuilt) is type(original)
        assert np.array_equal(rebuilt.encode(data), codes)


def _cells(*cells: tuple[int, int], tail: int) -> np.ndarray:
    """A flat observation of 4 cells of 2 values, then a one-value tail."""
    return np.array([v for cell in cells for v in cell] + [tail], dtype=np.uint8)


def test_cell_set_codes_the_set_of_cell_values_wherever_they_are():
    disc = CellSetDiscretizer(offset=0, num_cells=4, cell_size=2)
    wall, ball, empty = (2, 5), (6, 1), (1, 0)
    batch = np.stack(
        [
            _cells(wall, ball, empty, empty, tail=0),
            _cells(empty, empty, ball, wall, tail=0),  # same set, other places: same code
            _cells(ball, wall, wall, empty, tail=0),  # same set, other counts: same code
            _cells(wall, ball, empty, empty, tail=1),  # other tail: new code
            _cells(wall, (6, 2), empty, empty, tail=0),  # other ball colour: new code
            _cells(wall, empty, empty, empty, tail=0),  # ball gone: new code
            # (2, 5) and (6, 1) against (2, 1) and (6, 5): cells are whole values, not channels
            _cells((2, 1), (6, 5), empty, empty, tail=0),
        ]
    )
    assert disc.encode(batch).tolist() == [0, 0, 0, 1, 2, 3, 4]
    assert disc.encode(batch[::-1].copy()).tolist() == [4, 3, 2, 1, 0, 0, 0]
    assert disc.num_codes == 5


def test_cell_set_refuses_a_layout_longer_than_the_observation_and_non_categorical_cells():
    with pytest.raises(ThciError, match="--cell-layout"):
        CellSetDiscretizer(0, num_cells=4, cell_size=3).encode(np.zeros((2, 10)))
    with pytest.raises(ThciError, match="--cell-layout"):
        CellSetDiscretizer(1, num_cells=3, cell_size=3).encode(np.zeros((2, 9)))
    with pytest.raises(ThciError, match="not categorical"):
        CellSetDiscretizer(0, num_cells=2000, cell_size=1).encode(np.arange(2000.0)[None])


def test_cell_set_keeps_the_entries_around_the_cells_exactly():
    disc = CellSetDiscretizer(offset=1, num_cells=2, cell_size=2)
    rows = np.array(
        [[0, 3, 4, 5, 6, 9], [0, 5, 6, 3, 4, 9], [1, 3, 4, 5, 6, 9], [0, 3, 4, 5, 6, 8]]
    )
    assert disc.encode(rows).tolist() == [0, 0, 1, 2]


def random_babyai_views(seeds: range) -> tuple[np.ndarray, np.ndarray]:
    """(N, 151) observations of random-action BabyAI-L1 episodes and their causal labels."""
    env = gym.make("thci/BabyAI-L1-v0")
    rng = np.random.default_rng(seeds.start)
    views, labels = [], []
    for seed in seeds:
        obs, info = env.reset(seed=seed)
        done = False
        while not done:
            views.append(obs)
            labels.append(info["causal"])
            obs, _, terminated, truncated, info = env.step(int(rng.integers(6)))
            done = terminated or truncated
    return np.array(views), np.array(labels)


def test_cell_set_codes_of_babyai_views_separate_signpost_views():
    """Known answer: the signpost is the only coloured wall, so every code's observations
    agree on info["causal"], and codes recur far more often than exact views do."""
    views, labels = random_babyai_views(range(40))
    assert labels.any() and not labels.all()
    space = gym.make("thci/BabyAI-L1-v0").observation_space
    codes = make_discretizer("cell-set", space, cell_layout=(0, 49, 3)).encode(views)
    for code in np.unique(codes):
        assert len(set(labels[codes == code].tolist())) == 1
    exact = ExactDiscretizer().encode(views)
    assert len(np.unique(codes)) * 4 < len(np.unique(exact))

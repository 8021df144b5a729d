"""Observation discretization: observations → integer codes (the observed space Ô).

T-HCI is defined on a discrete observation space: an intervention Do(O^i) names a *set* of
observation values, and coarse-to-fine CI splits that set in halves (Prop. 3). The paper
handles rich or continuous observations by hashing them into discrete codes ("Combining RL and
Coarse-to-Fine Counterfactual Inference" and App. A.2, citing Zhu et al. 2018a; Hong et al.
2021; Burda et al. 2019b) and writes Ô for the constructed discrete space. Here Ô is the set of
codes handed out so far: every discretizer gives the codes 0, 1, 2, ... in the order their
observations are first seen, so ``num_codes`` is |Ô| and codes index dense tables.

Three discretizers:

* :class:`ExactDiscretizer`: one code per distinct observation (its exact bytes). Right for
  symbolic observations: Discrete / MultiDiscrete spaces, integer images (MiniGrid), one-hot
  vectors.
* :class:`SimHashDiscretizer`: angular locality-sensitive hashing (SimHash, Charikar 2002; as
  in the count-based exploration of Tang et al. 2017): the signs of ``bits`` random Gaussian
  projections. Nearby observations share a code more often than distant ones, so continuous
  observations fall into a bounded number (≤ 2**bits) of cells.
* :class:`CellSetDiscretizer`: for images of categorical cells (minigrid's egocentric view of
  (object, colour, state) triples), the *set* of distinct cell values in view, wherever they
  are, plus the rest of the observation exactly. Exact codes of whole views are too fine for
  CI when the observations that matter are rare views of one object (BabyAI's signpost is seen
  from many places, each view in one or two episodes: docs/babyai.md); under the set code every
  view of the same objects shares a code, which recurs often enough to be tested.

:func:`make_discretizer` picks one from the observation space (``kind="auto"``).

A discretizer's ``state_dict()`` holds only str / int / None and torch tensors, so it can live
in a checkpoint loaded with ``torch.load(weights_only=True)``; after ``load_state_dict`` the
same observations get the same codes again.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np
import torch

from thci.errors import ThciError

DISCRETIZER_KINDS = ("exact", "simhash", "cell-set", "auto")


@runtime_checkable
class Discretizer(Protocol):
    """Maps batches of observations to int64 codes, consistently across calls.

    The same observation gets the same code forever (across batches, and across a
    ``state_dict`` / ``load_state_dict`` round trip). Codes are dense: 0 .. num_codes - 1.
    """

    @property
    def num_codes(self) -> int:
        """Codes handed out so far (|Ô|)."""
        ...

    def encode(self, obs: np.ndarray) -> np.ndarray:
        """(B, *obs_shape) observations → (B,) int64 codes; new observations get new codes."""
        ...

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to reproduce the codes (plain Python values and torch tensors)."""
        ...

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore the state produced by :meth:`state_dict`."""
        ...


def _batch_rows(obs: np.ndarray) -> np.ndarray:
    """(B, *obs_shape) → (B, D) view/copy, D = prod(obs_shape) (1 for scalar observations)."""
    obs = np.asarray(obs)
    if obs.ndim == 0:
        raise ThciError(
            "encode() needs a batch of observations with a leading batch axis, got a scalar; "
            "wrap it as np.array([obs])"
        )
    return obs.reshape(obs.shape[0], -1)


def _dense_ids(ids: dict[Any, int], keys: list[Any], first_index: np.ndarray) -> np.ndarray:
    """Dense code of each distinct key; unseen keys get new codes in first-appearance order.

    Args:
        ids: key → code table, updated in place (insertion order == code order).
        keys: the batch's distinct keys (any order), length U.
        first_index: (U,) position in the batch where each key first appears.

    Returns:
        (U,) int64 codes of ``keys``.
    """
    lookup = np.empty(len(keys), dtype=np.int64)
    # Visit distinct keys in the order they first appear in the batch, so new codes follow
    # first-seen order within a batch too (np.unique sorts them otherwise).
    for j in np.argsort(first_index, kind="stable").tolist():
        key = keys[j]
        code = ids.get(key)
        if code is None:
            code = ids[key] = len(ids)
        lookup[j] = code
    return lookup


class ExactDiscretizer:
    """One code per distinct observation value: the id of the observation's exact bytes.

    Codes are given in first-seen order (0, 1, 2, ...). Float observations are canonicalized
    first so that equal values get equal codes: -0.0 becomes 0.0 and every NaN becomes the
    same NaN. The element dtype and the number of elements per observation are fixed by the
    first batch; later batches of another dtype are cast to it when that is lossless (so a
    one-hot float64 batch and a float32 batch agree) and rejected otherwise.

    Encoding is vectorized: each batch is viewed as (B,) opaque byte strings and deduplicated
    with ``np.unique``; only the batch's *distinct* rows are looked up in a dict in Python.
    """

    kind = "exact"

    def __init__(self) -> None:
        self._ids: dict[bytes, int] = {}
        self._dtype: np.dtype | None = None
        self._row_size: int | None = None

    @property
    def num_codes(self) -> int:
        return len(self._ids)

    def _canonical(self, obs: np.ndarray) -> np.ndarray:
        """(B, *obs_shape) → (B, D) C-contiguous rows in the locked dtype, floats canonical."""
        rows = _batch_rows(obs)
        if self._dtype is None:
            # Native byte order, so the same value always has the same bytes.
            self._dtype = rows.dtype.newbyteorder("=")
            self._row_size = rows.shape[1]
        if rows.shape[1] != self._row_size:
            raise ThciError(
                f"observation size changed: this discretizer encodes {self._row_size} values "
                f"per observation, got {rows.shape[1]}; use one discretizer per observation space"
            )
        if rows.dtype != self._dtype:
            cast = rows.astype(self._dtype)
            inexact = np.issubdtype(rows.dtype, np.inexact) or np.issubdtype(
                self._dtype, np.inexact
            )
            if not np.array_equal(cast, rows, equal_nan=inexact):
                raise ThciError(
                    f"observations of dtype {rows.dtype} cannot be encoded losslessly as "
                    f"{self._dtype} (the dtype of the first batch); keep one observation dtype"
                )
            rows = cast
        if np.issubdtype(self._dtype, np.inexact):
            rows = rows + 0  # a copy in which -0.0 + 0 == +0.0
            rows[np.isnan(rows)] = np.nan  # one NaN bit pattern
        return np.ascontiguousarray(rows)

    def encode(self, obs: np.ndarray) -> np.ndarray:
        """(B, *obs_shape) observations → (B,) int64 codes."""
        rows = self._canonical(obs)
        if rows.shape[0] == 0:
            return np.zeros(0, dtype=np.int64)
        if rows.shape[1] == 0:
            # Zero-size observations are all equal: one code.
            rows = np.zeros((rows.shape[0], 1), dtype=np.uint8)
        row_bytes = rows.dtype.itemsize * rows.shape[1]
        # One opaque void scalar per row: np.unique then compares whole rows as byte strings.
        opaque = rows.view(np.dtype((np.void, row_bytes))).ravel()
        distinct, first_index, inverse = np.unique(opaque, return_index=True, return_inverse=True)
        lookup = _dense_ids(self._ids, distinct.tolist(), first_index)
        return lookup[inverse.ravel()]

    def state_dict(self) -> dict[str, Any]:
        """{"kind", "dtype" (numpy dtype str or None), "row_size", "keys": (N, row_bytes) uint8
        tensor whose row i is the bytes of code i}."""
        if self._ids:
            flat = np.frombuffer(b"".join(self._ids), dtype=np.uint8)
            keys = torch.from_numpy(flat.reshape(len(self._ids), -1).copy())
        else:
            keys = torch.zeros((0, 0), dtype=torch.uint8)
        return {
            "kind": self.kind,
            "dtype": None if self._dtype is None else self._dtype.str,
            "row_size": self._row_size,
            "keys": keys,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state.get("kind") != self.kind:
            raise ThciError(
                f"cannot load a {state.get('kind')!r} discretizer state into an exact "
                "discretizer; build the discretizer with the kind that saved it"
            )
        self._dtype = None if state["dtype"] is None else np.dtype(state["dtype"])
        self._row_size = state["row_size"]
        keys = state["keys"].numpy()
        self._ids = {keys[i].tobytes(): i for i in range(keys.shape[0])}


class SimHashDiscretizer:
    """Angular LSH: code of the sign pattern of ``bits`` Gaussian projections.

    key(o) = sum_j [ (o - centre) · w_j > 0 ] * 2**j with w_j ~ N(0, I) (fixed by ``seed``),
    and keys are mapped to dense codes in first-seen order. Two observations agree on bit j
    with probability 1 - angle(o - centre, o' - centre) / pi, so nearby observations share a
    code more often than far ones, and at most 2**bits codes exist. Only the *direction* from
    ``centre`` matters (the hash is scale invariant), hence the centre: put it in the middle of
    the data (e.g. the mean of a sample, as :func:`make_discretizer` does) so that the
    hyperplanes cut through the data instead of all passing near one corner of it.

    Projections are computed in float64; an observation lying within rounding error of a
    hyperplane (probability ~1e-15 for continuous data) could in principle flip a bit between
    batches of different size.

    Args:
        obs_dim: elements per (flattened) observation.
        bits: number of hyperplanes, 1..63 (keys are int64).
        seed: seed of the projections.
        centre: (obs_dim,) point subtracted before projecting; default the origin.
    """

    kind = "simhash"

    def __init__(
        self,
        obs_dim: int,
        bits: int = 16,
        seed: int = 0,
        centre: np.ndarray | None = None,
    ) -> None:
        if obs_dim < 1:
            raise ThciError(f"simhash needs obs_dim >= 1, got {obs_dim}")
        if not 1 <= bits <= 63:
            raise ThciError(f"simhash bits must be in 1..63 (int64 keys), got {bits}")
        self.obs_dim = obs_dim
        self.bits = bits
        self.seed = seed
        self.projections = np.random.default_rng(seed).standard_normal((obs_dim, bits))
        self.centre = (
            np.zeros(obs_dim) if centre is None else np.asarray(centre, np.float64).reshape(-1)
        )
        if self.centre.shape != (obs_dim,):
            raise ThciError(f"simhash centre must have {obs_dim} values, got {self.centre.size}")
        self._shifts = np.arange(bits, dtype=np.int64)
        self._ids: dict[int, int] = {}

    @property
    def num_codes(self) -> int:
        return len(self._ids)

    def hash_keys(self, obs: np.ndarray) -> np.ndarray:
        """(B, *obs_shape) → (B,) int64 raw sign-pattern keys in [0, 2**bits)."""
        rows = _batch_rows(obs)
        if rows.shape[1] != self.obs_dim:
            raise ThciError(
                f"simhash was built for observations of {self.obs_dim} values, got "
                f"{rows.shape[1]}; use one discretizer per observation space"
            )
        signs = (rows.astype(np.float64) - self.centre) @ self.projections > 0  # (B, bits)
        return (signs.astype(np.int64) << self._shifts).sum(axis=1)

    def encode(self, obs: np.ndarray) -> np.ndarray:
        """(B, *obs_shape) observations → (B,) int64 dense codes."""
        keys = self.hash_keys(obs)
        if keys.shape[0] == 0:
            return np.zeros(0, dtype=np.int64)
        distinct, first_index, inverse = np.unique(keys, return_index=True, return_inverse=True)
        lookup = _dense_ids(self._ids, distinct.tolist(), first_index)
        return lookup[inverse.ravel()]

    def state_dict(self) -> dict[str, Any]:
        """{"kind", "obs_dim", "bits", "seed", "projections": (obs_dim, bits) float64,
        "centre": (obs_dim,) float64, "keys": (N,) int64 raw key of code i}.

        The projections are saved rather than re-drawn from the seed so that codes survive a
        change of numpy's random streams.
        """
        return {
            "kind": self.kind,
            "obs_dim": self.obs_dim,
            "bits": self.bits,
            "seed": self.seed,
            "projections": torch.from_numpy(self.projections.copy()),
            "centre": torch.from_numpy(self.centre.copy()),
            "keys": torch.tensor(list(self._ids), dtype=torch.int64),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state.get("kind") != self.kind:
            raise ThciError(
                f"cannot load a {state.get('kind')!r} discretizer state into a simhash "
                "discretizer; build the discretizer with the kind that saved it"
            )
        if (state["obs_dim"], state["bits"]) != (self.obs_dim, self.bits):
            raise ThciError(
                f"simhash state is for obs_dim={state['obs_dim']}, bits={state['bits']}, "
                f"this discretizer has obs_dim={self.obs_dim}, bits={self.bits}"
            )
        self.seed = state["seed"]
        self.projections = state["projections"].numpy().astype(np.float64)
        self.centre = state["centre"].numpy().astype(np.float64)
        self._ids = {key: i for i, key in enumerate(state["keys"].tolist())}


class CellSetDiscretizer:
    """Code of the set of distinct cell values in view, plus the observation's tail.

    A flat observation is read as ``offset`` leading entries, ``num_cells`` cells of
    ``cell_size`` values (e.g. minigrid's 7x7x3 image flattened cell by cell) and trailing
    entries; the leading and trailing ones (e.g. a one-hot heading) are kept exactly. Two
    observations share a code iff the same cell values appear in both (in any places, any
    number of times) and the rest is equal.

    Encoding is vectorized: cell values get ids from an :class:`ExactDiscretizer` over the
    (B·num_cells, cell_size) rows, each observation's ids become a presence bitmap, and the
    bitmap's bytes with the tail's bytes are coded by a second :class:`ExactDiscretizer`.

    Args:
        offset: entries before the first cell.
        num_cells: cells per observation.
        cell_size: values per cell.
    """

    kind = "cell-set"
    MAX_CELL_VALUES = 1024
    """Distinct cell values a discretizer can tell apart (the presence bitmap's width)."""

    def __init__(self, offset: int, num_cells: int, cell_size: int) -> None:
        if offset < 0 or num_cells < 1 or cell_size < 1:
            raise ThciError(
                f"cell-set discretizer needs offset >= 0, num_cells >= 1 and cell_size >= 1, "
                f"got {offset}, {num_cells} and {cell_size}"
            )
        self.offset, self.num_cells, self.cell_size = offset, num_cells, cell_size
        self._cells = ExactDiscretizer()
        self._sets = ExactDiscretizer()

    @property
    def num_codes(self) -> int:
        return self._sets.num_codes

    def encode(self, obs: np.ndarray) -> np.ndarray:
        """(B, *obs_shape) observations → (B,) int64 codes."""
        rows = _batch_rows(obs)
        start, end = self.offset, self.offset + self.num_cells * self.cell_size
        if rows.shape[1] < end:
            raise ThciError(
                f"cell-set discretizer reads {self.num_cells} cells of {self.cell_size} values "
                f"after {start} entries, but observations have {rows.shape[1]} values; set "
                "--cell-layout to the observation's (offset, cells, values per cell)"
            )
        batch = rows.shape[0]
        if batch == 0:
            return np.zeros(0, dtype=np.int64)
        cells = self._cells.encode(rows[:, start:end].reshape(batch * self.num_cells, -1))
        if self._cells.num_codes > self.MAX_CELL_VALUES:
            raise ThciError(
                f"cell-set discretizer saw {self._cells.num_codes} distinct cell values, more "
                f"than {self.MAX_CELL_VALUES}: the cells are not categorical; use --discretizer "
                "exact or simhash"
            )
        present = np.zeros((batch, self.MAX_CELL_VALUES), dtype=bool)
        present[np.repeat(np.arange(batch), self.num_cells), cells] = True
        rest = np.ascontiguousarray(np.concatenate((rows[:, :start], rows[:, end:]), axis=1))
        rest_bytes = rest.view(np.uint8).reshape(batch, -1)
        return self._sets.encode(np.concatenate([np.packbits(present, axis=1), rest_bytes], 1))

    def state_dict(self) -> dict[str, Any]:
        """{"kind", "offset", "num_cells", "cell_size", "cells": exact state of the cell
        values, "sets": exact state of the (bitmap, rest) keys}."""
        return {
            "kind": self.kind,
            "offset": self.offset,
            "num_cells": self.num_cells,
            "cell_size": self.cell_size,
            "cells": self._cells.state_dict(),
            "sets": self._sets.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state.get("kind") != self.kind:
            raise ThciError(
                f"cannot load a {state.get('kind')!r} discretizer state into a cell-set "
                "discretizer; build the discretizer with the kind that saved it"
            )
        self.offset = state["offset"]
        self.num_cells, self.cell_size = state["num_cells"], state["cell_size"]
        self._cells.load_state_dict(state["cells"])
        self._sets.load_state_dict(state["sets"])


def _integer_valued(sample: np.ndarray) -> bool:
    """True when every value of the batch is a finite integer (ints, bools, one-hot floats)."""
    sample = np.asarray(sample)
    if not np.issubdtype(sample.dtype, np.inexact):
        return np.issubdtype(sample.dtype, np.integer) or sample.dtype == np.bool_
    return bool(np.all(np.isfinite(sample)) and np.all(sample == np.rint(sample)))


def _default_centre(space: gym.Space, sample: np.ndarray | None, obs_dim: int) -> np.ndarray:
    """Sample mean if a sample is given, else a Box's midpoint where it is bounded, else 0."""
    if sample is not None and len(sample) > 0:
        return np.asarray(sample, np.float64).reshape(len(sample), -1).mean(axis=0)
    centre = np.zeros(obs_dim)
    if isinstance(space, gym.spaces.Box):
        low = np.asarray(space.low, np.float64).reshape(-1)
        high = np.asarray(space.high, np.float64).reshape(-1)
        bounded = np.isfinite(low) & np.isfinite(high)
        centre[bounded] = (low[bounded] + high[bounded]) / 2
    return centre


def make_discretizer(
    kind: str,
    observation_space: gym.Space,
    sample: np.ndarray | None = None,
    bits: int = 16,
    seed: int = 0,
    cell_layout: tuple[int, int, int] | None = None,
) -> Discretizer:
    """Build the discretizer for an observation space.

    Args:
        kind: "exact", "simhash" or "auto". "auto" picks exact for Discrete / MultiDiscrete /
            MultiBinary spaces, Boxes with an integer or bool dtype, and any space whose
            ``sample`` holds only integer values (one-hot floats, MiniGrid images stored as
            floats); simhash otherwise.
        observation_space: the (single-env) observation space; must have a shape (flatten
            Dict / Tuple spaces first, e.g. with gymnasium's FlattenObservation).
        sample: optional (N, *obs_shape) batch of observations; used by "auto" and to centre
            the simhash hyperplanes (its mean; without a sample, a Box's midpoint where it is
            bounded, else the origin).
        bits, seed: simhash parameters.
        cell_layout: (offset, num_cells, cell_size) of "cell-set"; default: the whole
            observation as cells of 3 values (minigrid's (object, colour, state)).

    Raises:
        ThciError: unknown kind or unsupported space.
    """
    if kind not in DISCRETIZER_KINDS:
        raise ThciError(
            f"unknown discretizer kind {kind!r}; valid kinds: {', '.join(DISCRETIZER_KINDS)}"
        )
    shape = observation_space.shape
    if shape is None:
        raise ThciError(
            f"cannot discretize observations of {type(observation_space).__name__} spaces; "
            "flatten them first (gymnasium.wrappers.FlattenObservation)"
        )
    if kind == "auto":
        symbolic = isinstance(
            observation_space,
            gym.spaces.Discrete | gym.spaces.MultiDiscrete | gym.spaces.MultiBinary,
        ) or (
            isinstance(observation_space, gym.spaces.Box)
            and (
                np.issubdtype(observation_space.dtype, np.integer)
                or observation_space.dtype == np.bool_
            )
        )
        if not symbolic and sample is not None and len(sample) > 0:
            symbolic = _integer_valued(sample)
        kind = "exact" if symbolic else "simhash"
    if kind == "exact":
        return ExactDiscretizer()
    obs_dim = int(np.prod(shape)) if len(shape) else 1
    if kind == "cell-set":
        return CellSetDiscretizer(*(cell_layout or (0, obs_dim // 3, 3)))
    centre = _default_centre(observation_space, sample, obs_dim)
    return SimHashDiscretizer(obs_dim, bits=bits, seed=seed, centre=centre)


def discretizer_from_state(state: dict[str, Any]) -> Discretizer:
    """Rebuild the discretizer that wrote `state` (its ``state_dict()``, e.g. from a checkpoint)."""
    kind = state.get("kind")
    discretizer: Discretizer
    if kind == ExactDiscretizer.kind:
        discretizer = ExactDiscretizer()
    elif kind == SimHashDiscretizer.kind:
        discretizer = SimHashDiscretizer(state["obs_dim"], state["bits"], state["seed"])
    elif kind == CellSetDiscretizer.kind:
        discretizer = CellSetDiscretizer(state["offset"], state["num_cells"], state["cell_size"])
    else:
        raise ThciError(f"unknown discretizer state kind {kind!r}: the checkpoint is damaged")
    discretizer.load_state_dict(state)
    return discretizer

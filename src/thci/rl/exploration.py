"""Intrinsic rewards for exploration: count-based and episodic novelty.

Every observation the agent reaches is mapped to a code by the same discretizers T-HCI uses
(exact codes for symbolic observations, SimHash for continuous ones). When the observation is
a poor proxy of the state (the maze's corridor codes repeat over many cells), ``count_key``
codes an info entry the environment reports instead (e.g. ``"agent_pos"``, which every
built-in environment provides); exploration then uses state information the agent's policy
never sees. Three bonuses are built on these codes:

* ``count`` (#Exploration, Tang et al. 2017): beta / sqrt(N(code)), N counting every visit
  so far. Rare observations pay most and the bonus fades as they become familiar.
* ``episodic`` (the episodic-novelty half of NGU, Badia et al. 2020): beta for each code
  reached for the first time *in the current episode*. It never fades, and it pays for going
  somewhere new rather than for dithering, which is what a sparse, far goal at the end of a
  corridor needs (Maze levels 3-4: four goals 11 steps away, 1.5% of random walks reach one).
  Keep beta · (most new codes per episode) well under the task's reward so the task decides.
* ``episodic-count`` (NGU's product of episodic and life-long novelty): beta / sqrt(N(code))
  for each code reached for the first time in the episode. Dithering pays nothing (episodic),
  and what the whole run has rarely reached pays most (count), so the bonus keeps pulling
  toward the part of the maze no variant has led to yet, and fades as the run covers it. With
  ``episodic`` alone, an agent that has learned three of Maze L3's four goals wanders for the
  bonus in the fourth variant and never finds its goal (a wrong goal ends the episode and its
  bonus stream; wandering does not); with ``count`` alone it dithers between rare cells.

All are options for every method (``--exploration count|episodic|episodic-count``), so
baselines can be compared under the same exploration.

``--count-memory`` adds to the code what the causal memory holds when the agent moves there:
the set of observations its gate has kept so far in the episode (:class:`MemoryContent`). The
counts are then of (place, memory) pairs, and a place the agent has often reached, but rarely
*while remembering what it remembers now*, pays again. On Maze L3 this is what finds the last
goals: a policy that has learned the goals of two variants never reaches the goal of a third
variant with that variant's indicator in memory, and no count over places alone pays for
trying. It needs a memory that keeps few observations: T-HCI's gate (the indicators) or the
oracle's labels. Other memories count places alone, and so does T-HCI before its first gate
(its memory is empty then). Counting pairs with a memory of every observation (Maze L3 seed 3,
when T-HCI's memory started full) made almost every pair new: the bonus never faded and the
agent wandered (success 0.00 at 1M steps).

What a memory content *means* depends on the gate: under T-HCI's gate {0, 2} on Maze L3, an
empty memory says "indicators 1 and 7" (the variant whose goal is 14), while before the first
gate it said nothing and was counted at every place of the memoryless phase. So each gate has
its own counts: the digest of a set is keyed by the gate's kept set on Ô
(:meth:`MemoryContent.set_gate`), and a gate seen before resumes its counts. Without the key,
Maze L3 seed 2 kept {0, 2}, learned three goals and stayed at success 0.75 for 900k steps:
nothing paid for trying the fourth goal with an empty memory.
"""

from __future__ import annotations

import hashlib
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from thci.causal.discretize import (
    Discretizer,
    ExactDiscretizer,
    discretizer_from_state,
    make_discretizer,
)
from thci.rl.rollout import Rollout


class MemoryContent:
    """The set of observations each environment's memory has kept so far in its episode.

    Sets are identified by a digest: the XOR of a random 63-bit key per observation code in the
    set, so no table of sets is stored and two different sets share a digest with probability
    about 2^-63.

    Args:
        observation_space: the flat single-env observation space.
        kind: discretizer kind for the observations (:data:`DISCRETIZER_KINDS`).
        num_envs: N.
        seed: seed of the per-code keys.
        cell_layout: (offset, cells, values per cell) of the "cell-set" discretizer.
    """

    def __init__(
        self,
        observation_space: gym.Space,
        kind: str,
        num_envs: int,
        seed: int = 0,
        cell_layout: tuple[int, int, int] | None = None,
    ):
        self.observation_space, self.kind, self.seed = observation_space, kind, seed
        self.cell_layout = cell_layout
        self.discretizer: Discretizer | None = None
        self.code_keys = np.zeros(0, dtype=np.int64)  # (codes,) the key of each code
        self.held = np.zeros((num_envs, 0), dtype=bool)  # (N, codes) in memory this episode
        self.digest = np.zeros(num_envs, dtype=np.int64)  # (N,) digest of each held set
        self.gate_key = 0  # keys every digest by the gate that decides what is kept
        self.pairs = ExactDiscretizer()  # (place code, digest) → one code

    def set_gate(self, kept_codes: np.ndarray) -> None:
        """Key the digests from now on by the gate that keeps `kept_codes` (its kept set on Ô,
        CI codes): counts of (place, memory) pairs are then per gate (module doc). The empty
        set gives key 0, the memory before any gate."""
        codes = np.unique(np.asarray(kept_codes, dtype=np.int64))
        digest = hashlib.blake2b(codes.tobytes(), digest_size=8).digest()
        self.gate_key = int.from_bytes(digest, "little") >> 1 if len(codes) else 0  # int64

    def pair(
        self, places: np.ndarray, obs: torch.Tensor, kept: np.ndarray, starts: np.ndarray
    ) -> np.ndarray:
        """(T, N) one code per (place, memory content) pair: `places` (T, N) codes of where each
        step went, paired with the memory's set after the step's observation (`digests`)."""
        held = self.digests(obs, kept, starts)
        return self.pairs.encode(np.stack((places.ravel(), held.ravel()), axis=1)).reshape(
            places.shape
        )

    def digests(self, obs: torch.Tensor, kept: np.ndarray, starts: np.ndarray) -> np.ndarray:
        """(T, N) int64 digest of the memory's set after each step's observation.

        Args:
            obs: (T, N, D) the observations of a rollout.
            kept: (T, N) bool, the memory keeps obs[t] (T-HCI: the gate's decision).
            starts: (T, N) bool, obs[t] is the first observation of an episode.
        """
        flat = obs.reshape(-1, obs.shape[-1]).numpy()
        if self.discretizer is None:
            self.discretizer = make_discretizer(
                self.kind, self.observation_space, sample=flat, cell_layout=self.cell_layout
            )
        codes = self.discretizer.encode(flat).reshape(kept.shape)
        size = int(codes.max()) + 1
        if size > len(self.code_keys):  # a fresh generator per growth step: resumable
            rng = np.random.default_rng([self.seed, len(self.code_keys)])
            new_keys = rng.integers(1, 2**63 - 1, size - len(self.code_keys), dtype=np.int64)
            self.code_keys = np.concatenate((self.code_keys, new_keys))
        self.held = _grow(self.held, size, axis=1)
        envs = np.arange(codes.shape[1])
        digests = np.empty(codes.shape, dtype=np.int64)
        for t in range(len(codes)):  # sequential: a set depends on the steps before
            self.held[starts[t]] = False
            self.digest[starts[t]] = 0
            new = kept[t] & ~self.held[envs, codes[t]]
            self.digest ^= np.where(new, self.code_keys[codes[t]], 0)
            self.held[envs, codes[t]] |= kept[t]
            digests[t] = self.digest ^ self.gate_key
        return digests

    def state_dict(self) -> dict[str, Any]:
        return {
            "discretizer": None if self.discretizer is None else self.discretizer.state_dict(),
            "code_keys": torch.as_tensor(self.code_keys),
            "held": torch.as_tensor(self.held),
            "digest": torch.as_tensor(self.digest),
            "pairs": self.pairs.state_dict(),
            "gate_key": self.gate_key,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state["discretizer"] is not None:
            self.discretizer = discretizer_from_state(state["discretizer"])
        self.pairs = discretizer_from_state(state["pairs"])
        self.gate_key = int(state.get("gate_key", 0))  # checkpoints from before the key: 0
        for name in ("code_keys", "held", "digest"):
            setattr(self, name, state[name].numpy().copy())


class ExplorationBonus:
    """Codes of the observations a rollout reached; subclasses turn them into a bonus.

    Args:
        observation_space: the flat single-env observation space.
        beta: scale of the bonus.
        kind: discretizer kind (:data:`DISCRETIZER_KINDS`; "cell-set" applies to observations,
            an info entry is then coded exactly).
        count_key: code this info entry of the reached observation instead (None: the
            observation itself).
        memory: pair each code with the memory's content when the step was taken
            (``--count-memory``); None: codes alone.
        cell_layout: (offset, cells, values per cell) of the "cell-set" discretizer.
    """

    def __init__(
        self,
        observation_space: gym.Space,
        beta: float,
        kind: str = "auto",
        count_key: str | None = None,
        memory: MemoryContent | None = None,
        cell_layout: tuple[int, int, int] | None = None,
    ) -> None:
        self.observation_space, self.beta, self.kind = observation_space, beta, kind
        self.count_key, self.memory, self.cell_layout = count_key, memory, cell_layout
        self.discretizer: Discretizer | None = None

    def reached_codes(
        self, rollout: Rollout, next_obs: torch.Tensor, kept: np.ndarray | None = None
    ) -> np.ndarray:
        """(T, N) codes of what each step reached (the final observation where one ended).

        Args:
            rollout: a collected rollout (T, N).
            next_obs: (N, D) the observations after the rollout's last step.
            kept: (T, N) bool, the memory keeps rollout.obs[t]; needed with ``memory``.
        """
        if self.count_key is None:
            reached = torch.cat((rollout.obs[1:], next_obs.unsqueeze(0)))  # (T, N, D)
            reached = torch.where(rollout.dones.unsqueeze(-1), rollout.final_obs, reached)
            flat = reached.reshape(-1, reached.shape[-1]).numpy()
            space = self.observation_space
        else:
            info = rollout.reached_info[self.count_key]
            flat = info.reshape(info.shape[0] * info.shape[1], -1)
            space = gym.spaces.Box(-np.inf, np.inf, flat.shape[1:])
        if self.discretizer is None:
            kind = "auto" if self.kind == "cell-set" and self.count_key else self.kind
            self.discretizer = make_discretizer(
                kind, space, sample=flat, cell_layout=self.cell_layout
            )
        codes = self.discretizer.encode(flat).reshape(rollout.rewards.shape)
        if self.memory is None:
            return codes
        if kept is None:
            raise ValueError("a bonus that counts memory content needs the kept flags")
        return self.memory.pair(codes, rollout.obs, kept, rollout.episode_starts.numpy())

    def add_bonus(
        self, rollout: Rollout, next_obs: torch.Tensor, kept: np.ndarray | None = None
    ) -> float:
        """Add the bonus to ``rollout.rewards`` in place; returns its mean per step.

        ``kept`` (T, N) bool: which observations the memory keeps (with ``memory`` only).
        """
        codes = self.reached_codes(rollout, next_obs, kept)
        bonus = self.bonus(codes, rollout.dones.numpy())
        rollout.rewards += torch.as_tensor(bonus, dtype=torch.float32)
        return float(bonus.mean())

    def bonus(self, codes: np.ndarray, dones: np.ndarray) -> np.ndarray:
        """(T, N) intrinsic reward of reaching `codes` (T, N); `dones` (T, N) ends episodes."""
        raise NotImplementedError

    def state_dict(self) -> dict[str, Any]:
        return {
            "discretizer": None if self.discretizer is None else self.discretizer.state_dict(),
            "memory": None if self.memory is None else self.memory.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state["discretizer"] is not None:
            self.discretizer = discretizer_from_state(state["discretizer"])
        if self.memory is not None:
            self.memory.load_state_dict(state["memory"])


class CountBonus(ExplorationBonus):
    """beta / sqrt(N(code of the observation reached)), N over the whole run."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.counts = np.zeros(0, dtype=np.int64)

    def bonus(self, codes: np.ndarray, dones: np.ndarray) -> np.ndarray:
        return self.beta / np.sqrt(self.count_visits(codes))

    def count_visits(self, codes: np.ndarray) -> np.ndarray:
        """Count the visits `codes` (T, N); returns (T, N) N(code) including them."""
        self.counts = _grow(self.counts, int(codes.max()) + 1, axis=0)
        self.counts += np.bincount(codes.ravel(), minlength=len(self.counts))
        return self.counts[codes]

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "counts": torch.as_tensor(self.counts)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.counts = state["counts"].numpy().copy()


class EpisodicNoveltyBonus(ExplorationBonus):
    """beta when the code reached is new in the current episode of that environment.

    Args:
        num_envs: N (each environment's episode keeps its own visited set).
        (the rest as :class:`ExplorationBonus`)
    """

    def __init__(self, *args: Any, num_envs: int, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.visited = np.zeros((num_envs, 0), dtype=bool)  # (N, codes seen so far)

    def bonus(self, codes: np.ndarray, dones: np.ndarray) -> np.ndarray:
        return self.beta * self.first_visits(codes, dones)

    def first_visits(self, codes: np.ndarray, dones: np.ndarray) -> np.ndarray:
        """(T, N) bool: `codes` (T, N) reached for the first time in its episode."""
        self.visited = _grow(self.visited, int(codes.max()) + 1, axis=1)
        envs = np.arange(codes.shape[1])
        new = np.empty(codes.shape, dtype=bool)
        for t in range(len(codes)):  # T vector steps: visits within a rollout are sequential
            new[t] = ~self.visited[envs, codes[t]]
            self.visited[envs, codes[t]] = True
            self.visited[dones[t]] = False  # the next episode starts with nothing visited
        return new

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "visited": torch.as_tensor(self.visited)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.visited = state["visited"].numpy().copy()


class EpisodicCountBonus(EpisodicNoveltyBonus, CountBonus):
    """beta / sqrt(N(code)) when the code reached is new in the current episode (NGU).

    N counts every visit of the run, first or not. Args as :class:`EpisodicNoveltyBonus`.
    """

    def bonus(self, codes: np.ndarray, dones: np.ndarray) -> np.ndarray:
        return self.beta * self.first_visits(codes, dones) / np.sqrt(self.count_visits(codes))


def _grow(array: np.ndarray, size: int, axis: int) -> np.ndarray:
    """Zero-pad `array` along `axis` up to `size` (the discretizer met new codes)."""
    missing = size - array.shape[axis]
    if missing <= 0:
        return array
    widths = [(0, 0)] * array.ndim
    widths[axis] = (0, missing)
    return np.pad(array, widths)


def make_exploration_bonus(
    kind: str,
    observation_space: gym.Space,
    beta: float,
    discretizer: str,
    count_key: str | None,
    num_envs: int,
    count_memory: bool = False,
    cell_layout: tuple[int, int, int] | None = None,
) -> ExplorationBonus | None:
    """The bonus named by ``--exploration`` (None for "none"); ``count_memory`` pairs its codes
    with the memory's content; ``cell_layout`` is the "cell-set" discretizer's."""
    memory = (
        MemoryContent(observation_space, discretizer, num_envs, cell_layout=cell_layout)
        if count_memory
        else None
    )
    args = (observation_space, beta, discretizer, count_key, memory, cell_layout)
    if kind == "count":
        return CountBonus(*args)
    episodic = {"episodic": EpisodicNoveltyBonus, "episodic-count": EpisodicCountBonus}
    if kind in episodic:
        return episodic[kind](*args, num_envs=num_envs)
    return None

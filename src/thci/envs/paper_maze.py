"""The T-HCI paper's symbolic Maze levels 1-4 (Fig. 4) as gymnasium environments.

The mazes are read from the shipped ``data/paper_maze.json``: per level a start cell, the
terminal goal codes, the codes a human labels as causal, and a few variants (grids of integer
codes 0-14, each with a probability and a rewarded goal). The agent observes only the one-hot
code of the cell it stands on, so it must remember the indicator seen at the start (and, in
levels 3-4, the one north of it) to know which goal pays. That memory problem is what the
history-based agents in this package are evaluated on.

Two implementations share the same dynamics code:

* :class:`PaperMazeEnv` - a plain ``gymnasium.Env`` (one maze).
* :class:`PaperMazeVectorEnv` - a native ``gymnasium.vector.VectorEnv`` that steps N mazes with
  numpy array operations only, with same-step autoreset.

The only randomness is the variant drawn at each reset. It comes from a counter-based hash
(:func:`episode_uniform`) of a per-environment 64-bit key and an episode counter, so the
batched environment reproduces N seeded single environments bit-for-bit without looping over
them, and its whole random state is two integer arrays that can be checkpointed.
"""

import json
from dataclasses import dataclass
from functools import cache
from importlib import resources
from numbers import Integral
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from thci.errors import ThciError

__all__ = [
    "MazeLevel",
    "PaperMazeEnv",
    "PaperMazeVectorEnv",
    "available_levels",
    "episode_uniform",
    "load_maze_level",
]

_DATA_FILE = "paper_maze.json"

# Action -> (d_row, d_col): 0 = col+1, 1 = col-1, 2 = row+1, 3 = row-1 (the JSON's "actions").
_MOVES = np.array([[0, 1], [0, -1], [1, 0], [-1, 0]], dtype=np.int64)
_NUM_ACTIONS = len(_MOVES)

_RENDER_MODES = ("ansi", "rgb_array")
_RENDER_FPS = 4
_CELL_PX = 16

# One colour per code (index = code). Code 4 (wall) is dark; the rest are Trubetskoy's
# "distinct colours" so that every code, not just every role, can be told apart on screen.
_PALETTE = np.array(
    [
        (230, 25, 75),  # 0  start indicator A
        (0, 130, 200),  # 1  start indicator B
        (245, 130, 48),  # 2  second indicator (levels 3-4)
        (170, 110, 40),  # 3
        (40, 40, 40),  # 4  wall
        (60, 180, 75),  # 5  goal
        (145, 30, 180),  # 6  goal
        (128, 128, 128),  # 7
        (255, 225, 25),  # 8
        (70, 240, 240),  # 9
        (0, 128, 128),  # 10
        (220, 190, 255),  # 11
        (128, 128, 0),  # 12
        (240, 50, 230),  # 13 goal (levels 3-4)
        (210, 245, 60),  # 14 goal (levels 3-4)
    ],
    dtype=np.uint8,
)


def _agent_sprite() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel offsets (K,), (K,) and colours (K, 3) of the agent marker inside its cell."""
    sprite = np.full((_CELL_PX, _CELL_PX, 3), -1, dtype=np.int16)
    sprite[3:-3, 3:-3] = 0  # black outline keeps the marker visible on light cells
    sprite[5:-5, 5:-5] = 255
    dy, dx = np.nonzero(sprite[:, :, 0] >= 0)
    return dy, dx, sprite[dy, dx].astype(np.uint8)


_SPRITE_DY, _SPRITE_DX, _SPRITE_RGB = _agent_sprite()

# SplitMix64 constants (Steele, Lea & Flood 2014; Vigna's reference implementation).
_GOLDEN_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_MIX_1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX_2 = np.uint64(0x94D049BB133111EB)


def episode_uniform(key: np.ndarray, counter: np.ndarray) -> np.ndarray:
    """Counter-based uniform draw in [0, 1): output ``counter`` of SplitMix64 seeded with ``key``.

    ``z = key + (counter + 1) * golden_gamma`` is exactly SplitMix64's state after
    ``counter + 1`` increments, so the result is the generator's ``counter``-th output (0-based),
    computed directly. The top 53 bits become a float64.

    Args:
        key: uint64 array (any shape), one 64-bit key per stream.
        counter: uint64 array broadcastable with ``key``, the draw index within the stream.

    Returns:
        float64 array of the broadcast shape, values in [0, 1).
    """
    key = np.asarray(key, dtype=np.uint64)
    counter = np.asarray(counter, dtype=np.uint64)
    # uint64 arithmetic is meant to wrap modulo 2**64; numpy only warns about it for 0-d input.
    with np.errstate(over="ignore"):
        z = key + (counter + np.uint64(1)) * _GOLDEN_GAMMA
        z = (z ^ (z >> np.uint64(30))) * _MIX_1
        z = (z ^ (z >> np.uint64(27))) * _MIX_2
        z = z ^ (z >> np.uint64(31))
    return np.asarray((z >> np.uint64(11)).astype(np.float64) * 2.0**-53)


def _derive_episode_key(rng: np.random.Generator) -> np.uint64:
    """The 64-bit key of an environment's variant stream, drawn from its seeded generator.

    Shared by both environments so that vector env ``i`` seeded ``s + i`` gets the same key as
    a single env reset with ``seed=s + i``.
    """
    return rng.integers(0, np.iinfo(np.uint64).max, dtype=np.uint64, endpoint=True)


@dataclass(frozen=True, eq=False)
class MazeLevel:
    """One paper maze level, parsed from the shipped JSON. All arrays are read-only.

    Attributes:
        level: Level number (1-4).
        grids: (V, H, W) int64 cell codes of each variant (H = 18 rows, W = 15 columns).
        probabilities: (V,) float64 probability of drawing each variant at reset.
        cumulative_probabilities: (V,) float64 running sum of ``probabilities``, last entry
            exactly 1.0, so ``searchsorted(..., u, side="right")`` maps u in [0, 1) to a variant.
        rewarded_goal: (V,) int64 goal code that pays reward 1 in each variant.
        start: (2,) int64 start cell [row, col].
        terminal_codes: (T,) int64 codes that end the episode when stepped on.
        causal_codes: (C,) int64 codes a human labels as causal (ground truth for TAIE/Oracle).
        is_terminal: (num_codes,) bool lookup ``code -> code in terminal_codes``.
        is_causal: (num_codes,) bool lookup ``code -> code in causal_codes``.
        num_codes: Number of distinct cell codes (observation size, 15).
        wall_code: Code of impassable cells (4).
        max_steps: Default episode length limit (30).
    """

    level: int
    grids: np.ndarray
    probabilities: np.ndarray
    cumulative_probabilities: np.ndarray
    rewarded_goal: np.ndarray
    start: np.ndarray
    terminal_codes: np.ndarray
    causal_codes: np.ndarray
    is_terminal: np.ndarray
    is_causal: np.ndarray
    num_codes: int
    wall_code: int
    max_steps: int

    @property
    def num_variants(self) -> int:
        """Number of variants V."""
        return int(self.grids.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        """Grid shape (H, W)."""
        return int(self.grids.shape[1]), int(self.grids.shape[2])


@cache
def _raw_data() -> dict[str, Any]:
    """The parsed JSON file (read once per process)."""
    text = resources.files("thci.envs").joinpath("data", _DATA_FILE).read_text(encoding="utf-8")
    return json.loads(text)


def available_levels() -> tuple[int, ...]:
    """The level numbers present in the shipped data, ascending."""
    return tuple(sorted(int(entry["level"]) for entry in _raw_data()["levels"]))


def _readonly(array: np.ndarray) -> np.ndarray:
    # Levels are cached and shared by every env instance, so nobody may mutate them.
    array.setflags(write=False)
    return array


@cache
def load_maze_level(level: int) -> MazeLevel:
    """Load one of the paper's maze levels from the shipped JSON (cached per level).

    Raises:
        ThciError: If ``level`` is not one of :func:`available_levels`.
    """
    data = _raw_data()
    entries = {int(entry["level"]): entry for entry in data["levels"]}
    if level not in entries:
        valid = ", ".join(str(k) for k in sorted(entries))
        raise ThciError(f"unknown paper maze level {level!r}; valid levels are {valid}")
    entry = entries[level]
    num_codes = int(data["num_codes"])
    variants = entry["variants"]
    probabilities = np.array([v["probability"] for v in variants], dtype=np.float64)
    cumulative = np.cumsum(probabilities) / probabilities.sum()
    # Rounding could leave the last entry just below 1 and let u ~ 1 index past the end.
    cumulative[-1] = 1.0
    terminal = np.array(entry["terminal_goal_codes"], dtype=np.int64)
    causal = np.array(entry["causal_codes_ground_truth"], dtype=np.int64)
    return MazeLevel(
        level=level,
        grids=_readonly(np.array([v["grid"] for v in variants], dtype=np.int64)),
        probabilities=_readonly(probabilities),
        cumulative_probabilities=_readonly(cumulative),
        rewarded_goal=_readonly(np.array([v["rewarded_goal"] for v in variants], np.int64)),
        start=_readonly(np.array(entry["start"], dtype=np.int64)),
        terminal_codes=_readonly(terminal),
        causal_codes=_readonly(causal),
        is_terminal=_readonly(np.isin(np.arange(num_codes), terminal)),
        is_causal=_readonly(np.isin(np.arange(num_codes), causal)),
        num_codes=num_codes,
        wall_code=int(data["wall_code"]),
        max_steps=int(data["max_steps"]),
    )


def _check_max_steps(maze: MazeLevel, max_steps: int | None) -> int:
    if max_steps is None:
        return maze.max_steps
    if not isinstance(max_steps, Integral) or isinstance(max_steps, bool) or max_steps < 1:
        raise ThciError(f"max_steps must be a positive integer, got {max_steps!r}")
    return int(max_steps)


def _check_render_mode(render_mode: str | None) -> None:
    if render_mode is not None and render_mode not in _RENDER_MODES:
        raise ThciError(
            f"unknown render_mode {render_mode!r}; use one of {', '.join(_RENDER_MODES)} or None"
        )


def _draw_variants(maze: MazeLevel, keys: np.ndarray, counters: np.ndarray) -> np.ndarray:
    """Variant indices (N,) int64 for streams ``keys`` (N,) at draw ``counters`` (N,)."""
    u = episode_uniform(keys, counters)
    return np.searchsorted(maze.cumulative_probabilities, u, side="right").astype(np.int64)


def _cell_codes(maze: MazeLevel, variants: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Codes (N,) int64 under the agents at ``positions`` (N, 2) in ``variants`` (N,)."""
    return maze.grids[variants, positions[:, 0], positions[:, 1]]


def _advance(
    maze: MazeLevel,
    variants: np.ndarray,
    positions: np.ndarray,
    steps: np.ndarray,
    actions: np.ndarray,
    max_steps: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One transition of N mazes; the single source of the dynamics for both env classes.

    Args:
        variants: (N,) int64 variant of each maze.
        positions: (N, 2) int64 agent [row, col] before the move.
        steps: (N,) int64 steps already taken this episode.
        actions: (N,) int64 actions in [0, 4).

    Returns:
        new positions (N, 2) int64, codes (N,) int64 under the agents after the move,
        success (N,) bool (stepped on the rewarded goal), terminated (N,) bool,
        truncated (N,) bool (limit reached without termination).
    """
    height, width = maze.shape
    target = positions + _MOVES[actions]
    rows, cols = target[:, 0], target[:, 1]
    inside = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
    # Clipping only makes the lookup legal; off-grid targets are rejected by `inside` anyway.
    target_codes = maze.grids[variants, np.clip(rows, 0, height - 1), np.clip(cols, 0, width - 1)]
    moved = inside & (target_codes != maze.wall_code)
    new_positions = np.where(moved[:, None], target, positions)
    codes = np.where(moved, target_codes, _cell_codes(maze, variants, positions))
    terminated = maze.is_terminal[codes]
    success = terminated & (codes == maze.rewarded_goal[variants])
    truncated = ~terminated & (steps + 1 >= max_steps)
    return new_positions, codes, success, terminated, truncated


def _one_hot(maze: MazeLevel, codes: np.ndarray) -> np.ndarray:
    """Observations (..., num_codes) float32 for ``codes`` (...); always a new array."""
    return np.eye(maze.num_codes, dtype=np.float32)[codes]


def _render_rgb(maze: MazeLevel, variants: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Images (N, H*16, W*16, 3) uint8 of N mazes with the agent drawn as a white square."""
    image = _PALETTE[maze.grids[variants]]
    image = image.repeat(_CELL_PX, axis=1).repeat(_CELL_PX, axis=2)
    index = np.arange(len(variants))[:, None]
    rows = positions[:, :1] * _CELL_PX + _SPRITE_DY
    cols = positions[:, 1:] * _CELL_PX + _SPRITE_DX
    image[index, rows, cols] = _SPRITE_RGB
    return image


def _render_ansi(maze: MazeLevel, variant: int, position: np.ndarray, step: int) -> str:
    """Text picture of one maze: codes as numbers, walls as ``##``, the agent as ``@``."""
    header = (
        f"PaperMaze level {maze.level}, variant {variant} "
        f"(rewarded goal {maze.rewarded_goal[variant]}), step {step}"
    )
    lines = [header]
    for r, row in enumerate(maze.grids[variant]):
        cells = ["##" if code == maze.wall_code else f"{code:2d}" for code in row]
        if r == position[0]:
            cells[position[1]] = " @"
        lines.append(" ".join(cells))
    return "\n".join(lines) + "\n"


class PaperMazeEnv(gym.Env[np.ndarray, np.int64]):
    """One paper maze (levels 1-4) with the gymnasium 1.x API.

    Observation: (15,) float32 one-hot of the code of the agent's cell. Actions: Discrete(4),
    0 = col+1, 1 = col-1, 2 = row+1, 3 = row-1; moving into a wall or off the grid is a no-op.
    Stepping on a terminal goal code ends the episode with reward 1.0 if it is the variant's
    rewarded goal, else 0.0. After ``max_steps`` steps without that, the episode is truncated
    (reward 0); a termination on the last step counts as termination only.

    ``info`` (reset and every step): ``causal`` (bool, current code is a ground-truth causal
    code), ``success`` (bool, this step terminated on the rewarded goal), ``agent_pos``
    ((2,) int64 [row, col]), ``variant`` (int), ``code`` (int, current cell code).

    Seeding: ``reset(seed=s)`` derives a 64-bit key from ``np_random`` and restarts an episode
    counter; every reset draws its variant as ``episode_uniform(key, counter)``.
    """

    metadata: ClassVar[dict[str, Any]] = {
        "render_modes": list(_RENDER_MODES),
        "render_fps": _RENDER_FPS,
    }

    def __init__(
        self, level: int = 1, max_steps: int | None = None, render_mode: str | None = None
    ) -> None:
        self.maze = load_maze_level(level)
        self.max_steps = _check_max_steps(self.maze, max_steps)
        _check_render_mode(render_mode)
        self.render_mode = render_mode
        self.observation_space = spaces.Box(0.0, 1.0, (self.maze.num_codes,), np.float32)
        self.action_space = spaces.Discrete(_NUM_ACTIONS)
        self._key: np.uint64 | None = None
        self._counter = 0
        self._variant = 0
        self._position = self.maze.start.copy()
        self._steps = 0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode in a freshly drawn variant. ``options`` is accepted and ignored."""
        super().reset(seed=seed)
        if seed is not None or self._key is None:
            self._key = _derive_episode_key(self.np_random)
            self._counter = 0
        self._variant = int(_draw_variants(self.maze, self._key, np.uint64(self._counter)))
        self._counter += 1
        self._position = self.maze.start.copy()
        self._steps = 0
        code = int(self.maze.grids[self._variant, self._position[0], self._position[1]])
        return self._observation(code), self._info(code, success=False)

    def step(
        self, action: int | np.integer
    ) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Move one cell; see the class docstring for rewards and episode ends."""
        if self._key is None:
            raise gym.error.ResetNeeded("call reset() before step() on PaperMazeEnv")
        if not self.action_space.contains(action):
            raise ValueError(
                f"invalid action {action!r}: expected an integer in [0, {_NUM_ACTIONS}) "
                "(0 = col+1, 1 = col-1, 2 = row+1, 3 = row-1)"
            )
        positions, codes, success, terminated, truncated = _advance(
            self.maze,
            np.array([self._variant]),
            self._position[None],
            np.array([self._steps]),
            np.array([int(action)]),
            self.max_steps,
        )
        self._position = positions[0]
        self._steps += 1
        code = int(codes[0])
        return (
            self._observation(code),
            float(success[0]),
            bool(terminated[0]),
            bool(truncated[0]),
            self._info(code, success=bool(success[0])),
        )

    def render(self) -> str | np.ndarray | None:
        """``"ansi"``: text picture; ``"rgb_array"``: (H*16, W*16, 3) uint8; None: nothing."""
        if self.render_mode == "ansi":
            return _render_ansi(self.maze, self._variant, self._position, self._steps)
        if self.render_mode == "rgb_array":
            return _render_rgb(self.maze, np.array([self._variant]), self._position[None])[0]
        return None

    def _observation(self, code: int) -> np.ndarray:
        return _one_hot(self.maze, np.array(code))

    def _info(self, code: int, success: bool) -> dict[str, Any]:
        return {
            "causal": bool(self.maze.is_causal[code]),
            "success": success,
            "agent_pos": self._position.copy(),
            "variant": self._variant,
            "code": code,
        }


def _masked(info: dict[str, np.ndarray], mask: np.ndarray) -> dict[str, np.ndarray]:
    """Gymnasium's vector-info layout: each ``key`` gets a ``_key`` (N,) bool mask."""
    out: dict[str, np.ndarray] = {}
    for key, value in info.items():
        out[key] = value
        out[f"_{key}"] = mask.copy()
    return out


class PaperMazeVectorEnv(VectorEnv[np.ndarray, np.ndarray, np.ndarray]):
    """N paper mazes stepped together with numpy array operations (no per-env Python loop).

    Env ``i`` behaves exactly like a :class:`PaperMazeEnv` of the same level reset with seed
    ``s + i`` (for ``reset(seed=s)``) and reset without a seed whenever its episode ends.
    Autoreset is ``SAME_STEP``: a row whose episode ended in this step already holds the first
    observation of the next episode.

    ``step`` returns obs (N, 15) float32, rewards (N,) float64, terminated (N,) bool,
    truncated (N,) bool and ``infos``:

    * ``causal`` (N,) bool, ``success`` (N,) bool, ``agent_pos`` (N, 2) int64, ``variant`` (N,)
      int64, ``code`` (N,) int64 - the info of the returned observation (for reset rows the
      reset info, with ``success`` False) - each with an all-True ``_key`` (N,) bool mask.
    * Only when at least one env ended (as in ``SyncVectorEnv``): ``final_obs`` (N, 15)
      float32 with ``_final_obs`` (N,) bool, and ``final_info`` (a dict with the same five keys
      and their ``_key`` masks, holding the ended step's info) with ``_final_info`` (N,) bool.
      Unlike ``SyncVectorEnv``, whose ``final_obs`` is an object array with None rows,
      ``final_obs`` here is dense; rows of envs that did not end (mask False) hold that step's
      ordinary observation/info, i.e. the same as the top-level rows.

    ``get_state``/``set_state`` capture everything needed to continue bit-identically.
    """

    metadata: ClassVar[dict[str, Any]] = {
        "autoreset_mode": AutoresetMode.SAME_STEP,
        "render_modes": list(_RENDER_MODES),
        "render_fps": _RENDER_FPS,
    }

    def __init__(
        self,
        num_envs: int,
        level: int = 1,
        max_steps: int | None = None,
        render_mode: str | None = None,
    ) -> None:
        if not isinstance(num_envs, Integral) or isinstance(num_envs, bool) or num_envs < 1:
            raise ThciError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.num_envs = int(num_envs)
        self.maze = load_maze_level(level)
        self.max_steps = _check_max_steps(self.maze, max_steps)
        _check_render_mode(render_mode)
        self.render_mode = render_mode
        self.single_observation_space = spaces.Box(0.0, 1.0, (self.maze.num_codes,), np.float32)
        self.single_action_space = spaces.Discrete(_NUM_ACTIONS)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        n = self.num_envs
        self._keys: np.ndarray | None = None  # (N,) uint64, set at the first reset
        self._counters = np.zeros(n, dtype=np.uint64)
        self._variants = np.zeros(n, dtype=np.int64)
        self._positions = np.tile(self.maze.start, (n, 1))
        self._steps = np.zeros(n, dtype=np.int64)

    def reset(
        self,
        *,
        seed: int | list[int | None] | None = None,
        options: dict[str, Any] | None = None,
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset all N mazes.

        Args:
            seed: None (keep each env's stream; random keys on the very first reset), an int
                ``s`` (env ``i`` uses ``s + i``, like ``SyncVectorEnv``), or a list of N seeds
                (None entries keep that env's stream).
            options: Accepted for API compatibility and ignored.

        Returns:
            obs (N, 15) float32 and infos (the five info keys with all-True masks).
        """
        n = self.num_envs
        if self._keys is None:
            # Consumed only by envs without a seed, like PaperMazeEnv's unseeded first reset.
            self._keys = self.np_random.integers(
                0, np.iinfo(np.uint64).max, size=n, dtype=np.uint64, endpoint=True
            )
            self._counters[:] = 0
        if seed is not None:
            # int(): gymnasium's seeding rejects numpy integers.
            seeds = [int(seed) + i for i in range(n)] if isinstance(seed, Integral) else seed
            if len(seeds) != n:
                raise ValueError(f"expected {n} seeds (one per env), got {len(seeds)}")
            for i, env_seed in enumerate(seeds):
                if env_seed is not None:
                    self._keys[i] = _derive_episode_key(seeding.np_random(int(env_seed))[0])
                    self._counters[i] = 0
        self._begin_episodes(np.arange(n))
        codes = _cell_codes(self.maze, self._variants, self._positions)
        infos = _masked(self._info(codes, np.zeros(n, dtype=bool)), np.ones(n, dtype=bool))
        return _one_hot(self.maze, codes), infos

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Advance all N mazes by one action each; ``actions`` is (N,) int in [0, 4)."""
        if self._keys is None:
            raise gym.error.ResetNeeded("call reset() before step() on PaperMazeVectorEnv")
        actions = np.asarray(actions)
        if (
            actions.shape != (self.num_envs,)
            or not np.issubdtype(actions.dtype, np.integer)
            or np.any((actions < 0) | (actions >= _NUM_ACTIONS))
        ):
            raise ValueError(
                f"invalid actions {actions!r}: expected shape ({self.num_envs},) integers in "
                f"[0, {_NUM_ACTIONS}) (0 = col+1, 1 = col-1, 2 = row+1, 3 = row-1)"
            )
        positions, codes, success, terminated, truncated = _advance(
            self.maze, self._variants, self._positions, self._steps, actions, self.max_steps
        )
        self._positions = positions
        self._steps += 1
        rewards = success.astype(np.float64)
        done = terminated | truncated
        all_envs = np.ones(self.num_envs, dtype=bool)
        if not done.any():
            infos = _masked(self._info(codes, success), all_envs)
            return _one_hot(self.maze, codes), rewards, terminated, truncated, infos

        final_obs = _one_hot(self.maze, codes)
        final_info = _masked(self._info(codes, success), done)
        ended = np.flatnonzero(done)
        self._begin_episodes(ended)
        codes = codes.copy()
        codes[ended] = _cell_codes(self.maze, self._variants[ended], self._positions[ended])
        infos = _masked(self._info(codes, success & ~done), all_envs)
        infos.update(
            final_obs=final_obs,
            _final_obs=done.copy(),
            final_info=final_info,
            _final_info=done.copy(),
        )
        return _one_hot(self.maze, codes), rewards, terminated, truncated, infos

    def render(self) -> tuple[str, ...] | tuple[np.ndarray, ...] | None:
        """One frame per env, like ``SyncVectorEnv.render``.

        ``"ansi"``: N strings; ``"rgb_array"``: N (H*16, W*16, 3) uint8 images (views of one
        (N, H*16, W*16, 3) array); None when no render mode was given.
        """
        if self.render_mode == "ansi":
            return tuple(
                _render_ansi(self.maze, int(v), p, int(t))
                for v, p, t in zip(self._variants, self._positions, self._steps, strict=True)
            )
        if self.render_mode == "rgb_array":
            return tuple(_render_rgb(self.maze, self._variants, self._positions))
        return None

    def get_state(self) -> dict[str, np.ndarray]:
        """Copy of the complete dynamic state (for exact checkpoint/resume).

        Returns:
            ``level`` () int64, ``max_steps`` () int64, ``positions`` (N, 2) int64,
            ``variants`` (N,) int64, ``steps`` (N,) int64, ``keys`` (N,) uint64,
            ``counters`` (N,) uint64.
        """
        if self._keys is None:
            raise gym.error.ResetNeeded("call reset() before get_state() on PaperMazeVectorEnv")
        return {
            "level": np.array(self.maze.level, dtype=np.int64),
            "max_steps": np.array(self.max_steps, dtype=np.int64),
            "positions": self._positions.copy(),
            "variants": self._variants.copy(),
            "steps": self._steps.copy(),
            "keys": self._keys.copy(),
            "counters": self._counters.copy(),
        }

    def set_state(self, state: dict[str, np.ndarray]) -> None:
        """Restore a :meth:`get_state` snapshot (arrays are copied).

        Raises:
            ThciError: If the snapshot is incomplete or belongs to a different level,
                ``max_steps`` or number of envs, or holds out-of-range values.
        """
        n = self.num_envs
        expected = {
            "level": ((), np.int64),
            "max_steps": ((), np.int64),
            "positions": ((n, 2), np.int64),
            "variants": ((n,), np.int64),
            "steps": ((n,), np.int64),
            "keys": ((n,), np.uint64),
            "counters": ((n,), np.uint64),
        }
        missing = sorted(set(expected) - set(state))
        if missing:
            raise ThciError(f"paper maze state is missing {', '.join(missing)}")
        arrays = {name: np.array(state[name], dtype=dtype) for name, (_, dtype) in expected.items()}
        for name, (shape, _) in expected.items():
            if arrays[name].shape != shape:
                raise ThciError(
                    f"paper maze state {name!r} has shape {arrays[name].shape}, expected {shape} "
                    f"(was it saved with num_envs={n}?)"
                )
        if int(arrays["level"]) != self.maze.level or int(arrays["max_steps"]) != self.max_steps:
            raise ThciError(
                f"paper maze state is for level {int(arrays['level'])} with max_steps "
                f"{int(arrays['max_steps'])}, but this env is level {self.maze.level} with "
                f"max_steps {self.max_steps}"
            )
        height, width = self.maze.shape
        rows, cols = arrays["positions"][:, 0], arrays["positions"][:, 1]
        # Negative indices would silently wrap around in numpy instead of failing.
        if (
            np.any((arrays["variants"] < 0) | (arrays["variants"] >= self.maze.num_variants))
            or np.any((rows < 0) | (rows >= height) | (cols < 0) | (cols >= width))
            or np.any((arrays["steps"] < 0) | (arrays["steps"] >= self.max_steps))
        ):
            raise ThciError("paper maze state holds out-of-range variants, positions or steps")
        self._positions = arrays["positions"]
        self._variants = arrays["variants"]
        self._steps = arrays["steps"]
        self._keys = arrays["keys"]
        self._counters = arrays["counters"]

    def _begin_episodes(self, envs: np.ndarray) -> None:
        """Draw a new variant for ``envs`` (K,) int64 indices and put their agents at start."""
        self._variants[envs] = _draw_variants(self.maze, self._keys[envs], self._counters[envs])
        self._counters[envs] += np.uint64(1)
        self._positions[envs] = self.maze.start
        self._steps[envs] = 0

    def _info(self, codes: np.ndarray, success: np.ndarray) -> dict[str, np.ndarray]:
        """Unmasked info arrays for the current state, given ``codes`` and ``success`` (N,)."""
        return {
            "causal": self.maze.is_causal[codes],
            "success": success,
            "agent_pos": self._positions.copy(),
            "variant": self._variants.copy(),
            "code": codes,
        }

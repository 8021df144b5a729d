"""The T-HCI paper's BabyAI levels 1-4: UnlockToUnlock-style memory tasks built on minigrid.

The paper evaluates on "UnlockToUnlock (Chevalier-Boisvert et al. 2019), including key-to-door,
key-to-box, and go-to-ball navigation tasks", where "the agent needs to depart and return from
the middle room", so that doorway (bottleneck) observations are frequent and confounded while
the observations that decide success are sparse. It gives no further detail, so the four levels
here are our reconstruction with minigrid's BabyAI machinery (:class:`RoomGridLevel`,
``add_door``, ``add_object``, ``GoToInstr`` / ``PickupInstr`` with ``ObjDesc`` verifiers).

Shared layout (every level): three rooms in a row (``num_rows=1, num_cols=3``). The agent starts
in the middle room M at a random cell, facing one side room, A (left or right at random), which
holds the **signpost**: one segment of A's outer wall painted in the *target colour*. The other
side room, B, holds two balls, the target (target colour) and a decoy (another colour), on the
two cells beside the first cell inside B's door, which is in the middle of B's wall. The task is
to go to (levels 1-3) or pick up (level 4) the ball whose colour the signpost shows; going to /
picking up the other ball fails the episode (reward 0). So the agent looks into A first (its
door is open in levels 1-3; in level 4 it must unlock it), returns through M and its doorways
to B, and chooses a ball at B's door, one turn away, with the signpost out of view: it must
remember the colour. Keys, boxes, locked doors and distractors on the way add sub-goals and
length from level to level. The cue first and the choice in one action: with A closed and the
balls anywhere in B no method learned to use the signpost (docs/babyai.md).

``info["causal"]`` (reset and every step) is True iff the signpost is drawn in the current
observation: its cell is inside the agent's 7x7 view and not hidden behind a wall or closed
door. Those are the observations whose colour decides which ball pays; the doorways, keys and
rooms seen on the way are only confounded with success.

Interface of the registered ids ``thci/BabyAI-L1-v0`` ... ``thci/BabyAI-L4-v0``
(:func:`make_babyai_env`):

* Observation: :class:`FlatBabyAIObservation` turns minigrid's Dict observation into one flat
  uint8 vector: the egocentric 7x7x3 ``image`` (object, colour, state indices, flattened in
  minigrid's (x, y, channel) order, 147 values) followed by the one-hot ``direction`` (4
  values). The mission string is dropped: it is the same for every episode of a level (the
  target colour is shown only by the signpost, never in the mission).
* Actions: Discrete(6), minigrid's first six actions 0 left, 1 right, 2 forward, 3 pickup,
  4 drop, 5 toggle. ``done`` (6) is left out: BabyAI only uses it under the
  ``BABYAI_DONE_ACTIONS`` flag, which these levels ignore. ``drop`` is kept because level 4
  needs it (the agent must put a key down to take the next key, and its hands must be empty
  to pick up the ball); the same action set is used by all levels.
* Reward: minigrid's ``1 - 0.9 * step_count / max_steps`` on success, else 0.
* ``info`` (reset and every step): ``causal`` (bool, above), ``success`` (bool, this step
  completed the task), ``agent_pos`` ((2,) int64 [row, col], i.e. minigrid's (y, x), the
  project's convention).

:class:`BabyAIExpert` is a scripted expert with full knowledge of the level (it is
privileged: it never explores). It first looks at the signpost, then plans each sub-goal with
a breadth-first search over (cell, heading); the tests use it to show every level solvable.
"""

from collections import deque
from collections.abc import Callable
from numbers import Integral
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from minigrid.core.constants import COLOR_NAMES, COLOR_TO_IDX, OBJECT_TO_IDX, STATE_TO_IDX
from minigrid.core.roomgrid import RoomGrid, reject_next_to
from minigrid.core.world_object import Ball, Box, Door, Key, Wall, WorldObj
from minigrid.envs.babyai.core.roomgrid_level import RejectSampling, RoomGridLevel
from minigrid.envs.babyai.core.verifier import GoToInstr, ObjDesc, PickupInstr

from thci.errors import ThciError

__all__ = [
    "ACTION_NAMES",
    "BABYAI_LEVELS",
    "BabyAIExpert",
    "BabyAILevel",
    "FlatBabyAIObservation",
    "GoToBallLevel",
    "KeyToBoxLevel",
    "KeyToDoorLevel",
    "UnlockToUnlockLevel",
    "make_babyai_env",
]

ACTION_NAMES: tuple[str, ...] = ("left", "right", "forward", "pickup", "drop", "toggle")
"""The action set: minigrid's actions 0-5 under the same indices (``done`` is left out)."""
LEFT, RIGHT, FORWARD, PICKUP, DROP, TOGGLE = range(len(ACTION_NAMES))
# The actions that can change a cell of the grid.
_GRID_ACTIONS = (PICKUP, DROP, TOGGLE)

# Room column indices (num_rows=1, so the row index is always 0).
_LEFT_ROOM, _MIDDLE_ROOM, _RIGHT_ROOM = 0, 1, 2
# Grey would make the signpost look like an ordinary wall.
_SIGNPOST_COLORS = tuple(c for c in COLOR_NAMES if c != "grey")
# minigrid's DIR_TO_VEC: 0 = +x (east), 1 = +y (south), 2 = -x (west), 3 = -y (north).
_DIR_VEC = ((1, 0), (0, 1), (-1, 0), (0, -1))
# Upper bounds of the (object, colour, state) indices in an image cell.
_CELL_HIGH = (
    max(OBJECT_TO_IDX.values()),
    max(COLOR_TO_IDX.values()),
    max(STATE_TO_IDX.values()),
)
# Codes of a cell outside the grid (minigrid shows a grey wall) and of an empty one.
_WALL = Wall()
_EMPTY_CODE = (OBJECT_TO_IDX["empty"], 0, 0)
# Rejection sampling resamples a layout rarely; this many failures in a row means a bug.
_MAX_GENERATION_TRIES = 1000


_State = tuple[int, int, int]  # x, y, heading


class _Subgoal:
    """Reach a state accepted by ``goal``, then take ``action`` (None: reaching it is all)."""

    def __init__(self, goal: Callable[[int, int, int], bool], action: int | None) -> None:
        self.goal, self.action = goal, action


class _GoToBallInstr(GoToInstr):
    """``GoToInstr`` that also fails when the agent faces a ball the description does not match."""

    def verify(self, action: int) -> str:
        # Skip ActionInstr's BABYAI_DONE_ACTIONS mode: the action set has no ``done``.
        return self.verify_action(action)

    def verify_action(self, action: int) -> str:
        status = super().verify_action(action)
        if status == "continue":
            front = self.env.grid.get(*self.env.front_pos)
            if isinstance(front, Ball) and all(front is not obj for obj in self.desc.obj_set):
                return "failure"
        return status


class _PickupBallInstr(PickupInstr):
    """``PickupInstr`` that also fails when the agent picks up a ball the description does not
    match (``strict=True`` would also fail on the keys the level needs)."""

    def verify(self, action: int) -> str:
        return self.verify_action(action)

    def verify_action(self, action: int) -> str:
        was_carrying = self.preCarrying
        status = super().verify_action(action)
        if (
            status == "continue"
            and action == self.env.actions.pickup
            and was_carrying is None
            and isinstance(self.env.carrying, Ball)
        ):
            return "failure"
        return status


class BabyAILevel(RoomGridLevel):
    """Shared layout, signpost, ``info`` entries and expert hooks of the four levels.

    Subclasses set the class constants and implement :meth:`_populate` (doors, objects and
    ``self.instrs``) and :meth:`_expert_subgoal`. Observations are minigrid's Dict (``image``,
    ``direction``, ``mission``); wrap with :class:`FlatBabyAIObservation` for a flat vector.

    Args:
        max_steps: episode length limit (default: the level's ``MAX_STEPS``); also the ``T``
            of the reward ``1 - 0.9 * t / T``.
        **kwargs: passed to minigrid's ``MiniGridEnv`` (e.g. ``render_mode="rgb_array"``).

    Attributes (set at reset): ``room_a`` / ``room_b`` (column of the signpost room / the
    ball room), ``signpost_pos`` ((x, y) grid cell), ``target_color``, ``target_ball``,
    ``door_a`` / ``door_b`` (the doors between M and A / B), ``signpost_seen`` (the signpost
    was in view at some step of this episode so far).

    :meth:`expert_action` is the action of a privileged expert (:class:`BabyAIExpert`), the
    π* over whose trajectories the paper defines TAIE (Table 2).
    """

    LEVEL: ClassVar[int]
    ROOM_SIZE: ClassVar[int]
    MAX_STEPS: ClassVar[int]
    MISSION: ClassVar[str]
    NUM_DISTRACTORS: ClassVar[int] = 0
    DISTRACTOR_KINDS: ClassVar[tuple[str, ...]] = ("key", "box")
    BALL_INSTR: ClassVar[type[GoToInstr | PickupInstr]]

    def __init__(self, max_steps: int | None = None, **kwargs: Any) -> None:
        if max_steps is None:
            max_steps = self.MAX_STEPS
        if not isinstance(max_steps, Integral) or isinstance(max_steps, bool) or max_steps < 1:
            raise ThciError(f"max_steps must be a positive integer, got {max_steps!r}")
        super().__init__(
            room_size=self.ROOM_SIZE, num_rows=1, num_cols=3, max_steps=int(max_steps), **kwargs
        )
        self.action_space = spaces.Discrete(len(ACTION_NAMES))
        self.signpost_seen = False
        # The grid's cell codes, cached for gen_obs (see there); None: rebuild from the grid.
        self._grid_codes: tuple[np.ndarray, np.ndarray] | None = None
        self._changed_cell: tuple[int, int] | None = None
        self._expert: BabyAIExpert | None = None

    # ------------------------------------------------------------------ layout generation

    def _gen_grid(self, width: int, height: int) -> None:
        # RoomGridLevel._gen_grid does the same loop but print()s every rejected layout.
        for _ in range(_MAX_GENERATION_TRIES):
            try:
                RoomGrid._gen_grid(self, width, height)
                self.gen_mission()
                self.validate_instrs(self.instrs)
            except (RejectSampling, RecursionError):
                continue  # resample silently
            break
        else:
            raise RuntimeError(f"{type(self).__name__}: no valid layout in {_MAX_GENERATION_TRIES}")
        # The verifier's surface form would name the target colour; keep the mission constant.
        self.surface = self.mission = self.MISSION

    def gen_mission(self) -> None:
        """Agent in M, signpost in A, then the level's doors and objects (``_populate``)."""
        self.place_agent(_MIDDLE_ROOM, 0)
        self.room_a = self._rand_elem((_LEFT_ROOM, _RIGHT_ROOM))
        self.room_b = 2 - self.room_a
        self.target_color = self._rand_elem(_SIGNPOST_COLORS)
        self._add_signpost()
        self._add_doors()
        self._add_balls_at_entry()  # before the other objects, which must not take their cells
        self._add_objects()
        self.check_objs_reachable()
        self.agent_dir = 2 if self.room_a == _LEFT_ROOM else 0  # facing A: the cue comes first

    def _add_doors(self) -> None:
        """Set ``door_a`` and ``door_b`` (B's in the middle of its wall: ``_add_side_door``)."""
        raise NotImplementedError

    def _add_objects(self) -> None:
        """Keys, boxes and distractors (after the balls, so never on their cells)."""

    def _add_signpost(self) -> None:
        """Paint one cell of room A's outer walls (not corners, not the wall shared with M)."""
        room = self.get_room(self.room_a, 0)
        (left, top), size = room.top, self.room_size
        right, bottom = left + size - 1, top + size - 1
        outer_x = left if self.room_a == _LEFT_ROOM else right
        # (cell, heading from which an agent inside A faces that wall)
        cells = [((x, top), 3) for x in range(left + 1, right)]
        cells += [((x, bottom), 1) for x in range(left + 1, right)]
        cells += [
            ((outer_x, y), 2 if self.room_a == _LEFT_ROOM else 0) for y in range(top + 1, bottom)
        ]
        self.signpost_pos, self.signpost_dir = self._rand_elem(cells)
        self.grid.set(*self.signpost_pos, Wall(self.target_color))

    def place_in_room(self, i: int, j: int, obj: WorldObj) -> tuple[WorldObj, tuple[int, int]]:
        """minigrid's ``place_in_room``, but never in a doorway's line (``_in_doorway_line``)."""
        room = self.get_room(i, j)
        pos = self.place_obj(obj, room.top, room.size, reject_fn=_blocks, max_tries=1000)
        room.objs.append(obj)
        return obj, pos

    def _add_side_door(self, side: int, color: str, locked: bool, middle: bool = False) -> Door:
        """The door between M and side room `side` (`middle`: in the middle of the wall,
        instead of minigrid's random place along it)."""
        # Added from the side room so that RoomGrid marks that room (not M) as locked.
        door_idx = 0 if side == _LEFT_ROOM else 2
        if middle:
            room = self.get_room(side, 0)
            x = room.door_pos[door_idx][0]
            room.door_pos[door_idx] = (x, room.top[1] + self.room_size // 2)
        door, _ = self.add_door(side, 0, door_idx=door_idx, color=color, locked=locked)
        return door

    def _add_grey_doors(self, b_locked: bool) -> None:
        """Levels 1-3: A's door grey and open (the signpost is in view through it), B's grey
        in the middle of its wall, locked or only closed."""
        self.door_a = self._add_side_door(self.room_a, "grey", locked=False)
        self.door_b = self._add_side_door(self.room_b, "grey", locked=b_locked, middle=True)
        self.door_a.is_open = True

    def _decoy_color(self) -> str:
        """Same palette as the target (no grey): no ball colour may hint at being the decoy."""
        return self._rand_elem([c for c in _SIGNPOST_COLORS if c != self.target_color])

    def _add_balls_at_entry(self) -> None:
        """Target and decoy on the two cells beside the first cell inside B's door."""
        door_x, door_y = self.door_b.cur_pos
        entry_x = door_x + (1 if self.room_b == _RIGHT_ROOM else -1)
        self.target_ball, self.decoy_ball = Ball(self.target_color), Ball(self._decoy_color())
        north_is_target = self._rand_bool()
        north, south = (
            (self.target_ball, self.decoy_ball)
            if north_is_target
            else (self.decoy_ball, self.target_ball)
        )
        self.put_obj(north, entry_x, door_y - 1)
        self.put_obj(south, entry_x, door_y + 1)
        self.get_room(self.room_b, 0).objs.extend((north, south))
        self.instrs = self.BALL_INSTR(ObjDesc("ball", self.target_color))

    def _add_distractors(self, door_colors: set[str]) -> None:
        """``NUM_DISTRACTORS`` keys / boxes in random rooms; no key fits a locked door."""
        for _ in range(self.NUM_DISTRACTORS):
            kind = self._rand_elem(self.DISTRACTOR_KINDS)
            colors = (
                COLOR_NAMES if kind == "box" else [c for c in COLOR_NAMES if c not in door_colors]
            )
            self.add_object(self._rand_int(0, 3), 0, kind, self._rand_elem(colors))

    # ------------------------------------------------------------------ gymnasium API

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """New random layout; ``info`` as in the module docstring."""
        self._grid_codes = None  # a new layout
        obs, _ = super().reset(seed=seed, options=options)
        self.signpost_seen = False
        self._expert = None  # its cached plan belongs to the previous layout
        return obs, self._info(obs, success=False)

    def expert_action(self) -> int:
        """The scripted expert's next action in the current state (call once per step).

        Any environment whose unwrapped class defines ``expert_action() -> int`` gets its TAIE
        measured over the expert's trajectories, as the paper defines it (``thci taie``).
        """
        if self._expert is None:
            self._expert = BabyAIExpert(self)
        return self._expert.act()

    def step(self, action: int | np.integer) -> tuple[dict[str, Any], float, bool, bool, dict]:
        """minigrid's step for one of the six actions, with the ``info`` entries added."""
        if not self.action_space.contains(action):
            raise ValueError(
                f"invalid action {action!r}: expected an integer in [0, {len(ACTION_NAMES)}) "
                f"({', '.join(f'{i} = {name}' for i, name in enumerate(ACTION_NAMES))})"
            )
        if action in _GRID_ACTIONS:
            # These change at most the cell in front (a key taken, a box opened, a door
            # unlocked), and the agent does not move: gen_obs re-encodes that cell.
            self._changed_cell = self.front_pos
        obs, reward, terminated, truncated, _ = super().step(int(action))
        # The verifier pays 1 - 0.9 t/T >= 0.1 on success and 0 on failure.
        success = bool(terminated and reward > 0)
        return obs, float(reward), terminated, truncated, self._info(obs, success)

    def gen_obs(self) -> dict[str, Any]:
        """minigrid's observation (the same arrays, bit for bit: a test compares them), cut from
        a cached array of the whole grid's cell codes instead of sliced, rotated and masked
        copies of the grid: minigrid's own took 8.6 s of the 9.7 s of environment steps in a
        cProfile of a BabyAI-L1 training (32k steps); encoding the 49 cells in view at every
        step was still 54% of a step."""
        size = self.agent_view_size
        top_x, top_y, _, _ = self.get_view_exts()
        codes, see = self._cell_codes()
        # The cached arrays are padded by `size` cells of wall on every side.
        x, y = top_x + size, top_y + size
        # minigrid rotates the slice left agent_dir + 1 times; on (x, y) arrays that is rot90(-1).
        turns = -(self.agent_dir + 1)
        image = np.rot90(codes[x : x + size, y : y + size], turns)
        if self.see_through_walls:
            visible = np.ones((size, size), bool)
        else:
            visible = _visible(np.rot90(see[x : x + size, y : y + size], turns).tolist())
        image = image * visible[..., None].astype(np.uint8)
        # The agent sees what it carries in its own cell (minigrid's convention).
        image[size // 2, size - 1] = (
            _EMPTY_CODE if self.carrying is None else self.carrying.encode()
        )
        return {"image": image, "direction": self.agent_dir, "mission": self.mission}

    def _cell_codes(self) -> tuple[np.ndarray, np.ndarray]:
        """(W + 2s, H + 2s, 3) uint8 codes of every cell of the grid and (W + 2s, H + 2s) bool
        "can be seen behind", indexed [x + s, y + s] with s the view size, padded with walls
        (what minigrid shows outside the grid). Built once per layout; afterwards only the cell
        a pickup, drop or toggle acted on is re-encoded (:meth:`step`)."""
        pad = self.agent_view_size
        if self._grid_codes is None:  # a new layout (reset)
            width, height = self.grid.width, self.grid.height
            codes = np.empty((width + 2 * pad, height + 2 * pad, 3), np.uint8)
            codes[:] = _WALL.encode()
            see = np.zeros(codes.shape[:2], bool)  # a wall cannot be seen behind
            for index, cell in enumerate(self.grid.grid):
                x, y = index % width + pad, index // width + pad
                codes[x, y] = _EMPTY_CODE if cell is None else cell.encode()
                see[x, y] = cell is None or cell.see_behind()
            self._grid_codes = (codes, see)
            self._changed_cell = None
        codes, see = self._grid_codes
        if self._changed_cell is not None:
            x, y = self._changed_cell
            cell = self.grid.get(x, y)
            codes[x + pad, y + pad] = _EMPTY_CODE if cell is None else cell.encode()
            see[x + pad, y + pad] = cell is None or cell.see_behind()
            self._changed_cell = None
        return codes, see

    def sees_signpost(self, image: np.ndarray) -> bool:
        """True iff the signpost is drawn in ``image``, this step's egocentric observation."""
        coords = self.relative_coords(*self.signpost_pos)
        if coords is None:
            return False
        obj, color, _ = image[coords[0], coords[1]]
        return obj == OBJECT_TO_IDX["wall"] and color == COLOR_TO_IDX[self.target_color]

    def _info(self, obs: dict[str, Any], success: bool) -> dict[str, Any]:
        causal = bool(self.sees_signpost(obs["image"]))
        self.signpost_seen = self.signpost_seen or causal
        x, y = self.agent_pos
        return {"causal": causal, "success": success, "agent_pos": np.array([y, x], np.int64)}

    # ------------------------------------------------------------------ expert hooks

    def _expert_subgoal(self) -> _Subgoal:
        """What the expert does next (called only after the signpost has been seen)."""
        raise NotImplementedError

    def _look_at_signpost(self) -> _Subgoal:
        if self.door_a.is_locked:  # level 4: key a and door a come first anyway
            return self._expert_subgoal()
        if not self.door_a.is_open:
            return _face(self, self.door_a, TOGGLE)
        # Anywhere inside A facing the painted wall: A's interior is at most 4 cells wide and
        # deep, so the wall is inside the 7x7 view, and keys, balls and boxes never occlude.
        room = self.get_room(self.room_a, 0)

        def looking(x: int, y: int, d: int) -> bool:
            inside = room.top[0] < x < room.top[0] + self.room_size - 1
            return inside and d == self.signpost_dir

        return _Subgoal(looking, None)


def _visible(see: list[list[bool]]) -> np.ndarray:
    """minigrid's ``Grid.process_vis`` on a rotated view: which cells the agent (bottom
    centre) sees, light spreading row by row away from it and stopped by cells that cannot be
    seen behind (`see`, [x][y]); (size, size) bool."""
    size = len(see)
    mask = [[False] * size for _ in range(size)]
    mask[size // 2][size - 1] = True
    for j in reversed(range(size)):
        for i in range(size - 1):
            if mask[i][j] and see[i][j]:
                mask[i + 1][j] = True
                if j > 0:
                    mask[i + 1][j - 1] = mask[i][j - 1] = True
        for i in reversed(range(1, size)):
            if mask[i][j] and see[i][j]:
                mask[i - 1][j] = True
                if j > 0:
                    mask[i - 1][j - 1] = mask[i][j - 1] = True
    return np.array(mask)


def _in_doorway_line(level: BabyAILevel, pos: tuple[int, int]) -> bool:
    """True for the two cells on each side of a doorway, in line with it.

    Nothing is placed (or dropped by the expert) there: an object right in front of a door
    would block it, and a ball two cells in would be faced by whoever walks through the door,
    which in levels 1-3 fails the episode when it is not the target. (All doorways are in
    vertical walls: the rooms form one row.)
    """
    doorways = (p for room in level.room_grid[0] for p in room.door_pos if p is not None)
    return any(pos[1] == dy and 1 <= abs(pos[0] - dx) <= 2 for dx, dy in doorways)


def _blocks(env: BabyAILevel, pos: tuple[int, int]) -> bool:
    """Placement filter: next to the agent (minigrid's rule) or in a doorway's line."""
    return reject_next_to(env, pos) or _in_doorway_line(env, pos)


class GoToBallLevel(BabyAILevel):
    """Level 1, go-to-ball: look into A, go back across M to B, choose a ball at B's door.

    Rooms 5x5 (3x3 inside). Door M-A is open, so the signpost is usually in view from the first
    step (in 89% of layouts; otherwise a step or a turn brings it in). Door M-B is closed, not
    locked (``toggle`` opens it). One step into B, a single turn faces one of the balls.
    Success: face the target ball (``GoToInstr``). Failure (reward 0): face the decoy. No
    distractors. Both doors are grey: no key must match them here, and random door colours
    spread the signpost over 3.6 times as many distinct views, each rarer, which is what CI has
    to find (on 600 known-answer episodes, 149 signpost codes of 557 cell-set codes against 41
    of 118). Scripted expert: 9 steps on average (at most 21 over 1500 seeds); limit 80 steps.

    ``info["causal"]``: the painted signpost cell of A's outer wall is drawn in the current
    7x7 observation (seen from M through the open door, or from inside A).
    """

    LEVEL = 1
    ROOM_SIZE = 5
    MAX_STEPS = 80
    MISSION = "go to the ball of the signpost's colour"
    BALL_INSTR = _GoToBallInstr

    def _add_doors(self) -> None:
        self._add_grey_doors(b_locked=False)

    def _expert_subgoal(self) -> _Subgoal:
        if not self.door_b.is_open:
            return _face(self, self.door_b, TOGGLE)
        return _face(self, self.target_ball, None)


class KeyToDoorLevel(BabyAILevel):
    """Level 2, key-to-door: as level 1, but B's door is locked and its key lies in M.

    Rooms 5x5. Door M-A open, as in level 1; door M-B locked, its key in M. Door B and its key
    are grey (no colour to match by sight, no extra variety of views; a carried key shows in
    every view). One distractor in a random room: a key of a colour other than grey (it fits no
    door) or a box. Success: face the target ball. Failure: face the decoy.
    Scripted expert: 12.4 steps on average (at most 26 over 1500 seeds); limit 120 steps.

    ``info["causal"]``: the signpost is drawn in the current observation (as in level 1).
    The key is needed too, but it stays visible while carried, so nothing about it has to be
    remembered.
    """

    LEVEL = 2
    ROOM_SIZE = 5
    MAX_STEPS = 120
    MISSION = "unlock the door and go to the ball of the signpost's colour"
    NUM_DISTRACTORS = 1
    BALL_INSTR = _GoToBallInstr

    def _add_doors(self) -> None:
        self._add_grey_doors(b_locked=True)

    def _add_objects(self) -> None:
        self.key, _ = self.add_object(_MIDDLE_ROOM, 0, "key", "grey")
        self._add_distractors({"grey"})

    def _fetch_key(self) -> _Subgoal:
        return _face(self, self.key, PICKUP)

    def _expert_subgoal(self) -> _Subgoal:
        if self.door_b.is_locked:
            if self.carrying is not self.key:
                return self._fetch_key() if self.carrying is None else _drop(self)
            return _face(self, self.door_b, TOGGLE)
        return _face(self, self.target_ball, None)


class KeyToBoxLevel(KeyToDoorLevel):
    """Level 3, key-to-box: as level 2, but bigger rooms and B's key hidden in a box in A
    (BabyAI's KeyInBox).

    Rooms 6x6 (4x4 inside). In A, a grey box holds B's grey key: ``toggle`` opens the box,
    which leaves the key in its place. Two distractor keys (colours other than grey: they fit
    no door) in random rooms. Success: face the target ball. Failure: face the decoy.
    Scripted expert: 27.1 steps on average (at most 42); limit 160 steps.

    ``info["causal"]``: the signpost is drawn in the current observation.
    """

    LEVEL = 3
    ROOM_SIZE = 6
    MAX_STEPS = 160
    MISSION = "open the box, unlock the door and go to the ball of the signpost's colour"
    NUM_DISTRACTORS = 2
    # Only keys: an empty distractor box would look like the one with the key.
    DISTRACTOR_KINDS = ("key",)

    def _add_objects(self) -> None:
        self.key = Key("grey")
        self.box = Box("grey", contains=self.key)
        self.place_in_room(self.room_a, 0, self.box)
        self._add_distractors({"grey"})

    def _fetch_key(self) -> _Subgoal:
        if _locate(self, self.box) is not None:
            return _face(self, self.box, TOGGLE)
        return _face(self, self.key, PICKUP)


class UnlockToUnlockLevel(BabyAILevel):
    """Level 4, unlock-to-unlock: minigrid's BabyAI-UnlockToUnlock-v0 plus signpost and decoy.

    Rooms 6x6, as in UnlockToUnlock. Door M-A locked (colour a), its key in M; door M-B
    locked (colour b), its key in A (with the signpost); colours a and b at random, as in
    UnlockToUnlock. Three distractors (keys of neither door colour, or boxes) in random rooms.
    The agent faces A's locked door at reset, so here the signpost is seen only once A is
    unlocked. It must drop a key to take another and have empty hands for the ball: take key a,
    unlock A, swap it for key b, go back through M, unlock B, drop key b, pick up the ball.
    Success: pick up the target ball (``PickupInstr``). Failure: pick up the decoy (facing it is
    harmless here). Scripted expert: 39.5 steps on average (at most 63); limit 250
    steps. Compared with UnlockToUnlock (same rooms, same key chain, limit 1080 steps) it adds
    the detour to the signpost, the choice between two balls, three distractors and a tighter
    limit.

    ``info["causal"]``: the signpost is drawn in the current observation.
    """

    LEVEL = 4
    ROOM_SIZE = 6
    MAX_STEPS = 250
    MISSION = "unlock the doors and pick up the ball of the signpost's colour"
    NUM_DISTRACTORS = 3
    BALL_INSTR = _PickupBallInstr

    def _add_doors(self) -> None:
        self.color_a, self.color_b = self._rand_subset(COLOR_NAMES, 2)
        self.door_a = self._add_side_door(self.room_a, self.color_a, locked=True)
        self.door_b = self._add_side_door(self.room_b, self.color_b, locked=True, middle=True)

    def _add_objects(self) -> None:
        self.key_a, _ = self.add_object(_MIDDLE_ROOM, 0, "key", self.color_a)
        self.key_b, _ = self.add_object(self.room_a, 0, "key", self.color_b)
        self._add_distractors({self.color_a, self.color_b})

    def _expert_subgoal(self) -> _Subgoal:
        for door, key in ((self.door_a, self.key_a), (self.door_b, self.key_b)):
            if door.is_locked:
                if self.carrying is key:
                    return _face(self, door, TOGGLE)
                return _face(self, key, PICKUP) if self.carrying is None else _drop(self)
        return _face(self, self.target_ball, PICKUP) if self.carrying is None else _drop(self)


BABYAI_LEVELS: dict[int, type[BabyAILevel]] = {
    cls.LEVEL: cls for cls in (GoToBallLevel, KeyToDoorLevel, KeyToBoxLevel, UnlockToUnlockLevel)
}
"""Level number -> class."""


class FlatBabyAIObservation(gym.ObservationWrapper):
    """minigrid's Dict observation -> (7*7*3 + 4,) uint8: flattened image, one-hot direction.

    The image keeps minigrid's (x, y, channel) order; each cell holds the object, colour and
    state indices (upper bounds in ``observation_space.high``). The mission is dropped (it is
    constant per level).
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        view = env.unwrapped.agent_view_size
        high = np.concatenate([np.tile(_CELL_HIGH, view * view), np.ones(4, np.int64)])
        self.observation_space = spaces.Box(0, high.astype(np.uint8), dtype=np.uint8)

    def observation(self, observation: dict[str, Any]) -> np.ndarray:
        flat = np.zeros(self.observation_space.shape, np.uint8)
        flat[:-4] = observation["image"].reshape(-1)
        flat[len(flat) - 4 + int(observation["direction"])] = 1
        return flat


def make_babyai_env(level: int = 1, **kwargs: Any) -> gym.Env:
    """The registered ``thci/BabyAI-L{level}-v0``: the level wrapped in FlatBabyAIObservation.

    Args:
        level: 1-4.
        **kwargs: passed to the level class (``max_steps``, ``render_mode``, ...).
    """
    if level not in BABYAI_LEVELS:
        valid = ", ".join(str(k) for k in BABYAI_LEVELS)
        raise ThciError(f"unknown BabyAI level {level!r}; valid levels are {valid}")
    return FlatBabyAIObservation(BABYAI_LEVELS[level](**kwargs))


# ---------------------------------------------------------------------- scripted expert


def _locate(level: BabyAILevel, obj: WorldObj) -> tuple[int, int] | None:
    """Grid cell of ``obj`` (by identity), or None when it is carried or gone."""
    for index, cell in enumerate(level.grid.grid):
        if cell is obj:
            return index % level.grid.width, index // level.grid.width
    return None


def _face(level: BabyAILevel, obj: WorldObj, action: int | None) -> _Subgoal:
    """Stand next to ``obj`` facing it."""
    cell = _locate(level, obj)
    if cell is None:
        raise RuntimeError(f"expert: {obj.color} {obj.type} is not on the grid")

    def facing(x: int, y: int, d: int) -> bool:
        return (x + _DIR_VEC[d][0], y + _DIR_VEC[d][1]) == cell

    return _Subgoal(facing, action)


def _drop(level: BabyAILevel) -> _Subgoal:
    """Face a cell where the carried object can be dropped without cutting any area off."""
    cells = _safe_drop_cells(level)

    def facing_free(x: int, y: int, d: int) -> bool:
        return (x + _DIR_VEC[d][0], y + _DIR_VEC[d][1]) in cells

    return _Subgoal(facing_free, DROP)


def _reachable(level: BabyAILevel, blocked: tuple[int, int] | None = None) -> int:
    """Number of cells the agent can walk to or reach out to (objects next to such cells),
    going through doors in any state, with the cell ``blocked`` taken as occupied."""
    start = tuple(level.agent_pos)
    seen, stack = {start}, [start]
    while stack:
        x, y = stack.pop()
        for dx, dy in _DIR_VEC:
            nxt = (x + dx, y + dy)
            cell = level.grid.get(*nxt)
            if nxt in seen or nxt == blocked or (cell is not None and cell.type == "wall"):
                continue
            seen.add(nxt)
            if cell is None or cell.type == "door":  # objects can be reached, not crossed
                stack.append(nxt)
    return len(seen)


def _safe_drop_cells(level: BabyAILevel) -> set[tuple[int, int]]:
    """Empty cells where a drop takes away that cell only, not access to anything else.

    Cells of the agent's own room are tried first (a flood fill each); the whole grid only
    when none of them will do.
    """
    total = _reachable(level)
    agent = tuple(int(v) for v in level.agent_pos)
    room = level.room_from_pos(*agent)
    columns = range(room.top[0] + 1, room.top[0] + level.room_size - 1)
    for xs in (columns, range(level.grid.width)):
        cells = {
            (x, y)
            for x in xs
            for y in range(level.grid.height)
            if level.grid.get(x, y) is None
            and (x, y) != agent
            and not _in_doorway_line(level, (x, y))
            and _reachable(level, (x, y)) == total - 1
        }
        if cells:
            return cells
    raise RuntimeError("expert: nowhere to drop the carried object")


class BabyAIExpert:
    """Privileged scripted expert for the four levels (knows the whole layout).

    It first brings the signpost into view (it opens A's door, which often shows the signpost
    already, else it walks into A and faces the painted wall; in level 4 it takes key a and
    unlocks A first), then works through the level's sub-goals, each planned as a shortest
    sequence of left / right / forward over (cell, heading) (in levels 1-3 never facing the
    decoy), followed by the sub-goal's toggle / pickup / drop. It drops keys only where no
    other cell or object gets cut off. Plans are cached while the agent follows them and
    redone when the state differs from the plan's, so call :meth:`act` once per step.

    Args:
        env: a BabyAI level, wrapped or not.
    """

    def __init__(self, env: gym.Env) -> None:
        level = env.unwrapped
        if not isinstance(level, BabyAILevel):
            raise ThciError(f"BabyAIExpert needs a thci BabyAI level, got {type(level).__name__}")
        self.level = level
        self._plan: deque[tuple[tuple[int, int, int, int], int]] = deque()

    def act(self) -> int:
        """The next action for the level's current state."""
        level = self.level
        now = (*(int(v) for v in level.agent_pos), int(level.agent_dir), int(level.step_count))
        if not self._plan or self._plan[0][0] != now:
            self._plan = deque(self._make_plan(now))
        return self._plan.popleft()[1]

    def _make_plan(self, now: tuple[int, int, int, int]) -> list[tuple[tuple[int, ...], int]]:
        level = self.level
        subgoal = level._expert_subgoal() if level.signpost_seen else level._look_at_signpost()
        states, actions = _shortest_path(level, now[:3], subgoal.goal)
        if subgoal.action is not None:
            actions.append(subgoal.action)
        elif not actions:
            raise RuntimeError("expert: the sub-goal is already reached but the episode goes on")
        # The state before each action; zip drops the last state when there is no final action.
        return [
            ((*state, now[3] + i), a)
            for i, (state, a) in enumerate(zip(states, actions, strict=False))
        ]


def _shortest_path(
    level: BabyAILevel, start: _State, goal: Callable[[int, int, int], bool]
) -> tuple[list[_State], list[int]]:
    """Breadth-first search over (x, y, heading) for a state accepted by ``goal``.

    Returns the states of the path (``start`` first, the accepted state last) and the moves
    (left / right / forward) between them. In levels 1-3, states facing a non-target ball are
    never entered (facing one fails the episode).
    """
    parents: dict[_State, tuple[_State, int] | None] = {start: None}
    queue = deque([start])
    end = start if goal(*start) else None
    while queue and end is None:
        state = queue.popleft()
        x, y, d = state
        dx, dy = _DIR_VEC[d]
        front = level.grid.get(x + dx, y + dy)
        moves = [(LEFT, (x, y, (d - 1) % 4)), (RIGHT, (x, y, (d + 1) % 4))]
        if front is None or front.can_overlap():
            moves.append((FORWARD, (x + dx, y + dy, d)))
        for action, nxt in moves:
            if nxt in parents or _faces_wrong_ball(level, nxt):
                continue
            parents[nxt] = (state, action)
            if goal(*nxt):
                end = nxt
                break
            queue.append(nxt)
    if end is None:
        raise RuntimeError("expert: no path to the sub-goal")
    states, actions = [end], []
    while (link := parents[states[-1]]) is not None:
        states.append(link[0])
        actions.append(link[1])
    return states[::-1], actions[::-1]


def _faces_wrong_ball(level: BabyAILevel, state: _State) -> bool:
    """In levels 1-3 (go-to), facing a ball other than the target fails the episode."""
    if not isinstance(level.instrs, _GoToBallInstr):
        return False
    x, y, d = state
    cell = level.grid.get(x + _DIR_VEC[d][0], y + _DIR_VEC[d][1])
    return isinstance(cell, Ball) and cell is not level.target_ball

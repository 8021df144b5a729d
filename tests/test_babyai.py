"""Tests for the paper's BabyAI levels 1-4: layout rules, interface, outcomes, expert, labels."""

import contextlib
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from minigrid.core.constants import DIR_TO_VEC
from minigrid.core.world_object import Ball, Box, Key
from minigrid.envs.babyai.core.roomgrid_level import RejectSampling

from thci.envs import BABYAI_IDS
from thci.envs.babyai import (
    BABYAI_LEVELS,
    BabyAIExpert,
    BabyAILevel,
    GoToBallLevel,
    UnlockToUnlockLevel,
    make_babyai_env,
)
from thci.envs.factory import make_vector_env

LEVELS = (1, 2, 3, 4)
LEFT, RIGHT, FORWARD, PICKUP, DROP, TOGGLE = range(6)
VIEW = 7
EXPERT_SEEDS = range(200)


def _room_of(level: BabyAILevel, x: int) -> int:
    """Column of the room whose interior holds grid column x."""
    return x // (level.room_size - 1)


def _objects(level: BabyAILevel) -> list[tuple[int, int, object]]:
    return [
        (i % level.grid.width, i // level.grid.width, cell)
        for i, cell in enumerate(level.grid.grid)
        if cell is not None and cell.type not in ("wall", "door")
    ]


def _direction(src: tuple[int, int], dst: tuple[int, int]) -> int:
    """Heading that makes an agent at src face the neighbouring cell dst."""
    step = (dst[0] - src[0], dst[1] - src[1])
    return next(d for d, vec in enumerate(DIR_TO_VEC) if tuple(vec) == step)


def _free_neighbour(level: BabyAILevel, cell: tuple[int, int]) -> tuple[int, int]:
    for vec in DIR_TO_VEC:
        nxt = (cell[0] + int(vec[0]), cell[1] + int(vec[1]))
        if level.grid.get(*nxt) is None:
            return nxt
    raise AssertionError(f"no free cell next to {cell}")


def _turn_to_face(level: BabyAILevel, cell: tuple[int, int], standing: tuple[int, int]) -> None:
    """Put the agent on `standing`, one left turn away from facing `cell`."""
    level.agent_pos = np.array(standing)
    level.agent_dir = (_direction(standing, cell) + 1) % 4


# ----------------------------------------------------------------------------- registration


def test_registered_ids_use_the_level_limits() -> None:
    assert tuple(f"thci/BabyAI-L{k}-v0" for k in LEVELS) == BABYAI_IDS
    for level, env_id in zip(LEVELS, BABYAI_IDS, strict=True):
        spec = gym.spec(env_id)
        cls = BABYAI_LEVELS[level]
        assert spec.max_episode_steps == cls.MAX_STEPS
        env = gym.make(env_id)
        assert type(env.unwrapped) is cls
        assert env.unwrapped.max_steps == cls.MAX_STEPS
        assert env.observation_space.shape == (VIEW * VIEW * 3 + 4,)
        assert env.observation_space.dtype == np.uint8
        assert env.action_space == gym.spaces.Discrete(6)
    # The difficulty (and the limit) rises with the level.
    assert [BABYAI_LEVELS[k].MAX_STEPS for k in LEVELS] == sorted(
        {BABYAI_LEVELS[k].MAX_STEPS for k in LEVELS}
    )


def test_importing_thci_envs_does_not_import_minigrid() -> None:
    code = "import sys, thci.envs; print('minigrid' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_unknown_level_and_bad_max_steps_are_rejected() -> None:
    from thci.errors import ThciError

    with pytest.raises(ThciError, match="unknown BabyAI level"):
        make_babyai_env(5)
    with pytest.raises(ThciError, match="max_steps"):
        GoToBallLevel(max_steps=0)
    assert GoToBallLevel(max_steps=7).max_steps == 7


@pytest.mark.parametrize("level", LEVELS)
def test_gymnasium_env_checker(level: int) -> None:
    with warnings.catch_warnings():
        # check_env cannot try other render modes on an env built without gym.make.
        warnings.filterwarnings("ignore", message=".*not having a spec.*")
        check_env(BABYAI_LEVELS[level](render_mode="rgb_array"))


def test_vector_env_factory_accepts_the_ids() -> None:
    envs = make_vector_env(BABYAI_IDS[3], 3)
    obs, infos = envs.reset(seed=0)
    assert obs.shape == (3, VIEW * VIEW * 3 + 4) and obs.dtype == np.uint8
    obs, _, _, _, infos = envs.step(np.array([LEFT, RIGHT, FORWARD]))
    assert obs.shape == (3, VIEW * VIEW * 3 + 4)
    assert infos["causal"].dtype == bool and infos["agent_pos"].shape == (3, 2)
    envs.close()


# ----------------------------------------------------------------------------- layouts


@pytest.mark.parametrize("level", LEVELS)
def test_layout_rules(level: int) -> None:
    env = BABYAI_LEVELS[level]()
    sides = set()
    for seed in range(60):
        env.reset(seed=seed)
        lv = env.unwrapped
        size = lv.room_size
        assert (lv.grid.width, lv.grid.height) == (3 * (size - 1) + 1, size)
        assert _room_of(lv, lv.agent_pos[0]) == 1  # starts in the middle room
        assert {lv.room_a, lv.room_b} == {0, 2}
        sides.add(lv.room_a)
        # Signpost: the only coloured wall, on A's outer walls (not the wall shared with M).
        painted = [
            (i % lv.grid.width, i // lv.grid.width, c)
            for i, c in enumerate(lv.grid.grid)
            if c is not None and c.type == "wall" and c.color != "grey"
        ]
        assert len(painted) == 1
        x, y, wall = painted[0]
        assert (x, y) == lv.signpost_pos and wall.color == lv.target_color
        shared_x = size - 1 if lv.room_a == 0 else 2 * (size - 1)
        assert x != shared_x and _room_of(lv, min(x, lv.grid.width - 2)) == lv.room_a
        # Exactly two balls, both in B, target in the signpost colour, decoy another colour.
        balls = [(bx, c) for bx, _, c in _objects(lv) if isinstance(c, Ball)]
        assert len(balls) == 2
        assert all(_room_of(lv, bx) == lv.room_b for bx, _ in balls)
        assert sorted(c.color == lv.target_color for _, c in balls) == [False, True]
        assert "grey" not in {c.color for _, c in balls}
        # Doors: A's is locked only in level 4 and open in the others; B's is closed, locked
        # from level 2 on, in the middle of B's wall; the balls flank the first cell inside it.
        assert lv.door_a.is_locked == (level == 4) and lv.door_a.is_open == (level != 4)
        assert lv.door_b.is_locked == (level >= 2) and not lv.door_b.is_open
        dx, dy = lv.door_b.cur_pos
        assert dy == size // 2
        inward = 1 if lv.room_b == 2 else -1
        balls_at = {tuple(lv.target_ball.cur_pos), tuple(lv.decoy_ball.cur_pos)}
        assert balls_at == {(dx + inward, dy - 1), (dx + inward, dy + 1)}
        assert lv.agent_dir == (2 if lv.room_a == 0 else 0)  # facing A: the cue comes first
        keys = [(kx, c) for kx, _, c in _objects(lv) if isinstance(c, Key)]
        where = {id(c): _room_of(lv, kx) for kx, c in keys}
        fits_b = [c for _, c in keys if c.color == lv.door_b.color]
        if level in (1, 2, 3):  # grey doors (and key): no colour to match, no extra variety
            assert lv.door_a.color == lv.door_b.color == "grey"
        if level == 2:  # B's key lies in M, and no other key fits B
            assert fits_b == [lv.key] and where[id(lv.key)] == 1
        if level == 3:  # B's key is inside the only box, in A
            boxes = [(bx, c) for bx, _, c in _objects(lv) if isinstance(c, Box)]
            assert len(boxes) == 1 and boxes[0][1].contains is lv.key
            assert _room_of(lv, boxes[0][0]) == lv.room_a and fits_b == []
        if level == 4:  # key a in M, key b in A, no distractor key fits either door
            assert where[id(lv.key_a)] == 1 and where[id(lv.key_b)] == lv.room_a
            assert lv.key_a.color == lv.door_a.color and lv.key_b.color == lv.door_b.color
            fitting = [c for _, c in keys if c.color in (lv.door_a.color, lv.door_b.color)]
            assert {id(c) for c in fitting} == {id(lv.key_a), id(lv.key_b)}
        non_ball = len(_objects(lv)) - 2
        assert non_ball == {1: 0, 2: 2, 3: 3, 4: 5}[level]
        # Nothing stands in a doorway's line (two cells on each side of every door).
        for door in (lv.door_a, lv.door_b):
            dx, dy = door.cur_pos
            for off in (-2, -1, 1, 2):
                assert lv.grid.get(dx + off, dy) is None
    assert sides == {0, 2}


@pytest.mark.parametrize("level", LEVELS)
def test_choice_is_one_action_from_the_entry(level: int) -> None:
    """From the first cell inside B's door, LEFT faces one ball and RIGHT the other: facing
    decides a go-to level; in level 4 the PICKUP after it does."""
    env = BABYAI_LEVELS[level]()
    for seed in range(40):
        for turn in (LEFT, RIGHT):
            env.reset(seed=seed)
            dx, dy = env.door_b.cur_pos
            inward = 1 if env.room_b == 2 else -1
            env.door_b.is_locked, env.door_b.is_open = False, True
            env.agent_pos, env.agent_dir = np.array((dx + inward, dy)), 0 if inward == 1 else 2
            _, reward, terminated, _, info = env.step(turn)
            faced = env.grid.get(*env.front_pos)
            assert isinstance(faced, Ball)
            if level == 4:
                assert not terminated
                _, reward, terminated, _, info = env.step(PICKUP)
            assert terminated and info["success"] == (faced is env.target_ball)
            assert (reward > 0) == info["success"]


def test_signpost_in_view_at_reset_where_a_is_open() -> None:
    """Levels 1-2 (5x5 rooms, A open, facing A): the signpost is mostly in view at once; in
    level 4 A is locked, so never."""
    seen = {level: 0 for level in (1, 2, 4)}
    for level in seen:
        env = BABYAI_LEVELS[level]()
        for seed in range(100):
            _, info = env.reset(seed=seed)
            seen[level] += info["causal"]
    assert seen[1] >= 80 and seen[2] >= 80 and seen[4] == 0


def test_same_seed_same_layout_and_constant_mission() -> None:
    env = BABYAI_LEVELS[4]()
    first, _ = env.reset(seed=3)
    grid = env.grid.encode().copy()
    again, _ = env.reset(seed=3)
    assert np.array_equal(env.grid.encode(), grid)
    assert np.array_equal(first["image"], again["image"])
    missions, colors = set(), set()
    for seed in range(30):
        obs, _ = env.reset(seed=seed)
        missions.add(obs["mission"])
        colors.add(env.target_color)
    assert len(missions) == 1 and len(colors) > 1
    (mission,) = missions
    assert not any(color in mission for color in colors)  # only the signpost shows the target


# ----------------------------------------------------------------------------- interface


@pytest.mark.parametrize("level", LEVELS)
def test_observation_and_info_invariants(level: int) -> None:
    env = gym.make(BABYAI_IDS[level - 1])
    lv = env.unwrapped
    rng = np.random.default_rng(level)
    obs, info = env.reset(seed=level)
    expert = BabyAIExpert(env)
    labels = []
    for _ in range(400):
        assert env.observation_space.contains(obs)
        image = lv.gen_obs()["image"]
        assert np.array_equal(obs[:-4], image.reshape(-1))
        assert np.array_equal(obs[-4:], np.eye(4, dtype=np.uint8)[lv.agent_dir])
        assert set(info) >= {"causal", "success", "agent_pos"}
        assert type(info["causal"]) is bool and type(info["success"]) is bool
        assert info["agent_pos"].dtype == np.int64
        assert info["agent_pos"].tolist() == [lv.agent_pos[1], lv.agent_pos[0]]  # [row, col]
        # Independent check of the label with minigrid's own visibility test.
        assert info["causal"] == lv.agent_sees(*lv.signpost_pos)
        labels.append(info["causal"])
        # Mostly the expert (so that the signpost gets seen), with random actions mixed in.
        action = int(rng.integers(6))
        if rng.random() < 0.7:
            # A random drop can leave something in the expert's way: then act randomly.
            with contextlib.suppress(RuntimeError):
                action = expert.act()
        obs, reward, terminated, truncated, info = env.step(action)
        assert info["success"] == (reward > 0)
        if info["success"]:
            assert terminated
        if terminated or truncated:
            obs, info = env.reset()
            assert not info["success"]
    assert any(labels) and not all(labels)


def test_invalid_action_is_rejected() -> None:
    env = GoToBallLevel()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="invalid action"):
        env.step(6)  # minigrid's "done" is not in the action set


def test_render_rgb_array() -> None:
    env = BABYAI_LEVELS[3](render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (env.height * 32, env.width * 32, 3) and frame.dtype == np.uint8


# ----------------------------------------------------------------------------- outcomes


@pytest.mark.parametrize("level", (1, 2, 3))
@pytest.mark.parametrize("which", ("target", "decoy"))
def test_facing_a_ball_ends_goto_levels(level: int, which: str) -> None:
    env = BABYAI_LEVELS[level]()
    env.reset(seed=11)
    ball = env.target_ball if which == "target" else env.decoy_ball
    _turn_to_face(env, ball.cur_pos, _free_neighbour(env, ball.cur_pos))
    _, reward, terminated, _, info = env.step(LEFT)
    assert terminated
    if which == "target":
        assert info["success"] and reward == pytest.approx(1 - 0.9 * 1 / env.max_steps)
    else:
        assert not info["success"] and reward == 0.0


def test_level4_decoy_fails_on_pickup_not_on_facing() -> None:
    env = UnlockToUnlockLevel()
    env.reset(seed=5)
    _turn_to_face(env, env.decoy_ball.cur_pos, _free_neighbour(env, env.decoy_ball.cur_pos))
    _, _, terminated, _, _ = env.step(LEFT)
    assert not terminated  # facing is fine in level 4
    _, reward, terminated, _, info = env.step(PICKUP)
    assert terminated and reward == 0.0 and not info["success"]
    assert env.carrying is env.decoy_ball


def test_level4_target_needs_empty_hands() -> None:
    env = UnlockToUnlockLevel()
    env.reset(seed=5)
    target = env.target_ball.cur_pos
    _turn_to_face(env, target, _free_neighbour(env, target))
    env.step(LEFT)
    env.carrying = env.key_b  # holding a key: the ball cannot be taken
    env.grid.set(*env.key_b.cur_pos, None)
    _, reward, terminated, _, _ = env.step(PICKUP)
    assert not terminated and reward == 0.0 and env.carrying is env.key_b
    env.carrying = None  # as if dropped; turn away and back so the verifier sees empty hands
    env.step(RIGHT)
    env.step(LEFT)
    _, reward, terminated, _, info = env.step(PICKUP)
    assert terminated and info["success"] and reward == pytest.approx(1 - 0.9 * 5 / 250)
    assert env.carrying is env.target_ball


# ----------------------------------------------------------------------------- causal labels


@pytest.mark.parametrize("level", LEVELS)
def test_causal_labels_in_hand_checked_situations(level: int) -> None:
    env = BABYAI_LEVELS[level]()
    _, info = env.reset(seed=7)
    if level == 4:
        assert not info["causal"]  # A's door is locked: the signpost cannot be seen from M
    room_a = env.get_room(env.room_a, 0)
    inside = [
        (x, y)
        for x in range(room_a.top[0] + 1, room_a.top[0] + env.room_size - 1)
        for y in range(1, env.room_size - 1)
        if env.grid.get(x, y) is None
    ]
    for cell in inside:
        # Inside A, turning to face the painted wall brings the signpost into view ...
        env.agent_pos, env.agent_dir = np.array(cell), (env.signpost_dir + 1) % 4
        _, _, _, _, info = env.step(LEFT)
        assert info["causal"]
        # ... and turning to face the opposite wall takes it out of view.
        env.agent_dir = (env.signpost_dir + 3) % 4
        _, _, _, _, info = env.step(LEFT)
        assert env.agent_dir == (env.signpost_dir + 2) % 4 and not info["causal"]
    # In B (the ball room) the signpost is never in view, whatever the heading.
    room_b = env.get_room(env.room_b, 0)
    cell = next(
        (x, y)
        for x in range(room_b.top[0] + 1, room_b.top[0] + env.room_size - 1)
        for y in range(1, env.room_size - 1)
        if env.grid.get(x, y) is None
    )
    env.agent_pos = np.array(cell)
    for _ in range(4):
        _, _, terminated, _, info = env.step(RIGHT)
        if terminated:  # turned to face a ball (levels 1-3)
            break
        assert not info["causal"]


# ----------------------------------------------------------------------------- silence


class _RejectingLevel(GoToBallLevel):
    """Rejects its first three layouts, as BabyAI's rejection sampling does."""

    rejections = 0

    def gen_mission(self) -> None:
        if type(self).rejections < 3:
            type(self).rejections += 1
            raise RejectSampling("test rejection")
        super().gen_mission()


def test_rejected_layouts_are_resampled_silently(capfd: pytest.CaptureFixture[str]) -> None:
    env = _RejectingLevel()
    _, info = env.reset(seed=0)
    assert _RejectingLevel.rejections == 3
    assert "agent_pos" in info
    out, err = capfd.readouterr()
    assert out == "" and err == ""


# ----------------------------------------------------------------------------- expert


@pytest.mark.parametrize("level", LEVELS)
def test_expert_solves_every_seed(level: int, capfd: pytest.CaptureFixture[str]) -> None:
    env = gym.make(BABYAI_IDS[level - 1])
    limit = env.unwrapped.max_steps
    lengths, shares = [], []
    for seed in EXPERT_SEEDS:
        _, info = env.reset(seed=seed)
        expert = BabyAIExpert(env)
        causal = [info["causal"]]
        t = 0
        while True:
            t += 1
            _, reward, terminated, truncated, info = env.step(expert.act())
            causal.append(info["causal"])
            if terminated or truncated:
                break
            assert not info["success"] and reward == 0.0
        assert terminated and not truncated, f"seed {seed}"
        assert info["success"] and reward == pytest.approx(1 - 0.9 * t / limit), f"seed {seed}"
        # The expert read the signpost before choosing.
        assert any(causal[:-1]), f"seed {seed}"
        lengths.append(t)
        shares.append(np.mean(causal))
    # Rejected layouts along the way print nothing (minigrid's RoomGridLevel would).
    assert capfd.readouterr().out == ""
    assert np.mean(lengths) < limit / 3
    assert np.mean(shares) < 1 / 3  # the label stays sparse (14-30% of the expert's steps)


@pytest.mark.parametrize("level", LEVELS)
def test_observations_are_minigrids_own_bit_for_bit(level):
    from minigrid.minigrid_env import MiniGridEnv

    env = make_babyai_env(level).unwrapped
    rng = np.random.default_rng(level)
    carried = seen_open_door = 0
    for episode in range(12):
        obs, _ = env.reset(seed=episode)
        assert np.array_equal(obs["image"], MiniGridEnv.gen_obs(env)["image"])
        expert = BabyAIExpert(env)
        done = False
        while not done:
            action = int(rng.choice(6, p=[0.2, 0.2, 0.3, 0.1, 0.05, 0.15]))
            if rng.random() < 0.5:  # the expert's help opens level 4's locked doors
                with contextlib.suppress(RuntimeError):
                    action = expert.act()
            obs, _, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
            assert np.array_equal(obs["image"], MiniGridEnv.gen_obs(env)["image"])
            carried += env.carrying is not None
            seen_open_door += bool(
                np.any((obs["image"][..., 0] == 4) & (obs["image"][..., 2] == 0))
            )
    # The comparison covered what changes a view: open doors, and objects carried (L2-L4).
    assert seen_open_door > 0 and (carried > 0 or level == 1)

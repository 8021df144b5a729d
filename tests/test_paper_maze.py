"""Tests for the paper's Maze levels 1-4: dynamics against the JSON, seeding, vector env."""

import importlib
import json
import warnings
from collections import deque
from importlib import resources

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

import thci.envs
from thci.envs import (
    PAPER_MAZE_IDS,
    PaperMazeEnv,
    PaperMazeVectorEnv,
    load_maze_level,
)
from thci.envs.paper_maze import _advance, episode_uniform
from thci.errors import ThciError

LEVELS = (1, 2, 3, 4)
# action -> (d_row, d_col), written out independently of the implementation.
MOVES = {0: (0, 1), 1: (0, -1), 2: (1, 0), 3: (-1, 0)}
WALL = 4
# Biased toward "north" so that random walks regularly reach the goals within 30 steps.
WALK_PROBS = (0.25, 0.25, 0.1, 0.4)


def _json_levels() -> dict[int, dict]:
    text = resources.files("thci.envs").joinpath("data", "paper_maze.json").read_text()
    return {entry["level"]: entry for entry in json.loads(text)["levels"]}


JSON_LEVELS = _json_levels()


def _seeds_covering_variants(level: int) -> dict[int, int]:
    """variant -> a seed whose first reset draws that variant."""
    env = PaperMazeEnv(level)
    found: dict[int, int] = {}
    for seed in range(200):
        found.setdefault(env.reset(seed=seed)[1]["variant"], seed)
    assert len(found) == len(JSON_LEVELS[level]["variants"])
    return found


def _bfs_actions(grid: np.ndarray, start: tuple[int, int], goal: tuple[int, int], terminal):
    """Shortest action list from start to goal that does not cross another terminal cell."""
    height, width = grid.shape
    parent: dict[tuple[int, int], tuple[tuple[int, int], int] | None] = {start: None}
    queue = deque([start])
    while queue:
        cell = queue.popleft()
        if cell == goal:
            actions = []
            while parent[cell] is not None:
                cell, action = parent[cell]
                actions.append(action)
            return actions[::-1]
        if cell != start and grid[cell] in terminal:
            continue  # the episode would end here
        for action, (dr, dc) in MOVES.items():
            nxt = (cell[0] + dr, cell[1] + dc)
            inside = 0 <= nxt[0] < height and 0 <= nxt[1] < width
            if inside and grid[nxt] != WALL and nxt not in parent:
                parent[nxt] = (cell, action)
                queue.append(nxt)
    return None


def _one_hot(code: int) -> np.ndarray:
    return np.eye(15, dtype=np.float32)[code]


# ----------------------------------------------------------------------------- randomness


def _splitmix64_reference(key: int, counter: int) -> float:
    mask = (1 << 64) - 1
    z = (key + (counter + 1) * 0x9E3779B97F4A7C15) & mask
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & mask
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & mask
    z ^= z >> 31
    return (z >> 11) / 2**53


def test_episode_uniform_matches_splitmix64_and_is_uniform():
    rng = np.random.default_rng(0)
    keys = rng.integers(0, 2**64 - 1, size=50, dtype=np.uint64, endpoint=True)
    counters = rng.integers(0, 1000, size=50).astype(np.uint64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # wrap-around must not warn, not even for 0-d input
        got = episode_uniform(keys, counters)
        scalar = float(episode_uniform(np.uint64(2**64 - 1), np.uint64(7)))
    expected = [_splitmix64_reference(int(k), int(c)) for k, c in zip(keys, counters, strict=True)]
    np.testing.assert_array_equal(got, expected)
    assert scalar == _splitmix64_reference(2**64 - 1, 7)
    # First output of SplitMix64 seeded with 0 (Vigna's reference): 0xE220A8397B1DCDAF.
    assert float(episode_uniform(0, 0)) == (0xE220A8397B1DCDAF >> 11) / 2**53

    draws = episode_uniform(np.uint64(12345), np.arange(100_000, dtype=np.uint64))
    assert draws.dtype == np.float64 and draws.shape == (100_000,)
    assert draws.min() >= 0.0 and draws.max() < 1.0
    assert abs(draws.mean() - 0.5) < 0.01
    assert np.histogram(draws, bins=10, range=(0, 1))[0].min() > 9_500
    assert len(np.unique(draws)) == len(draws)  # different counters give different draws
    np.testing.assert_array_equal(
        draws, episode_uniform(np.uint64(12345), np.arange(100_000, dtype=np.uint64))
    )
    assert not np.array_equal(
        draws[:100], episode_uniform(np.uint64(12346), np.arange(100, dtype=np.uint64))
    )


@pytest.mark.parametrize("level", LEVELS)
def test_variant_frequencies_match_probabilities(level):
    probabilities = np.array([v["probability"] for v in JSON_LEVELS[level]["variants"]])
    env = PaperMazeEnv(level)
    seeded = [env.reset(seed=seed)[1]["variant"] for seed in range(2000)]
    env.reset(seed=99)
    unseeded = [env.reset()[1]["variant"] for _ in range(2000)]
    for variants in (seeded, unseeded):
        freq = np.bincount(variants, minlength=len(probabilities)) / len(variants)
        np.testing.assert_allclose(freq, probabilities, atol=0.04)


def test_reset_seeding_is_deterministic():
    env = PaperMazeEnv(3)
    first = [env.reset(seed=5)[1]["variant"]] + [env.reset()[1]["variant"] for _ in range(30)]
    again = [env.reset(seed=5)[1]["variant"]] + [env.reset()[1]["variant"] for _ in range(30)]
    other = [env.reset(seed=6)[1]["variant"]] + [env.reset()[1]["variant"] for _ in range(30)]
    assert first == again
    assert first != other


# ----------------------------------------------------------------------------- dynamics


def test_level_data_loading():
    maze = load_maze_level(3)
    assert maze.grids.shape == (4, 18, 15) and maze.grids.dtype == np.int64
    np.testing.assert_array_equal(maze.start, [9, 7])
    np.testing.assert_array_equal(maze.cumulative_probabilities, [0.25, 0.5, 0.75, 1.0])
    np.testing.assert_array_equal(maze.rewarded_goal, [5, 6, 13, 14])
    assert (maze.num_codes, maze.wall_code, maze.max_steps) == (15, 4, 30)
    assert load_maze_level(3) is maze  # parsed once
    with pytest.raises(ValueError):
        maze.grids[0, 0, 0] = 0  # shared between envs, so read-only
    with pytest.raises(ThciError, match="valid levels are 1, 2, 3, 4"):
        load_maze_level(5)
    with pytest.raises(ThciError, match="valid levels"):
        PaperMazeEnv(level=0)


@pytest.mark.parametrize("level", LEVELS)
def test_start_observation_and_wall_bump(level):
    spec = JSON_LEVELS[level]
    start = tuple(spec["start"])
    env = PaperMazeEnv(level)
    for variant, seed in _seeds_covering_variants(level).items():
        grid = np.array(spec["variants"][variant]["grid"])
        obs, info = env.reset(seed=seed)
        assert obs.dtype == np.float32 and obs in env.observation_space
        np.testing.assert_array_equal(obs, _one_hot(grid[start]))
        assert info["code"] == grid[start] and info["causal"] and not info["success"]
        np.testing.assert_array_equal(info["agent_pos"], start)
        for action, (dr, dc) in MOVES.items():
            if grid[start[0] + dr, start[1] + dc] == WALL:
                env.reset(seed=seed)
                obs, reward, terminated, truncated, info = env.step(action)
                np.testing.assert_array_equal(info["agent_pos"], start)
                np.testing.assert_array_equal(obs, _one_hot(grid[start]))
                assert (reward, terminated, truncated) == (0.0, False, False)


@pytest.mark.parametrize("level", LEVELS)
def test_shortest_paths_to_every_goal(level):
    spec = JSON_LEVELS[level]
    terminal = set(spec["terminal_goal_codes"])
    start = tuple(spec["start"])
    env = PaperMazeEnv(level)
    rewarded_walks = 0
    for variant, seed in _seeds_covering_variants(level).items():
        grid = np.array(spec["variants"][variant]["grid"])
        rewarded_goal = spec["variants"][variant]["rewarded_goal"]
        goals = [tuple(int(x) for x in cell) for cell in np.argwhere(np.isin(grid, list(terminal)))]
        assert len(goals) == len(terminal)
        for goal in goals:
            path = _bfs_actions(grid, start, goal, terminal)
            assert path is not None and len(path) < 30
            env.reset(seed=seed)
            for i, action in enumerate(path):
                obs, reward, terminated, truncated, info = env.step(action)
                if i < len(path) - 1:
                    assert not terminated and not truncated and reward == 0.0
            should_pay = grid[goal] == rewarded_goal
            assert terminated and not truncated
            assert reward == (1.0 if should_pay else 0.0)
            assert info["success"] == should_pay
            assert info["code"] == grid[goal] and tuple(info["agent_pos"]) == goal
            np.testing.assert_array_equal(obs, _one_hot(grid[goal]))
            rewarded_walks += should_pay
    assert rewarded_walks == len(spec["variants"])  # exactly one paying goal per variant


def test_moves_off_the_grid_are_blocked():
    # No open cell of the shipped mazes is on the border except level 4's bottom goals, which
    # end the episode, so the off-grid rule is checked on the transition function directly.
    maze = load_maze_level(4)
    positions = np.array([[17, 2], [17, 12], [9, 7]])
    new_positions, codes, _, _, truncated = _advance(
        maze, np.zeros(3, np.int64), positions, np.zeros(3, np.int64), np.array([2, 2, 3]), 30
    )
    np.testing.assert_array_equal(new_positions, [[17, 2], [17, 12], [8, 7]])
    np.testing.assert_array_equal(codes, [6, 13, 2])
    assert not truncated.any()


@pytest.mark.parametrize("level", LEVELS)
def test_truncation_at_exactly_max_steps(level):
    env = PaperMazeEnv(level)
    env.reset(seed=0)
    for step in range(1, 31):
        _, reward, terminated, truncated, info = env.step(0)  # col+1 from start is a wall
        assert not terminated and reward == 0.0 and not info["success"]
        assert truncated == (step == 30)
    short = PaperMazeEnv(level, max_steps=3)
    short.reset(seed=0)
    assert [short.step(0)[3] for _ in range(3)] == [False, False, True]


def test_termination_on_last_step_is_not_truncation():
    spec = JSON_LEVELS[1]
    env = PaperMazeEnv(1)
    _, info = env.reset(seed=0)
    grid = np.array(spec["variants"][info["variant"]]["grid"])
    goal = tuple(int(x) for x in np.argwhere(grid == 6)[0])
    path = _bfs_actions(grid, tuple(spec["start"]), goal, set(spec["terminal_goal_codes"]))
    env = PaperMazeEnv(1, max_steps=len(path))
    env.reset(seed=0)
    for action in path:
        _, _, terminated, truncated, _ = env.step(action)
    assert terminated and not truncated


@pytest.mark.parametrize("level", LEVELS)
def test_causal_flag(level):
    spec = JSON_LEVELS[level]
    causal_codes = set(spec["causal_codes_ground_truth"])
    env = PaperMazeEnv(level)
    for variant, seed in _seeds_covering_variants(level).items():
        grid = np.array(spec["variants"][variant]["grid"])
        _, info = env.reset(seed=seed)
        assert info["causal"]  # the start indicator
        _, _, _, _, info = env.step(3)  # north of the start
        north_code = grid[spec["start"][0] - 1, spec["start"][1]]
        assert info["code"] == north_code
        assert info["causal"] == (level >= 3 and north_code == 2)
        if level >= 3:
            assert (north_code == 2) == (spec["variants"][variant]["rewarded_goal"] in (5, 6))
    rng = np.random.default_rng(level)
    env.reset(seed=0)
    seen = set()
    for _ in range(300):
        _, _, terminated, truncated, info = env.step(int(rng.choice(4, p=WALK_PROBS)))
        assert info["causal"] == (info["code"] in causal_codes)
        seen.add(info["causal"])
        if terminated or truncated:
            env.reset()
    assert seen == {False, True}


def test_invalid_actions_and_arguments():
    env = PaperMazeEnv(1)
    with pytest.raises(gym.error.ResetNeeded):
        env.step(0)
    env.reset(seed=0)
    for bad in (4, -1, 1.5, "up"):
        with pytest.raises(ValueError, match="invalid action"):
            env.step(bad)
    with pytest.raises(ThciError, match="max_steps"):
        PaperMazeEnv(1, max_steps=0)
    with pytest.raises(ThciError, match="render_mode"):
        PaperMazeEnv(1, render_mode="human")
    venv = PaperMazeVectorEnv(3, level=1)
    venv.reset(seed=0)
    for bad in ([0, 1], [0, 1, 4], [0.0, 1.0, 2.0]):
        with pytest.raises(ValueError, match="invalid actions"):
            venv.step(np.array(bad))
    with pytest.raises(ValueError, match="expected 3 seeds"):
        venv.reset(seed=[1, 2])


def test_render_modes():
    env = PaperMazeEnv(4, render_mode="rgb_array")
    env.reset(seed=0)
    before = env.render()
    assert before.shape == (18 * 16, 15 * 16, 3) and before.dtype == np.uint8
    env.step(3)
    after = env.render()
    changed_rows = np.unique(np.argwhere((before != after).any(axis=2))[:, 0] // 16)
    np.testing.assert_array_equal(changed_rows, [8, 9])  # agent moved from row 9 to row 8
    text = PaperMazeEnv(4, render_mode="ansi")
    text.reset(seed=0)
    lines = text.render().splitlines()
    assert len(lines) == 1 + 18 and lines[1 + 9].split()[7] == "@"
    venv = PaperMazeVectorEnv(3, level=4, render_mode="rgb_array")
    venv.reset(seed=0)
    frames = venv.render()
    assert len(frames) == 3
    np.testing.assert_array_equal(frames[0], before)


# ----------------------------------------------------------------------------- vector env


def _assert_info_equal(vector_info: dict, single_infos: list[dict], rows: np.ndarray) -> None:
    for key in ("causal", "success", "agent_pos", "variant", "code"):
        assert vector_info[f"_{key}"].dtype == np.bool_
        for i in np.flatnonzero(rows):
            np.testing.assert_array_equal(vector_info[key][i], single_infos[i][key], err_msg=key)


@pytest.mark.parametrize(("level", "seed"), [(1, 3), (2, 11), (3, 123), (4, 7)])
def test_vector_env_matches_single_envs(level, seed):
    n = 8
    venv = PaperMazeVectorEnv(n, level=level)
    envs = [PaperMazeEnv(level) for _ in range(n)]
    obs, infos = venv.reset(seed=seed)
    singles = [env.reset(seed=seed + i) for i, env in enumerate(envs)]
    np.testing.assert_array_equal(obs, np.stack([o for o, _ in singles]))
    _assert_info_equal(infos, [i for _, i in singles], np.ones(n, bool))
    rng = np.random.default_rng(level)
    ends = {"success": 0, "failure": 0, "truncated": 0}
    for _ in range(500):
        actions = rng.choice(4, size=n, p=WALK_PROBS)
        obs, rewards, terminated, truncated, infos = venv.step(actions)
        assert obs.dtype == np.float32 and rewards.dtype == np.float64
        assert obs in venv.observation_space
        results = [env.step(a) for env, a in zip(envs, actions, strict=True)]
        np.testing.assert_array_equal(rewards, [r[1] for r in results])
        np.testing.assert_array_equal(terminated, [r[2] for r in results])
        np.testing.assert_array_equal(truncated, [r[3] for r in results])
        single_obs = [r[0] for r in results]
        single_info = [r[4] for r in results]
        done = terminated | truncated
        if done.any():
            np.testing.assert_array_equal(infos["_final_obs"], done)
            np.testing.assert_array_equal(infos["_final_info"], done)
            assert infos["final_obs"].shape == (n, 15)
            assert infos["final_obs"].dtype == np.float32
            _assert_info_equal(infos["final_info"], single_info, done)
            np.testing.assert_array_equal(infos["final_info"]["_code"], done)
            for i in np.flatnonzero(done):
                np.testing.assert_array_equal(infos["final_obs"][i], single_obs[i])
                kind = "truncated" if truncated[i] else "success" if rewards[i] else "failure"
                ends[kind] += 1
                single_obs[i], single_info[i] = envs[i].reset()
        else:
            assert "final_obs" not in infos and "final_info" not in infos
        np.testing.assert_array_equal(obs, np.stack(single_obs))
        _assert_info_equal(infos, single_info, np.ones(n, bool))
        assert all(infos[f"_{k}"].all() for k in ("causal", "success", "agent_pos"))
    assert min(ends.values()) > 0, ends  # every kind of episode end was exercised
    # An unseeded reset continues every env's variant stream.
    obs, infos = venv.reset()
    singles = [env.reset() for env in envs]
    np.testing.assert_array_equal(infos["variant"], [i["variant"] for _, i in singles])
    np.testing.assert_array_equal(obs, np.stack([o for o, _ in singles]))


def test_vector_env_list_seeds_and_unseeded_first_reset():
    venv = PaperMazeVectorEnv(4, level=3)
    venv.reset(seed=[10, None, 30, None])
    variants = [venv.reset()[1]["variant"] for _ in range(20)]
    envs = [PaperMazeEnv(3) for _ in range(2)]
    envs[0].reset(seed=10)
    envs[1].reset(seed=30)
    expected = [[env.reset()[1]["variant"] for env in envs] for _ in range(20)]
    np.testing.assert_array_equal(np.array(variants)[:, [0, 2]], expected)
    numpy_seeded = PaperMazeVectorEnv(4, level=3).reset(seed=np.int64(10))[1]["variant"]
    np.testing.assert_array_equal(
        numpy_seeded, PaperMazeVectorEnv(4, 3).reset(seed=10)[1]["variant"]
    )
    unseeded = PaperMazeVectorEnv(64, level=3)
    assert len(np.unique(unseeded.reset()[1]["variant"])) > 1  # random keys, not all equal


def test_vector_env_info_layout_matches_sync_vector_env():
    n = 6
    native = gym.make_vec(PAPER_MAZE_IDS[2], num_envs=n, vectorization_mode="vector_entry_point")
    sync = gym.make_vec(
        PAPER_MAZE_IDS[2],
        num_envs=n,
        vectorization_mode="sync",
        vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP},
    )
    assert native.metadata["autoreset_mode"] == sync.metadata["autoreset_mode"]
    assert native.observation_space == sync.observation_space
    assert native.action_space == sync.action_space
    native_out, sync_out = native.reset(seed=1), sync.reset(seed=1)
    rng = np.random.default_rng(0)
    ended = 0
    for _ in range(200):
        actions = rng.choice(4, size=n, p=WALK_PROBS)
        native_out, sync_out = native.step(actions), sync.step(actions)
        for a, b in zip(native_out[:4], sync_out[:4], strict=True):
            np.testing.assert_array_equal(a, b)
            assert a.dtype == b.dtype
        native_info, sync_info = native_out[4], sync_out[4]
        assert native_info.keys() == sync_info.keys()
        for key, value in sync_info.items():
            if key == "final_obs":
                mask = sync_info["_final_obs"]
                np.testing.assert_array_equal(native_info[key][mask], np.stack(value[mask]))
                ended += mask.sum()
            elif key == "final_info":
                assert native_info[key].keys() == value.keys()
                for sub, sub_value in value.items():
                    mask = value[f"_{sub.lstrip('_')}"]
                    assert native_info[key][sub].dtype == sub_value.dtype
                    np.testing.assert_array_equal(native_info[key][sub][mask], sub_value[mask])
            else:
                assert native_info[key].dtype == value.dtype, key
                np.testing.assert_array_equal(native_info[key], value, err_msg=key)
    assert ended > 0


def test_get_state_set_state_resumes_bit_identically():
    venv = PaperMazeVectorEnv(8, level=4)
    venv.reset(seed=42)
    rng = np.random.default_rng(1)
    for _ in range(37):
        venv.step(rng.choice(4, size=8, p=WALK_PROBS))
    snapshot = venv.get_state()
    actions = rng.choice(4, size=(120, 8), p=WALK_PROBS)

    def rollout(env: PaperMazeVectorEnv) -> list:
        return [env.step(a) for a in actions]

    first = rollout(venv)
    venv.set_state(snapshot)
    resumed = PaperMazeVectorEnv(8, level=4)
    resumed.set_state(snapshot)
    assert any(out[2].any() for out in first)  # resets happened inside the rollout
    for other in (rollout(venv), rollout(resumed)):
        for a, b in zip(first, other, strict=True):
            for x, y in zip(a[:4], b[:4], strict=True):
                np.testing.assert_array_equal(x, y)
            assert a[4].keys() == b[4].keys()
            for key in ("variant", "agent_pos", "success", "causal", "code"):
                np.testing.assert_array_equal(a[4][key], b[4][key])
    state = venv.get_state()
    state["positions"][:] = -1  # get_state returns copies
    assert venv.get_state()["positions"].min() >= 0
    with pytest.raises(ThciError, match="level"):
        PaperMazeVectorEnv(8, level=3).set_state(snapshot)
    with pytest.raises(ThciError, match="num_envs=4"):
        PaperMazeVectorEnv(4, level=4).set_state(snapshot)
    with pytest.raises(ThciError, match="out-of-range"):
        PaperMazeVectorEnv(8, level=4).set_state({**snapshot, "variants": np.full(8, -1)})
    with pytest.raises(ThciError, match="missing counters"):
        PaperMazeVectorEnv(8, level=4).set_state({"level": snapshot["level"]})


# ----------------------------------------------------------------------------- registration


def test_registration_make_and_env_checker():
    assert tuple(f"thci/PaperMaze-L{k}-v0" for k in LEVELS) == PAPER_MAZE_IDS
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        importlib.reload(thci.envs)  # re-registration must neither warn nor fail
        for level, env_id in zip(LEVELS, PAPER_MAZE_IDS, strict=True):
            assert gym.spec(env_id).max_episode_steps is None
            env = gym.make(env_id)
            assert isinstance(env.unwrapped, PaperMazeEnv) and env.unwrapped.maze.level == level
            check_env(env.unwrapped)
            env.close()
            venv = gym.make_vec(env_id, num_envs=8, vectorization_mode="vector_entry_point")
            assert isinstance(venv, PaperMazeVectorEnv) and venv.maze.level == level
            assert venv.observation_space.shape == (8, 15)
            assert isinstance(gym.make_vec(env_id, num_envs=2), PaperMazeVectorEnv)
    assert gym.make(PAPER_MAZE_IDS[0], max_steps=5).unwrapped.max_steps == 5

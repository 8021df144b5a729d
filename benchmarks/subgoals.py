"""How far a trained BabyAI agent gets through its level's sub-goals.

A run that never reaches a ball (success 0, every episode at the time limit) says nothing
about where it stops. This plays a run's agent (sampled actions, one environment, layouts it
never saw) and counts the episodes in which each sub-goal of the level was reached at least
once: entering A, the key of B's door carried (levels 2-4), the box opened (level 3), door A
unlocked and key b carried (level 4), door B open, entering B, and success.

    .venv/bin/python benchmarks/subgoals.py RUN_DIR [RUN_DIR ...] [--episodes 100]

Writes benchmarks/results/subgoals.json (one entry per run, merged with earlier entries) and
prints a table.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
from choice_state import sampled_steps

from thci.rl.evaluate import load_run

RESULTS = Path(__file__).parent / "results"


def _in_room(level, room: int) -> bool:
    return int(level.agent_pos[0]) // (level.room_size - 1) == room


def _box_opened(level) -> bool:
    box, (x, y) = level.box, level.box.init_pos
    return level.grid.get(x, y) is not box


def subgoals(level) -> dict[str, Callable[[object], bool]]:
    """The level's sub-goals, each a test of the current state, in the order they come."""
    goals: dict[str, Callable[[object], bool]] = {"in_A": lambda lv: _in_room(lv, lv.room_a)}
    if hasattr(level, "key_a"):  # level 4: key a opens A, where key b lies
        goals["door_A_open"] = lambda lv: lv.door_a.is_open
        goals["carry_key_b"] = lambda lv: lv.carrying is lv.key_b
    elif hasattr(level, "key"):  # levels 2-3 (level 3 hides the key in a box)
        if hasattr(level, "box"):
            goals["box_opened"] = _box_opened
        goals["carry_key_b"] = lambda lv: lv.carrying is lv.key
    goals["door_B_open"] = lambda lv: lv.door_b.is_open
    goals["in_B"] = lambda lv: _in_room(lv, lv.room_b)
    return goals


def play(run_dir: Path, episodes: int, seed: int) -> dict:
    """Share of `episodes` episodes of the run's agent that reached each sub-goal."""
    _, envs, agent, checkpoint = load_run(run_dir, 1, seed=seed)
    obs, _ = envs.reset(seed=seed)
    level = envs.envs[0].unwrapped
    if not hasattr(level, "door_b"):
        raise SystemExit(f"{run_dir}: not a BabyAI level of thci (no door B)")
    goals = subgoals(level)

    def reached_now(lv) -> set[str]:
        return {name for name, test in goals.items() if test(lv)}

    counts = dict.fromkeys([*goals, "success"], 0)
    lengths: list[int] = []
    reached: set[str] = set()
    length = 0
    for now, _, _, reward, ended in sampled_steps(envs, agent, obs, reached_now):
        reached, length = reached | now, length + 1
        if ended:
            for name in reached | ({"success"} if reward > 0 else set()):
                counts[name] += 1
            lengths.append(length)
            reached, length = set(), 0
            if len(lengths) == episodes:
                break
    envs.close()
    return {
        "episodes": episodes,
        "checkpoint_step": int(checkpoint.get("global_step", -1)),
        "mean_length": float(np.mean(lengths)),
        **{name: count / episodes for name, count in counts.items()},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=123)
    args = parser.parse_args()
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / "subgoals.json"
    results = json.loads(path.read_text()) if path.is_file() else {}
    for run in args.runs:
        results[str(run)] = play(run, args.episodes, args.seed)
        row = results[str(run)]
        cells = " | ".join(f"{k} {v:.2f}" for k, v in row.items() if k not in ("episodes",))
        print(f"{run} | {cells}")
    path.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

"""How a trained BabyAI agent acts at the level's choice state: committed, or still guessing?

On BabyAI levels 1-3 the ball to face is one turn away from the *choice state*: the first cell
inside B's door, facing into B (target and decoy flank that cell). This plays a run's agent
(sampled actions, one environment) and, the first time each episode reaches the choice state,
records the policy's probability of the turn that faces the target and of the turn that faces
the decoy. A policy that has not learned to use its memory but is *committed* gives one turn
nearly all the mass, whichever ball is the target (a bimodal histogram of
p(correct | a turn)); a guessing one splits it; a solving one puts it on the correct turn.

    .venv/bin/python benchmarks/choice_state.py RUN_DIR [RUN_DIR ...] [--episodes 200]

Writes benchmarks/results/choice_state.json (one entry per run) and prints a table.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium.vector import VectorEnv

from thci.rl.agent import ActorCritic
from thci.rl.evaluate import load_run

RESULTS = Path(__file__).parent / "results"
LEFT, RIGHT = 0, 1
BINS = [0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 1.0]


def correct_turn(level) -> int | None:
    """The turn that faces the target if the agent is at the choice state, else None."""
    door_x, door_y = level.door_b.cur_pos
    east = level.room_b == 2  # B is the right-hand room: the agent faces east into it
    entry = (door_x + (1 if east else -1), door_y)
    if tuple(level.agent_pos) != entry or level.agent_dir != (0 if east else 2):
        return None
    target_north = level.target_ball.cur_pos[1] == door_y - 1
    # Facing east, a left turn faces north; facing west, it faces south.
    return LEFT if east == target_north else RIGHT


def sampled_steps(
    envs: VectorEnv, agent: ActorCritic, obs: np.ndarray, observe: Callable[[Any], Any]
) -> Iterator[tuple[Any, torch.Tensor, int, float, bool]]:
    """The agent playing `envs` (one environment, just reset to `obs`) with sampled actions,
    as trained, without end.

    Yields per step: `observe(level)` of the level *before* the step, the policy's logits
    (A,), the action, the reward and whether the episode ended (SAME_STEP autoreset: the level
    then already holds the next episode)."""
    level = envs.envs[0].unwrapped
    state, start = agent.initial_state(1), torch.ones(1, dtype=torch.bool)
    with torch.no_grad():
        while True:
            seen = observe(level)
            logits, _, state = agent.step(torch.as_tensor(obs, dtype=torch.float32), state, start)
            action = int(torch.distributions.Categorical(logits=logits).sample()[0])
            obs, reward, terminated, truncated, _ = envs.step(np.array([action]))
            start = torch.as_tensor(terminated | truncated)
            yield seen, logits[0], action, float(reward[0]), bool(start[0])


def play(run_dir: Path, episodes: int, seed: int) -> dict:
    """Choice-state statistics of `episodes` episodes of the run's agent."""
    _, envs, agent, _ = load_run(run_dir, 1, seed=seed)
    obs, _ = envs.reset(seed=seed)
    if not hasattr(envs.envs[0].unwrapped, "door_b"):
        raise SystemExit(f"{run_dir}: not a BabyAI level with a choice state")
    records = []  # (p correct turn, p wrong turn, took a turn, took the correct one, success)
    finished, choice = 0, None
    for turn, logits, action, reward, ended in sampled_steps(envs, agent, obs, correct_turn):
        if turn is not None and choice is None:
            probs = torch.softmax(logits, -1)
            choice = (float(probs[turn]), float(probs[1 - turn]), action in (LEFT, RIGHT))
            choice += (action == turn,)
        if ended:
            if choice is not None:
                records.append((*choice, reward > 0))
            finished, choice = finished + 1, None
            if finished == episodes:
                break
    envs.close()
    if not records:
        raise SystemExit(f"{run_dir}: no episode reached the choice state in {episodes}")
    r = np.array(records, dtype=float)
    share = r[:, 0] / np.maximum(r[:, 0] + r[:, 1], 1e-12)
    return {
        "episodes": episodes,
        "reached_choice_state": len(r),
        "p_correct_turn": float(r[:, 0].mean()),
        "p_wrong_turn": float(r[:, 1].mean()),
        "took_a_turn": float(r[:, 2].mean()),
        "took_the_correct_turn": float(r[:, 3].mean()),
        "success_when_reached": float(r[:, 4].mean()),
        "p_correct_given_a_turn_histogram": {
            "bins": BINS,
            "counts": np.histogram(share, bins=BINS)[0].tolist(),
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()
    torch.set_num_threads(1)
    out = RESULTS / "choice_state.json"
    results = json.loads(out.read_text()) if out.is_file() else {}
    print("run | reached | p(correct) | p(wrong) | turned | correct | success | histogram")
    for run in args.runs:
        stats = play(run, args.episodes, args.seed)
        results[str(run)] = stats
        print(
            f"{run} | {stats['reached_choice_state']} | {stats['p_correct_turn']:.3f} | "
            f"{stats['p_wrong_turn']:.3f} | {stats['took_a_turn']:.3f} | "
            f"{stats['took_the_correct_turn']:.3f} | {stats['success_when_reached']:.3f} | "
            f"{stats['p_correct_given_a_turn_histogram']['counts']}"
        )
    RESULTS.mkdir(exist_ok=True)
    out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()

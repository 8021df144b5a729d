"""Does a trained agent act on the causal observations it saw? Success with and without them.

Plays a run's agent (sampled actions, as in training) and splits its episodes by whether any
observation labelled causal (``info["causal"]``: the signpost on BabyAI, the indicator on the
maze) was seen. An agent that remembers and uses the cue succeeds more often after seeing it;
an agent that guesses succeeds equally often either way.

    .venv/bin/python benchmarks/cue_use.py RUN_DIR [RUN_DIR ...] [--episodes 600]

Prints a table and writes benchmarks/results/cue_use.json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from thci.rl.evaluate import load_run
from thci.rl.rollout import RolloutCollector

RESULTS = Path(__file__).parent / "results"
NUM_ENVS = 16


def play(run_dir: Path, episodes: int, seed: int) -> np.ndarray:
    """(E, 2) bool per finished episode: (saw a causal observation, succeeded)."""
    _, envs, agent, _ = load_run(run_dir, NUM_ENVS, seed=seed)
    try:
        collector = RolloutCollector(envs, agent, num_steps=256, gamma=0.99, greedy=False)
        collector.reset(seed)
        seen = np.zeros(NUM_ENVS, dtype=bool)
        outcomes: list[tuple[bool, bool]] = []
        while len(outcomes) < episodes:
            rollout, finished = collector.collect()
            if rollout.causal is None:
                raise SystemExit(f"{run_dir}: the environment reports no info['causal'] labels")
            causal, starts = rollout.causal.numpy(), rollout.episode_starts.numpy()
            ends = {(e.step, e.env): bool(e.success) for e in finished}
            for t in range(len(causal)):  # per step, in order: cheap next to the env steps
                seen = np.where(starts[t], False, seen) | causal[t]
                for n in range(NUM_ENVS):
                    if (t, n) in ends:
                        outcomes.append((bool(seen[n]), ends[(t, n)]))
        return np.array(outcomes[:episodes])
    finally:
        envs.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+")
    parser.add_argument("--episodes", type=int, default=600)
    parser.add_argument("--seed", type=int, default=123)
    args = parser.parse_args()
    torch.set_num_threads(1)
    records = []
    print("| run | episodes | saw the cue | success if seen | success if not | success |")
    print("|---|---|---|---|---|---|")
    for run in args.runs:
        outcome = play(run, args.episodes, args.seed)
        saw, success = outcome[:, 0], outcome[:, 1]
        record = {
            "run": str(run),
            "episodes": len(outcome),
            "saw_cue": round(float(saw.mean()), 3),
            "success_if_seen": round(float(success[saw].mean()), 3) if saw.any() else None,
            "success_if_not_seen": round(float(success[~saw].mean()), 3) if (~saw).any() else None,
            "success": round(float(success.mean()), 3),
        }
        records.append(record)
        print(" | ".join(["", *map(str, record.values()), ""]).strip())
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "cue_use.json").write_text(json.dumps(records, indent=2) + "\n")


if __name__ == "__main__":
    main()

"""Wall-clock of one CI round on real replay pools, measured alone on one thread.

A training run's CI rounds share the machine with its RL loop (and, on a busy machine, with
everything else), so the seconds in its ci_rounds.csv measure the machine as much as the
round. This benchmark takes the replay pool saved in each run's checkpoint, runs the round
that run would run (effect predictor fit, T-HCI or HCI search, gate fit: `run_ci_job`) in
this process with one torch thread, `--repeats` times, and records the median seconds,
|Ô|, interventions and the causal set found. A later round continues the previous round's
predictor (`--ci-warm-steps`); `--cold` times a first round instead (`--ci-base-steps` from
scratch).

    .venv/bin/python benchmarks/ci_rounds.py RUN_DIR [RUN_DIR ...] [--cold]

Writes benchmarks/results/ci_rounds.json and prints a table.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import torch
from saved_ci import load_ci_loop

from thci.causal.loop import run_ci_job

RESULTS = Path(__file__).parent / "results"


def time_round(run_dir: Path, repeats: int, cold: bool) -> dict:
    """Median seconds of the run's CI round on the pool of its last checkpoint."""
    config, loop = load_ci_loop(run_dir, cold)
    job = loop.make_job(loop.pool.arrays())
    outcomes = [run_ci_job(job) for _ in range(repeats)]
    result = outcomes[-1].result
    return {
        "run": str(run_dir),
        "env": config.env,
        "method": config.method,
        "round": "first (cold)" if job.warm_start is None else "later (warm)",
        "pool_episodes": len(job.pool.lengths),
        "observed": len(result.observed),
        "interventions": result.num_interventions,
        "kept": loop.describe(result.causal),
        "seconds_median": round(statistics.median(o.seconds for o in outcomes), 3),
        "seconds_all": [round(o.seconds, 3) for o in outcomes],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", nargs="+", type=Path)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--cold", action="store_true", help="time a first round")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = [time_round(d, args.repeats, args.cold) for d in args.run_dirs]
    RESULTS.mkdir(exist_ok=True)
    name = "ci_rounds_cold.json" if args.cold else "ci_rounds.json"
    (RESULTS / name).write_text(json.dumps(rows, indent=2) + "\n")
    print("| run | round | |Ô| | interventions | kept | seconds (median) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {Path(r['run']).name} | {r['round']} | {r['observed']} | {r['interventions']} "
            f"| {r['kept']} | {r['seconds_median']} |"
        )


if __name__ == "__main__":
    main()

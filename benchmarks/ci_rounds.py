"""Wall-clock of one CI round on real replay pools, measured alone on one thread.

A training run's CI rounds share the machine with its RL loop (and, on a busy machine, with
everything else), so the seconds in its ci_rounds.csv measure the machine as much as the
round. This benchmark takes the replay pool saved in each run's checkpoint, runs the round
that run would run (effect predictor fit, T-HCI or HCI search, gate fit: `run_ci_job`) in
this process with one torch thread, `--repeats` times, and records the median seconds,
|Ô|, interventions and the causal set found. A later round continues the previous round's
predictor (`--ci-warm-steps`); `--cold` times a first round instead (`--ci-base-steps` from
scratch). `--steps N` fits for N steps instead of the run's own setting (e.g. today's default
for an older run), `--learning-rate LR` with another Adam rate (these two write files of their
own, e.g. ci_rounds_cold_steps200_lr0.006.json), and `--two-cores` runs the round as the RL
loop runs one it waits for: the fit split between this process and a worker
(`run_ci_job_on_two_cores`); the seconds recorded are then the wall-clock of the round, the
compute of both processes beside them.

    .venv/bin/python benchmarks/ci_rounds.py RUN_DIR [RUN_DIR ...] [--cold] [--steps N]
        [--learning-rate LR] [--two-cores]

Writes benchmarks/results/ci_rounds[_cold][_two_cores].json and prints a table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from pathlib import Path

import torch
from saved_ci import load_ci_loop

from thci.causal.loop import CIWorker, run_ci_job, run_ci_job_on_two_cores, start_ci_worker

RESULTS = Path(__file__).parent / "results"


def time_round(
    run_dir: Path,
    repeats: int,
    cold: bool,
    steps: int | None,
    worker: CIWorker | None,
    learning_rate: float | None = None,
) -> dict:
    """Median seconds of the run's CI round on the pool of its last checkpoint."""
    config, loop = load_ci_loop(run_dir, cold)
    if steps is not None:
        loop.config = dataclasses.replace(loop.config, ci_base_steps=steps, ci_warm_steps=steps)
    job = loop.make_job(loop.pool.arrays())
    if learning_rate is not None:
        predictor = dataclasses.replace(job.predictor, learning_rate=learning_rate)
        job = dataclasses.replace(job, predictor=predictor)
    outcomes, walls = [], []
    for _ in range(repeats):
        started = time.perf_counter()
        outcomes.append(run_ci_job(job) if worker is None else run_ci_job_on_two_cores(job, worker))
        walls.append(time.perf_counter() - started)
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
        "fit_steps": job.predictor.base_steps
        if job.warm_start is None
        else job.predictor.warm_steps,
        "learning_rate": job.predictor.learning_rate,
        "two_cores": worker is not None,
        "seconds_median": round(statistics.median(walls), 3),
        "seconds_all": [round(w, 3) for w in walls],
        "compute_seconds_all": [round(o.seconds, 3) for o in outcomes],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", nargs="+", type=Path)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--cold", action="store_true", help="time a first round")
    parser.add_argument("--steps", type=int, default=None, help="fit steps (default: the run's)")
    parser.add_argument("--learning-rate", type=float, default=None, help="the fit's Adam rate")
    parser.add_argument("--two-cores", action="store_true", help="split the fit with a worker")
    args = parser.parse_args()
    torch.set_num_threads(1)
    worker = start_ci_worker() if args.two_cores else None
    if worker is not None:
        worker.ready.wait()  # time the rounds, not the worker's start-up
    rows = [
        time_round(d, args.repeats, args.cold, args.steps, worker, args.learning_rate)
        for d in args.run_dirs
    ]
    RESULTS.mkdir(exist_ok=True)
    name = "ci_rounds" + ("_cold" if args.cold else "") + ("_two_cores" if args.two_cores else "")
    # settings other than the runs' own get their own file
    name += f"_steps{args.steps}" if args.steps is not None else ""
    name += f"_lr{args.learning_rate:g}" if args.learning_rate is not None else ""
    name += ".json"
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

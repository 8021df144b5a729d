"""What T-HCI keeps for several thresholds ξ, on saved replay pools and on planted data.

The threshold ξ decides when an ATE's confidence interval is "near zero" (thci.causal.search).
Too small and noise keeps observations without effect; too large and a real cause is
eliminated, which the agent never recovers from. This benchmark fits the effect predictor
once per pool (default settings, one torch thread) and runs T-HCI for each ξ on:

* planted data (thci.causal.synthetic: 32 codes, 2 causes, one confounder each), seeds 3, 4;
* the replay pool in the checkpoint of each RUN_DIR (a t-hci or hci run), with the ground
  truth read from the pool's `info["causal"]` labels where the environment provides them.

    .venv/bin/python benchmarks/xi_calibration.py [RUN_DIR ...] [--xis 0.05 0.1 0.2]
        [--target reward|dynamics|inverse]

Writes benchmarks/results/xi_calibration_<target>.json and prints a table.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from saved_ci import load_ci_loop

from thci.causal.predictor import EffectEstimator, PredictorConfig
from thci.causal.replay import pad_episodes
from thci.causal.search import DEFAULT_Z, t_hci
from thci.causal.synthetic import generate_planted_episodes

RESULTS = Path(__file__).parent / "results"


def planted_rows(seed: int, xis: list[float], target: str) -> list[dict]:
    data = generate_planted_episodes(32, num_causal=2, num_episodes=1500, seed=seed)
    started = time.perf_counter()
    config = PredictorConfig(seed=0, target=target)
    estimator = EffectEstimator(pad_episodes(data.episodes), 4, config)
    fit = time.perf_counter() - started
    truth = sorted(data.causal_codes.tolist())
    return [
        _row(
            f"planted32 seed {seed}",
            xi,
            sorted(t_hci(estimator, xi=xi).causal.tolist()),
            truth,
            fit,
        )
        for xi in xis
    ]


def run_rows(run_dir: Path, xis: list[float], target: str) -> list[dict]:
    config, loop = load_ci_loop(run_dir)
    pool = loop.pool.arrays()
    truth = None
    if all(e.causal is not None for e in loop.pool.episodes):
        labelled = np.concatenate([e.codes[e.causal] for e in loop.pool.episodes])
        truth = loop.describe(np.unique(labelled))
    started = time.perf_counter()
    estimator = EffectEstimator(pool, loop.num_actions, PredictorConfig(seed=0, target=target))
    fit = time.perf_counter() - started
    steps = int(np.sum(pool.valid))
    name = f"{config.env} {config.method} s{config.seed} ({len(pool.lengths)} ep., {steps} steps)"
    z = config.ci_z or DEFAULT_Z
    return [
        _row(name, xi, loop.describe(t_hci(estimator, z=z, xi=xi).causal), truth, fit) for xi in xis
    ]


def _row(pool: str, xi: float, kept: list[int], truth: list[int] | None, fit: float) -> dict:
    missed = None if truth is None else sorted(set(truth) - set(kept))
    return {
        "pool": pool,
        "xi": xi,
        "kept": kept,
        "truth": truth,
        "missed": missed,
        "fit_seconds": round(fit, 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", nargs="*", type=Path)
    parser.add_argument("--xis", type=float, nargs="+", default=[0.05, 0.1, 0.2])
    parser.add_argument("--target", default="reward", choices=["reward", "dynamics", "inverse"])
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = [r for seed in (3, 4) for r in planted_rows(seed, args.xis, args.target)]
    rows += [r for d in args.run_dirs for r in run_rows(d, args.xis, args.target)]
    rows = [{"target": args.target, **r} for r in rows]
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / f"xi_calibration_{args.target}.json"
    out.write_text(json.dumps(rows, indent=2) + "\n")
    print("| pool | ξ | kept | labelled causal | missed |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['pool']} | {r['xi']} | {r['kept']} | {r['truth']} | {r['missed']} |")


if __name__ == "__main__":
    main()

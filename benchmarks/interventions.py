"""Interventions and CI wall-clock of fine-grained CI, HCI and T-HCI as |O| grows (App. J).

Synthetic histories with |O| distinct observations, of which two are causes and two are
confounded with them (:mod:`thci.causal.synthetic`). For each |O| the effect predictor is fitted
once and each search runs on it; we record the number of interventions, the search's wall-clock
and whether it recovered exactly the planted causes. Searches whose cost would exceed the
budget are skipped and marked as such (HCI needs |O| interventions, fine-grained |O|·T).

    .venv/bin/python benchmarks/interventions.py            # |O| = 1e2 .. 1e5
    .venv/bin/python benchmarks/interventions.py --sizes 100 1000
    .venv/bin/python benchmarks/interventions.py --sizes 1000 --draws-per-code 80
    .venv/bin/python benchmarks/interventions.py --target dynamics   # Eq. 9 whole

By default there are just enough episodes that almost every code appears (~3 draws per code):
most codes then occur in a few held-out episodes, too few for any test to decide them, and the
searches keep what they cannot decide. `--draws-per-code K` generates K draws per code on
average instead (the CI of each code then has ~K/4 held-out episodes), written to
interventions_draws{K}.json / .png beside the default files. The effect predictor learns the
reward given the transition, as in training (`--ci-target reward`, the default); with
`--target dynamics` (next observation and reward, Eq. 9 whole) or `inverse` the files get that
suffix.

Records of sizes not run keep their earlier values. Writes
benchmarks/results/interventions.json and interventions.png, and prints a table.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import get_args

import matplotlib
import torch

from thci.causal.predictor import EffectEstimator, PredictorConfig, Target
from thci.causal.replay import pad_episodes
from thci.causal.search import CIResult, fine_grained_ci, hci, t_hci
from thci.causal.synthetic import generate_planted_episodes

matplotlib.use("Agg")
import matplotlib.pyplot as plt

RESULTS = Path(__file__).parent / "results"
EPISODE_LENGTH = 12
DRAWS_PER_CODE = 3
"""Default draws per code: just enough that (almost) every code appears."""


def run_size(
    num_codes: int,
    hci_limit: int,
    fine_limit: int,
    z: int,
    draws_per_code: int = DRAWS_PER_CODE,
    target: Target = "reward",
) -> dict:
    """All searches on one |O|; returns a JSON-ready record."""
    # coverage ~ 1 - exp(-E (L+1) / |O|): ~95% of the codes appear with 3 draws per code
    episodes = max(2000, math.ceil(draws_per_code * num_codes / (EPISODE_LENGTH + 1)))
    data = generate_planted_episodes(
        num_codes, num_causal=2, num_episodes=episodes, episode_length=EPISODE_LENGTH, seed=0
    )
    started = time.perf_counter()
    with torch.random.fork_rng():
        estimator = EffectEstimator(
            pad_episodes(data.episodes), 4, PredictorConfig(seed=0, target=target)
        )
    fit_seconds = time.perf_counter() - started
    truth = sorted(data.causal_codes.tolist())
    record = {
        "num_codes": num_codes,
        "observed": estimator.data.num_codes,
        "episodes": episodes,
        "draws_per_code": draws_per_code,
        "target": target,
        "causal_codes": truth,
        "confounder_codes": sorted(data.confounder_codes.ravel().tolist()),
        "predictor_fit_seconds": round(fit_seconds, 2),
        "bound_t_hci": z * math.ceil(math.log(estimator.data.num_codes, z)) * len(truth) + z,
    }
    searches = {
        "t-hci": (lambda: t_hci(estimator, z=z), True),
        "hci": (lambda: hci(estimator), num_codes <= hci_limit),
        "fine-grained": (lambda: fine_grained_ci(estimator), num_codes <= fine_limit),
    }
    for name, (search, feasible) in searches.items():
        if not feasible:
            projected = num_codes if name == "hci" else num_codes * (EPISODE_LENGTH - 1)
            record[name] = {"skipped": True, "projected_interventions": projected}
            continue
        result: CIResult = search()
        record[name] = {
            "interventions": result.num_interventions,
            "seconds": round(result.seconds, 2),
            "exact": sorted(result.causal.tolist()) == truth,
            "causal_found": sorted(result.causal.tolist()),
        }
        print(
            f"  |O|={num_codes:>6} {name:<12} {result.num_interventions:>6} interventions "
            f"{result.seconds:8.1f} s  exact={record[name]['exact']}",
            flush=True,
        )
    return record


def plot(records: list[dict], path: Path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    styles = {
        "fine-grained": ("s", "tab:blue"),
        "hci": ("o", "tab:orange"),
        "t-hci": ("^", "tab:green"),
    }
    for name, (marker, color) in styles.items():
        done = [r for r in records if not r[name].get("skipped")]
        sizes = [r["observed"] for r in done]
        style = {"marker": marker, "color": color, "label": name}
        axes[0].plot(sizes, [r[name]["interventions"] for r in done], **style)
        axes[1].plot(sizes, [r[name]["seconds"] for r in done], **style)
        skipped = [r for r in records if r[name].get("skipped")]
        if skipped:
            axes[0].plot(
                [r["num_codes"] for r in skipped],
                [r[name]["projected_interventions"] for r in skipped],
                marker=marker,
                color=color,
                linestyle=":",
                alpha=0.5,
                label=f"{name} (projected)",
            )
    axes[0].plot(
        [r["observed"] for r in records],
        [r["bound_t_hci"] for r in records],
        "k--",
        linewidth=1,
        label="Z·⌈log_Z|Ô|⌉·|O^Ca|+Z",
    )
    axes[1].legend(fontsize=8)
    for ax, label in zip(axes, ("interventions", "search wall-clock (s)"), strict=True):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("|Ô| (observed observations)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("Counterfactual inference cost on synthetic histories (2 planted causes)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def _load(path: Path) -> list[dict]:
    """Earlier records, or none if the file is missing."""
    return json.loads(path.read_text()) if path.exists() else []


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[100, 1000, 10_000, 100_000])
    parser.add_argument("--hci-limit", type=int, default=10_000, help="largest |O| for HCI")
    parser.add_argument("--fine-limit", type=int, default=1000, help="largest |O| for fine CI")
    parser.add_argument("--z", type=int, default=4)
    parser.add_argument(
        "--draws-per-code",
        type=int,
        default=DRAWS_PER_CODE,
        help="average observations of each code",
    )
    parser.add_argument(
        "--target", choices=list(get_args(Target)), default="reward", help="what p_ζ predicts"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    RESULTS.mkdir(exist_ok=True)
    stem = "interventions"
    if args.draws_per_code != DRAWS_PER_CODE:
        stem += f"_draws{args.draws_per_code}"
    if args.target != "reward":
        stem += f"_{args.target}"
    path = RESULTS / f"{stem}.json"
    # Sizes not run now keep their earlier records, so one size can be (re)run on its own.
    records = [r for r in _load(path) if r["num_codes"] not in args.sizes]
    for n in args.sizes:  # results are written after every size, so a long run keeps them
        records.append(
            run_size(n, args.hci_limit, args.fine_limit, args.z, args.draws_per_code, args.target)
        )
        records.sort(key=lambda r: r["num_codes"])
        path.write_text(json.dumps(records, indent=2) + "\n")
        plot(records, RESULTS / f"{stem}.png")
    print(f"\n{'|Ô|':>7} | {'fine-grained':>16} | {'HCI':>16} | {'T-HCI':>16} | bound | exact")
    for r in records:
        cells = []
        for name in ("fine-grained", "hci", "t-hci"):
            item = r[name]
            cells.append(
                f"~{item['projected_interventions']} (skip)"
                if item.get("skipped")
                else f"{item['interventions']} / {item['seconds']}s"
            )
        exact = {k: r[k].get("exact") for k in ("hci", "t-hci")}
        print(
            f"{r['observed']:>7} | {cells[0]:>16} | {cells[1]:>16} | {cells[2]:>16} | "
            f"{r['bound_t_hci']:>5} | {exact}"
        )
    print(f"written to {path} and {stem}.png")


if __name__ == "__main__":
    main()

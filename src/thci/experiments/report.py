"""`thci report ROOT`: the paper's tables and figures for a grid of runs, beside its numbers.

Reads every run directory under ROOT (as written by `thci bench` or `thci train`) and writes,
into ROOT/report/ by default:

* ``report.md``: steps to solve (the paper's Fig. 5), wall-clock to solve (Table 1, with the
  paper's seconds beside ours), CI round wall-clock for the first rounds and interventions
  (Fig. 7, App. J), TAIE (Table 2, with the paper's values), learning curves (App. G), and the
  App. J benchmark (`benchmarks/interventions.py`) when its results are present;
* ``runs.csv`` (one row per run), ``aggregate.csv`` (one row per task and method),
  ``ci_rounds.csv`` (one row per CI round);
* ``steps_to_solve.png``, ``learning_curves.png``, ``ci_rounds.png``, ``interventions.png``.

Statistics are over seeds: mean and sample standard deviation. A run that did not solve its
task counts with its whole budget and makes the cell a lower bound ("> mean"), never a gap.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np

from thci.errors import ThciError
from thci.experiments.run_dir import atomic_write_bytes

matplotlib.use("Agg")
import matplotlib.pyplot as plt

CI_ROUNDS_SHOWN = 10  # Fig. 7 shows the first 10 CI rounds
METHOD_ORDER = ("lstm", "gru", "mlp", "nm", "wmg", "hci", "t-hci", "sai", "hai", "oracle")

# The paper's Table 1: average wall-clock seconds to solve, 10 trials.
_TABLE1_COLUMNS = [f"thci/PaperMaze-L{k}-v0" for k in range(1, 5)] + [
    f"thci/BabyAI-L{k}-v0" for k in range(1, 5)
]
PAPER_TABLE1: dict[str, dict[str, str]] = {
    method: dict(zip(_TABLE1_COLUMNS, row.split(), strict=True))
    for method, row in {
        "lstm": "277 2361 10950 13950 1560 6846 18909 22506",
        "gru": "213 2180 9442 11080 1743 6496 16683 20442",
        "nm": "405 1043 4339 6951 1684 4725 10846 14730",
        "wmg": "363 1797 5163 5152 1723 3982 7683 10155",
        "hci": "23146 33714 >70000 >70000 36775 64330 >70000 >70000",
        "t-hci": "4627 6169 10663 12570 7166 10846 14822 19804",
    }.items()
}
# The paper's Table 2: TAIE on level 3 (SAI: one value per attention head).
PAPER_TABLE2: dict[str, dict[str, str]] = {
    method: {"thci/PaperMaze-L3-v0": maze, "thci/BabyAI-L3-v0": babyai}
    for method, maze, babyai in (
        ("hai", "0.38", "0.32"),
        ("sai:head-1", "0.17", "0.16"),
        ("sai:head-2", "0.15", "0.17"),
        ("sai:head-3", "0.11", "0.18"),
        ("sai:head-4", "0.19", "0.16"),
        ("t-hci", "0.00", "0.00"),
    )
}


@dataclass
class RunResult:
    """The numbers of one finished run that the report uses."""

    name: str
    env: str
    method: str
    """Method, with the algorithm appended when it is not PPO (e.g. ``t-hci-a2c``)."""
    seed: int
    solved: bool
    steps: int
    """Steps to solve; the run's whole budget when it did not solve."""
    seconds: float
    """Wall-clock seconds to solve (from metrics.csv); the run's total when it did not solve."""
    taie: dict[str, float]
    """TAIE by row label: {method: value}, or one entry per attention head."""
    interventions: int | None
    ci_round_seconds: list[float]
    curve: tuple[np.ndarray, np.ndarray]
    """(env steps, success rate over the last 100 episodes) after each update."""


def env_label(env: str) -> str:
    """Short column label: thci/PaperMaze-L3-v0 -> Maze L3, thci/BabyAI-L1-v0 -> BabyAI L1."""
    for family, label in (("thci/PaperMaze-L", "Maze L"), ("thci/BabyAI-L", "BabyAI L")):
        if env.startswith(family) and env.endswith("-v0"):
            return label + env[len(family) : -3]
    return env


def load_runs(root: Path) -> tuple[list[RunResult], list[str]]:
    """Finished runs under `root` (any depth) and the names of runs that have not finished."""
    if not root.is_dir():
        raise ThciError(f"{root} is not a directory: pass the --root of a thci bench")
    finished, unfinished = [], []
    for config_path in sorted(root.rglob("config.json")):
        run_dir = config_path.parent
        try:
            summary = json.loads((run_dir / "summary.json").read_text())
        except (OSError, json.JSONDecodeError):
            unfinished.append(run_dir.name)
            continue
        finished.append(_run_result(run_dir, summary))
    if not finished and not unfinished:
        raise ThciError(
            f"{root} holds no thci run directories; train some first, e.g. "
            f"thci bench --preset paper-maze-quick --root {root}"
        )
    return finished, unfinished


def _run_result(run_dir: Path, summary: dict[str, Any]) -> RunResult:
    with (run_dir / "metrics.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    steps_axis = np.array([int(r["global_step"]) for r in rows], dtype=np.int64)
    wall_clock = np.array([float(r["wall_clock_s"]) for r in rows])
    success = np.nan_to_num(np.array([float(r["success_rate"]) for r in rows]))
    solved = bool(summary.get("solved"))
    if solved:
        steps = int(summary["steps_to_solve"])
        seconds = float(wall_clock[np.searchsorted(steps_axis, steps)])
    else:
        steps, seconds = int(summary["total_env_steps"]), float(summary["wall_clock_s"])
    method = summary["method"]
    if summary["algo"] != "ppo":
        method += f"-{summary['algo']}"
    return RunResult(
        name=run_dir.name,
        env=summary["env_id"],
        method=method,
        seed=int(summary["seed"]),
        solved=solved,
        steps=steps,
        seconds=seconds,
        taie=_taie_rows(method, summary.get("taie")),
        interventions=summary.get("interventions"),
        ci_round_seconds=list(summary.get("ci_round_seconds") or []),
        curve=(steps_axis, success),
    )


def _taie_rows(method: str, taie: float | list[float] | None) -> dict[str, float]:
    """TAIE as table rows: one for the method, or one per head (SAI's multi-head attention)."""
    if taie is None:
        return {}
    if isinstance(taie, list):
        return {f"{method}:head-{k}": float(v) for k, v in enumerate(taie, start=1)}
    return {method: float(taie)}


@dataclass
class Cell:
    """Mean and spread of one number over the seeds of one (task, method)."""

    values: list[float]
    lower_bound: bool = False
    """Some runs did not solve: the mean counts their budget and is a lower bound."""

    @property
    def mean(self) -> float:
        return float(np.mean(self.values))

    @property
    def std(self) -> float:
        return float(np.std(self.values, ddof=1)) if len(self.values) > 1 else math.nan

    def format(self, unit: Callable[[float], str]) -> str:
        text = unit(self.mean)
        if len(self.values) > 1:
            text += f" ± {unit(self.std)}"
        return ("> " if self.lower_bound else "") + text


def _kilo(value: float) -> str:
    return f"{value / 1000:.1f}k"


def _secs(value: float) -> str:
    return f"{value:.0f} s" if value >= 10 else f"{value:.1f} s"


def _plain(value: float) -> str:
    return f"{value:.2f}"


def _ordered_methods(methods: Iterable[str]) -> list[str]:
    def key(method: str) -> tuple[int, str]:
        base = method.split(":")[0].removesuffix("-a2c").removesuffix("-dmc")
        return (METHOD_ORDER.index(base) if base in METHOD_ORDER else len(METHOD_ORDER), method)

    return sorted(set(methods), key=key)


def aggregate(runs: Sequence[RunResult]) -> list[dict[str, Any]]:
    """One row per (env, method): runs, solved, and mean/std of each number (aggregate.csv)."""
    rows = []
    envs = sorted({r.env for r in runs})
    for env in envs:
        for method in _ordered_methods(r.method for r in runs if r.env == env):
            group = [r for r in runs if r.env == env and r.method == method]
            steps = _cell(group, lambda r: r.steps)
            seconds = _cell(group, lambda r: r.seconds)
            taie = [r.taie[method] for r in group if method in r.taie]
            interventions = [r.interventions for r in group if r.interventions is not None]
            rows.append(
                {
                    "env": env,
                    "method": method,
                    "runs": len(group),
                    "solved": sum(r.solved for r in group),
                    "steps_mean": steps.mean,
                    "steps_std": steps.std,
                    "seconds_mean": seconds.mean,
                    "seconds_std": seconds.std,
                    "taie_mean": float(np.mean(taie)) if taie else math.nan,
                    "interventions_mean": (
                        float(np.mean(interventions)) if interventions else math.nan
                    ),
                }
            )
    return rows


def _cell(group: Sequence[RunResult], value: Callable[[RunResult], float]) -> Cell:
    return Cell([float(value(r)) for r in group], lower_bound=not all(r.solved for r in group))


def _markdown_table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def _task_table(
    runs: Sequence[RunResult],
    value: Callable[[RunResult], float],
    unit: Callable[[float], str],
    paper: dict[str, dict[str, str]] | None = None,
    paper_unit: str = "",
) -> str:
    """Methods × tasks, each cell mean ± std over seeds (and the paper's number beside it)."""
    envs = sorted({r.env for r in runs})
    rows = []
    for method in _ordered_methods(r.method for r in runs):
        row = [method]
        for env in envs:
            group = [r for r in runs if r.env == env and r.method == method]
            text = _cell(group, value).format(unit) if group else "–"
            if group and not all(r.solved for r in group):
                text += f" ({sum(r.solved for r in group)}/{len(group)} solved)"
            reported = (paper or {}).get(method, {}).get(env)
            if reported is not None:
                text += f" (paper {reported}{paper_unit})"
            row.append(text)
        rows.append(row)
    return _markdown_table(["method", *map(env_label, envs)], rows)


def _taie_table(runs: Sequence[RunResult]) -> str | None:
    labels = _ordered_methods(label for r in runs for label in r.taie)
    if not labels:
        return None
    envs = sorted({r.env for r in runs if r.taie})
    rows = []
    for label in labels:
        row = [label]
        for env in envs:
            values = [r.taie[label] for r in runs if r.env == env and label in r.taie]
            text = Cell(values).format(_plain) if values else "–"
            reported = PAPER_TABLE2.get(label, {}).get(env)
            row.append(text + (f" (paper {reported})" if reported else ""))
        rows.append(row)
    return _markdown_table(["TAIE", *map(env_label, envs)], rows)


def _ci_table(runs: Sequence[RunResult]) -> str | None:
    causal = [r for r in runs if r.ci_round_seconds or r.interventions]
    if not causal:
        return None
    header = ["task", "method", "interventions", *(f"round {k}" for k in _rounds(causal))]
    rows = []
    for (env, method), group in _groups(causal):
        seconds = _mean_round_seconds(group)
        rows.append(
            [
                env_label(env),
                method,
                _plain(float(np.mean([r.interventions or 0 for r in group]))),
                *(_secs(s) if math.isfinite(s) else "–" for s in seconds),
                *["–"] * (len(header) - 3 - len(seconds)),
            ]
        )
    return _markdown_table(header, rows)


def _rounds(runs: Sequence[RunResult]) -> range:
    most = max(len(r.ci_round_seconds) for r in runs)
    return range(1, min(most, CI_ROUNDS_SHOWN) + 1)


def _groups(runs: Sequence[RunResult]) -> list[tuple[tuple[str, str], list[RunResult]]]:
    keys = sorted({(r.env, r.method) for r in runs})
    return [(key, [r for r in runs if (r.env, r.method) == key]) for key in keys]


def _mean_round_seconds(group: Sequence[RunResult]) -> list[float]:
    """Mean seconds of CI round k over the runs that reached it, k = 1..10."""
    most = min(CI_ROUNDS_SHOWN, max(len(r.ci_round_seconds) for r in group))
    return [
        float(np.mean([r.ci_round_seconds[k] for r in group if len(r.ci_round_seconds) > k]))
        for k in range(most)
    ]


# ---------------------------------------------------------------------------------- figures
def _save(figure: plt.Figure, path: Path) -> None:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=120, bbox_inches="tight")
    plt.close(figure)
    atomic_write_bytes(path, buffer.getvalue())


def plot_steps_to_solve(runs: Sequence[RunResult], path: Path) -> None:
    """Fig. 5: grouped bars of mean steps to solve per task and method (hatched: > budget)."""
    envs = sorted({r.env for r in runs})
    methods = _ordered_methods(r.method for r in runs)
    width = 0.8 / len(methods)
    figure, axes = plt.subplots(figsize=(max(6, 1.6 * len(envs)), 3.5))
    for i, method in enumerate(methods):
        label: str | None = method  # on the method's first bar only
        for j, env in enumerate(envs):
            group = [r for r in runs if r.env == env and r.method == method]
            if not group:
                continue
            cell = _cell(group, lambda r: r.steps)
            axes.bar(
                j + (i - (len(methods) - 1) / 2) * width,
                cell.mean / 1000,
                width,
                yerr=None if math.isnan(cell.std) else cell.std / 1000,
                color=f"C{i}",
                hatch="//" if cell.lower_bound else None,
                edgecolor="black" if cell.lower_bound else None,
                label=label,
            )
            label = None
    axes.set_xticks(range(len(envs)), [env_label(e) for e in envs])
    axes.set_ylabel("env steps to solve (thousand)")
    axes.set_title("Samples to solve, mean ± std over seeds (hatched: not all solved)")
    axes.legend(fontsize="small", ncols=min(len(methods), 5))
    _save(figure, path)


def plot_learning_curves(runs: Sequence[RunResult], path: Path) -> None:
    """Success rate vs env steps per task: mean over seeds, band = ± std.

    A run that stopped early (``--stop-on-solve``) keeps its last success rate afterwards.
    """
    envs = sorted({r.env for r in runs})
    columns = min(4, len(envs))
    rows = math.ceil(len(envs) / columns)
    figure, axes = plt.subplots(
        rows, columns, figsize=(4 * columns, 3 * rows), squeeze=False, sharey=True
    )
    for ax, env in zip(axes.flat, envs, strict=False):
        methods = _ordered_methods(r.method for r in runs if r.env == env)
        for method in methods:
            group = [r for r in runs if r.env == env and r.method == method]
            steps = np.linspace(0, max(int(r.curve[0][-1]) for r in group), 200)
            curves = np.array([np.interp(steps, *r.curve, left=0.0) for r in group])
            color = f"C{_ordered_methods(r.method for r in runs).index(method)}"
            ax.plot(steps, curves.mean(axis=0), color=color, label=method)
            ax.fill_between(
                steps,
                curves.mean(axis=0) - curves.std(axis=0),
                curves.mean(axis=0) + curves.std(axis=0),
                color=color,
                alpha=0.2,
            )
        ax.set_title(env_label(env))
        ax.set_xlabel("env steps")
        ax.legend(fontsize="small")
    for ax in axes[:, 0]:
        ax.set_ylabel("success rate (last 100 episodes)")
    for ax in list(axes.flat)[len(envs) :]:
        ax.set_visible(False)
    _save(figure, path)


def plot_ci_rounds(runs: Sequence[RunResult], path: Path) -> None:
    """Fig. 7: wall-clock seconds of each of the first CI rounds, mean over seeds."""
    figure, axes = plt.subplots(figsize=(6, 3.5))
    for (env, method), group in _groups([r for r in runs if r.ci_round_seconds]):
        seconds = _mean_round_seconds(group)
        axes.plot(
            range(1, len(seconds) + 1), seconds, marker="o", label=f"{method}, {env_label(env)}"
        )
    axes.set_xlabel("CI round")
    axes.set_ylabel("wall-clock (s)")
    axes.set_title(f"CI round wall-clock, first {CI_ROUNDS_SHOWN} rounds")
    axes.legend(fontsize="small")
    _save(figure, path)


# ------------------------------------------------------------------------------ App. J data
def interventions_section(results: Path, out: Path) -> str | None:
    """Table and plot of benchmarks/interventions.py's results (App. J); None if absent."""
    try:
        records = json.loads(results.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    searches = ("t-hci", "hci", "fine-grained")
    rows = []
    figure, axes = plt.subplots(figsize=(5, 3.5))
    for i, search in enumerate(searches):
        sizes, counts, projected = [], [], []
        for record in records:
            result = record[search]
            if result.get("skipped"):
                projected.append((record["num_codes"], result["projected_interventions"]))
            else:
                sizes.append(record["num_codes"])
                counts.append(result["interventions"])
        axes.plot(sizes, counts, marker="o", color=f"C{i}", label=search)
        if projected:
            axes.plot(*zip(*projected, strict=True), "o", mfc="none", color=f"C{i}")
    for record in records:
        rows.append(
            [
                str(record["num_codes"]),
                *(_search_cell(record[search]) for search in searches),
                str(record["bound_t_hci"]),
            ]
        )
    axes.set(xscale="log", yscale="log", xlabel="|O|", ylabel="interventions")
    axes.set_title("Interventions as |O| grows (hollow: projected)")
    axes.legend(fontsize="small")
    _save(figure, out / "interventions.png")
    table = _markdown_table(
        ["\\|O\\|", "T-HCI", "HCI", "fine-grained", "T-HCI bound (Prop. 3)"], rows
    )
    return (
        f"From `{results}` (`benchmarks/interventions.py`): interventions, search seconds and "
        f"whether the planted causes were recovered exactly.\n\n{table}\n\n"
        "![interventions](interventions.png)"
    )


def _search_cell(result: dict[str, Any]) -> str:
    if result.get("skipped"):
        return f"skipped (~{result['projected_interventions']} projected)"
    exact = "exact" if result["exact"] else "not exact"
    return f"{result['interventions']} ({result['seconds']:.0f} s, {exact})"


# ------------------------------------------------------------------------------------ report
def _csv_bytes(rows: Sequence[dict[str, Any]]) -> bytes:
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(rows[0]) if rows else ["empty"])
    writer.writeheader()
    writer.writerows(rows)
    return text.getvalue().encode()


DEFAULT_INTERVENTIONS = Path("benchmarks/results/interventions.json")


def write_report(
    root: Path, out: Path | None = None, interventions: Path = DEFAULT_INTERVENTIONS
) -> Path:
    """Write report.md, the CSVs and the PNGs for the runs under `root`; returns report.md."""
    runs, unfinished = load_runs(root)
    if not runs:
        raise ThciError(
            f"none of the {len(unfinished)} runs under {root} has finished yet; "
            "wait for thci bench (or rerun it) before reporting"
        )
    out = out or root / "report"
    out.mkdir(parents=True, exist_ok=True)
    run_rows = [
        {
            "run": r.name,
            "env": r.env,
            "method": r.method,
            "seed": r.seed,
            "solved": r.solved,
            "steps": r.steps,
            "seconds": round(r.seconds, 3),
            "taie": ";".join(f"{k}={v}" for k, v in r.taie.items()),
            "interventions": r.interventions,
            "ci_rounds": len(r.ci_round_seconds),
        }
        for r in runs
    ]
    atomic_write_bytes(out / "runs.csv", _csv_bytes(run_rows))
    atomic_write_bytes(out / "aggregate.csv", _csv_bytes(aggregate(runs)))
    ci_rows = [
        {"env": r.env, "method": r.method, "seed": r.seed, "round": k, "seconds": s}
        for r in runs
        for k, s in enumerate(r.ci_round_seconds, start=1)
    ]
    atomic_write_bytes(out / "ci_rounds.csv", _csv_bytes(ci_rows))

    plot_steps_to_solve(runs, out / "steps_to_solve.png")
    plot_learning_curves(runs, out / "learning_curves.png")
    sections = [
        f"# thci report: {root}\n\n{len(runs)} finished runs"
        + (f", {len(unfinished)} not finished (not counted)" if unfinished else "")
        + ". Cells are mean ± std over seeds; a run that did not solve counts with its whole "
        'budget, which makes the cell a lower bound ("> ...").',
        "## Samples to solve (Fig. 5)\n\nEnvironment steps until the success rate over the "
        "last 100 episodes reached 0.9. The paper gives these only as bars (Fig. 5), so no "
        "reported numbers are shown.\n\n"
        + _task_table(runs, lambda r: r.steps, _kilo)
        + "\n\n![steps to solve](steps_to_solve.png)",
        "## Wall-clock to solve (Table 1)\n\nSeconds of training (CI included) until solved, "
        "on this machine; the paper's seconds (its hardware) beside ours.\n\n"
        + _task_table(runs, lambda r: r.seconds, _secs, PAPER_TABLE1, " s"),
    ]
    ci_table = _ci_table(runs)
    if ci_table is not None:
        plot_ci_rounds(runs, out / "ci_rounds.png")
        sections.append(
            "## CI rounds (Fig. 7) and interventions (App. J)\n\nMean interventions per run "
            f"and mean wall-clock of the first {CI_ROUNDS_SHOWN} CI rounds.\n\n"
            f"{ci_table}\n\n![CI rounds](ci_rounds.png)"
        )
    taie_table = _taie_table(runs)
    if taie_table is not None:
        sections.append(
            "## TAIE (Table 2)\n\nTimely averaged inference error of the trained agent's "
            "weights against the human labels (0 is perfect); the paper's values beside.\n\n"
            + taie_table
        )
    sections.append(
        "## Learning curves (App. G)\n\nSuccess rate over the last 100 episodes, mean ± std "
        "over seeds.\n\n![learning curves](learning_curves.png)"
    )
    benchmark = interventions_section(interventions, out)
    if benchmark is not None:
        sections.append(f"## Interventions as |O| grows (App. J)\n\n{benchmark}")
    report = out / "report.md"
    atomic_write_bytes(report, ("\n\n".join(sections) + "\n").encode())
    return report

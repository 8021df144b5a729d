"""The ``thci`` command line: train, evaluate, taie, envs, demo, bench, report, heatmap.

User mistakes raise :class:`~thci.errors.ThciError`; :func:`main` prints its one line and
exits with status 2, so no traceback is ever shown for them.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import tyro

from thci.config import TrainConfig, Trajectories
from thci.errors import ThciError


@dataclass
class EvaluateArgs:
    """Play episodes with a trained run's latest checkpoint."""

    run_dir: Annotated[Path, tyro.conf.Positional]
    """Run directory written by `thci train`."""
    episodes: int = 100
    """Episodes to play."""
    greedy: bool = False
    """Take the most likely action instead of sampling from the policy (the trained one)."""
    seed: int = 10_000
    """Seed of the evaluation episodes."""


@dataclass
class TaieArgs:
    """TAIE (the paper's Table 2) of a trained run's memory against info["causal"]; writes
    RUN_DIR/taie.json."""

    run_dir: Annotated[Path, tyro.conf.Positional]
    """Run directory written by `thci train` (method t-hci, hci, sai, hai or oracle)."""
    trajectories: Trajectories = "auto"
    """expert: the environment's expert_action() (pi*, as the paper defines TAIE; the BabyAI
    levels have one); greedy: the run's own policy; auto: expert when the env has one."""
    episodes: int = 100
    """Trajectories to average over."""
    seed: int = 20_000
    """Seed of the episodes."""


@dataclass
class EnvsArgs:
    """List thci's built-in environments."""


@dataclass
class DemoArgs:
    """Run a demonstration of the method."""

    name: Annotated[Literal["confounding"], tyro.conf.Positional] = "confounding"
    """confounding: the key-to-door example of the paper's Fig. 1."""
    episodes: int = 4000
    seed: int = 0


@dataclass
class BenchArgs:
    """Train a grid of runs (env × method × algo × seed) under one root; resumes when rerun."""

    preset: str | None = None
    """Grid preset: paper-maze, paper-babyai, ablation, or their -quick variants."""
    grid: Path | None = None
    """Grid file (TOML or YAML) instead of a preset; see docs/experiments.md."""
    root: Path | None = None
    """Root directory of the runs (default: runs/bench/<preset or grid file name>)."""
    backend: Literal["local", "ray"] = "local"
    """local: worker processes on this machine; ray: Ray tasks (RAY_ADDRESS picks the cluster)."""
    workers: int | None = None
    """Runs at a time (default: cores // torch threads per run)."""


@dataclass
class ReportArgs:
    """Tables and figures of a grid of runs (the paper's Fig. 5, 7, Tables 1, 2)."""

    root: Annotated[Path, tyro.conf.Positional]
    """Root directory of the runs (the --root of `thci bench`)."""
    out: Path | None = None
    """Where to write report.md, CSVs and PNGs (default: ROOT/report)."""
    interventions: Path = Path("benchmarks/results/interventions.json")
    """Results of benchmarks/interventions.py to include (App. J), when the file exists."""


@dataclass
class HeatmapArgs:
    """Fig. 8: colour the cells of an episode by the memory's weight on each observation."""

    run_dir: Annotated[Path, tyro.conf.Positional]
    """Run directory written by `thci train` (or `thci bench`), on a Maze or BabyAI level."""
    out: Path | None = None
    """PNG to write (default: RUN_DIR/heatmap.png)."""
    seed: int = 10_000
    """Seed of the episode."""
    trajectories: Trajectories = "auto"
    """Whose episode: the environment's expert (expert_action(); the BabyAI levels have one),
    the run's greedy agent, or auto: the expert when the environment has one."""


def format_table(rows: dict[str, Any]) -> str:
    """Two-column text table of `rows`."""
    width = max(len(k) for k in rows)
    lines = [f"{'':-<{width}}-+-{'':-<24}"]
    for key, value in rows.items():
        if isinstance(value, float):
            value = f"{value:.4g}"
        lines.append(f"{key:<{width}} | {value}")
    return "\n".join([lines[0], *lines[1:], lines[0]])


Command = (
    TrainConfig | EvaluateArgs | TaieArgs | EnvsArgs | DemoArgs | BenchArgs | ReportArgs
) | HeatmapArgs


def run_command(args: Command) -> None:
    """Execute one parsed command."""
    if isinstance(args, TrainConfig):
        from thci.rl.trainer import train

        summary = train(args)
        print(format_table(summary))
    elif isinstance(args, EvaluateArgs):
        from thci.rl.evaluate import evaluate

        print(format_table(evaluate(args.run_dir, args.episodes, args.greedy, args.seed)))
    elif isinstance(args, TaieArgs):
        from thci.rl.evaluate import taie_of_run

        print(format_table(taie_of_run(args.run_dir, args.episodes, args.trajectories, args.seed)))
    elif isinstance(args, DemoArgs):
        from thci.experiments.demo import confounding_demo

        if args.episodes < 10:
            raise ThciError(f"--episodes must be at least 10, got {args.episodes}")
        print(confounding_demo(args.episodes, args.seed).format())
    elif isinstance(args, BenchArgs):
        bench(args)
    elif isinstance(args, ReportArgs):
        from thci.experiments.report import write_report

        report = write_report(args.root, args.out, args.interventions)
        print(f"wrote {report} and, beside it: ", end="")
        print(", ".join(sorted(p.name for p in report.parent.iterdir() if p != report)))
    elif isinstance(args, HeatmapArgs):
        from thci.experiments.heatmap import heatmap

        print(f"wrote {heatmap(args.run_dir, args.out, args.seed, args.trajectories)}")
    else:
        import gymnasium as gym

        import thci  # noqa: F401  (registers the environments)

        for env_id in sorted(k for k in gym.registry if k.startswith("thci/")):
            print(env_id)


def bench(args: BenchArgs) -> None:
    """`thci bench`: run the grid, then say what happened and how to see the results."""
    from thci.experiments.bench import run_bench
    from thci.experiments.presets import PRESETS, load_grid

    if (args.preset is None) == (args.grid is None):
        raise ThciError(f"pass --preset NAME ({', '.join(PRESETS)}) or --grid FILE, not both")
    grid = load_grid(args.preset or str(args.grid))
    root = args.root or Path("runs") / "bench" / Path(grid.name).stem
    result = run_bench(grid, root, args.backend, args.workers)
    print(
        f"grid {grid.name} in {root}: {len(result.skipped)} already finished, "
        f"{len(result.started)} started, {len(result.resumed)} resumed, "
        f"{len(result.failed)} failed"
    )
    if result.failed:
        raise ThciError(
            f"{len(result.failed)} runs failed (first: {next(iter(result.failed.items()))}); "
            f"see {root / 'logs'} and rerun the command to retry them"
        )
    print(f"next: thci report {root}")


def _flag_value(argv: list[str], name: str) -> str | None:
    """The value of ``--name VALUE`` or ``--name=VALUE`` (hyphens or underscores) in `argv`."""
    spellings = {name, name.replace("-", "_")}
    for i, arg in enumerate(argv):
        flag, equals, value = arg.partition("=")
        if flag in spellings:
            return value if equals else (argv[i + 1] if i + 1 < len(argv) else None)
    return None


def saved_train_config(argv: list[str]) -> TrainConfig | None:
    """For ``thci train --resume --run-dir DIR``: the settings saved in DIR, which the command
    line then only overrides, so that those two flags are enough to continue a run (and a
    flag that may not change on resume still gets the "config differs" error). None for any
    other command, or when DIR holds no config (the trainer then says what is missing)."""
    if not argv or argv[0] != "train" or "--resume" not in argv:
        return None
    run_dir = _flag_value(argv, "--run-dir")
    if run_dir is None:
        return None
    from thci.experiments.run_dir import RunDirectory

    run = RunDirectory(Path(run_dir))
    return run.read_config() if run.config_path.is_file() else None


def main(argv: list[str] | None = None) -> None:
    """Entry point of the ``thci`` console script."""
    argv = sys.argv[1:] if argv is None else argv
    try:
        saved = saved_train_config(argv)
        if saved is not None:
            args: Any = tyro.cli(
                TrainConfig, args=argv[1:], default=saved, prog="thci train", description=""
            )
        else:
            args = tyro.extras.subcommand_cli_from_dict(
                {
                    "train": TrainConfig,
                    "evaluate": EvaluateArgs,
                    "taie": TaieArgs,
                    "envs": EnvsArgs,
                    "demo": DemoArgs,
                    "bench": BenchArgs,
                    "report": ReportArgs,
                    "heatmap": HeatmapArgs,
                },
                args=argv,
                prog="thci",
                description="History-based RL with causal memory (T-HCI).",
            )
        run_command(args)
    except ThciError as exc:
        print(f"thci: error: {exc}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()

"""`thci bench`: train a grid of runs (env × method × algo × seed) under one root directory.

The paper compares methods over many tasks and 10 trials each (Fig. 5, Table 1, Table 2);
this module runs such a grid (:mod:`thci.experiments.presets`) and `thci report` summarizes it.
Every run is an ordinary `thci train` run directory ``ROOT/<env>__<method>__<algo>__s<seed>``,
trained by :func:`thci.rl.trainer.train` in a worker process, so a grid resumes the way a
single run does: finished runs (a valid ``summary.json``) are skipped, killed ones continue
from their checkpoint.

Backends: ``local`` runs the grid in worker processes on this machine (``cores // torch
threads`` at a time); ``ray`` submits the same runs as Ray tasks
(``pip install thci[ray]``), to a local Ray instance or to the cluster named by
``RAY_ADDRESS`` (the root must then be on a filesystem every node sees). Each run's output goes
to ``ROOT/logs/<run>.log``; the terminal shows one progress bar for the whole grid.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import fcntl
import multiprocessing
import os
import shutil
import sys
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from tqdm import tqdm

from thci.config import TrainConfig
from thci.envs.factory import resolve_env_spec
from thci.errors import ThciError
from thci.experiments.presets import PAPER_METHOD_NAMES, Grid, available_methods
from thci.experiments.run_dir import RunDirectory
from thci.workers import die_with_parent

Backend = Literal["local", "ray"]
POLL_SECONDS = 1.0


@dataclass
class PlannedRun:
    """One run of the grid and what the bench does with it."""

    name: str
    config: TrainConfig  # run_dir set
    action: Literal["skip", "resume", "start"]

    @property
    def run_dir(self) -> Path:
        assert self.config.run_dir is not None
        return self.config.run_dir


@dataclass
class BenchResult:
    """Names of the runs by what happened to them."""

    skipped: list[str] = field(default_factory=list)
    """Finished before this call (valid summary.json)."""
    resumed: list[str] = field(default_factory=list)
    started: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    """Run name -> one-line reason."""
    unavailable_methods: list[str] = field(default_factory=list)
    """Methods of the grid that this install of thci does not have (their runs were left out)."""


def run_name(config: TrainConfig) -> str:
    """Directory name of a grid run: <env>__<method>__<algo>__s<seed>."""
    env = config.env.split(":")[-1].replace("/", "_")
    return f"{env}__{config.method}__{config.algo}__s{config.seed}"


def plan(grid: Grid, root: Path) -> tuple[list[PlannedRun], list[str]]:
    """The grid's runs under `root`, each marked skip / resume / start, and the methods left out.

    A method of the paper that this install does not have yet is left out (the caller notes
    it); any other unknown method is a mistake.

    Raises ThciError for an unknown environment, an invalid setting, or a run directory that
    was trained with other settings than the grid's.
    """
    if root.exists() and not root.is_dir():
        raise ThciError(f"--root {root} is a file; choose a directory")
    for env in grid.envs:
        resolve_env_spec(env)
    known = available_methods()
    unknown = [m for m in grid.methods if m not in known and m not in PAPER_METHOD_NAMES]
    if unknown:
        raise ThciError(f"grid {grid.name}: unknown methods {unknown}; choose from {known}")
    unavailable = [m for m in grid.methods if m not in known]
    planned = []
    for config in grid.configs():
        if config.method in unavailable:
            continue
        name = run_name(config)
        config.run_dir = root / name
        try:
            config.validate()
        except ThciError as exc:
            raise ThciError(f"grid {grid.name}, run {name}: {exc}") from None
        planned.append(PlannedRun(name, config, _action(config)))
    return planned, unavailable


def _action(config: TrainConfig) -> Literal["skip", "resume", "start"]:
    assert config.run_dir is not None
    run = RunDirectory(config.run_dir)
    if not run.config_path.is_file():
        return "start"
    saved = run.read_config()
    differing = saved.differences(config)
    if differing:
        raise ThciError(
            f"{run.path} was trained with other settings ({', '.join(differing)} differ from the "
            "grid's): use another --root, or delete that run directory"
        )
    summary = run.read_summary()
    if summary is not None and saved.total_steps >= config.total_steps:
        return "skip"
    return "resume" if run.checkpoint_path.is_file() else "start"


def default_workers(configs: list[TrainConfig]) -> int:
    """Runs at a time such that workers × torch threads ≤ the cores this process may use."""
    return max(1, available_cores() // _threads_per_run(configs))


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one, e.g. Linux)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def _threads_per_run(configs: list[TrainConfig]) -> int:
    return max((max(c.torch_threads, c.ci_threads) for c in configs), default=1)


def run_bench(
    grid: Grid, root: Path, backend: Backend = "local", workers: int | None = None
) -> BenchResult:
    """Train every run of `grid` under `root` that has not finished yet; see the module doc."""
    runs, unavailable = plan(grid, root)
    result = BenchResult(unavailable_methods=unavailable)
    for method in unavailable:
        tqdm.write(
            f"note: method {method!r} is not in this install of thci (it has "
            f"{', '.join(available_methods())}); its runs are left out"
        )
    result.skipped = [r.name for r in runs if r.action == "skip"]
    todo = [r for r in runs if r.action != "skip"]
    if not todo:
        return result
    threads = _threads_per_run([r.config for r in todo])
    if workers is None:
        workers = default_workers([r.config for r in todo])
    if workers <= 0:
        raise ThciError(f"--workers must be a positive integer, got {workers}")
    cores = available_cores()
    if backend == "local" and workers * threads > cores:
        raise ThciError(
            f"--workers {workers} × {threads} torch threads per run exceeds this machine's "
            f"{cores} cores; pass --workers {max(1, cores // threads)} or fewer"
        )
    (root / "logs").mkdir(parents=True, exist_ok=True)
    with _executor(backend, workers, threads) as submit:
        _execute(runs, todo, submit, result)
    return result


def _execute(
    runs: list[PlannedRun],
    todo: list[PlannedRun],
    submit: Callable[[PlannedRun], concurrent.futures.Future],
    result: BenchResult,
) -> None:
    """Submit `todo`, show one progress bar over all `runs` until every future is done."""
    futures = {submit(run): run for run in todo}
    finished = {r.name for r in runs if r.action == "skip"}
    bar = tqdm(
        total=sum(r.config.total_steps for r in runs), unit="step", dynamic_ncols=True, desc="grid"
    )
    pending = set(futures)
    try:
        while pending:
            bar.n = sum(
                r.config.total_steps if r.name in finished else _steps_done(r.run_dir) for r in runs
            )
            bar.set_postfix_str(
                f"{len(finished)}/{len(runs)} runs done, {len(result.failed)} failed"
            )
            done, pending = concurrent.futures.wait(pending, timeout=POLL_SECONDS)
            for future in done:
                run = futures[future]
                finished.add(run.name)
                error = future.exception() or future.result()
                if error is None:
                    (result.resumed if run.action == "resume" else result.started).append(run.name)
                    tqdm.write(f"{run.name}: {_describe(run)}")
                else:
                    result.failed[run.name] = str(error)
                    tqdm.write(f"{run.name}: FAILED: {error} (log: {_log_path(run)})")
        bar.n = bar.total
        bar.set_postfix_str(f"{len(runs)} runs done, {len(result.failed)} failed")
    except KeyboardInterrupt:
        for future in futures:
            future.cancel()
        raise ThciError(
            "interrupted; run the same command again to resume the grid "
            "(finished runs are kept, the others continue from their checkpoints)"
        ) from None
    finally:
        bar.close()


def _describe(run: PlannedRun) -> str:
    summary = RunDirectory(run.run_dir).read_summary() or {}
    time_s = summary.get("wall_clock_s", float("nan"))
    if summary.get("solved"):
        return f"solved at {summary['steps_to_solve']} steps ({time_s:.0f} s)"
    return f"not solved in {summary.get('total_env_steps')} steps ({time_s:.0f} s)"


def _steps_done(run_dir: Path) -> int:
    """global_step of the last row of the run's metrics.csv (0 before the first update)."""
    try:
        lines = (run_dir / "metrics.csv").read_text().splitlines()
    except OSError:
        return 0
    if len(lines) < 2:
        return 0
    try:
        return int(lines[-1].split(",")[lines[0].split(",").index("global_step")])
    except (ValueError, IndexError):
        return 0  # a row being written right now


def _log_path(run: PlannedRun) -> Path:
    return run.run_dir.parent / "logs" / f"{run.name}.log"


@contextlib.contextmanager
def _executor(
    backend: Backend, workers: int, threads: int
) -> Iterator[Callable[[PlannedRun], concurrent.futures.Future]]:
    """A function that submits one run to `backend` and returns its future."""
    if backend == "local":
        pool = concurrent.futures.ProcessPoolExecutor(
            max_workers=workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=die_with_parent,
        )
        try:
            yield lambda run: pool.submit(train_in_worker, run.config.to_dict(), run.action)
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
    elif backend == "ray":
        ray = _import_ray()
        started_here = not ray.is_initialized()
        if started_here:
            ray.init(**_ray_init_args(workers * threads))
        task = ray.remote(num_cpus=threads, max_retries=0)(train_in_worker)
        refs = []

        def submit(run: PlannedRun) -> concurrent.futures.Future:
            refs.append(task.remote(run.config.to_dict(), run.action))
            return refs[-1].future()

        try:
            yield submit
        finally:
            for ref in refs:
                with contextlib.suppress(Exception):
                    ray.cancel(ref, force=True)  # no-op for finished tasks
            if started_here:
                ray.shutdown()
    else:
        raise ThciError(f"--backend must be local or ray, got {backend!r}")


def _import_ray() -> Any:
    try:
        import ray
    except ImportError:
        raise ThciError(
            "--backend ray needs Ray: pip install 'thci[ray]' (or use --backend local)"
        ) from None
    return ray


def _ray_init_args(num_cpus: int) -> dict[str, Any]:
    """ray.init arguments: connect to RAY_ADDRESS if set, else a quiet local instance.

    The local instance has no dashboard, no usage reporting and no token authentication (which
    would write ~/.ray/auth_token); its logs stay in Ray's temporary directory.
    """
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    if os.environ.get("RAY_ADDRESS"):
        return {"log_to_driver": False}
    os.environ.setdefault("RAY_AUTH_MODE", "disabled")
    return {
        "num_cpus": num_cpus,
        "include_dashboard": False,
        "log_to_driver": False,  # each run's output is in ROOT/logs/<run>.log
        "configure_logging": False,
    }


def train_in_worker(config_data: dict[str, Any], action: str) -> str | None:
    """Train one run in a worker process; None when it finished, else the one-line reason.

    Runs in a spawned process (local backend) or a Ray worker. A lock file keeps two benches on
    the same root from training the same run; the run's output goes to ROOT/logs/<run>.log.
    """
    from thci.rl.trainer import train

    config = TrainConfig.from_dict(config_data)
    config.resume = action == "resume"
    assert config.run_dir is not None
    root, name = config.run_dir.parent, config.run_dir.name
    (root / ".locks").mkdir(exist_ok=True)
    with (root / ".locks" / f"{name}.lock").open("w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return "another process is training this run"
        # Only under the lock: a run killed before its first checkpoint has nothing to keep,
        # but a run directory without one may also belong to a run still in progress.
        if action == "start" and config.run_dir.exists():
            shutil.rmtree(config.run_dir)
        with _output_to(root / "logs" / f"{name}.log"):
            try:
                train(config)
            except ThciError as exc:
                print(f"thci: error: {exc}", file=sys.stderr)
                return str(exc)
            except Exception as exc:
                traceback.print_exc()
                return f"{type(exc).__name__}: {exc}"
    return None


@contextlib.contextmanager
def _output_to(path: Path) -> Iterator[None]:
    """Send this process's stdout and stderr (file descriptors 1 and 2) to `path`, appending."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with path.open("a") as log:
        log.write(f"--- {time.strftime('%Y-%m-%d %H:%M:%S')}\n")
        log.flush()
        os.dup2(log.fileno(), 1)
        os.dup2(log.fileno(), 2)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])

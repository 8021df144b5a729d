"""`thci bench`: a tiny grid through the local backend (and Ray), resume, presets, bad input."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from thci.cli import main
from thci.config import TrainConfig
from thci.errors import ThciError
from thci.experiments import bench
from thci.experiments.bench import run_bench
from thci.experiments.presets import PRESETS, grid_from_dict, load_grid
from thci.experiments.run_dir import RunDirectory
from thci.rl.trainer import TIMING_FIELDS

TINY = {
    "envs": ["thci/PaperMaze-L1-v0", "thci/PaperMaze-L2-v0"],
    "methods": ["lstm", "t-hci"],
    "seeds": [1, 2],
    "train": {"total_steps": 256, "num_envs": 4, "num_steps": 32, "num_minibatches": 4},
}
WORKERS = min(2, bench.available_cores())


def summaries(root: Path) -> dict[str, dict]:
    return {p.parent.name: json.loads(p.read_text()) for p in sorted(root.glob("*/summary.json"))}


@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory) -> Path:
    """The tiny grid (2 envs x 2 methods x 2 seeds, 256 steps each), trained once."""
    root = tmp_path_factory.mktemp("bench") / "tiny"
    result = run_bench(grid_from_dict("tiny", TINY), root, workers=WORKERS)
    assert len(result.started) == 8 and not result.failed
    return root


def test_tiny_grid_trains_every_run(tiny_root):
    found = summaries(tiny_root)
    expected = {
        f"thci_PaperMaze-L{level}-v0__{method}__ppo__s{seed}"
        for level in (1, 2)
        for method in ("lstm", "t-hci")
        for seed in (1, 2)
    }
    assert set(found) == expected
    for name, summary in found.items():
        assert name == (
            f"{summary['env_id'].replace('/', '_')}__{summary['method']}__ppo__s{summary['seed']}"
        )
        assert summary["total_env_steps"] == 256
    assert (tiny_root / "logs" / f"{min(expected)}.log").stat().st_size > 0


def test_rerun_skips_finished_runs(tiny_root):
    mtimes = {p: p.stat().st_mtime_ns for p in tiny_root.glob("*/summary.json")}
    result = run_bench(grid_from_dict("tiny", TINY), tiny_root, workers=WORKERS)
    assert len(result.skipped) == 8
    assert not result.started and not result.resumed
    assert {p: p.stat().st_mtime_ns for p in mtimes} == mtimes


def test_killed_grid_resumes_from_checkpoint(tmp_path):
    grid_file = tmp_path / "grid.toml"
    grid_file.write_text(
        'envs = ["thci/PaperMaze-L1-v0"]\nmethods = ["lstm"]\nseeds = [1, 2]\n'
        "[train]\ntotal_steps = 1024\nnum_envs = 4\nnum_steps = 32\nnum_minibatches = 4\n"
        "checkpoint_every = 2\n"
    )
    root = tmp_path / "root"
    first, second = (root / f"thci_PaperMaze-L1-v0__lstm__ppo__s{s}" for s in (1, 2))
    command = [sys.executable, "-m", "thci.cli", "bench", "--grid", str(grid_file)]
    command += ["--root", str(root), "--workers", "1"]
    with (tmp_path / "bench.log").open("w") as log:
        process = subprocess.Popen(command, start_new_session=True, stdout=log, stderr=log)
        deadline = time.monotonic() + 120
        while not (second / "checkpoint.pt").is_file() and time.monotonic() < deadline:
            assert process.poll() is None, (tmp_path / "bench.log").read_text()
            time.sleep(0.02)
        os.killpg(process.pid, signal.SIGKILL)  # the bench and its worker, mid-run
        process.wait()
    assert (first / "summary.json").is_file() and not (second / "summary.json").exists()
    finished_at = (first / "summary.json").stat().st_mtime_ns
    checkpoint_update = RunDirectory(second).load_checkpoint()["update"]
    rows_before = (second / "metrics.csv").read_text().splitlines()[: checkpoint_update + 1]

    result = run_bench(load_grid(str(grid_file)), root, workers=1)

    assert result.skipped == [first.name] and result.resumed == [second.name]
    assert (first / "summary.json").stat().st_mtime_ns == finished_at
    # The resumed run kept the rows written before its checkpoint (their wall-clock times
    # would differ had it started over) and went on to the full budget.
    rows_after = (second / "metrics.csv").read_text().splitlines()
    assert rows_after[: checkpoint_update + 1] == rows_before
    assert len(rows_after) == 1 + 1024 // 128
    assert json.loads((second / "summary.json").read_text())["total_env_steps"] == 1024


def test_method_not_in_this_install_is_noted_and_left_out(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(bench, "available_methods", lambda: ("lstm", "gru"))
    grid = grid_from_dict("g", {**TINY, "envs": ["thci/PaperMaze-L1-v0"], "seeds": [1]})
    runs, unavailable = bench.plan(grid, tmp_path)
    assert unavailable == ["t-hci"]
    assert [r.config.method for r in runs] == ["lstm"]
    with pytest.raises(ThciError, match="unknown methods"):
        bench.plan(grid_from_dict("g", {**TINY, "methods": ["lstmm"]}), tmp_path)


def test_overrides_apply_per_env_then_algo_then_method():
    grid = grid_from_dict(
        "g",
        {
            **TINY,
            "algos": ["ppo", "a2c"],
            "env_overrides": {TINY["envs"][1]: {"ent_coef": 0.05, "total_steps": 512}},
            "algo_overrides": {"a2c": {"ent_coef": 0.02, "num_steps": 64}},
            "method_overrides": {"t-hci": {"num_steps": 16}},
        },
    )
    settings = {
        (c.env[-5:-3], c.algo, c.method): (c.ent_coef, c.num_steps, c.total_steps)
        for c in grid.configs()
    }
    default_ent = TrainConfig().ent_coef
    assert settings[("L1", "ppo", "lstm")] == (default_ent, 32, 256)
    assert settings[("L2", "ppo", "lstm")] == (0.05, 32, 512)
    assert settings[("L2", "a2c", "lstm")] == (0.02, 64, 512)  # the algo's wins over the env's
    assert settings[("L2", "a2c", "t-hci")] == (0.02, 16, 512)  # the method's over the algo's
    with pytest.raises(ThciError, match="algo_overrides names 'dmc', which is not in the grid"):
        grid_from_dict("g", {**TINY, "algo_overrides": {"dmc": {"ent_coef": 0.1}}})


def test_presets_name_the_papers_methods_and_are_valid():
    for name in PRESETS:
        grid = load_grid(name)
        assert grid.configs()
        for config in grid.configs():
            config.validate()
    assert set(load_grid("paper-maze").methods) == {"lstm", "gru", "nm", "wmg", "hci", "t-hci"}
    assert set(load_grid("ablation").methods) == {"t-hci", "sai", "hai", "oracle"}
    assert len(load_grid("paper-maze").seeds) == 10
    quick = load_grid("paper-maze-quick").configs()
    assert len(quick) < len(load_grid("paper-maze").configs())
    level3 = [c for c in quick if c.env == "thci/PaperMaze-L3-v0"]
    assert all(c.exploration == "episodic-count" and c.count_key == "agent_pos" for c in level3)
    assert all(c.ent_coef == 0.03 and c.num_steps == 128 for c in level3)
    assert all((c.update_epochs, c.num_minibatches) == (4, 4) for c in level3 if c.method == "nm")
    paper_nm = [c for c in load_grid("paper-maze").configs() if c.method == "nm"]
    assert paper_nm and all(c.update_epochs == 4 for c in paper_nm)
    comparison = load_grid("maze-lstm-vs-thci").configs()
    assert len(comparison) == 4 * 2 * 5
    hard = [c for c in comparison if c.env.endswith(("L3-v0", "L4-v0"))]
    assert all(c.total_steps == 2_000_000 for c in hard)
    assert {c.total_steps for c in comparison if c not in hard} == {200_000}
    # one set of settings on every level: the count-memory bonus applies to t-hci, lstm
    # counts places alone
    assert all(c.exploration == "episodic-count" and c.count_memory for c in comparison)
    budgets = {c.method: c.total_steps for c in level3}
    assert budgets["lstm"] == 300_000 and budgets["wmg"] == 4_000  # the method's budget wins
    algos = {c.algo: c for c in load_grid("babyai-algos").configs() if c.seed == 1}
    assert set(algos) == {"ppo", "a2c", "dmc"}
    assert (algos["ppo"].ent_coef, algos["a2c"].ent_coef, algos["dmc"].ent_coef) == (
        0.03,
        0.01,
        0.03,
    )
    assert algos["a2c"].num_steps == 128 and algos["dmc"].dmc_buffer_episodes == 2048


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (["--preset", "paper-mazes"], "neither a preset"),
        (["--preset", "paper-maze", "--grid", "x.toml"], "not both"),
        ([], "--preset NAME"),
        (["--grid", "{dir}/bad.toml"], "not valid TOML"),
        (["--grid", "{dir}/env.toml"], "unknown environment id"),
        (["--grid", "{dir}/key.toml"], "unknown settings ['total_step']"),
        (["--grid", "{dir}/progress.toml"], "['progress'] (set by the grid itself)"),
        (["--grid", "{dir}/seed.toml"], "'seeds' must be a non-empty list of int"),
        (["--grid", "{dir}/over.toml"], "method_overrides names 'gru', which is not in the grid"),
        (["--grid", "{dir}/ok.toml", "--workers", "999"], "exceeds this machine's"),
    ],
)
def test_bad_bench_input_is_one_line(tmp_path, capsys, argv, fragment):
    (tmp_path / "bad.toml").write_text("envs = [\n")
    base = 'methods = ["lstm"]\nseeds = [1]\n'
    (tmp_path / "env.toml").write_text(base + 'envs = ["thci/NoSuchMaze-v0"]\n')
    (tmp_path / "key.toml").write_text(
        base + 'envs = ["thci/PaperMaze-L1-v0"]\n[train]\ntotal_step = 5\n'
    )
    (tmp_path / "progress.toml").write_text(
        base + 'envs = ["thci/PaperMaze-L1-v0"]\n[train]\nprogress = false\n'
    )
    (tmp_path / "seed.toml").write_text('envs = ["x"]\nmethods = ["lstm"]\nseeds = []\n')
    (tmp_path / "ok.toml").write_text(base + 'envs = ["thci/PaperMaze-L1-v0"]\n')
    (tmp_path / "over.toml").write_text(
        base + 'envs = ["x"]\n[method_overrides.gru]\ntotal_steps = 5\n'
    )
    argv = [a.replace("{dir}", str(tmp_path)) for a in argv]
    with pytest.raises(SystemExit) as exc:
        main(["bench", "--root", str(tmp_path / "root"), *argv])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1 and fragment in err, err
    assert not (tmp_path / "root").exists()


def test_ray_backend_finishes_the_same_runs(tiny_root, tmp_path):
    pytest.importorskip("ray")
    root = tmp_path / "ray"
    result = run_bench(grid_from_dict("tiny", TINY), root, backend="ray", workers=WORKERS)
    assert not result.failed
    local, remote = summaries(tiny_root), summaries(root)
    assert set(remote) == set(local)

    def without_timing(summary: dict) -> dict:
        return {k: v for k, v in summary.items() if k not in TIMING_FIELDS}

    assert {k: without_timing(v) for k, v in remote.items()} == {
        k: without_timing(v) for k, v in local.items()
    }

"""`thci report`: numbers recomputed independently from the run files, figures, bad input."""

import csv
import json
import statistics
from pathlib import Path

import pytest

from thci.cli import main
from thci.errors import ThciError
from thci.experiments.report import write_report

MAZE1, MAZE3 = "thci/PaperMaze-L1-v0", "thci/PaperMaze-L3-v0"


def fake_run(
    root: Path,
    env: str,
    method: str,
    seed: int,
    solve_at: int | None,
    budget: int = 10_000,
    taie: float | list[float] | None = None,
    ci_seconds: tuple[float, ...] = (),
) -> None:
    """A finished run directory: metrics every 500 steps at 100 steps/s, and its summary."""
    run = root / f"{env.replace('/', '_')}__{method}__ppo__s{seed}"
    run.mkdir(parents=True)
    (run / "config.json").write_text("{}")
    last = solve_at if solve_at is not None else budget
    with (run / "metrics.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["update", "global_step", "success_rate", "wall_clock_s"])
        for update, step in enumerate(range(500, last + 500, 500), start=1):
            writer.writerow([update, step, min(1.0, step / last), step / 100 + seed])
    summary = {
        "env_id": env,
        "method": method,
        "algo": "ppo",
        "seed": seed,
        "total_env_steps": last,
        "solved": solve_at is not None,
        "steps_to_solve": solve_at,
        "taie": taie,
        "interventions": 7 * len(ci_seconds) if ci_seconds else None,
        "ci_round_seconds": list(ci_seconds),
        "wall_clock_s": last / 100 + seed + 0.5,
    }
    (run / "summary.json").write_text(json.dumps(summary))


@pytest.fixture
def root(tmp_path) -> Path:
    root = tmp_path / "runs"
    fake_run(root, MAZE1, "lstm", 1, 2000)
    fake_run(root, MAZE1, "lstm", 2, 3500)
    fake_run(root, MAZE1, "lstm", 3, 5000)
    fake_run(root, MAZE1, "t-hci", 1, 1500, taie=0.0, ci_seconds=(4.0, 2.0, 1.0))
    fake_run(root, MAZE1, "t-hci", 2, None, taie=0.5, ci_seconds=(6.0, 2.0))
    fake_run(root, MAZE3, "sai", 1, None, taie=[0.1, 0.2, 0.3, 0.4])
    fake_run(root, MAZE3, "sai", 2, 9000, taie=[0.3, 0.2, 0.1, 0.0])
    (root / "unfinished").mkdir()
    (root / "unfinished" / "config.json").write_text("{}")
    return root


def recomputed(root: Path) -> dict[tuple[str, str], dict]:
    """Steps and seconds to solve per (env, method), straight from summary.json and metrics.csv."""
    groups: dict[tuple[str, str], dict] = {}
    for path in root.glob("*/summary.json"):
        summary = json.loads(path.read_text())
        with (path.parent / "metrics.csv").open() as f:
            rows = list(csv.DictReader(f))
        if summary["solved"]:
            steps = summary["steps_to_solve"]
            seconds = next(float(r["wall_clock_s"]) for r in rows if int(r["global_step"]) >= steps)
        else:
            steps, seconds = summary["total_env_steps"], summary["wall_clock_s"]
        group = groups.setdefault((summary["env_id"], summary["method"]), {"steps": []})
        group["steps"].append(steps)
        group.setdefault("seconds", []).append(seconds)
        group.setdefault("solved", []).append(summary["solved"])
    return groups


def test_aggregate_numbers_equal_those_recomputed_from_the_runs(root):
    report = write_report(root, interventions=root / "absent.json")
    with (report.parent / "aggregate.csv").open() as f:
        rows = {(r["env"], r["method"]): r for r in csv.DictReader(f)}
    expected = recomputed(root)
    assert set(rows) == set(expected)
    for key, group in expected.items():
        row = rows[key]
        assert int(row["runs"]) == len(group["steps"])
        assert int(row["solved"]) == sum(group["solved"])
        assert float(row["steps_mean"]) == pytest.approx(statistics.mean(group["steps"]))
        assert float(row["steps_std"]) == pytest.approx(statistics.stdev(group["steps"]))
        assert float(row["seconds_mean"]) == pytest.approx(statistics.mean(group["seconds"]))
        assert float(row["seconds_std"]) == pytest.approx(statistics.stdev(group["seconds"]))
    assert float(rows[(MAZE1, "t-hci")]["taie_mean"]) == pytest.approx(0.25)
    assert float(rows[(MAZE1, "t-hci")]["interventions_mean"]) == pytest.approx((21 + 14) / 2)


def test_report_tables_show_lower_bounds_paper_numbers_and_heads(root):
    text = write_report(root, interventions=root / "absent.json").read_text()
    assert "1 not finished" in text
    # Fig. 5: LSTM solved in 2000, 3500, 5000 steps; T-HCI solved one of two (1500, > 10000).
    assert "| lstm | 3.5k ± 1.5k |" in text
    assert "> 5.8k ± 6.0k (1/2 solved)" in text
    # Table 1 with the paper's seconds beside ours; Table 2 per attention head.
    assert "(paper 277 s)" in text and "(paper 4627 s)" in text
    assert "| sai:head-1 | – | 0.20 ± 0.14 (paper 0.17) |" in text
    # Fig. 7: round 1 of T-HCI averages 4 s and 6 s; round 3 only one run reached.
    assert "| Maze L1 | t-hci | 17.50 | 5.0 s | 2.0 s | 1.0 s |" in text
    for png in ("steps_to_solve.png", "learning_curves.png", "ci_rounds.png"):
        assert (root / "report" / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "Interventions as |O| grows" not in text  # no benchmark results given


def test_interventions_benchmark_is_included_when_present(root, tmp_path):
    results = tmp_path / "interventions.json"
    record = {"num_codes": 100, "bound_t_hci": 36, "fine-grained": {"skipped": True}}
    record["fine-grained"]["projected_interventions"] = 1100
    record["t-hci"] = {"interventions": 28, "seconds": 15.1, "exact": True}
    record["hci"] = {"interventions": 107, "seconds": 52.5, "exact": True}
    results.write_text(json.dumps([record]))
    text = write_report(root, tmp_path / "out", results).read_text()
    assert "| 100 | 28 (15 s, exact) | 107 (52 s, exact) | skipped (~1100 projected) | 36 |" in text
    assert (tmp_path / "out" / "interventions.png").is_file()


@pytest.mark.parametrize("make", ["empty", "unfinished", "missing"])
def test_report_of_nothing_is_a_one_line_error(tmp_path, capsys, make):
    root = tmp_path / "root"
    if make != "missing":
        root.mkdir()
    if make == "unfinished":
        (root / "run").mkdir()
        (root / "run" / "config.json").write_text("{}")
    with pytest.raises(SystemExit) as exc:
        main(["report", str(root)])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1 and err.startswith("thci: error:")
    with pytest.raises(ThciError):
        write_report(root)

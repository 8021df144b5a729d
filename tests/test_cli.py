"""`thci train` / `thci evaluate` end to end: bad input, determinism, resume, learning."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from thci.cli import main
from thci.config import TrainConfig
from thci.rl.trainer import TIMING_FIELDS

FAST = ["--no-progress", "--num-envs", "8", "--num-steps", "32"]


def run_cli(args: list[str]) -> int:
    try:
        main(args)
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


def train(tmp_path: Path, name: str, *extra: str) -> dict:
    run_dir = tmp_path / name
    code = run_cli(["train", "--run-dir", str(run_dir), *FAST, *extra])
    assert code == 0
    return json.loads((run_dir / "summary.json").read_text())


def without_timing(summary: dict) -> dict:
    return {k: v for k, v in summary.items() if k not in TIMING_FIELDS}


def assert_one_line_error(capsys, code: int, *fragments: str) -> None:
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1, err
    assert err.startswith("thci: error: ")
    for fragment in fragments:
        assert fragment in err


@pytest.mark.parametrize(
    ("args", "fragments"),
    [
        (["--env", "thci/PaperMaze-L5-v0"], ["unknown environment id", "thci/PaperMaze-L"]),
        (["--env", "NoSuchThing-v9"], ["unknown environment id"]),
        (["--env", "Pendulum-v1"], ["Discrete action space"]),
        (["--learning-rate", "-1"], ["--learning-rate"]),
        (["--gamma", "1.5"], ["--gamma"]),
        (["--num-envs", "0"], ["--num-envs"]),
        (["--num-minibatches", "32"], ["--num-minibatches"]),
        (["--resume"], ["--run-dir"]),
        (["--count-memory"], ["--count-memory", "--exploration"]),
        (["--cell-layout", "0", "0", "3"], ["--cell-layout", "three integers"]),
        (["--encoder", "grid"], ["--encoder grid", "--encoder flat"]),
        (["--algo", "dmc", "--dmc-target-every", "8"], ["--dmc-target-every", "--dmc-n-step"]),
    ],
)
def test_bad_train_input_is_one_line_and_writes_nothing(tmp_path, capsys, args, fragments):
    run_dir = tmp_path / "run"
    base = [] if "--resume" in args else ["--run-dir", str(run_dir)]
    code = run_cli(["train", *base, "--total-steps", "256", *FAST, *args])
    assert_one_line_error(capsys, code, *fragments)
    assert not run_dir.exists()


def test_existing_run_dir_needs_resume(tmp_path, capsys):
    train(tmp_path, "run", "--total-steps", "256")
    before = (tmp_path / "run" / "summary.json").read_text()
    code = run_cli(["train", "--run-dir", str(tmp_path / "run"), *FAST, "--total-steps", "256"])
    assert_one_line_error(capsys, code, "already exists", "--resume")
    assert (tmp_path / "run" / "summary.json").read_text() == before


def test_resume_with_different_config_is_refused(tmp_path, capsys):
    train(tmp_path, "run", "--total-steps", "256")
    code = run_cli(
        [
            "train",
            "--run-dir",
            str(tmp_path / "run"),
            "--resume",
            *FAST,
            "--total-steps",
            "512",
            "--learning-rate",
            "0.01",
        ]
    )
    assert_one_line_error(capsys, code, "config differs", "learning_rate")


def test_resume_takes_the_saved_settings_so_run_dir_and_total_steps_are_enough(tmp_path):
    settings = ["--seed", "4", "--learning-rate", "0.002", "--ent-coef", "0.03"]
    reference = train(tmp_path, "reference", "--total-steps", "512", *settings)
    train(tmp_path, "run", "--total-steps", "256", *settings)
    # No FAST flags and no settings: the run's own (8 envs x 32 steps, lr 0.002, ...) apply.
    code = run_cli(["train", "--resume", "--run-dir", str(tmp_path / "run"), "--total-steps=512"])
    assert code == 0
    resumed = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert resumed["updates"] == 2 and resumed["total_env_steps"] == 512
    assert without_timing(resumed) == without_timing(reference)


@pytest.mark.parametrize("damage", ["truncate", "garbage", "pickle", "renamed"])
def test_damaged_checkpoint_is_refused(tmp_path, capsys, damage):
    train(tmp_path, "run", "--total-steps", "256")
    checkpoint = tmp_path / "run" / "checkpoint.pt"
    if damage == "truncate":
        checkpoint.write_bytes(checkpoint.read_bytes()[: checkpoint.stat().st_size // 2])
    elif damage == "garbage":
        checkpoint.write_bytes(b"not a checkpoint at all")
    elif damage == "pickle":  # an arbitrary pickled object must not be loaded (weights_only)
        torch.save({"format": "thci-checkpoint-v1", "payload": Path("x")}, checkpoint)
    else:  # a model of another layout (e.g. another thci version's)
        saved = torch.load(checkpoint, weights_only=True)
        agent = saved["agent"]
        agent["encoder.9.weight"] = agent.pop(next(iter(agent)))
        torch.save(saved, checkpoint)
    code = run_cli(
        ["train", "--run-dir", str(tmp_path / "run"), "--resume", *FAST, "--total-steps", "512"]
    )
    assert_one_line_error(capsys, code, "checkpoint")
    code = run_cli(["evaluate", str(tmp_path / "run"), "--episodes", "4"])
    assert_one_line_error(capsys, code, "checkpoint")


def test_evaluate_unknown_dir(tmp_path, capsys):
    code = run_cli(["evaluate", str(tmp_path / "missing")])
    assert_one_line_error(capsys, code, "not found")


def test_same_seed_same_result_and_other_seed_differs(tmp_path):
    a = train(tmp_path, "a", "--total-steps", "3000", "--seed", "7")
    b = train(tmp_path, "b", "--total-steps", "3000", "--seed", "7")
    train(tmp_path, "c", "--total-steps", "3000", "--seed", "8")
    assert without_timing(a) == without_timing(b)
    assert (tmp_path / "a" / "metrics.csv").read_text().count(
        "\n"
    ) == 1 + 12  # header + ceil(3000 / 256) updates
    metrics = [
        (tmp_path / name / "metrics.csv").read_text().splitlines() for name in ("a", "b", "c")
    ]
    strip = [[",".join(row.split(",")[:-1]) for row in rows] for rows in metrics]  # drop clock
    assert strip[0] == strip[1]
    assert strip[0] != strip[2]


def test_resume_after_kill_gives_the_uninterrupted_result(tmp_path):
    args = ["--total-steps", "8192", "--checkpoint-every", "3", "--seed", "3", *FAST]
    reference = train(tmp_path, "reference", *args)

    run_dir = tmp_path / "killed"
    cmd = [sys.executable, "-m", "thci.cli", "train", "--run-dir", str(run_dir), *args]
    process = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    metrics = run_dir / "metrics.csv"
    deadline = time.time() + 120
    while time.time() < deadline and process.poll() is None:
        if metrics.is_file() and metrics.read_text().count("\n") >= 6:  # past the checkpoint
            break
        time.sleep(0.02)
    assert process.poll() is None, "the run finished before it could be killed"
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    assert not (run_dir / "summary.json").exists()
    assert (run_dir / "checkpoint.pt").is_file()

    code = run_cli(["train", "--run-dir", str(run_dir), "--resume", *args])
    assert code == 0
    resumed = json.loads((run_dir / "summary.json").read_text())
    assert without_timing(resumed) == without_timing(reference)
    strip = [
        [",".join(r.split(",")[:-1]) for r in (d / "metrics.csv").read_text().splitlines()]
        for d in (tmp_path / "reference", run_dir)
    ]
    assert strip[0] == strip[1]


def test_lstm_ppo_learns_paper_maze_level1(tmp_path):
    summary = train(
        tmp_path,
        "learn",
        "--total-steps",
        "80000",
        "--stop-on-solve",
        "--seed",
        "1",
        "--num-envs",
        "16",
        "--num-steps",
        "64",
    )
    assert summary["solved"] is True
    assert summary["success_rate_last100"] >= 0.9
    code = run_cli(["evaluate", str(tmp_path / "learn"), "--episodes", "64"])
    assert code == 0
    evaluation = json.loads((tmp_path / "learn" / "evaluation.json").read_text())
    assert evaluation["episodes"] == 64
    # Memoryless play can reach at most 0.5: the indicator is only visible at the start.
    assert evaluation["success_rate"] >= 0.8


def assert_stop_and_resume_matches(
    tmp_path: Path,
    reference: dict,
    args: list[str],
    round_in_flight: bool = False,
    total: int = 4096,
) -> None:
    """A run stopped at total / 2 steps and resumed to `total` ends like `reference` (`total`
    at once); with `round_in_flight`, the stopped checkpoint holds a CI round not yet applied."""
    train(tmp_path, "split", "--total-steps", str(total // 2), *args)
    if round_in_flight:
        checkpoint = torch.load(tmp_path / "split" / "checkpoint.pt", weights_only=True)
        assert checkpoint["ci"]["round_in_flight"] is not None
        assert checkpoint["ci"]["pool"]["first_episode"] > 0  # the pool has slid
    resume = ["--run-dir", str(tmp_path / "split"), "--resume", "--total-steps", str(total)]
    assert run_cli(["train", *resume, *FAST, *args]) == 0
    resumed = json.loads((tmp_path / "split" / "summary.json").read_text())
    assert without_timing(resumed) == without_timing(reference)


T_HCI_FAST = [
    "--method",
    "t-hci",
    "--ci-every",
    "512",
    "--ci-lag",
    "512",
    "--ci-first-lag",
    "1024",
    "--ci-min-episodes",
    "50",
    "--ci-min-rewarded-episodes",
    "0",
    "--ci-base-steps",
    "30",
    "--ci-warm-steps",
    "10",
    "--ci-pool-episodes",
    "50",  # slides within the run: folds must follow the episodes across a resume
    "--seed",
    "5",
]


def test_t_hci_run_reports_ci_and_resumes_to_the_same_result(tmp_path):
    reference = train(tmp_path, "reference", "--total-steps", "4096", *T_HCI_FAST)
    assert reference["ci_rounds"] >= 2
    assert reference["interventions"] == sum(reference["interventions_per_round"]) > 0
    assert reference["observation_space_size"] >= 10
    assert 0.0 <= reference["taie"] <= 1.0
    final = reference["final_ci"]  # a round on the final pool, reported, never applied
    assert final["pool_episodes"] >= 50 and final["observation_space_size"] >= 10
    assert final["interventions"] > 0 and 0.0 <= final["taie"] <= 1.0
    assert reference["final_ci_seconds"] > 0
    rounds = (tmp_path / "reference" / "ci_rounds.csv").read_text().splitlines()
    assert len(rounds) == 1 + reference["ci_rounds"]
    rows = [dict(zip(rounds[0].split(","), r.split(","), strict=True)) for r in rounds[1:]]
    lags = [int(r["applied_step"]) - int(r["global_step"]) for r in rows]
    assert lags == [1024] + [512] * (len(rows) - 1)  # --ci-first-lag, then --ci-lag
    log = json.loads((tmp_path / "reference" / "ci_interventions.json").read_text())
    assert len(log) == reference["interventions"]

    # Stopped at 2048 steps, a round is in flight: the resumed run computes it again.
    assert_stop_and_resume_matches(tmp_path, reference, T_HCI_FAST, round_in_flight=True)

    # The worker process changes where a round runs, never what it finds or when it applies.
    in_process = train(
        tmp_path, "in-process", "--total-steps", "4096", "--no-ci-async", *T_HCI_FAST
    )
    assert without_timing(in_process) == without_timing(reference)
    assert in_process["ci_blocking_s"] >= in_process["ci_wall_clock_s"] * 0.9

    # A round due at once (first lag 0) runs in the worker beside the update's training and
    # the next rollout, neither of which could use its gate: the same result as one process
    # computing it on the spot, and as a first lag of one update (256 steps), whose gate
    # applies at that update too. (Whether the RL loop then waits depends on the machine.)
    def with_first_lag(lag: str) -> list[str]:
        args = list(T_HCI_FAST)
        args[args.index("--ci-first-lag") + 1] = lag
        return args

    at_once = train(tmp_path, "at-once", "--total-steps", "2048", *with_first_lag("0"))
    one_core = train(
        tmp_path, "one-core", "--total-steps", "2048", "--no-ci-async", *with_first_lag("0")
    )
    one_update = train(tmp_path, "one-update", "--total-steps", "2048", *with_first_lag("256"))
    assert at_once["ci_rounds"] >= 1
    assert without_timing(at_once) == without_timing(one_core) == without_timing(one_update)
    applied = [
        [row.split(",")[:2] + row.split(",")[9:10] for row in rows[1:]]
        for rows in (
            (tmp_path / name / "ci_rounds.csv").read_text().splitlines()
            for name in ("at-once", "one-update")
        )
    ]
    assert applied[0] == applied[1]  # round, pool step, applied step


@pytest.mark.parametrize("algo", ["a2c", "dmc"])
def test_a2c_and_dmc_train_the_causal_memory_and_resume_to_the_same_result(
    tmp_path, monkeypatch, algo
):
    # (and the optional per-intervention fine-tuning of the effect predictor)
    from thci.causal.loop import CausalInferenceLoop
    from thci.rl.dmc import DMC

    # Record each applied round's kept set and each DMC refit, in the order they happen.
    events: list[tuple[str, tuple[int, ...]]] = []
    step, refit = CausalInferenceLoop.step, DMC.refit

    def recording_step(self, *args, **kwargs):
        record = step(self, *args, **kwargs)
        if record is not None:
            events.append(("round", tuple(self.last_result.causal.tolist())))
        return record

    def recording_refit(self, *args, **kwargs):
        events.append(("refit", ()))
        return refit(self, *args, **kwargs)

    monkeypatch.setattr(CausalInferenceLoop, "step", recording_step)
    monkeypatch.setattr(DMC, "refit", recording_refit)
    args = [*T_HCI_FAST, "--algo", algo, "--ci-finetune-steps", "5"]
    reference = train(tmp_path, "reference", "--total-steps", "4096", *args)
    assert reference["algo"] == algo and reference["ci_rounds"] >= 1
    # DMC refits Q right after a round whose kept set differs from the last one, never else.
    expected, last = [], None
    for kind, kept in events:
        if kind == "round":
            expected.append(("round", kept))
            if algo == "dmc" and kept != last:
                expected.append(("refit", ()))
            last = kept
    assert events == expected
    assert reference["episodes"] > 0
    # DMC carries unfinished episodes across rollouts: they must survive the checkpoint too
    assert_stop_and_resume_matches(tmp_path, reference, args)


def test_count_key_missing_from_info_is_refused_before_anything_is_written(tmp_path, capsys):
    run_dir = tmp_path / "run"
    code = run_cli(
        [
            "train",
            "--env",
            "CartPole-v1",
            "--exploration",
            "count",
            "--count-key",
            "agent_pos",
            "--run-dir",
            str(run_dir),
            "--total-steps",
            "256",
            *FAST,
        ]
    )
    assert_one_line_error(capsys, code, "agent_pos")
    assert not run_dir.exists()


@pytest.mark.parametrize(
    "exploration",
    [["count"], ["episodic-count"], ["episodic-count", "--count-memory", "--method", "oracle"]],
)
def test_count_exploration_adds_bonus_and_resumes_to_the_same_result(tmp_path, exploration):
    args = [
        "--exploration",
        *exploration,
        "--count-key",
        "agent_pos",
        "--count-beta",
        "0.5",
        "--seed",
        "2",
    ]
    reference = train(tmp_path, "reference", "--total-steps", "2048", *args)
    plain = train(tmp_path, "plain", "--total-steps", "2048", "--seed", "2")
    assert without_timing(reference) != without_timing(plain)  # the bonus changes learning
    assert_stop_and_resume_matches(tmp_path, reference, args, total=2048)


def test_count_memory_leaves_a_memory_that_keeps_everything_to_count_places(tmp_path):
    args = ["--exploration", "episodic-count", "--count-key", "agent_pos", "--seed", "3"]
    plain = train(tmp_path, "plain", "--total-steps", "2048", *args)
    with_memory = train(tmp_path, "memory", "--total-steps", "2048", *args, "--count-memory")
    assert without_timing(plain) == without_timing(with_memory)


def test_atomic_writes_get_the_mode_of_a_plain_open(tmp_path):
    from thci.experiments.run_dir import atomic_write_bytes

    plain, atomic = tmp_path / "plain", tmp_path / "atomic"
    plain.write_bytes(b"x")
    atomic_write_bytes(atomic, b"x")
    assert atomic.stat().st_mode & 0o777 == plain.stat().st_mode & 0o777


def test_a_config_written_before_the_empty_start_resumes_with_a_full_memory():
    current = TrainConfig(method="t-hci", ci_lag=4096).to_dict()
    assert TrainConfig.from_dict(current) == TrainConfig(method="t-hci", ci_lag=4096)
    old = {k: v for k, v in current.items() if k not in ("ci_initial_memory", "ci_first_lag")}
    restored = TrainConfig.from_dict(old)
    # as such runs ran: everything in memory until the first gate, ci_lag steps after its round
    assert restored.ci_initial_memory == "full" and restored.ci_first_lag == 4096


def test_a_config_written_before_substitutes_and_whole_batch_fits_resumes_without_them():
    current = TrainConfig(method="t-hci").to_dict()
    assert current["ci_substitutes"] and current["ci_whole_batch_steps"] > 0
    assert current["hai_read"] == "max"
    new_fields = ("ci_substitutes", "ci_whole_batch_steps", "hai_read")
    restored = TrainConfig.from_dict({k: v for k, v in current.items() if k not in new_fields})
    assert not restored.ci_substitutes and restored.ci_whole_batch_steps == 0
    assert restored.hai_read == "mean"

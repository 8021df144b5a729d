"""Throughput of the environments and of training, beside sb3-contrib.

``--suite maze`` (default) measures, on PaperMaze-L1 with random actions:
  * env steps/s of the single gymnasium env, of gymnasium's SyncVectorEnv over it, and of
    thci's native batched env at several batch sizes;
  * training env steps/s of thci's LSTM-PPO and GRU-PPO, and of sb3-contrib's RecurrentPPO
    with the same LSTM size, the same number of environments and rollout length, in this run.

``--suite babyai`` measures, on BabyAI-L1 (minigrid, image observations): env steps/s of
the single env and of the vector env thci trains on, beside training env steps/s of LSTM with
each algorithm (PPO, A2C, DMC), so the trainer's overhead over minigrid's own step shows.

Run by hand (sb3-contrib is the optional ``bench`` extra):

    .venv/bin/pip install -e ".[bench]"
    .venv/bin/python benchmarks/throughput.py                 # -> results/throughput.json
    .venv/bin/python benchmarks/throughput.py --suite babyai  # -> results/throughput_babyai.json

Prints a table.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode, SyncVectorEnv

import thci
from thci.config import TrainConfig
from thci.envs.factory import make_vector_env
from thci.envs.paper_maze import PaperMazeEnv, PaperMazeVectorEnv
from thci.rl.trainer import train

ENV_ID = "thci/PaperMaze-L1-v0"
BABYAI_ID = "thci/BabyAI-L1-v0"
RESULTS = Path(__file__).parent / "results"


def single_env_rate(steps: int) -> float:
    """Env steps/s of one PaperMazeEnv stepped in a Python loop."""
    env = PaperMazeEnv(level=1)
    env.reset(seed=0)
    actions = np.random.default_rng(0).integers(0, 4, steps)
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    return steps / (time.perf_counter() - start)


def vector_env_rate(envs: gym.vector.VectorEnv, calls: int) -> float:
    """Env steps/s of a vector env (num_envs steps per call)."""
    envs.reset(seed=0)
    actions = np.random.default_rng(0).integers(0, 4, (calls, envs.num_envs))
    start = time.perf_counter()
    for batch in actions:
        envs.step(batch)
    rate = calls * envs.num_envs / (time.perf_counter() - start)
    envs.close()
    return rate


def thci_training_rate(
    method: str, steps: int, num_envs: int, num_steps: int, env: str = ENV_ID, algo: str = "ppo"
) -> float:
    """Env steps/s of `thci train` (rollouts + updates, no early stop), with the same PPO
    work per rollout as the RecurrentPPO run (4 epochs of 4 minibatches)."""
    with tempfile.TemporaryDirectory() as tmp:
        summary = train(
            TrainConfig(
                env=env,
                algo=algo,
                method=method,
                total_steps=steps,
                num_envs=num_envs,
                num_steps=num_steps,
                update_epochs=4,
                num_minibatches=4,
                run_dir=Path(tmp) / "run",
                progress=False,
            )
        )
    return summary["steps_per_second"]


def sb3_training_rate(steps: int, num_envs: int, num_steps: int) -> float | None:
    """Env steps/s of sb3-contrib's RecurrentPPO with a 64-unit LSTM, or None if absent."""
    try:
        from sb3_contrib import RecurrentPPO
        from stable_baselines3.common.env_util import make_vec_env
    except ImportError:
        return None
    envs = make_vec_env(lambda: PaperMazeEnv(level=1), n_envs=num_envs, seed=0)
    model = RecurrentPPO(
        "MlpLstmPolicy",
        envs,
        n_steps=num_steps,
        batch_size=num_envs * num_steps // 4,
        n_epochs=4,
        policy_kwargs={"lstm_hidden_size": 64},
        seed=0,
        device="cpu",
        verbose=0,
    )
    start = time.perf_counter()
    model.learn(total_timesteps=steps)
    rate = model.num_timesteps / (time.perf_counter() - start)
    envs.close()
    return rate


def babyai_rows(train_steps: int) -> list[tuple[str, float | None]]:
    """Env and training steps/s on BabyAI-L1 (see the module doc)."""
    env = gym.make(BABYAI_ID)
    env.reset(seed=0)
    actions = np.random.default_rng(0).integers(0, env.action_space.n, 20_000)
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    rows: list[tuple[str, float | None]] = [
        ("env: BabyAI-L1 (single, Python loop)", len(actions) / (time.perf_counter() - start))
    ]
    rows.append(
        (
            "env: BabyAI-L1 vector env as trained on x16",
            vector_env_rate(make_vector_env(BABYAI_ID, 16, "auto"), 1_000),
        )
    )
    for algo in ("ppo", "a2c", "dmc"):
        rows.append(
            (
                f"train: thci lstm-{algo} on BabyAI-L1 (16 envs x 64 steps)",
                thci_training_rate("lstm", train_steps, 16, 64, env=BABYAI_ID, algo=algo),
            )
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", choices=("maze", "babyai"), default="maze")
    parser.add_argument("--train-steps", type=int, default=65_536)
    parser.add_argument("--sb3-steps", type=int, default=16_384)
    args = parser.parse_args()
    torch.set_num_threads(1)
    num_envs, num_steps = 16, 64
    if args.suite == "babyai":
        write_and_print(babyai_rows(args.train_steps), "throughput_babyai.json", {})
        return

    rows: list[tuple[str, float | None]] = [
        ("env: PaperMazeEnv (single, Python loop)", single_env_rate(100_000)),
        (
            "env: gymnasium SyncVectorEnv x16",
            vector_env_rate(
                SyncVectorEnv(
                    [lambda: PaperMazeEnv(level=1) for _ in range(16)],
                    autoreset_mode=AutoresetMode.SAME_STEP,
                ),
                5_000,
            ),
        ),
    ]
    for n in (16, 256, 4096, 16384):
        rows.append(
            (
                f"env: native PaperMazeVectorEnv x{n}",
                vector_env_rate(PaperMazeVectorEnv(n, level=1), max(200, 2_000_000 // n)),
            )
        )
    for method in ("lstm", "gru"):
        rows.append(
            (
                f"train: thci {method}-ppo (16 envs x 64 steps)",
                thci_training_rate(method, args.train_steps, num_envs, num_steps),
            )
        )
    rows.append(
        (
            "train: sb3-contrib RecurrentPPO lstm-64 (16 envs x 64 steps)",
            sb3_training_rate(args.sb3_steps, num_envs, num_steps),
        )
    )

    sb3, lstm = rows[-1][1], rows[-3][1]
    speedup = lstm / sb3 if sb3 and lstm else None
    write_and_print(rows, "throughput.json", {"lstm_ppo_speedup_over_recurrent_ppo": speedup})
    if speedup:
        print(f"LSTM-PPO / RecurrentPPO: {speedup:.1f}x")


def write_and_print(rows: list[tuple[str, float | None]], name: str, extra: dict) -> None:
    """Write the rows (with the machine's description) to results/`name`; print a table."""
    results = {
        "thci_version": thci.__version__,
        "torch_version": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "machine": f"{platform.machine()}, {platform.processor() or 'cpu'}, "
        f"python {platform.python_version()}",
        "steps_per_second": {label: rate for label, rate in rows},
        **extra,
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / name).write_text(json.dumps(results, indent=2) + "\n")
    width = max(len(label) for label, _ in rows)
    print(f"{'measurement':<{width}} | env steps/s")
    print(f"{'':-<{width}}-+------------")
    for label, rate in rows:
        shown = "n/a (sb3-contrib missing)" if rate is None else f"{rate:,.0f}"
        print(f"{label:<{width}} | {shown}")
    print(f"written to {RESULTS / name}")


if __name__ == "__main__":
    main()

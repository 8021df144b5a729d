"""Throughput of the maze environments and of recurrent PPO training, beside sb3-contrib.

Measures, on PaperMaze-L1 with random actions:
  * env steps/s of the single gymnasium env, of gymnasium's SyncVectorEnv over it, and of
    thci's native batched env at several batch sizes;
  * training env steps/s of thci's LSTM-PPO and GRU-PPO, and of sb3-contrib's RecurrentPPO
    with the same LSTM size, the same number of environments and rollout length, in this run.

Run by hand (sb3-contrib is the optional ``bench`` extra):

    .venv/bin/pip install -e ".[bench]"
    .venv/bin/python benchmarks/throughput.py

Writes benchmarks/results/throughput.json and prints a table.
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
from thci.envs.paper_maze import PaperMazeEnv, PaperMazeVectorEnv
from thci.rl.trainer import train

ENV_ID = "thci/PaperMaze-L1-v0"
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


def thci_training_rate(method: str, steps: int, num_envs: int, num_steps: int) -> float:
    """Env steps/s of `thci train` (rollouts + PPO updates, no early stop), with the same PPO
    work per rollout as the RecurrentPPO run (4 epochs of 4 minibatches)."""
    with tempfile.TemporaryDirectory() as tmp:
        summary = train(
            TrainConfig(
                env=ENV_ID,
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train-steps", type=int, default=65_536)
    parser.add_argument("--sb3-steps", type=int, default=16_384)
    args = parser.parse_args()
    torch.set_num_threads(1)
    num_envs, num_steps = 16, 64

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

    results = {
        "thci_version": thci.__version__,
        "torch_version": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "machine": f"{platform.machine()}, {platform.processor() or 'cpu'}, "
        f"python {platform.python_version()}",
        "steps_per_second": {name: rate for name, rate in rows},
    }
    sb3, lstm = results["steps_per_second"][rows[-1][0]], rows[-3][1]
    results["lstm_ppo_speedup_over_recurrent_ppo"] = lstm / sb3 if sb3 else None
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "throughput.json").write_text(json.dumps(results, indent=2) + "\n")

    width = max(len(name) for name, _ in rows)
    print(f"{'measurement':<{width}} | env steps/s")
    print(f"{'':-<{width}}-+------------")
    for name, rate in rows:
        print(
            f"{name:<{width}} | {'n/a (sb3-contrib missing)' if rate is None else f'{rate:,.0f}'}"
        )
    if results["lstm_ppo_speedup_over_recurrent_ppo"]:
        print(f"LSTM-PPO / RecurrentPPO: {results['lstm_ppo_speedup_over_recurrent_ppo']:.1f}x")
    print(f"written to {RESULTS / 'throughput.json'}")


if __name__ == "__main__":
    main()

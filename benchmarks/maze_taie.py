"""TAIE of trained T-HCI runs on PaperMaze against the labels and against a sufficient set.

The maze's indicator codes 0 and 1 are complementary (every episode shows exactly one of them
at the start), so a causal memory that keeps only one of them keeps all the information. The
*sufficient set* of a run is the labelled causal codes with the member of {0, 1} the run's CI
eliminated taken out, when it eliminated exactly one of them; otherwise it is the labels.
Labels are never changed: both numbers are reported.

    .venv/bin/python benchmarks/maze_taie.py RUN_DIR [RUN_DIR ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from thci.causal.taie import observation_weights, taie_of_rollout
from thci.envs.factory import make_vector_env
from thci.envs.paper_maze import load_maze_level
from thci.experiments.run_dir import RunDirectory
from thci.rl.rollout import RolloutCollector
from thci.rl.trainer import build_agent

COMPLEMENTARY = (0, 1)


@torch.no_grad()
def run_taie(run_dir: Path, episodes: int = 100) -> dict:
    run = RunDirectory(run_dir)
    config = run.read_config()
    summary = run.read_summary() or {}
    level = int(config.env.split("-L")[1][0])
    labels = set(load_maze_level(level).causal_codes.tolist())
    kept = set(summary.get("causal_observations") or [])
    sufficient = set(labels)
    if len(kept & set(COMPLEMENTARY)) == 1:
        sufficient -= set(COMPLEMENTARY) - kept
    envs = make_vector_env(config.env, 16)
    agent = build_agent(config, envs)
    agent.load_state_dict(run.load_checkpoint()["agent"])
    collector = RolloutCollector(envs, agent, num_steps=128, gamma=0.99, greedy=True)
    collector.reset(config.seed + 20_000)
    against_labels, against_sufficient = [], []
    while sum(len(t) for t in against_labels) < episodes:
        rollout, _ = collector.collect()
        weights = observation_weights(agent, rollout.obs)
        codes = rollout.obs.argmax(dim=-1)
        for target, out in ((labels, against_labels), (sufficient, against_sufficient)):
            truth = torch.as_tensor(np.isin(codes.numpy(), sorted(target)))
            out.append(taie_of_rollout(weights, truth, rollout.episode_starts, rollout.dones))
    envs.close()
    return {
        "run": str(run_dir),
        "kept": sorted(kept),
        "sufficient_set": sorted(sufficient),
        "taie_labels": round(float(torch.cat(against_labels)[:episodes].mean()), 4),
        "taie_sufficient": round(float(torch.cat(against_sufficient)[:episodes].mean()), 4),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+")
    parser.add_argument("--episodes", type=int, default=100)
    args = parser.parse_args()
    torch.set_num_threads(1)
    for run_dir in args.runs:
        print(json.dumps(run_taie(run_dir, args.episodes)))


if __name__ == "__main__":
    main()

"""One T-HCI round on BabyAI pools with a known answer: exact codes against cell-set codes.

The pool comes from a behaviour policy with a known causal structure: a scripted expert that
reads the signpost, then goes to a ball drawn at random (the target or the decoy, 1/2 each),
with a random action instead of the expert's in `--noise` of the steps. Facing a ball pays
iff its colour is the signpost's, so given the transition, what decides the reward is exactly
the signpost views (``info["causal"]``); the doorways, doors and rooms on the way are only
confounded with it. The round is the one training runs (`run_ci_job`: effect predictor with
the reward target, T-HCI search, gate fit), once per discretizer, on the same episodes.

``cell-values`` is the cell-set codes with interventions on cell values (``--ci-units cells``,
thci.causal.units; Z as the BabyAI presets set it, 32).

Reported per discretizer: |Ô|, the signpost codes among them, interventions, seconds, and
how the round's gate decides on *held-out* episodes of the same policy: the share of signpost
views it keeps (recall), of other views it removes, and TAIE over those episodes' steps.

    .venv/bin/python benchmarks/babyai_ci.py [--level 1] [--episodes 600] [--seed 0]
        [--discretizers exact cell-set cell-values]

Writes benchmarks/results/babyai_ci_l{LEVEL}_{EPISODES}.json and prints a table.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

import thci.envs  # noqa: F401  (registers the ids)
from thci.causal.discretize import make_discretizer
from thci.causal.gate import GateSpec
from thci.causal.loop import CIJob, run_ci_job
from thci.causal.predictor import PredictorConfig
from thci.causal.replay import PoolEpisode, pad_episodes
from thci.causal.search import DEFAULT_XI, DEFAULT_Z
from thci.causal.units import cell_units
from thci.envs.babyai import BabyAIExpert
from thci.experiments.presets import BABYAI_TRAIN
from thci.rl.encoders import observation_categories

RESULTS = Path(__file__).parent / "results"
CELL_LAYOUT = (0, 49, 3)


def collect(
    level: int, episodes: int, noise: float, seed: int
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Episodes of the behaviour policy: (observations (L+1, D), actions, rewards, labels)."""
    env = gym.make(f"thci/BabyAI-L{level}-v0")
    rng = np.random.default_rng(seed)
    out = []
    for index in range(episodes):
        obs, info = env.reset(seed=seed * 100_000 + index)
        lv = env.unwrapped
        if rng.random() < 0.5:  # the expert heads for the decoy: a wrong choice, paid 0
            lv.target_ball, lv.decoy_ball = lv.decoy_ball, lv.target_ball
        expert = BabyAIExpert(env)
        views, actions, rewards, labels = [obs], [], [], [info["causal"]]
        done = False
        while not done:
            action = int(rng.integers(6))
            if rng.random() >= noise:
                # A random step may leave the expert's plan unreachable: act randomly then.
                with contextlib.suppress(RuntimeError):
                    action = expert.act()
            obs, reward, terminated, truncated, info = env.step(action)
            views.append(obs)
            actions.append(action)
            rewards.append(reward)
            labels.append(info["causal"])
            done = terminated or truncated
        out.append(
            (np.array(views), np.array(actions), np.array(rewards, np.float32), np.array(labels))
        )
    return out


def one_round(kind: str, train: list, held_out: list, env: gym.Env, seed: int) -> dict:
    """Run a CI round on `train` with discretizer `kind`; score its gate on `held_out`."""
    space = env.observation_space
    units = kind == "cell-values"
    disc = make_discretizer("cell-set" if units else kind, space, cell_layout=CELL_LAYOUT)
    episodes, representatives, signpost_codes = [], {}, set()
    for views, actions, rewards, labels in train:
        codes = disc.encode(views)
        for code, view in zip(codes.tolist(), views, strict=True):
            representatives.setdefault(code, view)
        signpost_codes.update(codes[labels].tolist())
        episodes.append(PoolEpisode(codes, actions, rewards, labels))
    gate_spec = GateSpec(
        int(np.prod(space.shape)),
        observation_categories(space),
        CELL_LAYOUT if kind != "exact" else None,
    )
    job = CIJob(
        pool=pad_episodes(episodes),
        observations=representatives,
        gate_state=gate_spec.build().state_dict(),
        gate=gate_spec,
        num_actions=int(env.action_space.n),
        method="t-hci",
        z=BABYAI_TRAIN["ci_z"] if units else DEFAULT_Z,
        xi=DEFAULT_XI,
        predictor=PredictorConfig(target="reward", seed=seed),
        threads=1,
        units={c: cell_units(v, CELL_LAYOUT) for c, v in representatives.items()}
        if units
        else None,
    )
    started = time.perf_counter()
    outcome = run_ci_job(job)
    seconds = time.perf_counter() - started
    gate = gate_spec.build()
    gate.load_state_dict(outcome.gate_state)
    views = torch.as_tensor(np.concatenate([v for v, *_ in held_out]), dtype=torch.float32)
    labels = np.concatenate([lab for *_, lab in held_out])
    keep = gate.keep(views).numpy()
    causal = set(outcome.result.causal.tolist())
    return {
        "discretizer": kind,
        "observed": len(outcome.result.observed),
        "signpost_codes": len(signpost_codes),
        "kept_codes": len(causal),
        "kept_signpost_codes": len(causal & signpost_codes),
        "interventions": outcome.result.num_interventions,
        "seconds": round(seconds, 2),
        "held_out_signpost_kept": round(float(keep[labels].mean()), 3),
        "held_out_other_removed": round(float((~keep[~labels]).mean()), 3),
        "held_out_taie": round(float(np.abs(keep.astype(float) - labels).mean()), 4),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--level", type=int, default=1)
    parser.add_argument("--episodes", type=int, default=600)
    parser.add_argument("--noise", type=float, default=0.2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--discretizers", nargs="+", default=["exact", "cell-set"])
    args = parser.parse_args()
    torch.set_num_threads(1)
    train = collect(args.level, args.episodes, args.noise, args.seed)
    held_out = collect(args.level, 200, args.noise, args.seed + 1)
    env = gym.make(f"thci/BabyAI-L{args.level}-v0")
    rows = [one_round(kind, train, held_out, env, args.seed) for kind in args.discretizers]
    paid = np.mean([r.sum() > 0 for _, _, r, _ in train])
    saw = np.mean([lab.any() for *_, lab in train])
    print(
        f"BabyAI-L{args.level}: {args.episodes} episodes, {paid:.2f} paid, {saw:.2f} saw the "
        f"signpost, noise {args.noise}"
    )
    keys = list(rows[0])
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for row in rows:
        print("| " + " | ".join(str(row[k]) for k in keys) + " |")
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / f"babyai_ci_l{args.level}_{args.episodes}.json"
    record = {
        "level": args.level,
        "episodes": args.episodes,
        "noise": args.noise,
        "seed": args.seed,
        "paid": float(paid),
        "saw_signpost": float(saw),
        "rows": rows,
    }
    out.write_text(json.dumps(record, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

"""Does each BabyAI level need memory? Imitate the expert with and without one.

Reinforcement learning has not yet learned to use the signpost on any level (docs/babyai.md),
so RL runs cannot show what a memory is worth there. Behaviour cloning can: the same agent as
training (thci's ActorCritic with `--method mlp`, no memory, or `lstm`, flat one-hot encoder),
trained by cross-entropy on the scripted expert's actions (``expert_action()``) over whole
expert episodes, then played on fresh episodes. Both see the same data; the memoryless one
cannot know the target colour once the signpost is out of view, so at the balls it can only
guess (success at most 1/2 of the episodes it navigates), where a recurrent one can match the
expert (1.0).

    .venv/bin/python benchmarks/imitation_memory.py [--levels 1 2 3 4] [--episodes 3000]
        [--epochs 40] [--seed 0] [--methods mlp lstm oracle] [--encoder flat] [--size 64]

Writes benchmarks/results/imitation_memory_{ENCODER}_{SIZE}.json and prints a table.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from torch.nn.utils.rnn import pad_sequence
from tqdm import tqdm

from thci.config import TrainConfig
from thci.envs.factory import make_vector_env
from thci.rl.agent import ActorCritic
from thci.rl.rollout import RolloutCollector
from thci.rl.sequences import cut_into_segments
from thci.rl.trainer import build_agent

RESULTS = Path(__file__).parent / "results"
NUM_ENVS = 16


def write_result(name: str, result: object) -> None:
    """Write `result` as benchmarks/results/NAME (JSON) and say where."""
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / name
    path.write_text(json.dumps(result, indent=1))
    print(f"wrote {path}")


def expert_episodes(
    env_id: str, agent: ActorCritic, episodes: int, seed: int
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """`episodes` whole expert episodes: (agent inputs (L, D), expert actions (L,)) each."""
    envs = make_vector_env(env_id, NUM_ENVS, "sync")
    collector = RolloutCollector(envs, agent, num_steps=256, gamma=0.99, expert=True)
    collector.reset(seed)
    out: list[tuple[torch.Tensor, torch.Tensor]] = []
    while len(out) < episodes:
        rollout, _ = collector.collect()
        segments = cut_into_segments(rollout.episode_starts)
        last = segments.gather(rollout.dones)[torch.arange(len(segments.column)),
                                              segments.lengths - 1]  # fmt: skip
        inputs, actions = segments.gather(rollout.inputs), segments.gather(rollout.actions)
        for s in torch.nonzero(~segments.continues & last).squeeze(1).tolist():
            length = int(segments.lengths[s])
            out.append((inputs[s, :length], actions[s, :length]))
    envs.close()
    return out[:episodes]


def clone(
    agent: ActorCritic,
    data: list[tuple[torch.Tensor, ...]],
    epochs: int,
    weight: float = 1.0,
    generator: torch.Generator | None = None,
) -> list[dict]:
    """Fit the agent's policy to the expert's actions over whole episodes (minibatches of 64,
    in an order drawn from `generator`, or torch's global RNG; Adam 1e-3, clipping 0.5).

    Args:
        data: per episode (agent inputs (L, D), expert actions (L,)), optionally with its
            choice steps (L,) bool, whose loss is multiplied by `weight`.

    Returns:
        The training accuracy, on all steps and on the choice steps (None without them), every
        10 epochs and at the last.
    """
    optimizer = torch.optim.Adam(agent.parameters(), lr=1e-3, eps=1e-5)
    labelled = len(data[0]) > 2
    curve = []
    for epoch in tqdm(range(1, epochs + 1), desc="cloning", leave=False):
        hits = steps = choice_hits = choice_steps = 0
        for batch in torch.randperm(len(data), generator=generator).split(64):
            inputs = pad_sequence([data[i][0] for i in batch], batch_first=True)
            actions = pad_sequence([data[i][1] for i in batch], batch_first=True)
            valid = pad_sequence(
                [torch.ones(len(data[i][1]), dtype=torch.bool) for i in batch], batch_first=True
            )
            logits, _ = agent.evaluate(inputs, agent.initial_state(len(batch)))
            if labelled:
                choices = pad_sequence([data[i][2] for i in batch], batch_first=True)[valid]
                losses = torch.nn.functional.cross_entropy(
                    logits[valid], actions[valid], reduction="none"
                )
                weights = 1 + (weight - 1) * choices.float()
                loss = (weights * losses).sum() / weights.sum()
            else:
                loss = torch.nn.functional.cross_entropy(logits[valid], actions[valid])
            optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(agent.parameters(), 0.5)
            optimizer.step()
            hit = logits[valid].argmax(dim=-1) == actions[valid]
            hits, steps = hits + int(hit.sum()), steps + int(valid.sum())
            if labelled:
                choice_hits += int(hit[choices].sum())
                choice_steps += int(choices.sum())
        if epoch % 10 == 0 or epoch == epochs:
            curve.append(
                {
                    "epoch": epoch,
                    "accuracy": round(hits / steps, 4),
                    "choice_accuracy": round(choice_hits / choice_steps, 4) if labelled else None,
                }
            )
    return curve


@torch.no_grad()
def play(env_id: str, agent: ActorCritic, episodes: int, greedy: bool, seed: int) -> dict:
    """Success rate and mean length of the cloned policy over `episodes` fresh episodes."""
    envs = make_vector_env(env_id, NUM_ENVS, "sync")
    collector = RolloutCollector(envs, agent, num_steps=256, gamma=0.99, greedy=greedy)
    collector.reset(seed)
    finished = []
    while len(finished) < episodes:
        finished += collector.collect()[1]
    envs.close()
    finished = finished[:episodes]
    return {
        "success": round(float(np.mean([e.success for e in finished])), 3),
        "length": round(float(np.mean([e.length for e in finished])), 1),
    }


def run(
    level: int, method: str, encoder: str, size: int, episodes: int, epochs: int, seed: int
) -> dict:
    env_id = f"thci/BabyAI-L{level}-v0"
    torch.manual_seed(seed)
    envs = make_vector_env(env_id, 1, "sync")
    config = TrainConfig(
        env=env_id, method=method, encoder=encoder, encoder_size=size, hidden_size=size
    )
    agent = build_agent(config, envs)
    envs.close()
    started = time.perf_counter()
    data = expert_episodes(env_id, agent, episodes, seed)
    curve = clone(agent, data, epochs, generator=torch.Generator().manual_seed(seed))
    return {
        "level": level,
        "method": method,
        "encoder": encoder,
        "size": size,
        "episodes": episodes,
        "epochs": epochs,
        "seed": seed,
        "train_action_accuracy": curve[-1]["accuracy"],
        "greedy": play(env_id, agent, 300, True, seed + 1_000),
        "sampled": play(env_id, agent, 300, False, seed + 2_000),
        "seconds": round(time.perf_counter() - started, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--levels", type=int, nargs="+", default=[1, 2, 3, 4])
    parser.add_argument("--methods", nargs="+", default=["mlp", "lstm"])
    parser.add_argument("--encoder", choices=["flat", "cells", "grid"], default="flat")
    parser.add_argument("--size", type=int, default=64, help="encoder and memory width")
    parser.add_argument("--episodes", type=int, default=3000)
    parser.add_argument("--epochs", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = []
    print("level | method | action accuracy | success greedy / sampled | length greedy | s")
    for level in args.levels:
        for method in args.methods:
            row = run(level, method, args.encoder, args.size, args.episodes, args.epochs, args.seed)
            rows.append(row)
            print(
                f"L{level} | {method} {args.encoder} {args.size} | "
                f"{row['train_action_accuracy']:.3f} | "
                f"{row['greedy']['success']:.3f} / {row['sampled']['success']:.3f} | "
                f"{row['greedy']['length']} | {row['seconds']}",
                flush=True,
            )
    write_result(f"imitation_memory_{args.encoder}_{args.size}.json", rows)


if __name__ == "__main__":
    main()

"""Clone a BabyAI level's expert with the choice steps weighted: can the agent use its memory?

Plain cloning (``imitation_memory.py``) leaves every agent guessing the ball, though the same
agent learns the choice when taught the choice steps alone (``choice_probe.py``). Here the
oracle agent is cloned on whole expert episodes with the loss of the *choice steps* (those
whose expert action depends on which ball is the target, ``choice_probe.is_choice``)
multiplied by ``--weight``, then played on fresh episodes.

With ``--method mlp`` (no memory) the same training is the control: a memoryless agent can
only guess the ball, so it stays at or below half of the episodes it navigates, whatever the
weight. Comparing it with ``lstm`` and ``oracle`` measures, per level, what a memory is worth
when the choice is taught.

    .venv/bin/python benchmarks/weighted_cloning.py [--level 1] [--weight 7] [--epochs 150]
        [--episodes 3000] [--encoder cells] [--method oracle|lstm|mlp]

Writes benchmarks/results/weighted_cloning_{METHOD}_{ENCODER}_w{WEIGHT}.json on level 1 and
weighted_cloning_L{LEVEL}_{METHOD}_{ENCODER}_w{WEIGHT}.json on the others.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from choice_probe import is_choice
from imitation_memory import clone, play, write_result
from tqdm import tqdm

from thci.config import TrainConfig
from thci.envs.factory import make_vector_env
from thci.rl.agent import ActorCritic
from thci.rl.trainer import build_agent

Episode = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def labelled_episodes(env_id: str, agent: ActorCritic, episodes: int, seed: int) -> list[Episode]:
    """Expert episodes: agent inputs (L, D + side), expert actions (L,), choice steps (L,)."""
    envs = make_vector_env(env_id, 1, "sync")
    level = envs.envs[0].unwrapped
    obs, info = envs.reset(seed=seed)
    out: list[Episode] = []
    for _ in tqdm(range(episodes), desc="expert episodes", leave=False):
        inputs, actions, choices = [], [], []
        done = False
        while not done:
            action = level.expert_action()
            side = [float(info["causal"][0])] if agent.memory.side_size else []
            inputs.append(np.concatenate([obs[0], side]))
            actions.append(action)
            choices.append(is_choice(level, action))
            obs, _, terminated, truncated, info = envs.step(np.array([action]))
            done = bool(terminated[0] or truncated[0])
        out.append(
            (
                torch.as_tensor(np.array(inputs), dtype=torch.float32),
                torch.as_tensor(actions),
                torch.as_tensor(choices),
            )
        )
    envs.close()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--level", type=int, choices=[1, 2, 3, 4], default=1)
    parser.add_argument("--weight", type=float, default=7.0)
    parser.add_argument("--epochs", type=int, default=150)
    parser.add_argument("--episodes", type=int, default=3000)
    parser.add_argument("--encoder", choices=["flat", "cells", "grid"], default="cells")
    parser.add_argument("--method", default="oracle")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    env_id = f"thci/BabyAI-L{args.level}-v0"
    envs = make_vector_env(env_id, 1, "sync")
    agent = build_agent(TrainConfig(env=env_id, method=args.method, encoder=args.encoder), envs)
    envs.close()
    started = time.perf_counter()
    data = labelled_episodes(env_id, agent, args.episodes, args.seed)
    curve = clone(agent, data, args.epochs, args.weight)
    result = {
        **vars(args),
        "choice_share": round(float(torch.cat([d[2] for d in data]).float().mean()), 4),
        "curve": curve,
        "greedy": play(env_id, agent, 300, True, args.seed + 1_000),
        "sampled": play(env_id, agent, 300, False, args.seed + 2_000),
        "seconds": round(time.perf_counter() - started, 1),
    }
    for point in curve:
        print(point)
    print("greedy", result["greedy"], "sampled", result["sampled"])
    level = "" if args.level == 1 else f"L{args.level}_"
    name = f"weighted_cloning_{level}{args.method}_{args.encoder}_w{args.weight:g}.json"
    write_result(name, result)


if __name__ == "__main__":
    main()

"""What does a network need to make BabyAI-L1's choice? A supervised probe at the choice steps.

A *choice step* is one where the scripted expert's action depends on which ball is the target:
a copy of the level with target and decoy swapped asks the expert again, and the two answers
differ. At the choice steps of expert episodes that have shown the signpost, an MLP is fitted
to the expert's action from the current view plus one of several forms of the signpost, and
scored on held-out choice steps:

* ``none``: the current view only (what a memoryless agent has);
* ``view``: the last signpost view, one-hot per entry (what a memory of raw views holds);
* ``colour``: the signpost's colour, 6-way one-hot (the answer, extracted);
* ``cells``: the signpost view's set of whole cells, multi-hot over (object, colour, state),
  position-free (what ``--encoder cells`` pools).

Then thci's own oracle agent (``build_agent``, ``--encoder flat`` and ``cells``) is fitted to
the same choice steps as two-step sequences, the signpost observation (kept by the oracle's
memory) followed by the current one, with the loss on the second step's action only: whether
the agent can learn the choice when it is all it is taught.

    .venv/bin/python benchmarks/choice_probe.py [--episodes 2500] [--epochs 150] [--hidden 256]

Writes benchmarks/results/choice_probe_{HIDDEN}.json and prints a table.
"""

from __future__ import annotations

import argparse
import copy

import gymnasium as gym
import numpy as np
import torch
from imitation_memory import write_result
from tqdm import tqdm

import thci.envs  # noqa: F401  (registers the ids)
from thci.config import TrainConfig
from thci.envs.babyai import BabyAIExpert
from thci.envs.factory import make_vector_env
from thci.rl.trainer import build_agent

CELLS, VALUES = 49, 12  # a 7x7 view; entries below 12 (objects 0..10, colours 0..5, states 0..2)
WALL, GREY = 2, 5


def is_choice(level: gym.Env, action: int) -> bool:
    """Whether the expert's `action` in `level`'s current state depends on which ball is the
    target: an expert on a copy with target and decoy swapped would act otherwise."""
    twin = copy.deepcopy(level)
    twin.target_ball, twin.decoy_ball = twin.decoy_ball, twin.target_ball
    try:
        return BabyAIExpert(twin).act() != action
    except RuntimeError:  # no plan to the swapped target: not a choice step
        return False


def choice_steps(episodes: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(last signpost observation (n, D), current observation (n, D), expert action (n,)) at
    the choice steps of `episodes` expert episodes on BabyAI-L1 (flat observations: the view's
    147 entries first)."""
    env = gym.make("thci/BabyAI-L1-v0")
    signs, views, actions = [], [], []
    for episode in tqdm(range(episodes), desc="expert episodes", leave=False):
        obs, info = env.reset(seed=seed + episode)
        level, done, last_sign = env.unwrapped, False, None
        while not done:
            if info["causal"]:
                last_sign = np.asarray(obs).copy()
            action = level.expert_action()
            if is_choice(level, action) and last_sign is not None:
                signs.append(last_sign)
                views.append(np.asarray(obs).copy())
                actions.append(action)
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
    return np.array(signs, dtype=np.int64), np.array(views, dtype=np.int64), np.array(actions)


def one_hot_entries(views: np.ndarray) -> torch.Tensor:
    """(n, 147) entries -> (n, 147 * 12) one-hot per entry."""
    index = torch.as_tensor(views[:, : CELLS * 3]).clamp(max=VALUES - 1)
    return torch.nn.functional.one_hot(index, VALUES).flatten(1).float()


def signpost_inputs(signs: np.ndarray) -> dict[str, torch.Tensor]:
    """The forms of the signpost that the probe compares (module docstring)."""
    cells = signs[:, : CELLS * 3].reshape(len(signs), CELLS, 3)
    painted = (cells[:, :, 0] == WALL) & (cells[:, :, 1] != GREY)
    first_painted = painted.argmax(axis=1)  # the signpost's cell (a view shows one at most)
    colour = np.where(painted.any(axis=1), cells[np.arange(len(cells)), first_painted, 1], 0)
    category = cells[:, :, 0] * 36 + cells[:, :, 1] * 6 + cells[:, :, 2]
    cell_set = torch.zeros(len(signs), 11 * 36)
    cell_set.scatter_(1, torch.as_tensor(category).clamp(max=11 * 36 - 1), 1.0)
    return {
        "none": torch.zeros(len(signs), 0),
        "view": one_hot_entries(signs),
        "colour": torch.nn.functional.one_hot(torch.as_tensor(colour), 6).float(),
        "cells": cell_set,
    }


def fit(x: torch.Tensor, y: torch.Tensor, hidden: int, epochs: int, seed: int) -> dict:
    """Two hidden ReLU layers (one tanh layer if `hidden` <= 64, as the agent's heads); 80% of
    the rows fitted, 20% held out."""
    torch.manual_seed(seed)
    if hidden <= 64:
        layers = [torch.nn.Linear(x.shape[1], hidden), torch.nn.Tanh()]
    else:
        layers = [torch.nn.Linear(x.shape[1], hidden), torch.nn.ReLU()]
        layers += [torch.nn.Linear(hidden, hidden), torch.nn.ReLU()]
    net = torch.nn.Sequential(*layers, torch.nn.Linear(hidden, 6))
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3, weight_decay=1e-5)
    split = int(0.8 * len(y))
    for _ in range(epochs):
        for batch in torch.randperm(split).split(128):
            loss = torch.nn.functional.cross_entropy(net(x[batch]), y[batch])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    with torch.no_grad():
        predicted = net(x).argmax(dim=1) == y
    return {
        "train": round(float(predicted[:split].float().mean()), 3),
        "held_out": round(float(predicted[split:].float().mean()), 3),
    }


def fit_agent(
    encoder: str, signs: np.ndarray, views: np.ndarray, y: torch.Tensor, epochs: int
) -> dict:
    """thci's oracle agent on (signpost, current) two-step sequences; loss on the second step."""
    env_id = "thci/BabyAI-L1-v0"
    envs = make_vector_env(env_id, 1, "sync")
    torch.manual_seed(0)
    agent = build_agent(TrainConfig(env=env_id, method="oracle", encoder=encoder), envs)
    envs.close()
    kept = torch.ones(len(y), 1)  # the oracle's side input: the signpost step is kept
    x = torch.stack(
        (
            torch.cat((torch.as_tensor(signs, dtype=torch.float32), kept), 1),
            torch.cat((torch.as_tensor(views, dtype=torch.float32), 0 * kept), 1),
        ),
        dim=1,
    )  # (n, 2, D + 1)
    optimizer = torch.optim.Adam(agent.parameters(), lr=1e-3, eps=1e-5)
    split = int(0.8 * len(y))
    for _ in range(epochs):
        for batch in torch.randperm(split).split(128):
            logits, _ = agent.evaluate(x[batch], agent.initial_state(len(batch)))
            loss = torch.nn.functional.cross_entropy(logits[:, 1], y[batch])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    with torch.no_grad():
        logits, _ = agent.evaluate(x, agent.initial_state(len(y)))
        predicted = logits[:, 1].argmax(dim=1) == y
    return {
        "train": round(float(predicted[:split].float().mean()), 3),
        "held_out": round(float(predicted[split:].float().mean()), 3),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=2500)
    parser.add_argument("--epochs", type=int, default=150)
    parser.add_argument("--hidden", type=int, default=256)
    parser.add_argument("--agent-epochs", type=int, default=150)
    parser.add_argument("--seed", type=int, default=10_000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    signs, views, actions = choice_steps(args.episodes, args.seed)
    current, y = one_hot_entries(views), torch.as_tensor(actions)
    rows = {"choice_steps": len(y), "episodes": args.episodes, "hidden": args.hidden}
    print(f"{len(y)} choice steps; accuracy against the expert's action (train / held out)")
    for name, signpost in signpost_inputs(signs).items():
        rows[name] = fit(torch.cat((signpost, current), 1), y, args.hidden, args.epochs, 0)
        print(f"{name:>7}: {rows[name]['train']:.3f} / {rows[name]['held_out']:.3f}", flush=True)
    for encoder in ("flat", "cells"):
        name = f"oracle agent, {encoder}"
        rows[name] = fit_agent(encoder, signs, views, y, args.agent_epochs)
        print(f"{name}: {rows[name]['train']:.3f} / {rows[name]['held_out']:.3f}", flush=True)
    write_result(f"choice_probe_{args.hidden}.json", rows)


if __name__ == "__main__":
    main()

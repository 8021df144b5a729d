"""Can an encoder tell the signpost's colour from one cell of a minigrid view? And can an agent
remember it?

BabyAI's signpost is one wall cell painted in the target colour among 48 other cells: grey
walls, empty cells, and doors, keys and balls of any colour. This module makes views of that
kind (thci's flat BabyAI layout: 49 cells of (object, colour, state), then the one-hot heading)
and measures, with a known answer:

1. **Supervised** (``main``): views with a green or a blue signpost, the label its colour; an
   encoder of each ``--encoder`` kind (width 64, ReLU) plus a linear readout, trained with Adam
   (lr 1e-3, 170 views per step, about one rollout's decisions); how many views until 95%
   held-out accuracy.
2. **Reinforcement learning**: ``CellRecall-v0``, a 12-step episode that shows the signpost
   once in its first half (``info["causal"]`` there only) among random views; at the last step
   action 0 pays 1 if the signpost was green, action 1 if blue. Train on it with

       PYTHONPATH=benchmarks .venv/bin/thci train --env cell_recall:CellRecall-v0 \\
           --method oracle --encoder cells --total-steps 300000 --stop-on-solve \\
           --num-steps 128 --update-epochs 4 --num-minibatches 4

   (``CellRecallNow-v0`` shows the signpost view at the last step instead: no memory needed.)

    .venv/bin/python benchmarks/cell_recall.py [--max-views 100000] [--seeds 1 2 3]

Prints a table and writes benchmarks/results/cell_recall.json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, get_args

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from torch import nn

from thci.config import EncoderKind
from thci.rl.encoders import make_encoder

RESULTS = Path(__file__).parent / "results"
CELLS, CHANNELS = 49, 3
EMPTY, WALL, BOX = 1, 2, 7
DISTRACTORS = (4, 5, 6)  # door, key, ball
GREEN, BLUE, GREY = 1, 2, 5
HIGH = np.concatenate([np.tile([10, 5, 2], CELLS), np.ones(4, np.int64)]).astype(np.uint8)
CATEGORIES = (HIGH.astype(np.int64) + 1).tolist()


def random_view(rng: np.random.Generator, signpost: int | None) -> np.ndarray:
    """(151,) uint8: 40% grey walls, empty cells, 0-3 doors / keys / balls of any colour, and
    when `signpost` is 0 (green) or 1 (blue) one wall cell of that colour."""
    cells = np.zeros((CELLS, CHANNELS), np.uint8)
    wall = rng.random(CELLS) < 0.4
    cells[:, 0] = np.where(wall, WALL, EMPTY)
    cells[:, 1] = np.where(wall, GREY, 0)
    count = rng.integers(0, 4)
    where = rng.choice(CELLS, count, replace=False)
    cells[where, 0] = rng.choice(DISTRACTORS, count)
    cells[where, 1] = rng.integers(0, 6, count)
    if signpost is not None:
        walls = np.flatnonzero(cells[:, 0] == WALL)
        cells[rng.choice(walls) if len(walls) else rng.integers(CELLS)] = (WALL, 1 + signpost, 0)
    view = np.zeros(len(HIGH), np.uint8)
    view[: CELLS * CHANNELS] = cells.reshape(-1)
    view[CELLS * CHANNELS + rng.integers(4)] = 1
    return view


class CellRecallEnv(gym.Env):
    """Remember the colour of one wall cell for a few steps (see the module docstring).

    Args:
        length: steps per episode; the signpost is shown at a step in [0, length // 2).
        signpost_now: show the signpost view at the last step (heading entries all 1) instead.
    """

    def __init__(self, length: int = 12, signpost_now: bool = False) -> None:
        self.length, self.signpost_now = length, signpost_now
        self.observation_space = spaces.Box(0, HIGH, dtype=np.uint8)
        self.action_space = spaces.Discrete(6)

    def _observation(self) -> np.ndarray:
        if self.t < self.length - 1:
            return random_view(self.np_random, self.colour if self.t == self.shown_at else None)
        if self.signpost_now:
            view = random_view(self.np_random, self.colour)
            view[CELLS * CHANNELS :] = 1
            return view
        view = np.zeros(len(HIGH), np.uint8)  # the choice: a view of boxes, the same every time
        view[: CELLS * CHANNELS] = np.tile([BOX, 0, 0], CELLS)
        return view

    def _info(self, success: bool = False) -> dict[str, Any]:
        return {"causal": self.t == self.shown_at, "success": success}

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self.t = 0
        self.colour = int(self.np_random.integers(2))
        self.shown_at = int(self.np_random.integers(self.length // 2))
        return self._observation(), self._info()

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self.t == self.length - 1:
            success = int(action) == self.colour
            self.t += 1
            return np.zeros(len(HIGH), np.uint8), float(success), True, False, self._info(success)
        self.t += 1
        return self._observation(), 0.0, False, False, self._info()


gym.register(id="CellRecall-v0", entry_point=CellRecallEnv)
gym.register(id="CellRecallNow-v0", entry_point=CellRecallEnv, kwargs={"signpost_now": True})


def labelled_views(rng: np.random.Generator, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """n views with a signpost (n, 151) and its colour (n,)."""
    colours = rng.integers(0, 2, n)
    views = np.stack([random_view(rng, int(c)) for c in colours])
    return torch.as_tensor(views).float(), torch.as_tensor(colours)


def views_to_accuracy(
    kind: EncoderKind, seed: int, max_views: int, target: float = 0.95, batch: int = 170
) -> tuple[int | None, float]:
    """Views an encoder + linear readout needs to reach `target` held-out accuracy (None: not
    within `max_views`), and its final accuracy."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    encoder = make_encoder(kind, len(HIGH), CATEGORIES, (0, CELLS, CHANNELS), 64)
    net = nn.Sequential(encoder, nn.ReLU(), nn.Linear(64, 2))
    optimizer = torch.optim.Adam(net.parameters(), 1e-3)
    test_views, test_colours = labelled_views(rng, 2000)
    seen, accuracy = 0, 0.0
    while seen < max_views:
        views, colours = labelled_views(rng, batch)
        loss = nn.functional.cross_entropy(net(views), colours)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        seen += batch
        if seen % (10 * batch) == 0:
            with torch.no_grad():
                accuracy = (net(test_views).argmax(1) == test_colours).float().mean().item()
            if accuracy >= target:
                return seen, accuracy
    return None, accuracy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--max-views", type=int, default=100_000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    args = parser.parse_args()
    torch.set_num_threads(1)
    records = []
    for kind in get_args(EncoderKind):
        for seed in args.seeds:
            views, accuracy = views_to_accuracy(kind, seed, args.max_views)
            records.append(
                {
                    "encoder": kind,
                    "seed": seed,
                    "views_to_95": views,
                    "final_accuracy": round(accuracy, 3),
                }
            )
            shown = "-" if views is None else f"{views:,}"
            print(f"{kind:6s} seed {seed}: views to 95% {shown:>8s}, accuracy {accuracy:.3f}")
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / "cell_recall.json"
    path.write_text(json.dumps({"max_views": args.max_views, "runs": records}, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

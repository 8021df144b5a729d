"""Draw docs/images/babyai_l1.png ... babyai_l4.png, the pictures of docs/babyai.md.

Each picture shows one scripted-expert episode of a level rendered by minigrid
(``render_mode="rgb_array"``, the agent's 7x7 view highlighted) twice: left, the first step at
which the signpost is in view (``info["causal"]`` is True); right, the choice, the state
before the expert's last action (facing / picking up the target), with the signpost out of
view. The seeds are chosen so that the pictures show the signpost room on both sides and the
signpost on different walls.

Run from the repository root: ``.venv/bin/python docs/make_babyai_pictures.py``. Needs
Pillow (installed with matplotlib, the ``bench`` extra).
"""

from pathlib import Path

import numpy as np
from PIL import Image

from thci.envs.babyai import BABYAI_LEVELS, BabyAIExpert

OUT_DIR = Path(__file__).resolve().parent / "images"
SEEDS = {1: 0, 2: 9, 3: 4, 4: 3}
GAP_PX = 16  # white gap between the two panels


def level_picture(level: int, seed: int) -> np.ndarray:
    """(H, 2W + gap, 3) uint8: the level at the expert's first causal step and at its choice."""
    env = BABYAI_LEVELS[level](render_mode="rgb_array")
    _, info = env.reset(seed=seed)
    expert = BabyAIExpert(env)
    cue = env.render() if info["causal"] else None
    while True:
        before = env.render()
        _, _, terminated, truncated, info = env.step(expert.act())
        if terminated or truncated:
            break
        if cue is None and info["causal"]:
            cue = env.render()
    if cue is None or not info["success"]:
        raise RuntimeError(f"level {level}, seed {seed}: the expert failed or never saw the cue")
    gap = np.full((cue.shape[0], GAP_PX, 3), 255, np.uint8)
    return np.concatenate([cue, gap, before], axis=1)


def main() -> None:
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    for level in BABYAI_LEVELS:
        path = OUT_DIR / f"babyai_l{level}.png"
        Image.fromarray(level_picture(level, SEEDS[level])).save(path, optimize=True)
        print(path)


if __name__ == "__main__":
    main()

"""Built-in environments, registered with gymnasium on import.

``thci/PaperMaze-L1-v0`` ... ``thci/PaperMaze-L4-v0`` are the paper's Maze levels 1-4. Both
``gym.make`` (single :class:`PaperMazeEnv`) and ``gym.make_vec`` (native batched
:class:`PaperMazeVectorEnv`, the default vectorization mode for these ids) work. No
``max_episode_steps`` is registered: the envs truncate themselves after 30 steps, and a
``TimeLimit`` wrapper on top would only duplicate that (pass ``max_steps=`` to change it).

``thci/KeyDoorTV-v0`` is the paper's Fig. 1 key-to-door example (:class:`KeyDoorTVEnv`); it
ends itself after 2 steps.

``thci/BabyAI-L1-v0`` ... ``thci/BabyAI-L4-v0`` are the paper's BabyAI levels 1-4
(:mod:`thci.envs.babyai`, built on minigrid), with flat uint8 observations. They are
registered by entry-point string so that ``import thci.envs`` does not import minigrid (which
registers ~180 ids of its own); ``max_episode_steps`` equals the level's own ``max_steps``.
"""

import gymnasium as gym

from thci.envs.key_door_tv import KeyDoorTVEnv
from thci.envs.paper_maze import (
    MazeLevel,
    PaperMazeEnv,
    PaperMazeVectorEnv,
    available_levels,
    load_maze_level,
)

__all__ = [
    "BABYAI_IDS",
    "KEY_DOOR_TV_ID",
    "PAPER_MAZE_IDS",
    "KeyDoorTVEnv",
    "MazeLevel",
    "PaperMazeEnv",
    "PaperMazeVectorEnv",
    "load_maze_level",
]

KEY_DOOR_TV_ID = "thci/KeyDoorTV-v0"
PAPER_MAZE_IDS: tuple[str, ...] = tuple(f"thci/PaperMaze-L{k}-v0" for k in available_levels())


def _register_paper_mazes() -> None:
    for level, env_id in zip(available_levels(), PAPER_MAZE_IDS, strict=True):
        # Re-importing (e.g. importlib.reload) must not make gymnasium warn about overriding.
        if env_id in gym.registry:
            continue
        gym.register(
            id=env_id,
            entry_point="thci.envs.paper_maze:PaperMazeEnv",
            vector_entry_point="thci.envs.paper_maze:PaperMazeVectorEnv",
            kwargs={"level": level},
        )


_register_paper_mazes()


def _register_key_door_tv() -> None:
    # Same guard as above: re-importing must not re-register (gymnasium would warn).
    if KEY_DOOR_TV_ID not in gym.registry:
        gym.register(id=KEY_DOOR_TV_ID, entry_point="thci.envs.key_door_tv:KeyDoorTVEnv")


_register_key_door_tv()


BABYAI_IDS: tuple[str, ...] = tuple(f"thci/BabyAI-L{k}-v0" for k in (1, 2, 3, 4))
# Episode limits, the MAX_STEPS of the level classes in thci.envs.babyai (a test checks that
# they agree); repeated here so that registering does not import minigrid.
_BABYAI_MAX_STEPS = {1: 80, 2: 120, 3: 160, 4: 250}


def _register_babyai() -> None:
    for level, env_id in zip(_BABYAI_MAX_STEPS, BABYAI_IDS, strict=True):
        if env_id in gym.registry:  # same guard as above
            continue
        max_steps = _BABYAI_MAX_STEPS[level]
        gym.register(
            id=env_id,
            entry_point="thci.envs.babyai:make_babyai_env",
            kwargs={"level": level, "max_steps": max_steps},
            max_episode_steps=max_steps,
        )


_register_babyai()

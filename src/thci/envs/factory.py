"""Build the batched environment a trainer runs on, for any registered gymnasium id.

Built-in environments ship a native batched implementation (``vector_entry_point``); any other
registered id runs in gymnasium's ``SyncVectorEnv``. Both use gymnasium 1.x's SAME_STEP
autoreset, which the rollout code relies on: when an episode ends, the returned observation is
already the next episode's first one and the last one is in ``infos["final_obs"]``.

A user's own environment needs no change to the library: register it with gymnasium and pass
its id, or pass ``"my_package.my_module:MyEnv-v0"`` and gymnasium imports the module first.
``Dict`` observations (e.g. minigrid's ``{"image", "direction", "mission"}``) keep their
``Box`` / ``Discrete`` / ``MultiDiscrete`` entries, flattened into one vector; other entries
(the mission ``Text``) are ignored, and a note names them.

minigrid declares its image of (object, colour, state) cells as 0..255; thci declares the
bounds the cells really have (:class:`MinigridCells`), so that they are read as categories
(one-hot, ``--encoder cells``, ``--discretizer cell-set``) and not as magnitudes.
"""

from __future__ import annotations

import difflib
import importlib
import sys
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, SyncVectorEnv, VectorEnv
from gymnasium.wrappers import FilterObservation, FlattenObservation

from thci.errors import ThciError

SUPPORTED_OBSERVATION_SPACES = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete)
# The vector env's metadata entry that says where an image of cells lies in its observations.
CELL_LAYOUT_KEY = "thci_cell_layout"
_NOTED: set[str] = set()  # env ids whose ignored Dict entries were already reported


def resolve_env_spec(env_id: str) -> gym.envs.registration.EnvSpec:
    """The registered spec of `env_id`, or ThciError suggesting close matches."""
    if ":" in env_id:  # gymnasium's "module:EnvId" convention: import the user's module first
        module, env_id = env_id.split(":", 1)
        try:
            importlib.import_module(module)
        except ImportError as exc:
            raise ThciError(f"cannot import module {module!r} for --env: {exc}") from None
    if env_id in gym.registry:
        return gym.registry[env_id]
    close = difflib.get_close_matches(env_id, list(gym.registry), n=3, cutoff=0.6)
    hint = f"did you mean {', '.join(close)}?" if close else "run `thci envs` to list them"
    raise ThciError(f"unknown environment id {env_id!r}: {hint}")


def usable_keys(space: spaces.Dict) -> tuple[list[str], list[str]]:
    """The entries of a Dict observation space thci uses, and those it ignores."""
    used = [k for k, sub in space.spaces.items() if isinstance(sub, SUPPORTED_OBSERVATION_SPACES)]
    return used, [k for k in space.spaces if k not in used]


def check_spaces(observation_space: spaces.Space, action_space: spaces.Space, env_id: str) -> None:
    """ThciError unless the spaces are ones the agents handle."""
    if not isinstance(action_space, spaces.Discrete):
        raise ThciError(
            f"{env_id} has action space {action_space}; thci agents need a Discrete action space"
        )
    if isinstance(observation_space, spaces.Dict):
        if not usable_keys(observation_space)[0]:
            names = ", ".join(s.__name__ for s in SUPPORTED_OBSERVATION_SPACES)
            raise ThciError(
                f"{env_id} has observation space {observation_space} with no {names} entry "
                "to learn from (wrap the environment to produce one)"
            )
        return
    if not isinstance(observation_space, SUPPORTED_OBSERVATION_SPACES):
        names = ", ".join(s.__name__ for s in SUPPORTED_OBSERVATION_SPACES)
        raise ThciError(
            f"{env_id} has observation space {observation_space}; supported: {names} "
            "(wrap the environment to produce one of these)"
        )


def make_vector_env(
    env_id: str, num_envs: int, vectorization: str = "auto", **env_kwargs: object
) -> VectorEnv:
    """A SAME_STEP-autoreset vector env of `num_envs` copies of `env_id` with flat observations.

    Args:
        env_id: registered id, optionally prefixed by ``"module:"``.
        num_envs: number of parallel environments.
        vectorization: "native" (the env's own vector_entry_point), "sync" (gymnasium's
            SyncVectorEnv), or "auto" (native when it is usable as it is, else sync).
        env_kwargs: passed to the environment constructor.

    Returns:
        A vector env whose ``single_observation_space`` is a flat float Box and whose
        ``single_action_space`` is Discrete.
    """
    spec = resolve_env_spec(env_id)
    if vectorization not in ("auto", "native", "sync"):
        raise ThciError(f"--vectorization must be auto, native or sync, got {vectorization!r}")
    native = spec.vector_entry_point is not None
    if vectorization == "native" and not native:
        raise ThciError(f"{spec.id} has no native batched implementation: use --vectorization sync")
    if native and vectorization != "sync":
        envs = _construct(
            lambda: gym.make_vec(
                spec.id, num_envs, vectorization_mode="vector_entry_point", **env_kwargs
            ),
            spec.id,
        )
        problem = _native_problem(envs)
        if problem is None:
            return envs
        envs.close()
        if vectorization == "native":
            raise ThciError(f"{spec.id}'s native vector env {problem}: use --vectorization sync")
    envs = _construct(
        lambda: SyncVectorEnv(
            [_flat_env_factory(spec.id, env_kwargs) for _ in range(num_envs)],
            autoreset_mode=AutoresetMode.SAME_STEP,
        ),
        spec.id,
    )
    try:
        check_spaces(envs.single_observation_space, envs.single_action_space, spec.id)
    except ThciError:
        envs.close()
        raise
    layout = flat_cell_layout(envs.envs[0])
    if layout is not None:  # a copy: the dict may be the environment class's own
        envs.metadata = {**envs.metadata, CELL_LAYOUT_KEY: layout}
    return envs


def _construct(make, env_id: str) -> VectorEnv:
    """Call `make`, turning a third-party constructor's failure into a one-line ThciError."""
    try:
        return make()
    except ThciError:
        raise
    except Exception as exc:
        raise ThciError(f"could not create {env_id}: {type(exc).__name__}: {exc}") from None


def _native_problem(envs: VectorEnv) -> str | None:
    """Why a native vector env cannot be used as it is (None when it can)."""
    if envs.metadata.get("autoreset_mode") != AutoresetMode.SAME_STEP:
        return "does not use SAME_STEP autoreset"
    space = envs.single_observation_space
    if not isinstance(space, spaces.Box) or len(space.shape) != 1:
        return "does not give flat Box observations"
    if not isinstance(envs.single_action_space, spaces.Discrete):
        return f"has action space {envs.single_action_space}, not Discrete"
    return None


class MinigridCells(gym.ObservationWrapper):
    """minigrid's cell image with the bounds its cells have instead of 0..255.

    A minigrid image holds, per cell, the object, colour and state indices (at most 10, 5
    and 2; in a full view from ``FullyObsWrapper`` the agent's cell holds its heading, 0..3,
    as state). Declared 0..255, it would be read as magnitudes. Values beyond the bounds
    (an image that is not minigrid's encoding after all) raise a ThciError.

    Args:
        env: a minigrid environment, possibly wrapped.
        key: the Dict entry holding the image, or None when the observation is the image.
    """

    def __init__(self, env: gym.Env, key: str | None) -> None:
        super().__init__(env)
        from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX

        self.key = key
        image = env.observation_space if key is None else env.observation_space[key]
        self.high = np.array([max(OBJECT_TO_IDX.values()), max(COLOR_TO_IDX.values()), 3])
        tight = spaces.Box(
            0, np.broadcast_to(self.high, image.shape).astype(np.uint8), dtype=np.uint8
        )
        if key is None:
            self.observation_space = tight
        else:
            self.observation_space = spaces.Dict({**env.observation_space.spaces, key: tight})

    def observation(self, observation: Any) -> Any:
        image = observation if self.key is None else observation[self.key]
        if np.any(image.reshape(-1, 3).max(axis=0) > self.high):
            raise ThciError(
                f"a minigrid image holds values above the cell bounds {self.high.tolist()} "
                "(object, colour, state): it is not minigrid's cell encoding; wrap the "
                "environment to declare its own observation space"
            )
        return observation


def minigrid_image_key(env: gym.Env) -> tuple[bool, str | None]:
    """Whether `env` gives minigrid's cell image declared 0..255, and its Dict key (None: the
    observation is the image). Pixel images (minigrid's RGB wrappers) have other shapes."""
    minigrid_env = sys.modules.get("minigrid.minigrid_env")
    if minigrid_env is None or not isinstance(env.unwrapped, minigrid_env.MiniGridEnv):
        return False, None
    base = env.unwrapped
    shapes = {(base.agent_view_size, base.agent_view_size, 3), (base.width, base.height, 3)}
    space = env.observation_space
    key = "image" if isinstance(space, spaces.Dict) and "image" in space.spaces else None
    image = space if key is None else space[key]
    found = (
        isinstance(image, spaces.Box)
        and image.dtype == np.uint8
        and image.shape in shapes
        and bool(np.all(image.high == 255))
    )
    return found, key


def flat_cell_layout(env: gym.Env) -> tuple[int, int, int] | None:
    """(offset, cells, 3): where a minigrid image lies in the flat observation that
    :func:`make_vector_env` makes of `env` (a single env as built there), or None."""
    while isinstance(env, gym.Wrapper) and not isinstance(env, MinigridCells):
        env = env.env
    if not isinstance(env, MinigridCells):
        return None
    space = env.observation_space
    image = space if env.key is None else space[env.key]
    cells = image.shape[0] * image.shape[1]
    if env.key is None:
        return (0, cells, 3)
    # The used entries in the Dict's order, which FilterObservation and FlattenObservation keep.
    used, _ = usable_keys(space)
    offset = sum(spaces.flatdim(space[k]) for k in used[: used.index(env.key)])
    return (offset, cells, 3)


def _flat_env_factory(env_id: str, env_kwargs: dict[str, object]):
    def make() -> gym.Env:
        env = gym.make(env_id, **env_kwargs)
        check_spaces(env.observation_space, env.action_space, env_id)
        is_minigrid, key = minigrid_image_key(env)
        if is_minigrid:
            env = MinigridCells(env, key)
        if isinstance(env.observation_space, spaces.Dict):
            used, ignored = usable_keys(env.observation_space)
            if ignored and env_id not in _NOTED:  # said once per environment id
                _NOTED.add(env_id)
                print(
                    f"note: {env_id}: observation entries {ignored} are ignored; thci uses the "
                    f"Box, Discrete and MultiDiscrete entries {used}",
                    file=sys.stderr,
                )
            env = FilterObservation(env, used)
        return FlattenObservation(env)

    return make

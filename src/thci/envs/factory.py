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
"""

from __future__ import annotations

import difflib
import importlib
import sys

import gymnasium as gym
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, SyncVectorEnv, VectorEnv
from gymnasium.wrappers import FilterObservation, FlattenObservation

from thci.errors import ThciError

SUPPORTED_OBSERVATION_SPACES = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete)
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


def _flat_env_factory(env_id: str, env_kwargs: dict[str, object]):
    def make() -> gym.Env:
        env = gym.make(env_id, **env_kwargs)
        check_spaces(env.observation_space, env.action_space, env_id)
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

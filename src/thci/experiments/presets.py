"""Experiment grids: which (env, method, algo, seed) runs `thci bench` trains, with what settings.

A grid is the cross product ``envs × methods × algos × seeds``. Every run of it is an ordinary
`thci train` run: ``train`` holds TrainConfig fields shared by all runs, ``env_overrides`` the
fields one environment needs on top (e.g. exploration for Maze levels 3-4), ``algo_overrides``
those of one algorithm (e.g. A2C's smaller entropy bonus; they win over the env's) and
``method_overrides`` those of one method (they win over both, e.g. a smaller budget for a
slow method). The same structure is read from a TOML or YAML file::

    envs = ["thci/PaperMaze-L1-v0", "thci/PaperMaze-L2-v0"]
    methods = ["lstm", "t-hci"]
    algos = ["ppo"]                      # optional, default ["ppo"]
    seeds = [1, 2, 3]

    [train]                              # any `thci train` flag, as its field name
    total_steps = 100000
    stop_on_solve = true

    [env_overrides."thci/PaperMaze-L2-v0"]
    total_steps = 200000

    [algo_overrides.a2c]
    ent_coef = 0.01

    [method_overrides.t-hci]
    ci_every = 4096

The presets reproduce the paper's experiments: ``paper-maze`` and ``paper-babyai`` (Fig. 5,
Fig. 7, Table 1: LSTM, GRU, NM, WMG, HCI, T-HCI on levels 1-4, 10 trials each) and
``ablation`` (Table 2, Fig. 8, Fig. 9: T-HCI, SAI, HAI, Oracle on level 3). Each has a
``-quick`` variant with fewer seeds and smaller budgets that finishes in under an hour on two
cores: there the slow baselines (NM ~130, WMG ~30 env steps/s on this project's two-core
machine, vs ~1700 for LSTM) get small budgets, so their cells read "> budget".
``maze-lstm-vs-thci`` and ``babyai-lstm-vs-thci`` are issues 3 and 4's comparisons: LSTM-PPO
beside T-HCI-PPO on every level, 5 and 3 seeds; ``babyai-algos`` is T-HCI with PPO, A2C and DMC
on BabyAI-L1, 3 seeds.
"""

from __future__ import annotations

import dataclasses
import itertools
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, get_args

from thci.config import Algo, Method, TrainConfig
from thci.errors import ThciError

# Fields the grid itself sets for each run: they may not appear in `train` or `env_overrides`
# (progress is always off: the runs of a bench share one terminal).
GRID_FIELDS = frozenset({"env", "method", "algo", "seed", "run_dir", "resume", "progress"})
TRAIN_FIELDS = frozenset(f.name for f in dataclasses.fields(TrainConfig)) - GRID_FIELDS

PAPER_MAZE = tuple(f"thci/PaperMaze-L{k}-v0" for k in range(1, 5))
PAPER_BABYAI = tuple(f"thci/BabyAI-L{k}-v0" for k in range(1, 5))
PAPER_METHODS = ("lstm", "gru", "nm", "wmg", "hci", "t-hci")  # Fig. 5, Table 1
ABLATION_METHODS = ("t-hci", "sai", "hai", "oracle")  # Table 2, Fig. 8, Fig. 9
PAPER_METHOD_NAMES = frozenset(PAPER_METHODS + ABLATION_METHODS)

# Budgets that keep the -quick presets under an hour on two cores (see the module docstring).
# Neural Map with the default PPO updates (8 epochs of 8 minibatches) stayed at 0 successes on
# Maze L1 seed 2 for 57k steps: before the first reward, normalized advantages are noise, and
# they drove its policy into a two-cell loop. 4 epochs of 4 minibatches solved seeds 1-3 at
# 26k-44k steps (docs/baselines.md).
NM_TRAIN = {"update_epochs": 4, "num_minibatches": 4}
QUICK_SLOW_METHODS = {"nm": {**NM_TRAIN, "total_steps": 15_000}, "wmg": {"total_steps": 4_000}}

# BabyAI: an episodic bonus for new cells (per episode, never fading) and gentler PPO updates
# (128-step rollouts, 4 epochs of 4 minibatches) took LSTM-PPO on BabyAI-L1 to the memoryless
# optimum (success 0.5) in 400k steps; a run-wide count bonus on positions with the default
# updates stayed at 0.1-0.2 after 300k (docs/babyai.md, "Measurements"). CI codes views by the
# set of cells in view: on a BabyAI-L1 pool with a known answer, 735 codes against 5,303 exact
# ones, a round 12x faster, and its gate kept 42% of unseen signpost views against 2% (not yet
# reliably: 2% on a 3,600-episode pool; docs/babyai.md, benchmarks/babyai_ci.py). The `cells`
# encoder gives each cell's whole value (a green wall, a grey door) one input, pooled over
# places; every BabyAI run in docs/babyai.md since the Level 1 redesign used it. An entropy
# bonus of 0.03 keeps the policy from committing to one turn at the choice before its memory
# tells the target: T-HCI-PPO solved level 1 at 525k / 1.10M / 1.50M steps (seeds 1-3) against
# 589k / 1.92M / 1.83M at 0.01 (docs/babyai.md, "Level 1: a stronger entropy bonus").
# CI intervenes on cell values (a painted wall wherever it is seen), each tested alone first
# (Z 32 >= the ~28 values): on known-answer pools of levels 1-3 its gate kept every signpost
# view and removed every other (TAIE 0.000-0.0004, 16-29 interventions) where whole-view codes
# kept 4-60% of them; T-HCI-PPO then solved level 1 at 438k / 476k / 1.31M (seeds 1-3) and level
# 2 at 2.34M, which no method had solved in 3M (docs/babyai.md, "Interventions on cell values").
BABYAI_TRAIN = {
    "ci_units": "cells",
    "ci_z": 32,
    "ent_coef": 0.03,
    "encoder": "cells",
    "stop_on_solve": True,
    "exploration": "episodic",
    "count_key": "agent_pos",
    "count_beta": 0.01,
    "num_steps": 128,
    "update_epochs": 4,
    "num_minibatches": 4,
    "discretizer": "cell-set",
}

# Maze levels 3-4 are rewarded in ~0.5% of random episodes: without a bonus on the agent's
# position no method finds the goals within the budget. First visits paid by run-wide rarity,
# a stronger entropy bonus and gentler updates took LSTM-PPO on L3 to 0.9 in 3 of 4 seeds within
# 1M steps, where the run-wide count bonus with the default updates solved 0 of 2 in 300k
# (docs/experiments.md, "Maze levels 3-4"). Causal memories (t-hci, hci, oracle) also count
# what they remember (--count-memory; other methods count places alone): T-HCI on L3 solved
# 4 of 5 seeds within 1M instead of 2 of 5. Beta 0.2 instead of 0.1 took LSTM from 5 to 7 of
# its 10 L3-L4 runs and left T-HCI at 9 of 10 (L3 5/5 and L4 4/5, against 4/5 and 5/5), so it
# is the setting (docs/experiments.md, "Measured: LSTM-PPO against T-HCI-PPO").
MAZE_HARD_TRAIN = {
    "exploration": "episodic-count",
    "count_key": "agent_pos",
    "count_beta": 0.2,
    "count_memory": True,
    "ent_coef": 0.03,
    "num_steps": 128,
    "update_epochs": 4,
    "num_minibatches": 4,
}


def _budgets(envs: tuple[str, ...], small: int, large: int, explore: bool) -> dict[str, dict]:
    """Per-env overrides: levels 1-2 get `small` steps, levels 3-4 `large` (and exploration)."""
    easy, hard = envs[:2], envs[2:]
    overrides = {env: {"total_steps": small} for env in easy}
    extra = MAZE_HARD_TRAIN if explore else {}
    overrides.update({env: {"total_steps": large, **extra} for env in hard})
    return overrides


# BabyAI levels 2-4 wait for 500 rewarded episodes before the first CI round: on level 2 the
# default 50 came at 2-15% success, and those rounds kept no wall colour but balls, keys and
# boxes too rarely paid to decide, each such round one of --ci-max-rounds; with 500 the first
# round (at 848k steps) confirmed the five wall colours (docs/babyai.md).
BABYAI_LATE_CI = {"ci_min_rewarded_episodes": 500}

# BabyAI levels 3-4 pay the episodic bonus for new *views* (their cell-set codes), not new
# places: a view changes when a box opens, a key is carried or a door unlocks, a place does
# not. On level 3 (seed 1, T-HCI-PPO) with places the agent carried B's key in 3% of episodes
# at 1M and 2.09M steps and never opened door B; with views it carried it in 83% and opened B
# in 41% at 3M (88% at 4.9M, success 0.44; docs/babyai.md, "Level 3: a bonus for new views").
BABYAI_VIEW_COUNTS = {"count_key": None, "count_beta": 0.005}

# On BabyAI levels 3-4 the causal memory holds every observation until the first gate. Empty,
# the policy is memoryless until the first round, and the round waits for 500 rewarded
# episodes, a quarter of the 2,000-episode pool: on level 3 (seed 1) the memoryless policy ended
# at 0.10 at 4M steps (last 8 updates) and no round ever ran (rounds from 50 rewarded episodes,
# at 2-6% success, kept nothing). Full, T-HCI learned as the LSTM does until its first round
# (seed 1 at 3.30M, seed 2 at 2.47M), whose gate kept the five wall colours (TAIE 0), and ended
# at 0.35 / 0.47 / 0.05 over seeds 1-3 (seed 3 ran no round; LSTM: 0.46 / 0.00 / 0.48). Level 4
# follows level 3: its seed 1 ran no round either and ended at 0.02 (LSTM 0.10; docs/babyai.md,
# "Level 3: the full memory before the first gate", "Level 4 at the preset settings").
BABYAI_FULL_START = {"ci_initial_memory": "full"}


def _babyai_level(env: str, steps: int) -> dict[str, Any]:
    """Overrides of BABYAI_TRAIN for one BabyAI level: its budget, CI's late start on L2-L4,
    and on L3-L4 the bonus for new views and a full memory before the first gate."""
    level = PAPER_BABYAI.index(env)
    return {
        "total_steps": steps,
        **(BABYAI_LATE_CI if level >= 1 else {}),
        **({**BABYAI_VIEW_COUNTS, **BABYAI_FULL_START} if level >= 2 else {}),
    }


def _babyai_budgets(small: int, large: int) -> dict[str, dict]:
    """Per-env overrides of the BabyAI presets: `small` steps for L1, `large` for L2-L4 (T-HCI
    solved L2 at 2.34M / 3.14M / 2.95M steps); see `_babyai_level`."""
    return {
        env: _babyai_level(env, small if env == PAPER_BABYAI[0] else large) for env in PAPER_BABYAI
    }


PRESETS: dict[str, dict[str, Any]] = {
    "paper-maze": {
        "envs": list(PAPER_MAZE),
        "methods": list(PAPER_METHODS),
        "seeds": list(range(1, 11)),
        "train": {"stop_on_solve": True},
        "env_overrides": _budgets(PAPER_MAZE, 200_000, 1_000_000, explore=True),
        "method_overrides": {"nm": NM_TRAIN},
    },
    # Issue 3's comparison: T-HCI-PPO beside LSTM-PPO on every maze level, 5 seeds, one set of
    # settings for all four levels (docs/results/maze-lstm-vs-thci). With the default PPO
    # settings on L1-L2, T-HCI's L2 seed 5 learned to go to one goal while its memory was still
    # empty and never left it (success 0.50 at 200k); the bonus for what the memory newly tells
    # apart solved it at 33k, and every other L1-L2 run of both methods too.
    # L3-L4 get 2M steps: PPO can sit at success ~0.75 (three of the four goals) for hundreds of
    # thousands of steps whatever the memory; at 1M, T-HCI L3 seed 4 (sufficient gate from its
    # first round) and LSTM L3 seed 2 had not solved, at 2M both had (1.97M and 1.29M; with
    # the search's substitutes T-HCI's seed 4 solves at 771k).
    "maze-lstm-vs-thci": {
        "envs": list(PAPER_MAZE),
        "methods": ["lstm", "t-hci"],
        "seeds": list(range(1, 6)),
        "train": {"stop_on_solve": True, **MAZE_HARD_TRAIN},
        "env_overrides": _budgets(PAPER_MAZE, 200_000, 2_000_000, explore=False),
    },
    "paper-maze-quick": {
        "envs": list(PAPER_MAZE),
        "methods": list(PAPER_METHODS),
        "seeds": [1, 2],
        "train": {"stop_on_solve": True},
        "env_overrides": _budgets(PAPER_MAZE, 60_000, 300_000, explore=True),
        "method_overrides": QUICK_SLOW_METHODS,
    },
    "paper-babyai": {
        "envs": list(PAPER_BABYAI),
        "methods": list(PAPER_METHODS),
        "seeds": list(range(1, 11)),
        "train": BABYAI_TRAIN,
        "env_overrides": _babyai_budgets(1_000_000, 3_000_000),
    },
    # Issue 4's comparison on BabyAI: LSTM-PPO beside T-HCI-PPO, 3 seeds, the BabyAI settings.
    # T-HCI-PPO solved L1 at 438k-1.31M steps and L2 at 2.34M-3.14M, so L1 gets 2M steps and
    # L2-L4 4M.
    "babyai-lstm-vs-thci": {
        "envs": list(PAPER_BABYAI),
        "methods": ["lstm", "t-hci"],
        "seeds": [1, 2, 3],
        "train": BABYAI_TRAIN,
        "env_overrides": _babyai_budgets(2_000_000, 4_000_000),
    },
    # Issue 4's algorithms: T-HCI with PPO, A2C and DMC on BabyAI-L1. A2C trains the LSTM per
    # rollout, so it needs 128-step rollouts (the BabyAI setting) and a smaller entropy bonus:
    # with 0.01 it solved seed 1 at 4.07M steps, with 0.03 it stayed at the guess to 3.2M
    # (docs/babyai.md, "A2C on level 1"). DMC keeps 2,048 episodes: with 256 its greedy policy
    # collapsed to turning in place at 1.41M (docs/babyai.md, "DMC with an episode buffer").
    "babyai-algos": {
        "envs": [PAPER_BABYAI[0]],
        "methods": ["t-hci"],
        "algos": ["ppo", "a2c", "dmc"],
        "seeds": [1, 2, 3],
        "train": {**BABYAI_TRAIN, "total_steps": 2_000_000},
        "algo_overrides": {
            "a2c": {"ent_coef": 0.01, "total_steps": 6_000_000},
            "dmc": {"dmc_buffer_episodes": 2048, "total_steps": 3_000_000},
        },
    },
    "paper-babyai-quick": {
        "envs": list(PAPER_BABYAI),
        "methods": list(PAPER_METHODS),
        "seeds": [1],
        "train": BABYAI_TRAIN,
        "env_overrides": _babyai_budgets(100_000, 100_000),
        "method_overrides": QUICK_SLOW_METHODS,
    },
    "ablation": {
        "envs": [PAPER_MAZE[2], PAPER_BABYAI[2]],
        "methods": list(ABLATION_METHODS),
        "seeds": list(range(1, 11)),
        "train": {"stop_on_solve": True},
        "env_overrides": {
            PAPER_MAZE[2]: {"total_steps": 1_000_000, **MAZE_HARD_TRAIN},
            PAPER_BABYAI[2]: {**BABYAI_TRAIN, **_babyai_level(PAPER_BABYAI[2], 3_000_000)},
        },
    },
    "ablation-quick": {
        "envs": [PAPER_MAZE[2]],
        "methods": list(ABLATION_METHODS),
        "seeds": [1, 2],
        "train": {"stop_on_solve": True, "total_steps": 300_000, **MAZE_HARD_TRAIN},
    },
}


@dataclass(frozen=True)
class Grid:
    """A validated experiment grid."""

    name: str
    envs: tuple[str, ...]
    methods: tuple[str, ...]
    algos: tuple[str, ...]
    seeds: tuple[int, ...]
    train: dict[str, Any]
    env_overrides: dict[str, dict[str, Any]]
    algo_overrides: dict[str, dict[str, Any]]
    method_overrides: dict[str, dict[str, Any]]

    def configs(self) -> list[TrainConfig]:
        """One TrainConfig per run, in grid order (run_dir not set yet)."""
        return [
            TrainConfig(
                env=env,
                method=method,  # type: ignore[arg-type]  (checked against Method by the bench)
                algo=algo,  # type: ignore[arg-type]
                seed=seed,
                progress=False,
                **{
                    **self.train,
                    **self.env_overrides.get(env, {}),
                    **self.algo_overrides.get(algo, {}),
                    **self.method_overrides.get(method, {}),
                },
            )
            for env, method, algo, seed in itertools.product(
                self.envs, self.methods, self.algos, self.seeds
            )
        ]


def available_methods() -> tuple[str, ...]:
    """Methods `thci train --method` accepts in this install."""
    return get_args(Method)


# A grid's override tables, each keyed by names from one of its lists; later ones win.
OVERRIDES = {"env_overrides": "envs", "algo_overrides": "algos", "method_overrides": "methods"}


def grid_from_dict(name: str, data: dict[str, Any]) -> Grid:
    """Validate a grid description (a preset or a parsed file); ThciError on any mistake."""
    known = {"envs", "methods", "algos", "seeds", "train", *OVERRIDES}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ThciError(f"grid {name}: unknown keys {unknown}; a grid has {sorted(known)}")
    lists: dict[str, tuple] = {}
    for key, kind in (("envs", str), ("methods", str), ("algos", str), ("seeds", int)):
        value = data.get(key, ["ppo"] if key == "algos" else None)
        if (
            not isinstance(value, list)
            or not value
            or not all(isinstance(v, kind) and not isinstance(v, bool) for v in value)
        ):
            raise ThciError(f"grid {name}: '{key}' must be a non-empty list of {kind.__name__}")
        lists[key] = tuple(dict.fromkeys(value))
    bad_algos = [a for a in lists["algos"] if a not in get_args(Algo)]
    if bad_algos:
        raise ThciError(f"grid {name}: unknown algos {bad_algos}; choose from {get_args(Algo)}")
    train = _check_fields(name, "train", data.get("train", {}))
    overrides = {
        key: _check_overrides(name, key, data.get(key, {}), lists[list_key])
        for key, list_key in OVERRIDES.items()
    }
    return Grid(
        name=name,
        envs=lists["envs"],
        methods=lists["methods"],
        algos=lists["algos"],
        seeds=lists["seeds"],
        train=train,
        env_overrides=overrides["env_overrides"],
        algo_overrides=overrides["algo_overrides"],
        method_overrides=overrides["method_overrides"],
    )


def _check_overrides(
    name: str, key: str, overrides: Any, names: tuple[str, ...]
) -> dict[str, dict[str, Any]]:
    """`key` (one of OVERRIDES): settings per name, each name in `names`."""
    if not isinstance(overrides, dict):
        raise ThciError(f"grid {name}: '{key}' must be a table of settings per name")
    for which in overrides:
        if which not in names:
            raise ThciError(f"grid {name}: {key} names {which!r}, which is not in the grid")
    return {
        which: _check_fields(name, f"{key}.{which}", fields) for which, fields in overrides.items()
    }


def _check_fields(name: str, where: str, fields: Any) -> dict[str, Any]:
    if not isinstance(fields, dict):
        raise ThciError(f"grid {name}: '{where}' must be a table of `thci train` settings")
    unknown = sorted(set(fields) - TRAIN_FIELDS)
    if unknown:
        hint = " (set by the grid itself)" if set(unknown) & GRID_FIELDS else ""
        raise ThciError(
            f"grid {name}: '{where}' has unknown settings {unknown}{hint}; use TrainConfig "
            "field names, e.g. total_steps, stop_on_solve (see `thci train --help`)"
        )
    return dict(fields)


def load_grid(preset_or_path: str) -> Grid:
    """The preset named `preset_or_path`, or the grid in that TOML/YAML file."""
    if preset_or_path in PRESETS:
        return grid_from_dict(preset_or_path, PRESETS[preset_or_path])
    path = Path(preset_or_path)
    if not path.is_file():
        raise ThciError(
            f"{preset_or_path!r} is neither a preset ({', '.join(PRESETS)}) nor a grid file"
        )
    text = path.read_text()
    if path.suffix == ".toml":
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ThciError(f"{path} is not valid TOML ({exc})") from None
    elif path.suffix in (".yaml", ".yml"):
        data = _load_yaml(path, text)
    else:
        raise ThciError(f"{path}: a grid file must end in .toml, .yaml or .yml")
    if not isinstance(data, dict):
        raise ThciError(f"{path} must hold a table with envs, methods and seeds")
    return grid_from_dict(path.name, data)


def _load_yaml(path: Path, text: str) -> Any:
    try:
        import yaml
    except ImportError:
        raise ThciError(
            f"{path}: reading YAML needs PyYAML (pip install pyyaml), or write the grid as TOML"
        ) from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        reason = " ".join(str(exc).split())
        raise ThciError(f"{path} is not valid YAML ({reason})") from None

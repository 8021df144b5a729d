"""The training loop: collect a rollout, update the agent, log, checkpoint; repeat.

Read :func:`train` top to bottom: it is the whole run. Everything that can be wrong with the
user's input is checked before the run directory is created, and a run killed at any point
resumes from its last checkpoint to the same result an uninterrupted run gives.
"""

from __future__ import annotations

import dataclasses
import math
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium.vector import VectorEnv
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

import thci
from thci.causal.gate import Gate, GateSpec
from thci.causal.loop import CausalInferenceLoop, CIWorker, start_ci_worker
from thci.causal.taie import kept_observations, measure_taie
from thci.config import (
    CAUSAL_METHODS,
    DEFAULT_CELL_LAYOUT,
    GATED_METHODS,
    WEIGHING_METHODS,
    TrainConfig,
)
from thci.envs.factory import CELL_LAYOUT_KEY, make_vector_env
from thci.errors import ThciError
from thci.experiments.run_dir import (
    MetricsLog,
    RunDirectory,
    atomic_write_bytes,
    atomic_write_json,
)
from thci.memory import make_memory
from thci.rl.agent import ActorCritic
from thci.rl.dmc import DMC, epsilon_at
from thci.rl.encoders import observation_categories
from thci.rl.exploration import make_exploration_bonus
from thci.rl.ppo import A2C, PPO
from thci.rl.rollout import RolloutCollector
from thci.rl.tracking import SolveTracker

# summary.json fields that depend on the machine's speed, not on the seed.
TIMING_FIELDS = (
    "wall_clock_s",
    "steps_per_second",
    "ci_wall_clock_s",
    "ci_round_seconds",
    "ci_blocking_s",
    "final_ci_seconds",
)


def build_agent(config: TrainConfig, envs: VectorEnv) -> ActorCritic:
    """The agent for `config.method` on the spaces of `envs` (initialized from torch's RNG).

    T-HCI and HCI use the causal memory: an LSTM behind a gate fitted by the CI loop.
    """
    config = with_cell_layout(config, envs)
    causal = config.method in CAUSAL_METHODS
    observation_size = int(envs.single_observation_space.shape[0])
    memory = make_memory(
        "lstm" if causal else config.method,
        config.encoder_size,
        config.hidden_size,
        observation_size=observation_size,
        babyai_observations=config.env.startswith("thci/BabyAI-"),
        window=config.history_window,
        hai_read=config.hai_read,
        nm_map_size=config.nm_map_size,
        nm_channels=config.nm_channels,
        wmg_memos=config.wmg_memos,
        wmg_layers=config.wmg_layers,
        wmg_heads=config.wmg_heads,
        wmg_head_size=config.wmg_head_size,
    )
    categories = observation_categories(envs.single_observation_space)
    gate = None
    if causal:  # built only when used: building it draws from torch's RNG, as the agent does
        gate_spec = GateSpec(
            observation_size,
            categories,
            config.cell_layout if config.discretizer == "cell-set" else None,
        )
        gate = gate_spec.build(empty_before_fit=config.ci_initial_memory == "empty")
    return ActorCritic(
        observation_size,
        int(envs.single_action_space.n),
        memory,
        config.encoder_size,
        gate=gate,
        categories=categories,
        encoder=config.encoder,
        cell_layout=config.cell_layout,
    )


def make_algorithm(config: TrainConfig) -> PPO | DMC:
    """The update rule named by ``--algo``."""
    if config.algo == "dmc":
        return DMC(config, config.num_envs)
    return A2C(config) if config.algo == "a2c" else PPO(config)


def default_run_dir(config: TrainConfig) -> Path:
    """runs/<env>__<method>__<algo>__s<seed>__<timestamp>."""
    env = config.env.split(":")[-1].replace("/", "_")
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{env}__{config.method}__{config.algo}__s{config.seed}__{stamp}"


def train(config: TrainConfig) -> dict[str, Any]:
    """Train as `config` says; returns the summary also written to summary.json."""
    config.validate()
    torch.set_num_threads(config.torch_threads)
    # The CI worker's start-up (a fresh interpreter importing torch, ~1.3 s) overlaps the
    # run's own; started with the first rollout instead, it was not ready for the first round.
    # The CI loop closes it at the end of training; this closes it too when training fails first.
    worker = start_ci_worker() if config.method in CAUSAL_METHODS and config.ci_async else None
    envs = None
    try:
        envs = make_vector_env(config.env, config.num_envs, config.vectorization)
        config = with_cell_layout(config, envs)
        _check_info_keys(config, envs)
        config = dataclasses.replace(config, run_dir=config.run_dir or default_run_dir(config))
        assert config.run_dir is not None
        if config.resume:
            run = RunDirectory.open_for_resume(config.run_dir, config)
            checkpoint = run.load_checkpoint()  # fail on a corrupt one before touching files
        else:
            run = RunDirectory.create(config.run_dir, config)
            checkpoint = None
        return _train(config, envs, run, checkpoint, worker)
    finally:
        if envs is not None:
            envs.close()
        if worker is not None:
            worker.close()


def with_cell_layout(config: TrainConfig, envs: VectorEnv) -> TrainConfig:
    """`config` with ``cell_layout`` filled in when it was left to the environment: where
    :func:`~thci.envs.factory.make_vector_env` found a minigrid image, else
    ``DEFAULT_CELL_LAYOUT`` (the thci/BabyAI levels'). The run's config.json records it."""
    if config.cell_layout is not None:
        return config
    layout = envs.metadata.get(CELL_LAYOUT_KEY, DEFAULT_CELL_LAYOUT)
    return dataclasses.replace(config, cell_layout=tuple(layout))


# What a memory's side input means, for the error when the environment does not report it.
SIDE_INPUT_NEEDS = {"agent_pos": "the agent's grid position", "causal": "the human labels"}


def _check_info_keys(config: TrainConfig, envs: VectorEnv) -> None:
    """Fail with one line, before a run directory exists, when the environment's info lacks an
    entry that --count-key or the method's memory reads."""
    needed: list[tuple[str, str]] = []
    if config.exploration != "none" and config.count_key is not None:
        needed.append((config.count_key, "for --count-key; count observations by leaving it out"))
    for key, _ in build_agent(config, envs).memory.side_inputs:  # the seed resets it in _train
        if key in SIDE_INPUT_NEEDS:
            needed.append((key, f"which --method {config.method} needs ({SIDE_INPUT_NEEDS[key]})"))
    if not needed:
        return
    _, infos = envs.reset(seed=config.seed)
    for key, why in needed:
        if key not in infos:
            reported = ", ".join(k for k in infos if not k.startswith("_")) or "nothing"
            raise ThciError(
                f"{config.env} reports no info[{key!r}] {why} (its info holds: {reported})"
            )


def _train(
    config: TrainConfig,
    envs: VectorEnv,
    run: RunDirectory,
    checkpoint: dict[str, Any] | None,
    worker: CIWorker | None = None,
) -> dict[str, Any]:
    torch.manual_seed(config.seed)
    agent = build_agent(config, envs)
    optimizer = torch.optim.Adam(agent.policy_parameters(), lr=config.learning_rate, eps=1e-5)
    counted = (config.count_key,) if config.exploration != "none" and config.count_key else ()
    dmc = config.algo == "dmc"
    collector = RolloutCollector(
        envs,
        agent,
        config.num_steps,
        config.gamma,
        config.success_return,
        info_keys=counted,
        epsilon=config.dmc_epsilon_start if dmc else None,
        bootstrap_truncation=not dmc,
    )
    tracker = SolveTracker(config.solve_window, config.solve_threshold)
    algorithm = make_algorithm(config)
    count_memory = config.count_memory and config.method in GATED_METHODS
    bonus = make_exploration_bonus(
        config.exploration,
        envs.single_observation_space,
        config.count_beta,
        config.discretizer,
        config.count_key,
        config.num_envs,
        count_memory,
        config.cell_layout,
    )
    ci = None
    if agent.gate is not None:
        ci = CausalInferenceLoop(
            config,
            envs.single_observation_space,
            int(envs.single_action_space.n),
            config.num_envs,
            agent.gate,
            worker,
        )
    steps_per_update = config.num_envs * config.num_steps
    num_updates = math.ceil(config.total_steps / steps_per_update)
    num_parameters = sum(p.numel() for p in agent.parameters())

    update, global_step, wall_clock_before = 0, 0, 0.0
    if checkpoint is None:
        collector.reset(config.seed)
    else:
        try:
            agent.load_state_dict(checkpoint["agent"])
            optimizer.load_state_dict(checkpoint["optimizer"])
        except (KeyError, RuntimeError, ValueError) as exc:
            raise ThciError(
                f"checkpoint {run.checkpoint_path} does not match this model "
                f"({checkpoint_mismatch(checkpoint, agent, exc)}); resume with the settings "
                "and the thci version that wrote it"
            ) from None
        update, global_step = checkpoint["update"], checkpoint["global_step"]
        wall_clock_before = checkpoint["wall_clock_s"]
        tracker.load_state_dict(checkpoint["tracker"])
        algorithm.load_state_dict(checkpoint["algorithm"])
        if ci is not None:
            ci.load_state_dict(checkpoint["ci"])
        if bonus is not None:
            bonus.load_state_dict(checkpoint["exploration"])
        torch.set_rng_state(checkpoint["torch_rng"])
        if not collector.load_state_dict(checkpoint["collector"], seed=config.seed + update):
            tqdm.write(f"note: {config.env} cannot save its state; episodes restart on resume")

    metrics = MetricsLog(run.metrics_path, keep_until_update=update if checkpoint else None)
    writer = SummaryWriter(str(run.tensorboard_path), purge_step=global_step or None)
    if checkpoint is None:
        tqdm.write(
            f"thci: {config.method}-{config.algo} on {config.env}, "
            f"{num_parameters} parameters, run dir {run.path}"
        )

    started = time.perf_counter()
    bar = tqdm(
        total=num_updates * steps_per_update,
        initial=global_step,
        unit="step",
        disable=not config.progress,
        dynamic_ncols=True,
        desc=config.env,
    )

    def save_checkpoint() -> None:
        run.save_checkpoint(
            {
                "config": config.to_dict(),
                "update": update,
                "global_step": global_step,
                "wall_clock_s": wall_clock_before + time.perf_counter() - started,
                "agent": agent.state_dict(),
                "optimizer": optimizer.state_dict(),
                "collector": collector.state_dict(),
                "tracker": tracker.state_dict(),
                "algorithm": algorithm.state_dict(),
                "ci": None if ci is None else ci.state_dict(),
                "exploration": None if bonus is None else bonus.state_dict(),
                "torch_rng": torch.get_rng_state(),
            }
        )

    try:
        # A run that stops on solve stops there; a CI round in flight is dropped (its gate would
        # reach a policy that solved without it, at the step the run ends).
        while update < num_updates and not (config.stop_on_solve and tracker.solved):
            if config.anneal_lr:
                for group in optimizer.param_groups:
                    group["lr"] = config.learning_rate * (1 - update / num_updates)
            if dmc:  # a function of the step count alone, so resumption needs no extra state
                collector.epsilon = epsilon_at(config, global_step)
                writer.add_scalar("charts/epsilon", collector.epsilon, global_step)
            rollout, episodes = collector.collect()
            tracker.add(episodes, global_step, config.num_envs)
            global_step += steps_per_update
            if bonus is not None:
                kept = kept_observations(agent, rollout) if count_memory else None
                mean_bonus = bonus.add_bonus(rollout, collector.obs, kept)
                writer.add_scalar("charts/intrinsic_reward", mean_bonus, global_step)
            if ci is not None:  # the CI loop runs on the pool beside the RL updates (Fig. 3)
                ci.observe(rollout)
                # This update trains on the rollout as collected, never with a new gate, so a
                # round due now runs beside it.
                ci.start_if_due(global_step, solved=tracker.solved)
            losses = algorithm.update(agent, optimizer, rollout)
            update += 1
            if ci is not None:
                kept_before = None if ci.last_result is None else ci.last_result.causal
                record = ci.step(global_step, solved=tracker.solved)
                if record is not None:
                    write_ci_rounds(run, ci)
                    kept = ci.last_result.causal
                    if isinstance(algorithm, DMC) and not np.array_equal(kept_before, kept):
                        algorithm.refit(agent, optimizer)  # Q was fitted to the old memory
                    if bonus is not None and bonus.memory is not None:  # --count-memory
                        bonus.memory.set_gate(kept)
                    for key in ("interventions", "observed", "causal", "seconds"):
                        writer.add_scalar(f"ci/{key}", getattr(record, key), global_step)
                    writer.add_scalar("ci/blocking_seconds", record.blocking_seconds, global_step)
                    tqdm.write(
                        f"CI round {record.round} (pool at {record.global_step} steps, gate from "
                        f"{global_step}): |Ô|={record.observed}, {record.interventions} "
                        f"interventions, keeps {ci.describe_causal()}, {record.seconds:.1f}s, "
                        f"RL waited {record.blocking_seconds:.1f}s"
                    )

            elapsed = wall_clock_before + time.perf_counter() - started
            row = {
                "update": update,
                "global_step": global_step,
                "episodes": tracker.episodes,
                "success_rate": tracker.success_rate,
                "episodic_return": tracker.mean_reward,
                "episodic_length": tracker.mean_length,
                "learning_rate": optimizer.param_groups[0]["lr"],
                **losses,
                "wall_clock_s": elapsed,
            }
            metrics.append(row)
            for key in ("success_rate", "episodic_return", "episodic_length", "learning_rate"):
                writer.add_scalar(f"charts/{key}", row[key], global_step)
            writer.add_scalar("charts/SPS", global_step / max(elapsed, 1e-9), global_step)
            for key, value in losses.items():
                writer.add_scalar(f"losses/{key}", value, global_step)
            bar.update(steps_per_update)
            bar.set_postfix(success=f"{tracker.success_rate:.2f}", ret=f"{tracker.mean_reward:.2f}")
            if update % config.checkpoint_every == 0:
                save_checkpoint()
    except BaseException as exc:
        if ci is not None:
            ci.close()
        if isinstance(exc, KeyboardInterrupt):
            raise ThciError(
                f"interrupted; continue with: thci train --resume --run-dir {run.path}"
            ) from None
        raise
    finally:
        bar.close()
        writer.close()
    try:
        save_checkpoint()
        wall_clock = wall_clock_before + time.perf_counter() - started
        # Measurements of the trained run, not part of its wall-clock (like TAIE below); the
        # final CI round still has the CI worker for half of its fit.
        final_ci, final_ci_seconds = (
            _final_inference(agent, ci, config, tracker.solved)
            if ci is not None and config.ci_final
            else (None, None)
        )
    finally:
        if ci is not None:
            ci.close()
    summary = {
        "env_id": config.env,
        "method": config.method,
        "algo": config.algo,
        "seed": config.seed,
        "total_env_steps": global_step,
        "updates": update,
        "episodes": tracker.episodes,
        "solved": tracker.solved if tracker.success_known else None,
        "steps_to_solve": tracker.steps_to_solve,
        "success_rate_last100": _finite_or_none(tracker.success_rate),
        "mean_return_last100": _finite_or_none(tracker.mean_reward),
        "num_parameters": num_parameters,
        **(ci.summary() if ci is not None else {}),
        **_taie(agent, config),
        **({} if ci is None else {"final_ci": final_ci, "final_ci_seconds": final_ci_seconds}),
        "wall_clock_s": round(wall_clock, 3),
        "steps_per_second": round(global_step / max(wall_clock, 1e-9), 1),
        "thci_version": thci.__version__,
    }
    run.write_summary(summary)
    return summary


def checkpoint_mismatch(checkpoint: dict[str, Any], agent: ActorCritic, exc: Exception) -> str:
    """One line saying how a checkpoint's parameters differ from the model's."""
    saved = checkpoint.get("agent")
    if not isinstance(saved, dict):
        return str(exc).splitlines()[0]
    missing = sorted(set(agent.state_dict()) - set(saved))
    unexpected = sorted(set(saved) - set(agent.state_dict()))
    if not missing and not unexpected:
        return "parameters of other shapes"
    return f"missing {missing[:3]}, unexpected {unexpected[:3]}"


def _taie(agent: ActorCritic, config: TrainConfig, gate: Gate | None = None) -> dict[str, Any]:
    """summary.json's ``taie`` of the trained agent (of `gate` instead of its own, if given;
    one value per attention head for SAI) and ``taie_trajectories`` (whose trajectories: the
    environment's expert when it has one, else the greedy policy's); None for memories that
    weigh nothing."""
    if config.method not in WEIGHING_METHODS:
        return {"taie": None, "taie_trajectories": None}
    taie = measure_taie(
        agent, config.env, seed=config.seed + 20_000, vectorization=config.vectorization, gate=gate
    )
    value = taie.rounded()
    return {"taie": value, "taie_trajectories": taie.trajectories if value is not None else None}


def _final_inference(
    agent: ActorCritic, ci: CausalInferenceLoop, config: TrainConfig, solved: bool
) -> tuple[dict[str, Any] | None, float | None]:
    """summary.json's ``final_ci`` (a CI round on the final pool, not applied to the policy,
    with the TAIE of its gate on the trained policy's trajectories) and its seconds; None, None
    when the pool is too small for a round, or when the run `solved`: its pool then comes from
    a policy that acts on its memory, where causes show no effect (no round starts during
    training either, see CausalInferenceLoop.due; the quick start's final round kept [] there,
    TAIE 0.11, beside the gate [0, 1] the policy solved with)."""
    if solved:
        tqdm.write(
            "no final CI round: the run solved, and a solving policy's pool shows no effects"
        )
        return None, None
    tqdm.write("final CI round on the whole pool (--no-ci-final skips it)")
    final = ci.final_inference()
    if final is None:
        return None, None
    fields, gate, seconds = final
    return {**fields, **_taie(agent, config, gate)}, round(seconds, 3)


def write_ci_rounds(run: RunDirectory, ci: CausalInferenceLoop) -> None:
    """ci_rounds.csv (one row per CI round) and ci_interventions.json (every intervention: the
    observations intervened on, the ATE, the batch's seconds), rewritten whole each round."""
    rows = [dataclasses.asdict(r) for r in ci.rounds]
    lines = [",".join(rows[0])] + [",".join(str(v) for v in r.values()) for r in rows]
    atomic_write_bytes(run.path / "ci_rounds.csv", ("\n".join(lines) + "\n").encode())
    atomic_write_json(run.path / "ci_interventions.json", ci.intervention_log)


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None

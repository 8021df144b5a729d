"""The CI loop of a trained t-hci/hci run, restored from its checkpoint (for the benchmarks)."""

from __future__ import annotations

from pathlib import Path

from thci.causal.loop import CausalInferenceLoop
from thci.config import TrainConfig
from thci.rl.evaluate import load_run


def load_ci_loop(run_dir: Path, cold: bool = False) -> tuple[TrainConfig, CausalInferenceLoop]:
    """The run's config and its CI loop with the pool (and, unless `cold`, the effect
    predictor) of its last checkpoint; a round that was in flight is not restarted."""
    config, envs, agent, checkpoint = load_run(run_dir, 1, seed=0)
    envs.close()
    if agent.gate is None:
        raise SystemExit(f"{run_dir} is not a t-hci/hci run")
    loop = CausalInferenceLoop(
        config, envs.single_observation_space, int(envs.single_action_space.n), 1, agent.gate
    )
    state = checkpoint["ci"]
    state["round_in_flight"] = None
    if cold:
        state["predictor"] = None
    loop.load_state_dict(state)
    return config, loop

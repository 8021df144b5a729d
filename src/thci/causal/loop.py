"""The CI loop of Fig. 3: replay pool -> HCI / T-HCI -> gate, alternating with the RL loop.

After every rollout the loop discretizes the observations, cuts the rollout into whole
episodes and adds them to the replay pool. On its schedule it runs a CI round: fit the effect
predictor on the pool, search the observed space Ô for the observations without causal effect
(O^w), and fit the gate to O^w (Eq. 10), from which moment the agent's causal memory drops
those observations. Rounds stop once two in a row agree (or after ``ci_max_rounds``).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from thci.causal.discretize import Discretizer, discretizer_from_state, make_discretizer
from thci.causal.gate import Gate
from thci.causal.predictor import EffectEstimator, PredictorConfig
from thci.causal.replay import PoolEpisode, ReplayPool, pad_episodes
from thci.causal.search import CIResult, hci, t_hci
from thci.config import TrainConfig
from thci.rl.episodes import EpisodeAssembler
from thci.rl.rollout import Rollout


@dataclass(frozen=True)
class CIRound:
    """What one CI round did (a row of ci_rounds.csv)."""

    round: int
    global_step: int
    pool_episodes: int
    observed: int
    interventions: int
    eliminated: int
    causal: int
    seconds: float
    gate_accuracy: float


class CausalInferenceLoop:
    """Replay pool, discretizer, search and gate of one training run.

    Args:
        config: the run's config (method "hci" or "t-hci", ci_* settings).
        observation_space: the flat single-env observation space.
        num_actions: A.
        num_envs: N, the rollouts' width.
        gate: the agent's gate, fitted here after each round.
    """

    def __init__(
        self,
        config: TrainConfig,
        observation_space: gym.Space,
        num_actions: int,
        num_envs: int,
        gate: Gate,
    ) -> None:
        self.config, self.observation_space = config, observation_space
        self.num_actions, self.gate = num_actions, gate
        self.pool = ReplayPool(config.ci_pool_episodes)
        self.discretizer: Discretizer | None = None
        self.assembler = EpisodeAssembler(num_envs)
        self.rounds: list[CIRound] = []
        self.intervention_log: list[dict[str, Any]] = []
        self.last_result: CIResult | None = None
        self.stable_rounds = 0
        self.next_round_step = config.ci_every

    # ------------------------------------------------------------------ the RL loop's side
    def observe(self, rollout: Rollout) -> None:
        """Add the episodes that ended in `rollout` to the pool (unfinished ones carry over)."""
        T, N = rollout.dones.shape
        obs = rollout.obs.numpy()
        if self.discretizer is None:  # chosen from the first data, e.g. one-hot -> exact codes
            self.discretizer = make_discretizer(
                self.config.discretizer, self.observation_space, sample=obs.reshape(T * N, -1)
            )
        codes = self.discretizer.encode(obs.reshape(T * N, -1)).reshape(T, N)
        dones = rollout.dones.numpy()
        final_obs = rollout.final_obs.numpy()
        final_codes = np.full((T, N), -1, dtype=np.int64)
        if dones.any():
            final_codes[dones] = self.discretizer.encode(final_obs[dones])
        steps = {
            "codes": codes,
            "obs": obs,
            "actions": rollout.actions.numpy(),
            "rewards": rollout.env_rewards.numpy(),
        }
        labelled = rollout.causal is not None and rollout.final_causal is not None
        if labelled:
            steps["causal"] = rollout.causal.numpy()
        for n, end, piece in self.assembler.add(steps, dones):
            episode = PoolEpisode(
                codes=np.append(piece["codes"], final_codes[end, n]),
                actions=piece["actions"],
                rewards=piece["rewards"].astype(np.float32),
                causal=np.append(piece["causal"], rollout.final_causal[end, n].item())
                if labelled
                else None,
            )
            self.pool.add(episode, np.concatenate([piece["obs"], final_obs[end, n][None]]))

    # ------------------------------------------------------------------ the CI loop's side
    def due(self, global_step: int) -> bool:
        """Whether a CI round should run now."""
        return (
            global_step >= self.next_round_step
            and len(self.pool) >= self.config.ci_min_episodes
            and self.pool.num_rewarded >= self.config.ci_min_rewarded_episodes
            and len(self.rounds) < self.config.ci_max_rounds
            and self.stable_rounds < 2
        )

    def run_round(self, global_step: int) -> CIRound:
        """One CI round on the pool: search Ô, then fit the gate to O^w."""
        started = time.perf_counter()
        cfg = self.config
        predictor = PredictorConfig(
            target=cfg.ci_target,
            base_steps=cfg.ci_base_steps,
            finetune_steps=cfg.ci_finetune_steps,
            seed=cfg.seed + len(self.rounds),
        )
        rl_threads = torch.get_num_threads()
        torch.set_num_threads(cfg.ci_threads)
        with torch.random.fork_rng():  # CI must not shift the RL loop's random stream
            estimator = EffectEstimator(self.pool.arrays(), self.num_actions, predictor)
            if cfg.method == "hci":
                result = hci(estimator, xi=cfg.ci_xi)
            else:
                result = t_hci(estimator, z=cfg.ci_z, xi=cfg.ci_xi)
        torch.set_num_threads(rl_threads)
        observations = torch.as_tensor(
            np.stack([self.pool.observations[int(c)] for c in result.observed]),
            dtype=torch.float32,
        )
        eliminated = torch.as_tensor(np.isin(result.observed, result.eliminated))
        fit = self.gate.fit(observations, eliminated)

        same = self.last_result is not None and np.array_equal(
            self.last_result.causal, result.causal
        )
        self.stable_rounds = self.stable_rounds + 1 if same else 1
        self.last_result = result
        self.next_round_step = global_step + cfg.ci_every
        record = CIRound(
            round=len(self.rounds) + 1,
            global_step=global_step,
            pool_episodes=len(self.pool),
            observed=len(result.observed),
            interventions=result.num_interventions,
            eliminated=len(result.eliminated),
            causal=len(result.causal),
            seconds=time.perf_counter() - started,
            gate_accuracy=fit.accuracy,
        )
        self.rounds.append(record)
        for item in result.interventions:
            self.intervention_log.append(
                {
                    "round": record.round,
                    "observations": self._describe(item.codes),
                    "ate": round(item.ate, 5),
                    "kind": item.kind,
                    "batch_seconds": round(item.seconds, 4),
                }
            )
        return record

    def describe_causal(self) -> list[int]:
        """The causal observations of the last round, as the index of the one-hot entry when
        observations are one-hot (e.g. the maze's cell codes), else as discretizer codes."""
        return [] if self.last_result is None else self._describe(self.last_result.causal)

    def _describe(self, codes) -> list[int]:
        described = []
        for code in codes:
            obs = self.pool.observations[int(code)]
            one_hot = obs.ndim == 1 and np.isin(obs, (0, 1)).all() and obs.sum() == 1
            described.append(int(obs.argmax()) if one_hot else int(code))
        return sorted(described)

    def summary(self) -> dict[str, Any]:
        """The CI fields of summary.json."""
        return {
            "ci_rounds": len(self.rounds),
            "interventions": sum(r.interventions for r in self.rounds),
            "interventions_per_round": [r.interventions for r in self.rounds],
            "observation_space_size": self.rounds[-1].observed if self.rounds else None,
            "causal_observations": self.describe_causal(),
            "ci_wall_clock_s": round(sum(r.seconds for r in self.rounds), 3),
            "ci_round_seconds": [round(r.seconds, 3) for r in self.rounds],
        }

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Pool, pending episodes, discretizer and schedule (tensors and plain values only)."""
        episodes = list(self.pool.episodes)
        arrays = pad_episodes(episodes) if episodes else None
        labelled = bool(episodes) and episodes[0].causal is not None
        return {
            "pool": None
            if arrays is None
            else {
                "codes": torch.as_tensor(arrays.codes),
                "actions": torch.as_tensor(arrays.actions),
                "rewards": torch.as_tensor(arrays.rewards),
                "lengths": torch.as_tensor(arrays.lengths),
                "causal": [torch.as_tensor(e.causal) for e in episodes] if labelled else None,
            },
            "observations": {int(c): torch.as_tensor(o) for c, o in self.pool.observations.items()},
            "pending": self.assembler.state_dict(),
            "discretizer": None if self.discretizer is None else self.discretizer.state_dict(),
            "rounds": [asdict(r) for r in self.rounds],
            "intervention_log": self.intervention_log,
            "last_causal": None
            if self.last_result is None
            else torch.as_tensor(self.last_result.causal),
            "last_eliminated": None
            if self.last_result is None
            else torch.as_tensor(self.last_result.eliminated),
            "last_observed": None
            if self.last_result is None
            else torch.as_tensor(self.last_result.observed),
            "stable_rounds": self.stable_rounds,
            "next_round_step": self.next_round_step,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Inverse of :meth:`state_dict`."""
        self.pool = ReplayPool(self.config.ci_pool_episodes)
        pool = state["pool"]
        if pool is not None:
            for i, length in enumerate(pool["lengths"].tolist()):
                self.pool.add(
                    PoolEpisode(
                        codes=pool["codes"][i, : length + 1].numpy(),
                        actions=pool["actions"][i, :length].numpy(),
                        rewards=pool["rewards"][i, :length].numpy(),
                        causal=None if pool["causal"] is None else pool["causal"][i].numpy(),
                    )
                )
        self.pool.observations = {c: o.numpy() for c, o in state["observations"].items()}
        self.assembler.load_state_dict(state["pending"])
        if state["discretizer"] is not None:
            self.discretizer = discretizer_from_state(state["discretizer"])
        self.rounds = [CIRound(**r) for r in state["rounds"]]
        self.intervention_log = state["intervention_log"]
        if state["last_causal"] is not None:
            self.last_result = CIResult(
                "restored",
                state["last_observed"].numpy(),
                state["last_eliminated"].numpy(),
                state["last_causal"].numpy(),
            )
        self.stable_rounds = state["stable_rounds"]
        self.next_round_step = state["next_round_step"]

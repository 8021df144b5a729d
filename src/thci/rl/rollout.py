"""Collect fixed-length rollouts from a SAME_STEP-autoreset vector env (the RL loop of Fig. 3).

The collector is shared by every algorithm: it steps N environments T times with the agent,
keeps the agent's memory state across rollouts, bootstraps truncated episodes with the value
of their final observation, and reports each finished episode (return, length, success).

Side inputs: a memory may read more than the observation each step (the Neural Map the agent's
position, the Oracle the human label, hard attention a uniform draw; see
:attr:`thci.memory.Memory.side_inputs`). The collector reads them from the step's ``info`` (or
draws the noise) and keeps them next to the observation: ``Rollout.side``, and
``Rollout.inputs`` = observation ⊕ side inputs is what the agent acts on. So they travel through
PPO/A2C minibatches, DMC's episodes and the checkpoint like the observation itself, with no
algorithm knowing about them, while ``Rollout.obs`` stays the plain observation that the
replay pool, the discretizer and the exploration bonus see.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from gymnasium.vector import VectorEnv

from thci.errors import ThciError
from thci.memory import NOISE
from thci.rl.agent import ActorCritic


@dataclass
class Rollout:
    """T steps of N environments, time-major.

    Attributes:
        obs: (T, N, D) observation the agent acted on.
        actions: (T, N) long.
        logprobs: (T, N) log pi(a_t | h_t) at collection time.
        values: (T, N) V(h_t) at collection time.
        rewards: (T, N) reward, plus gamma * V(final obs) where an episode was truncated.
        dones: (T, N) bool, the episode ended with step t (terminated or truncated).
        episode_starts: (T, N) bool, obs[t] is the first observation of an episode.
        initial_state: (N, S) memory state before step 0 (used where episodes continue).
        last_value: (N,) V of the observation after step T-1 (for bootstrapping).
        env_rewards: (T, N) the environment's reward (without the truncation bootstrap).
        final_obs: (T, N, D) last observation of the episodes that ended with step t (zeros
            elsewhere).
        causal: (T, N) bool info["causal"] of obs, or None when the env gives no labels.
        final_causal: (T, N) bool info["causal"] of final_obs, or None.
        reached_info: the requested info keys of the observation each step reached, each
            (T, N, ...) (the final observation's info where an episode ended).
        side: (T, N, E) the memory's side inputs of obs (E = 0 for most memories; None: none).
    """

    obs: torch.Tensor
    actions: torch.Tensor
    logprobs: torch.Tensor
    values: torch.Tensor
    rewards: torch.Tensor
    dones: torch.Tensor
    episode_starts: torch.Tensor
    initial_state: torch.Tensor
    last_value: torch.Tensor
    env_rewards: torch.Tensor
    final_obs: torch.Tensor
    causal: torch.Tensor | None
    final_causal: torch.Tensor | None
    reached_info: dict[str, np.ndarray]
    side: torch.Tensor | None = None

    @property
    def inputs(self) -> torch.Tensor:
        """(T, N, D + E) what the agent acted on: the observation followed by the side inputs."""
        if self.side is None or self.side.shape[-1] == 0:
            return self.obs
        return torch.cat((self.obs, self.side), dim=-1)


@dataclass(frozen=True)
class Episode:
    """A finished episode of environment `env`; `step` is its last step's index in the rollout."""

    reward: float
    length: int
    success: bool | None
    step: int
    env: int


class RolloutCollector:
    """Steps a vector env with an agent, one rollout of `num_steps` steps at a time.

    Args:
        envs: vector env with SAME_STEP autoreset and flat Box observations.
        agent: the actor-critic.
        num_steps: T, steps per environment per rollout.
        gamma: discount, for the truncation bootstrap.
        success_return: for envs without info["success"], the return that counts as success.
        greedy: act with the most likely action instead of sampling (for evaluation).
        info_keys: info entries to record for every reached observation (e.g. "agent_pos").
        epsilon: act epsilon-greedily on the policy head's outputs (DMC's Q-values) instead of
            sampling from their softmax.
        bootstrap_truncation: credit gamma * V(final observation) to truncated episodes (off
            for DMC, whose targets are plain Monte-Carlo returns).
        expert: act with the environments' own expert (:func:`has_expert`) instead of the
            agent, which still runs alongside (its memory sees the expert's trajectories).
    """

    def __init__(
        self,
        envs: VectorEnv,
        agent: ActorCritic,
        num_steps: int,
        gamma: float,
        success_return: float | None = None,
        greedy: bool = False,
        info_keys: tuple[str, ...] = (),
        epsilon: float | None = None,
        bootstrap_truncation: bool = True,
        expert: bool = False,
    ) -> None:
        if expert and not has_expert(envs):
            raise ThciError(
                "this environment has no expert: expert trajectories need an env whose "
                "unwrapped class defines expert_action() -> int (thci's BabyAI levels do)"
            )
        self.envs, self.agent, self.expert = envs, agent, expert
        self.num_envs, self.num_steps, self.gamma = envs.num_envs, num_steps, gamma
        self.success_return, self.greedy = success_return, greedy
        self.info_keys = info_keys
        self.epsilon, self.bootstrap_truncation = epsilon, bootstrap_truncation
        self.obs = torch.zeros(0)
        self.side_inputs = agent.memory.side_inputs
        self.side = torch.zeros(self.num_envs, agent.memory.side_size)
        self.causal: torch.Tensor | None = None
        self.episode_start = torch.ones(self.num_envs, dtype=torch.bool)
        self.state = agent.initial_state(self.num_envs)
        self.episode_reward = np.zeros(self.num_envs)
        self.episode_length = np.zeros(self.num_envs, dtype=np.int64)

    def reset(self, seed: int) -> None:
        """Start fresh episodes in every environment."""
        obs, infos = self.envs.reset(seed=seed)
        self.obs = torch.as_tensor(obs, dtype=torch.float32)
        self.side = self._side(infos)
        self.causal = _labels(infos)
        self.episode_start[:] = True
        self.state = self.agent.initial_state(self.num_envs)
        self.episode_reward[:] = 0
        self.episode_length[:] = 0

    @torch.no_grad()
    def collect(self) -> tuple[Rollout, list[Episode]]:
        """Run T steps in each environment; return the rollout and the episodes that ended."""
        T, N = self.num_steps, self.num_envs
        obs = torch.zeros(T, N, *self.obs.shape[1:])
        side = torch.zeros(T, N, self.side.shape[1])
        actions = torch.zeros(T, N, dtype=torch.long)
        logprobs, values, rewards = (torch.zeros(T, N) for _ in range(3))
        dones = torch.zeros(T, N, dtype=torch.bool)
        episode_starts = torch.zeros(T, N, dtype=torch.bool)
        env_rewards = torch.zeros(T, N)
        final_obs = torch.zeros(T, N, *self.obs.shape[1:])
        labelled = self.causal is not None
        causal = torch.zeros(T, N, dtype=torch.bool) if labelled else None
        final_causal = torch.zeros(T, N, dtype=torch.bool) if labelled else None
        reached_info: dict[str, list[np.ndarray]] = {key: [] for key in self.info_keys}
        initial_state = self.state.clone()
        episodes: list[Episode] = []

        for t in range(T):
            logits, value, state = self.agent.step(self._inputs(), self.state, self.episode_start)
            # Sampling from the logits directly: torch.distributions' argument checks cost
            # about as much as the environment step here.
            log_probs = torch.log_softmax(logits, dim=-1)
            if self.expert:
                action = torch.as_tensor(self.envs.call("expert_action"), dtype=torch.long)
            elif self.greedy:
                action = logits.argmax(dim=-1)
            elif self.epsilon is not None:
                explore = torch.rand(N) < self.epsilon
                uniform = torch.randint(logits.shape[-1], (N,))
                action = torch.where(explore, uniform, logits.argmax(dim=-1))
            else:
                action = torch.multinomial(log_probs.exp(), 1, replacement=True).squeeze(1)
            next_obs, reward, terminated, truncated, infos = self.envs.step(action.numpy())

            obs[t], side[t], actions[t], logprobs[t], values[t] = (
                self.obs,
                self.side,
                action,
                log_probs.gather(1, action.unsqueeze(1)).squeeze(1),
                value,
            )
            episode_starts[t] = self.episode_start
            done = np.logical_or(terminated, truncated)
            dones[t] = torch.as_tensor(done)
            step_reward = torch.tensor(reward, dtype=torch.float32)
            env_rewards[t] = step_reward
            ended = np.flatnonzero(done)
            if len(ended):
                final_obs[t, ended] = torch.as_tensor(
                    final_observations(infos, ended), dtype=torch.float32
                )
            for key in self.info_keys:
                reached_info[key].append(_reached(infos, key, ended))
            if causal is not None and final_causal is not None:
                causal[t] = self.causal
                final_labels = _labels(infos.get("final_info", {}))
                if final_labels is not None:
                    final_causal[t] = final_labels

            # A truncated episode did not end in the MDP: credit the value of where it stopped.
            cut = np.flatnonzero(truncated & ~terminated)
            if len(cut) and self.bootstrap_truncation:
                final = torch.as_tensor(final_observations(infos, cut), dtype=torch.float32)
                final_side = self._side(infos["final_info"])[cut]
                _, final_value, _ = self.agent.step(
                    torch.cat((final, final_side), dim=-1),
                    state[cut],
                    torch.zeros(len(cut), dtype=torch.bool),
                )
                step_reward[cut] += self.gamma * final_value
            rewards[t] = step_reward

            self.episode_reward += reward
            self.episode_length += 1
            if len(ended):
                success = self._success(infos, ended)
                for i, k in enumerate(ended):
                    episodes.append(
                        Episode(
                            float(self.episode_reward[k]),
                            int(self.episode_length[k]),
                            None if success is None else bool(success[i]),
                            t,
                            int(k),
                        )
                    )
                self.episode_reward[ended] = 0
                self.episode_length[ended] = 0

            self.obs = torch.as_tensor(next_obs, dtype=torch.float32)
            self.side = self._side(infos)
            self.causal = _labels(infos) if labelled else None
            self.episode_start = torch.as_tensor(done)
            self.state = state

        _, last_value, _ = self.agent.step(self._inputs(), self.state, self.episode_start)
        rollout = Rollout(
            obs,
            actions,
            logprobs,
            values,
            rewards,
            dones,
            episode_starts,
            initial_state,
            last_value,
            env_rewards,
            final_obs,
            causal,
            final_causal,
            {key: np.stack(values) for key, values in reached_info.items()},
            side,
        )
        return rollout, episodes

    def _inputs(self) -> torch.Tensor:
        """(N, D + E) the agent's input for the current observations."""
        return torch.cat((self.obs, self.side), dim=-1)

    def _side(self, infos: dict[str, Any]) -> torch.Tensor:
        """(N, E) the memory's side inputs for the observations `infos` describes."""
        columns = []
        for name, width in self.side_inputs:
            if name == NOISE:
                columns.append(torch.rand(self.num_envs, width))
                continue
            if name not in infos:
                raise ThciError(
                    f"the environment reports no info[{name!r}], which the agent's memory "
                    f"({type(self.agent.memory).__name__}) reads every step"
                )
            value = np.asarray(infos[name], dtype=np.float32).reshape(self.num_envs, width)
            columns.append(torch.as_tensor(value))
        return torch.cat(columns, dim=1) if columns else torch.zeros(self.num_envs, 0)

    def _success(self, infos: dict[str, Any], ended: np.ndarray) -> np.ndarray | None:
        """Success flags (len(ended),) of the episodes that just ended, or None if unknown."""
        final_info = infos.get("final_info", {})
        if "success" in final_info:
            return np.asarray(final_info["success"])[ended].astype(bool)
        if self.success_return is not None:
            return self.episode_reward[ended] >= self.success_return
        return None

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue collecting bit-identically (env state if capturable)."""
        state: dict[str, Any] = {
            "obs": self.obs.clone(),
            "side": self.side.clone(),
            "causal": self.causal,
            "episode_start": self.episode_start.clone(),
            "memory_state": self.state.clone(),
            "episode_reward": torch.as_tensor(self.episode_reward),
            "episode_length": torch.as_tensor(self.episode_length),
        }
        if hasattr(self.envs, "get_state"):
            state["envs"] = {k: torch.as_tensor(v) for k, v in self.envs.get_state().items()}
        return state

    def load_state_dict(self, state: dict[str, Any], seed: int) -> bool:
        """Restore a :meth:`state_dict`. Returns False when the envs had to be reset instead.

        Environments that cannot capture their state restart their episodes, seeded by `seed`.
        """
        if "envs" in state and hasattr(self.envs, "set_state"):
            self.envs.set_state({k: v.numpy() for k, v in state["envs"].items()})
            self.obs = state["obs"].clone()
            # checkpoints written before side inputs existed belong to memories without any
            self.side = state.get("side", torch.zeros(self.num_envs, 0)).clone()
            self.causal = state["causal"]
            self.episode_start = state["episode_start"].clone()
            self.state = state["memory_state"].clone()
            self.episode_reward = state["episode_reward"].numpy().copy()
            self.episode_length = state["episode_length"].numpy().copy()
            return True
        self.reset(seed)
        return False


def has_expert(envs: VectorEnv) -> bool:
    """Whether every environment of `envs` offers ``expert_action()`` (read through
    gymnasium's ``call``, which reaches the unwrapped env through any wrappers)."""
    sub_envs = getattr(envs, "envs", None)  # SyncVectorEnv's; native vector envs have none
    return bool(sub_envs) and all(
        callable(getattr(env.unwrapped, "expert_action", None)) for env in sub_envs
    )


def plays_expert(envs: VectorEnv, trajectories: str) -> bool:
    """Whether `trajectories` ("expert", "greedy" or "auto": the expert where there is one)
    means acting with the environments' expert."""
    return trajectories == "expert" or (trajectories == "auto" and has_expert(envs))


def _reached(infos: dict[str, Any], key: str, ended: np.ndarray) -> np.ndarray:
    """info[key] (N, ...) of the observations just reached (final_info where episodes ended)."""
    if key not in infos:
        raise ThciError(f"the environment's info has no {key!r} entry (needed by --count-key)")
    values = np.array(infos[key])
    if len(ended):
        values[ended] = np.asarray(infos["final_info"][key])[ended]
    return values


def _labels(infos: dict[str, Any]) -> torch.Tensor | None:
    """info["causal"] as an (N,) bool tensor, or None when the env does not report it."""
    if "causal" not in infos:
        return None
    return torch.as_tensor(np.asarray(infos["causal"], dtype=bool))


def final_observations(infos: dict[str, Any], which: np.ndarray) -> np.ndarray:
    """Final observations (len(which), D) of the episodes that ended in envs `which`.

    Native vector envs give ``infos["final_obs"]`` as a dense array; gymnasium's SyncVectorEnv
    gives an object array of per-env observations.
    """
    final = infos["final_obs"]
    if final.dtype == object:
        return np.stack([final[k] for k in which]).astype(np.float32)
    return final[which]

"""Typed hyperparameters of a training run (CleanRL style: one flat dataclass, one flag each).

`TrainConfig` is what `thci train` parses from the command line and what a run directory
stores in ``config.json``. :meth:`TrainConfig.validate` turns every invalid value into a
one-line :class:`~thci.errors.ThciError` before anything is created on disk.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from thci.errors import ThciError

EncoderKind = Literal["flat", "grid", "cells"]
"""The agent's first layer (``--encoder``; :func:`thci.rl.encoders.make_encoder`)."""

DEFAULT_CELL_LAYOUT = (0, 49, 3)
"""``--cell-layout`` where the environment names none: minigrid's 7x7 view of (object, colour,
state) cells first, as in the thci/BabyAI levels."""

Method = Literal["lstm", "gru", "mlp", "nm", "wmg", "sai", "hai", "oracle", "t-hci", "hci"]
CAUSAL_METHODS = ("t-hci", "hci")
# Methods whose memory weighs each observation (ν of TAIE): the gate, attention, the labels.
WEIGHING_METHODS = ("t-hci", "hci", "sai", "hai", "oracle")
# Methods with a causal memory: a gate (or the labels) decides which observations it keeps.
GATED_METHODS = (*CAUSAL_METHODS, "oracle")
Algo = Literal["ppo", "a2c", "dmc"]
Trajectories = Literal["auto", "expert", "greedy"]
"""Whose episodes TAIE and heatmaps weigh: the environment's expert (``expert_action()``,
the paper's π*), the trained agent's greedy ones, or auto: the expert where there is one."""

# Fields that may differ between a run and its resumption: where it lives, the resume flag
# itself, how long to train (extending a finished run is legitimate) and machine settings.
RESUMABLE_DIFFERENCES = frozenset(
    {"run_dir", "resume", "total_steps", "torch_threads", "ci_threads", "progress"}
)


@dataclass
class TrainConfig:
    """Train an agent with recurrent memory on a gymnasium environment."""

    env: str = "thci/PaperMaze-L1-v0"
    """Registered gymnasium id (discrete actions; Box, Discrete or MultiDiscrete observations)."""
    method: Method = "lstm"
    """Memory of the agent: lstm, gru, mlp (none), nm (Neural Map), wmg (Working Memory Graph),
    sai / hai (soft / hard attention over the history), oracle (causal memory on the human
    labels), t-hci / hci (causal memory on CI). See docs/baselines.md."""
    algo: Algo = "ppo"
    """RL algorithm: ppo (clipped surrogate), a2c (one policy-gradient step per rollout) or dmc
    (Deep Monte Carlo: Q regressed on whole-episode returns, epsilon-greedy)."""
    total_steps: int = 100_000
    """Environment steps to train for (summed over the parallel environments)."""
    seed: int = 1
    """Seed of the run: the same seed gives the same result."""
    run_dir: Path | None = None
    """Run directory (default: runs/<env>__<method>__<algo>__s<seed>__<time>)."""
    resume: bool = False
    """Continue the run in --run-dir from its last checkpoint."""

    # Rollouts
    num_envs: int = 16
    """Parallel environments."""
    num_steps: int = 64
    """Steps per environment per rollout (a rollout holds num_envs * num_steps steps)."""
    vectorization: Literal["auto", "native", "sync"] = "auto"
    """auto: the environment's native batched implementation when it has one, else sync."""

    # Model
    encoder: EncoderKind = "flat"
    """The observation encoder, for images of categorical cells laid out as ``cell_layout``
    says: one layer on the flat observation (integer codes one-hot each), convolutions over
    the square image (grid), or the flat layer plus each cell's whole value as one category,
    pooled over places (cells: a green wall and a green door are different inputs;
    docs/babyai.md)."""
    encoder_size: int = 64
    """Width of the observation encoder."""
    hidden_size: int = 64
    """Width of the recurrent memory."""
    history_window: int = 32
    """sai, hai: how many of the episode's latest observations a step attends to."""
    hai_read: Literal["max", "mean"] = "max"
    """hai: how the memory reads the selected observations' values. The mean (before
    2026-12-06) diluted a selected cue among the other selected steps (Maze L2: 1 of 3 seeds
    solved, 3 of 3 with max; docs/baselines.md)."""
    nm_map_size: int = 18
    """nm: the Neural Map is nm_map_size x nm_map_size cells (PaperMaze is 18 x 15)."""
    nm_channels: int = 16
    """nm: features C of one map cell."""
    wmg_memos: int = 8
    """wmg: Memos S kept (WMG's factored-BabyAI setting, as the next three)."""
    wmg_layers: int = 4
    wmg_heads: int = 2
    wmg_head_size: int = 128

    # Optimization (PPO, A2C, DMC)
    learning_rate: float = 1e-3
    anneal_lr: bool = False
    """Anneal the learning rate linearly to 0 over total_steps."""
    gamma: float = 0.99
    gae_lambda: float = 0.95
    update_epochs: int = 8
    """Epochs per rollout (PPO; A2C takes one step; DMC: --dmc-gradient-steps)."""
    num_minibatches: int = 8
    """Minibatches per epoch; each holds whole episode segments, never cut sequences."""
    dmc_epsilon: float = 0.1
    """DMC's exploration: probability of a uniformly random action, after the decay."""
    dmc_epsilon_start: float = 1.0
    """DMC's epsilon at the first step; it falls linearly to --dmc-epsilon (as in DQN)."""
    dmc_epsilon_decay: int = 50_000
    """Env steps over which DMC's epsilon falls from --dmc-epsilon-start to --dmc-epsilon."""
    dmc_buffer_episodes: int = 256
    """DMC keeps the last this many finished episodes (FIFO) to draw its minibatches from."""
    dmc_batch_episodes: int = 32
    """Episodes per DMC gradient step, drawn from the buffer without replacement."""
    dmc_refit_steps: int = 200
    """Gradient steps DMC takes on its buffer alone when a CI round changes the gate's kept set,
    so the greedy policy does not act on a Q fitted to the old memory (0: none). Evidence is
    one seed each way on BabyAI-L1 (docs/babyai.md): without, a dip around the third gate never
    recovered; with, a similar dip recovered within 6k steps."""
    dmc_n_step: int = 0
    """0: DMC's Monte-Carlo targets (the paper). N > 0: bootstrapped N-step targets instead,
    G_t - γ^N G_{t+N} + γ^N Q(h_{t+N}, a_{t+N}), which stops being Monte Carlo. Refitting a
    trained BabyAI-L1 checkpoint, Monte Carlo left Q's fit of the choice at R² 0.13 where N = 1
    reached 0.60; online from scratch N = 1 still ended at the guess (0.50 at 2M steps;
    docs/babyai.md, "Why DMC's Q does not read the signpost")."""
    dmc_target_every: int = 0
    """With --dmc-n-step N > 0: bootstrap from a copy of the agent refreshed every this many
    gradient steps (DQN's target network) rather than from the network being fitted (0).
    On BabyAI-L1 online N = 1 at lr 3e-3 oscillated (0.1-0.5) without one; with K = 16 it
    held the guess to 1.3M steps, then solved at 1.79M (one seed; docs/babyai.md)."""
    dmc_gradient_steps: int = 16
    """DMC's gradient steps per rollout (on BabyAI-L1, 4 stayed at random play for 125k steps;
    16 reached the memoryless optimum by 125k)."""
    clip_coef: float = 0.2
    ent_coef: float = 0.01
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    norm_adv: bool = True

    # Exploration
    exploration: Literal["none", "count", "episodic", "episodic-count"] = "none"
    """Intrinsic reward: count = count_beta / sqrt(N(code)) over the run (Tang et al. 2017);
    episodic = count_beta for each code reached for the first time in the episode (NGU);
    episodic-count = count_beta / sqrt(N(code)) for each first visit in the episode."""
    count_beta: float = 0.1
    count_key: str | None = None
    """Count this info entry (e.g. agent_pos) instead of the observation."""
    count_memory: bool = False
    """Count (place, memory content) pairs: the set of observations the causal memory has kept
    so far in the episode joins the count key, so reaching a place while remembering something
    new pays (thci.rl.exploration). Applies to t-hci, hci and oracle (other methods ignore it,
    as they ignore the ci_* settings); before the first gate, places alone are counted."""

    # Counterfactual inference (methods t-hci and hci)
    ci_every: int = 8192
    """Env steps between CI rounds (the first runs once ci_min_episodes episodes are pooled)."""
    ci_lag: int = 65536
    """Env steps from a round's start (on the pool as it was) to the update at which its gate
    takes effect; the RL loop waits only if the round has not finished by then, and the next
    round starts then. A round overlaps with the next ci_lag steps of training (Fig. 3). A
    later round (1000 warm-start steps, 11-15 s in the worker beside training) outlasted 32768
    steps (~6 s of Maze training), and the RL loop waited ~6 s for each; with 65536 it waited
    0-3.3 s for each (Maze L1-L4, seeds 1-5). Maze L3-L4, commit cb73f35: mean wall-clock to solve
    72.7 s against 90.2 s on L3 and 41.5 s against 45.8 s on L4; mean steps 321k against 375k
    and 169k against 162k: the gates take effect later, which changes the runs."""
    ci_first_lag: int = 0
    """ci_lag of the first round; 0: its gate takes effect at the next update, and the RL loop
    waits there for what is left of the round (it runs in the worker beside the training on the
    rollout that completed its pool and beside the next rollout, neither of which could use
    its gate; a few seconds on the maze). Before
    the first gate the causal memory is empty (ci_initial_memory), so the policy is memoryless
    until then, and the longer that lasts the more firmly it settles on one guess. On Maze L1
    T-HCI solved at 48.6k-49.8k steps (seeds 1-3) with a first lag of 32768, at 20.4k-43.4k
    (seeds 1-5) with 8192 and at 13.4k-16.5k with 0 (LSTM: 11.9k-17.3k); on L2 it solved 3 of 5
    within 80k steps with 8192 and 4 of 5 with 0 (the others tell the variants apart but, in
    one of them, never find its goal)."""
    ci_initial_memory: Literal["empty", "full"] = "empty"
    """What the causal memory holds before the first gate. empty: nothing (the policy is
    memoryless until CI has found what matters); full: every observation (the paper's O^w = ∅
    at the start). With full, the first gate changes the input sequence of an LSTM trained on
    everything, and a policy that already solved was thrown off (Maze L1, seeds 1-5 trained
    past solving: success 1.0 to 0.0 at the gate in seed 1, and 3 of 5 ended at ~0.5); and the
    first round's pool comes from a policy that already exploits the causes, which hides their
    effect (seed 2's first round, at success 0.52, eliminated both indicators). A memoryless
    policy cannot exploit history, so its pool shows what history decides. Where a memoryless
    policy never earns the rewarded episodes the first round waits for, full is the way out:
    on BabyAI-L3 (seed 1, 4M steps, first round at 500 rewarded episodes) empty ran no round
    and ended at success 0.10, full ran its first at 3.30M (the five signpost colours, TAIE 0)
    and ended at 0.35 (docs/babyai.md)."""
    ci_async: bool = True
    """Run CI rounds in a worker process beside the RL loop (Fig. 3); results are identical
    either way, as the gate takes effect at the same step."""
    ci_cumulative: bool = True
    """Observations confirmed causal in a round (ATE estimate above xi, lower bound above 0)
    stay causal in later rounds: they are not tested again (undecided ones are). Once the
    policy acts on a cause, the path it takes tells the outcome as well, and a round on such a
    pool finds the cause redundant: on Maze L1 the third round (pool of a solved policy) kept
    nothing and success fell from 0.9+ to 0.52."""
    ci_substitutes: bool = True
    """After the search, keep the eliminated observations that stand in for a cause: those
    that never share an episode with it and, visible, make it redundant (the other values of its
    variable, such as Maze's two indicator codes; thci.causal.search._Search.admit_substitutes).
    The eliminated set alone is sufficient, but a policy reads a value from its presence in
    memory faster than from the absence of another."""
    ci_min_episodes: int = 200
    """Episodes the replay pool must hold before the first CI round (cross-fitting holds each
    out once: 200 is 4 folds of 50). Maze L1-L2 are solved in ~1000 episodes."""
    ci_min_rewarded_episodes: int = 50
    """...of which this many with a non-zero reward: before the agent has reached any outcome
    worth predicting, every observation looks like it has no effect, and a round would eliminate
    the very causes (seen in Maze L3, where random play is rewarded in 0.5% of episodes)."""
    ci_max_rounds: int = 8
    """At most this many CI rounds that keep something (rounds also stop once two in a row
    agree on a non-empty causal set). Rounds that keep nothing count against
    --ci-max-empty-rounds instead: the memory is then empty, the policy memoryless, and a later
    pool can show what an early one did not."""
    ci_max_empty_rounds: int = 24
    """At most this many CI rounds that keep nothing (a round starts once the last one is
    applied, --ci-lag steps after its start: 24 look for ~1.6M steps at the defaults), so a
    task without causal observations stops paying for them.
    On BabyAI-L2 (seed 1) the first eight rounds ran on pools of a policy that reached a ball
    in at most 13% of episodes, seven kept nothing, and with the old cap of 8 rounds in all
    the memory stayed empty for good."""
    ci_pool_episodes: int = 2000
    """Capacity of the replay pool (whole episodes, oldest dropped first)."""
    ci_z: int | None = None
    """Z: parts each candidate set is split into (T-HCI). Default: 4 with --ci-units
    observations; with --ci-units cells the number of cell values in the round's pool, so each
    is tested alone first (Z 4 on a BabyAI-L2 pool missed the rarely seen blue wall)."""
    ci_min_support: int = 10
    """T-HCI splits a part with an effect only while it occurs in at least this many held-out
    episodes; rarer parts are kept whole (thci.causal.search.DEFAULT_MIN_SUPPORT)."""
    ci_xi: float = 0.1
    """xi: an observation set whose ATE (extra prediction error per episode) lies confidently
    within [-xi, xi] has no causal effect (thci.causal.search.DEFAULT_XI)."""
    ci_target: Literal["dynamics", "reward", "inverse"] = "reward"
    """What p_zeta predicts: the reward given the transition it pays for (reward: the factor
    p(r_t | h, o_t, a_t, o_{t+1}) of Eq. 9, what decides the task), next observation and reward
    (dynamics, Eq. 9 whole: in mazes every corridor code predicts where the agent is), or the
    action (inverse dynamics). See thci.causal.predictor."""
    ci_units: Literal["observations", "cells"] = "observations"
    """What an intervention removes from the histories: whole observations (their codes,
    Eq. 3), or cell values (images of categorical cells, e.g. minigrid's views: "a red wall"
    wherever it is seen; a view stays in memory iff it shows a kept cell value). On BabyAI
    views the signpost is spread over hundreds of rare codes, but is 5 cell values seen in
    hundreds of episodes (thci.causal.units, docs/babyai.md). Needs --ci-target reward.
    Cell values are few (28 on BabyAI-L2): testing each alone first (--ci-z's default here)
    avoids parts whose common values (floor, keys) dilute a rare one's effect."""
    ci_unit_steps: int = 1000
    """Adam steps of the cell-value predictor's first fit (--ci-units cells; later rounds
    continue it for --ci-warm-steps). A BabyAI-L2 pool's signpost showed no effect after 400
    steps (ATE 0.007) and 0.30 [0.27, 0.33] after 1000."""
    ci_base_steps: int = 400
    """Adam steps of the effect predictor in the first round (fitted once per round, answers
    every intervention). An underfitted predictor reads effects into corridor codes. Before the
    reward target left out the transitions it explains (thci.causal.predictor), 400 steps kept
    extra codes on five of eleven first-round Maze L1-L3 pools and 1000 steps were needed; since,
    every batch holds ~6x more of the transitions that decide the reward, and on eleven new
    pools 400 steps kept what 1000 did on all eleven (250 steps: extra codes on three)."""
    ci_whole_batch_steps: int = 250
    """A fit from scratch (the first round's; every round's with --ci-warm-steps 0) whose pool
    holds at most 2048 transitions to predict (Maze pools) takes them all at every step, for
    this many steps from Adam rate 1e-2 decayed linearly, instead of ci_base_steps minibatch
    steps (0: minibatches). The first round is the one the RL loop may wait for: with 250,
    Maze L1-L2 runs solve at the same steps as with minibatches and wait 3-10% of the run
    instead of 9-20% (PredictorConfig.whole_batch_steps, docs/experiments.md)."""
    ci_warm_steps: int = 1000
    """Adam steps of the effect predictor in later rounds, which continue the previous round's
    predictor on the grown pool (0: every round fits from scratch for ci_base_steps). On a
    second-round Maze-L3 pool, 300 steps confirmed a corridor code, 1000 kept the labels."""
    ci_ensemble: int = 4
    """Effect predictors fitted side by side per round; their spread is part of each ATE's
    confidence interval."""
    ci_finetune_steps: int = 0
    """Optional Adam steps of per-intervention fine-tuning (0: off, see causal/predictor.py)."""
    ci_final: bool = True
    """After training, run one more CI round on the final pool and report what it infers
    (summary's ``final_ci``: causal set, interventions, seconds, TAIE of its gate on the trained
    policy's greedy trajectories). It is not applied to the policy. It tells what CI concludes
    from all the data of a run that did not solve; a run that solved skips it (a solving
    policy's pool shows no effect of what it remembers)."""
    ci_threads: int = 1
    """torch threads during CI rounds. 2 is ~1.3x faster on two cores, but multi-threaded
    reductions make CI results differ between processes in the last bits, which can flip a
    threshold decision: the default keeps runs bit-reproducible."""
    discretizer: Literal["auto", "exact", "simhash", "cell-set"] = "auto"
    """How observations become codes: exact bytes, SimHash, the set of cell values in view
    (images of categorical cells, e.g. minigrid's), or chosen from the data (exact or SimHash)."""
    cell_layout: tuple[int, int, int] | None = None
    """For ``cell-set`` and the grid / cells encoders: entries before the first cell, cells,
    and values per cell of a flat observation; the other entries are coded exactly. Default:
    where the environment's image lies (a minigrid env flattened by thci: after its one-hot
    direction, 4 49 3 for a 7x7 view), else minigrid's 7x7 view first, as in the thci/BabyAI
    levels (0 49 3); the run's config.json records the layout used."""

    # Success and solving
    solve_threshold: float = 0.9
    """The run is solved when the success rate over the last solve_window episodes reaches this."""
    solve_window: int = 100
    success_return: float | None = None
    """For environments without info['success']: an episode whose return reaches this succeeds."""
    stop_on_solve: bool = False
    """Stop training once the run is solved (hci, t-hci: with the gate it solved with; a CI round
    still in flight is dropped. Waiting for it kept Maze-L1 runs training for ci_lag more steps,
    22k steps to solve and 86k in all)."""

    # Bookkeeping
    checkpoint_every: int = 20
    """Write a checkpoint every this many updates (and always at the end)."""
    torch_threads: int = 1
    """torch intra-op threads (small recurrent nets run fastest on one thread)."""
    progress: bool = True
    """Show a progress bar."""

    def validate(self) -> None:
        """Raise ThciError naming the first invalid value and how to fix it."""
        positive_ints = {
            "total_steps": self.total_steps,
            "num_envs": self.num_envs,
            "num_steps": self.num_steps,
            "encoder_size": self.encoder_size,
            "hidden_size": self.hidden_size,
            "history_window": self.history_window,
            "nm_map_size": self.nm_map_size,
            "nm_channels": self.nm_channels,
            "wmg_memos": self.wmg_memos,
            "wmg_layers": self.wmg_layers,
            "wmg_heads": self.wmg_heads,
            "wmg_head_size": self.wmg_head_size,
            "update_epochs": self.update_epochs,
            "num_minibatches": self.num_minibatches,
            "solve_window": self.solve_window,
            "checkpoint_every": self.checkpoint_every,
            "torch_threads": self.torch_threads,
            "ci_every": self.ci_every,
            "ci_min_episodes": self.ci_min_episodes,
            "ci_max_rounds": self.ci_max_rounds,
            "ci_max_empty_rounds": self.ci_max_empty_rounds,
            "ci_pool_episodes": self.ci_pool_episodes,
            "ci_base_steps": self.ci_base_steps,
            "ci_unit_steps": self.ci_unit_steps,
            "ci_ensemble": self.ci_ensemble,
            "ci_threads": self.ci_threads,
        }
        for name, value in positive_ints.items():
            if value <= 0:
                raise ThciError(f"--{_flag(name)} must be a positive integer, got {value}")
        if self.ci_min_rewarded_episodes < 0:
            raise ThciError(
                f"--ci-min-rewarded-episodes must be >= 0, got {self.ci_min_rewarded_episodes}"
            )
        for name in ("ci_lag", "ci_first_lag"):
            if getattr(self, name) < 0:
                flag = "--" + name.replace("_", "-")
                raise ThciError(f"{flag} must be >= 0, got {getattr(self, name)}")
        for name in ("ci_finetune_steps", "ci_warm_steps", "ci_whole_batch_steps"):
            if getattr(self, name) < 0:
                raise ThciError(f"--{_flag(name)} must be >= 0, got {getattr(self, name)}")
        floats = {
            "learning_rate": self.learning_rate,
            "gamma": self.gamma,
            "gae_lambda": self.gae_lambda,
            "clip_coef": self.clip_coef,
            "ent_coef": self.ent_coef,
            "vf_coef": self.vf_coef,
            "max_grad_norm": self.max_grad_norm,
            "solve_threshold": self.solve_threshold,
            "ci_xi": self.ci_xi,
            "count_beta": self.count_beta,
        }
        for name, value in floats.items():
            if not math.isfinite(value):
                raise ThciError(f"--{_flag(name)} must be a finite number, got {value}")
        if self.learning_rate <= 0:
            raise ThciError(f"--learning-rate must be > 0, got {self.learning_rate}")
        for name in ("gamma", "gae_lambda", "solve_threshold"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ThciError(f"--{_flag(name)} must lie in [0, 1], got {value}")
        for name in ("clip_coef", "ent_coef", "vf_coef", "max_grad_norm", "count_beta"):
            if getattr(self, name) < 0:
                raise ThciError(f"--{_flag(name)} must be >= 0, got {getattr(self, name)}")
        for name in ("dmc_epsilon", "dmc_epsilon_start"):
            if not 0 <= getattr(self, name) <= 1:
                raise ThciError(f"--{_flag(name)} must be in [0, 1], got {getattr(self, name)}")
        for name in ("dmc_buffer_episodes", "dmc_batch_episodes", "dmc_gradient_steps"):
            if getattr(self, name) < 1:
                raise ThciError(f"--{_flag(name)} must be >= 1, got {getattr(self, name)}")
        if self.dmc_n_step < 0:
            raise ThciError(f"--dmc-n-step must be >= 0 (0: Monte Carlo), got {self.dmc_n_step}")
        if self.dmc_target_every < 0:
            raise ThciError(f"--dmc-target-every must be >= 0, got {self.dmc_target_every}")
        if self.dmc_target_every and not self.dmc_n_step:
            raise ThciError(
                "--dmc-target-every needs --dmc-n-step N > 0: Monte-Carlo targets (N = 0) "
                "bootstrap from nothing"
            )
        if self.dmc_refit_steps < 0:
            raise ThciError(f"--dmc-refit-steps must be >= 0, got {self.dmc_refit_steps}")
        if self.dmc_epsilon_decay < 0:
            raise ThciError(f"--dmc-epsilon-decay must be >= 0, got {self.dmc_epsilon_decay}")
        if self.method == "sai" and self.encoder_size % 4:
            raise ThciError(
                f"--method sai splits --encoder-size over 4 attention heads: it must be a "
                f"multiple of 4, got {self.encoder_size}"
            )
        if self.count_memory and self.exploration == "none":
            raise ThciError("--count-memory adds to the count key: it needs --exploration")
        if self.ci_min_support < 1:
            raise ThciError(f"--ci-min-support must be >= 1, got {self.ci_min_support}")
        offset, *sizes = self.cell_layout or DEFAULT_CELL_LAYOUT
        if len(sizes) != 2 or offset < 0 or min(sizes) < 1:
            raise ThciError(
                "--cell-layout takes three integers (offset >= 0, cells >= 1, values per "
                f"cell >= 1), got {self.cell_layout}"
            )
        if self.ci_units == "cells" and self.ci_target != "reward":
            raise ThciError(
                f"--ci-units cells predicts the reward: use --ci-target reward (got "
                f"{self.ci_target})"
            )
        if self.ci_z is not None and self.ci_z < 2:
            raise ThciError(f"--ci-z must be at least 2, got {self.ci_z}")
        if self.ci_xi < 0:
            raise ThciError(f"--ci-xi must be >= 0, got {self.ci_xi}")
        if self.algo == "ppo" and self.num_minibatches > self.num_envs:  # a2c, dmc: unused
            raise ThciError(
                f"--num-minibatches ({self.num_minibatches}) cannot exceed --num-envs "
                f"({self.num_envs}): each minibatch needs whole sequences"
            )
        if self.resume and self.run_dir is None:
            raise ThciError("--resume needs --run-dir: name the run directory to continue")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (paths as strings)."""
        data = dataclasses.asdict(self)
        data["run_dir"] = None if self.run_dir is None else str(self.run_dir)
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainConfig:
        """Inverse of :meth:`to_dict`; unknown keys are an error (a config from another version)."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ThciError(
                f"config has unknown fields {unknown}: written by another thci version?"
            )
        values = dict(data)
        # Configs written before the causal memory could start empty (commit c38c35b) ran with
        # it full and their first gate ci_lag steps after its round: resume them as they ran.
        if "ci_initial_memory" not in values:
            values["ci_initial_memory"] = "full"
            values.setdefault("ci_first_lag", values.get("ci_lag", cls.ci_lag))
        # Configs written before substitutes were admitted (2026-12-06) ran without them.
        values.setdefault("ci_substitutes", False)
        # ... and before the whole-batch first fit (2026-12-06, later), with minibatches,
        # and HAI runs with the mean read.
        values.setdefault("ci_whole_batch_steps", 0)
        values.setdefault("hai_read", "mean")
        if values.get("run_dir") is not None:
            values["run_dir"] = Path(values["run_dir"])
        if values.get("cell_layout") is not None:  # JSON has no tuples
            values["cell_layout"] = tuple(values["cell_layout"])
        return cls(**values)

    def differences(self, other: TrainConfig) -> list[str]:
        """Names of fields that differ and may not differ on resume. A ``cell_layout`` left
        to the environment (None) matches the layout a run recorded for it."""
        mine, theirs = self.to_dict(), other.to_dict()
        if None in (mine["cell_layout"], theirs["cell_layout"]):
            mine["cell_layout"] = theirs["cell_layout"]
        return [k for k in mine if k not in RESUMABLE_DIFFERENCES and mine[k] != theirs[k]]


def _flag(name: str) -> str:
    return name.replace("_", "-")

"""The T-HCI paper's key-to-door example (Fig. 1) as a tiny history-based environment.

Whether the door opens depends only on whether the agent started at (and so collected) the
key; the TV on the way has no effect. A *sampling policy* that passes the TV far more often
when it started from the key nevertheless makes the TV look predictive: with the defaults of
:func:`confounded_sampling_policy`, p(Open | TV) = 0.88, while the backdoor adjustment of Eq. 1
over the start (KEY vs BALL) recovers the causal p(Open | do(TV)) = 0.5. This module provides
the environment (registered as ``thci/KeyDoorTV-v0``), that confounded policy, and
:func:`sample_episodes`, which turns its play into replay-pool episodes
(:class:`thci.causal.replay.PoolEpisode`) for the estimators in :mod:`thci.causal.backdoor`.

Episode (always 3 actions, 4 observations):

* reset: the agent stands on KEY (key collected) or BALL, ½ each.
* step 1: action 0 walks past the TV (observe TV), action 1 the plain corridor (CORRIDOR).
* step 2: any action enters the HALLWAY in front of the door, so that the TV (or corridor) is
  part of the history when the door decides, as in Fig. 1.
* step 3: any action reaches the door: DOOR_OPEN with reward 1 if the key was collected, else
  DOOR_CLOSED with reward 0; the episode terminates.

Made-up layout used only for ``info["agent_pos"]`` (e.g. for heatmaps), rows top to bottom::

    KEY  TV
                HALLWAY DOOR
    BALL CORRIDOR
"""

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from thci.causal.replay import PoolEpisode
from thci.errors import ThciError

__all__ = [
    "BALL",
    "CORRIDOR",
    "DOOR_CLOSED",
    "DOOR_OPEN",
    "HALLWAY",
    "KEY",
    "NUM_CODES",
    "TV",
    "KeyDoorTVEnv",
    "confounded_sampling_policy",
    "sample_episodes",
]

# Observation codes (index of the hot entry of the one-hot observation).
KEY = 0
"""Start cell with the key; standing on it means the key is collected. Causal."""
BALL = 1
"""The other start cell (no key). Causal: the complementary indicator of KEY."""
CORRIDOR = 2
"""The plain corridor walked on step 1 by action 1."""
TV = 3
"""The corridor with the TV walked on step 1 by action 0. Not causal, only confounded."""
DOOR_OPEN = 4
"""The door, seen open (reward 1): the key was collected."""
DOOR_CLOSED = 5
"""The door, seen closed (reward 0): the key was not collected."""
HALLWAY = 6
"""The hallway in front of the door, walked on step 2."""
NUM_CODES = 7
"""Size of the one-hot observation."""

CODE_NAMES: tuple[str, ...] = (
    "KEY",
    "BALL",
    "CORRIDOR",
    "TV",
    "DOOR_OPEN",
    "DOOR_CLOSED",
    "HALLWAY",
)

ACTION_TV = 0
"""Step-1 action that walks past the TV."""
ACTION_CORRIDOR = 1
"""Step-1 action that walks the plain corridor."""
EPISODE_STEPS = 3
"""Every episode terminates after exactly this many steps."""

# [row, col] of each code in the made-up layout of the module docstring.
_POSITIONS = np.array(
    [[0, 0], [2, 0], [2, 1], [0, 1], [1, 3], [1, 3], [1, 2]],
    dtype=np.int64,
)
_CAUSAL = np.zeros(NUM_CODES, dtype=bool)
_CAUSAL[[KEY, BALL]] = True


class KeyDoorTVEnv(gym.Env[np.ndarray, np.int64]):
    """Fig. 1's key-to-door task: a 2-step episode whose reward only the start decides.

    Observation: (NUM_CODES,) float32 one-hot of the current code. Actions: Discrete(2); on
    step 1, 0 = past the TV, 1 = plain corridor; on step 2 every action goes to the door, which
    is open (reward 1, ``terminated``) iff the episode started on KEY, else closed (reward 0,
    ``terminated``). The episode is never truncated.

    ``info`` (reset and every step): ``causal`` (bool: the current code is KEY or BALL, the
    human label of what decides the door; KEY and BALL are complementary indicators of the
    same fact, so either one alone is a sufficient causal set), ``success`` (bool: this step
    opened the door), ``agent_pos`` ((2,) int64 [row, col] in the module docstring's layout),
    ``code`` (int, the current code).

    ``reset(options={"start_code": KEY or BALL})`` forces the start; otherwise it is drawn
    from ``np_random`` with probability ½ each.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["ansi"], "render_fps": 4}

    def __init__(self, render_mode: str | None = None) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"invalid render_mode {render_mode!r}: expected None or one of "
                f"{self.metadata['render_modes']}"
            )
        self.render_mode = render_mode
        self.observation_space = spaces.Box(0.0, 1.0, (NUM_CODES,), np.float32)
        self.action_space = spaces.Discrete(2)
        self._code = KEY
        self._has_key = False
        self._steps = 0
        self._started = False

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start on KEY or BALL (½ each, or ``options["start_code"]``)."""
        super().reset(seed=seed)
        start = (options or {}).get("start_code")
        if start is None:
            # Always draw, so a seeded run's later starts do not depend on forced ones.
            start = KEY if self.np_random.random() < 0.5 else BALL
        elif start not in (KEY, BALL):
            raise ValueError(f"invalid start_code {start!r}: expected KEY={KEY} or BALL={BALL}")
        self._code = int(start)
        self._has_key = self._code == KEY
        self._steps = 0
        self._started = True
        return self._observation(), self._info(success=False)

    def step(
        self, action: int | np.integer
    ) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Step 1: TV (action 0) or corridor (action 1); step 2: hallway; step 3: the door."""
        if not self._started:
            raise gym.error.ResetNeeded("call reset() before step() on KeyDoorTVEnv")
        if self._steps >= EPISODE_STEPS:
            raise gym.error.ResetNeeded("the episode is over (the door was reached): call reset()")
        if not self.action_space.contains(action):
            raise ValueError(
                f"invalid action {action!r}: expected 0 (past the TV) or 1 (plain corridor)"
            )
        self._steps += 1
        if self._steps < EPISODE_STEPS:
            if self._steps == 1:
                self._code = TV if int(action) == ACTION_TV else CORRIDOR
            else:
                self._code = HALLWAY
            return self._observation(), 0.0, False, False, self._info(success=False)
        self._code = DOOR_OPEN if self._has_key else DOOR_CLOSED
        reward = 1.0 if self._has_key else 0.0
        return self._observation(), reward, True, False, self._info(success=self._has_key)

    def render(self) -> str | None:
        """``"ansi"``: one text line (step, cell, key status); None: nothing."""
        if self.render_mode != "ansi":
            return None
        row, col = _POSITIONS[self._code].tolist()
        key = "collected" if self._has_key else "not collected"
        return (
            f"KeyDoorTV step {self._steps}: {CODE_NAMES[self._code]} at ({row}, {col}), key {key}\n"
        )

    def _observation(self) -> np.ndarray:
        obs = np.zeros(NUM_CODES, dtype=np.float32)
        obs[self._code] = 1.0
        return obs

    def _info(self, success: bool) -> dict[str, Any]:
        return {
            "causal": bool(_CAUSAL[self._code]),
            "success": success,
            "agent_pos": _POSITIONS[self._code].copy(),
            "code": self._code,
        }


def _check_probability(name: str, value: float) -> None:
    if not 0.0 <= value <= 1.0:
        raise ThciError(f"{name}={value!r} is not a probability: pass a value in [0, 1]")


def confounded_sampling_policy(
    start_code: int,
    rng: np.random.Generator,
    p_tv_given_key: float = 0.88,
    p_tv_given_ball: float = 0.12,
) -> int:
    """Fig. 1's sampling policy: the step-1 action, biased toward the TV after a key start.

    Args:
        start_code: the first observation's code, KEY or BALL.
        rng: source of the random choice.
        p_tv_given_key: probability of walking past the TV after starting on KEY.
        p_tv_given_ball: probability of walking past the TV after starting on BALL.

    Returns:
        ACTION_TV (0) or ACTION_CORRIDOR (1).
    """
    _check_probability("p_tv_given_key", p_tv_given_key)
    _check_probability("p_tv_given_ball", p_tv_given_ball)
    if start_code == KEY:
        p_tv = p_tv_given_key
    elif start_code == BALL:
        p_tv = p_tv_given_ball
    else:
        raise ThciError(f"start_code={start_code!r} is not a start: pass KEY={KEY} or BALL={BALL}")
    return ACTION_TV if rng.random() < p_tv else ACTION_CORRIDOR


def sample_episodes(
    num_episodes: int,
    seed: int,
    p_tv_given_key: float = 0.88,
    p_tv_given_ball: float = 0.12,
) -> list[PoolEpisode]:
    """Play ``num_episodes`` KeyDoorTV episodes with :func:`confounded_sampling_policy`.

    With the defaults, p(Open | TV) = 0.5·0.88 / (0.5·0.88 + 0.5·0.12) = 0.88 in the data,
    although p(Open | do(TV)) = 0.5.

    Args:
        num_episodes: number of episodes (>= 1).
        seed: seeds both the environment's starts and the policy's choices.
        p_tv_given_key: see :func:`confounded_sampling_policy`.
        p_tv_given_ball: see :func:`confounded_sampling_policy`.

    Returns:
        Replay-pool episodes: codes (4,) of o_1..o_4 (argmax of the one-hot observations),
        actions (3,), rewards (3,) and the environment's ``info["causal"]`` labels (4,).
    """
    if num_episodes < 1:
        raise ThciError(f"num_episodes={num_episodes!r} must be at least 1")
    _check_probability("p_tv_given_key", p_tv_given_key)
    _check_probability("p_tv_given_ball", p_tv_given_ball)
    env = KeyDoorTVEnv()
    # A separate stream for the policy, so its choices are not interleaved with (and do not
    # shift) the environment's start draws.
    policy_rng = np.random.default_rng([seed, 1])
    episodes: list[PoolEpisode] = []
    for i in range(num_episodes):
        obs, info = env.reset(seed=seed if i == 0 else None)
        codes, causal = [int(np.argmax(obs))], [info["causal"]]
        actions: list[int] = []
        rewards: list[float] = []
        terminated = False
        while not terminated:
            if len(actions) == 0:
                action = confounded_sampling_policy(
                    codes[0], policy_rng, p_tv_given_key, p_tv_given_ball
                )
            else:
                action = ACTION_TV  # the door is reached whatever the action
            obs, reward, terminated, _, info = env.step(action)
            codes.append(int(np.argmax(obs)))
            causal.append(info["causal"])
            actions.append(action)
            rewards.append(reward)
        episodes.append(
            PoolEpisode(
                codes=np.array(codes, dtype=np.int64),
                actions=np.array(actions, dtype=np.int64),
                rewards=np.array(rewards, dtype=np.float32),
                causal=np.array(causal, dtype=bool),
            )
        )
    return episodes

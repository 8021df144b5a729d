"""``thci demo confounding``: the paper's key-to-door example (Fig. 1), end to end.

Samples episodes of ``thci/KeyDoorTV-v0`` with the confounded sampling policy, estimates the
naive p(Open | TV) and the backdoor-adjusted p(Open | do(TV)) (Eq. 1), then runs T-HCI on the
same episodes, which must eliminate the TV and keep what decides the door.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from thci.causal.backdoor import backdoor_adjusted, naive_conditional
from thci.causal.predictor import EffectEstimator, PredictorConfig
from thci.causal.replay import pad_episodes
from thci.causal.search import CIResult, t_hci
from thci.envs.key_door_tv import BALL, CODE_NAMES, DOOR_OPEN, KEY, TV, sample_episodes


@dataclass(frozen=True)
class ConfoundingDemo:
    """Results of the demo."""

    episodes: int
    naive_p_open_given_tv: float
    adjusted_p_open_do_tv: float
    result: CIResult

    @property
    def causal_names(self) -> list[str]:
        return [CODE_NAMES[int(c)] for c in self.result.causal]

    def format(self) -> str:
        lines = [
            f"KeyDoorTV, {self.episodes} episodes of the confounded sampling policy",
            f"  naive     p(Open | TV)     = {self.naive_p_open_given_tv:.3f}",
            f"  backdoor  p(Open | do(TV)) = {self.adjusted_p_open_do_tv:.3f}   (Eq. 1)",
            f"T-HCI: {self.result.num_interventions} interventions in {self.result.seconds:.1f} s",
        ]
        for record in self.result.interventions:
            names = ", ".join(CODE_NAMES[c] for c in record.codes)
            lines.append(f"    {record.kind:<11} {{{names}}}  ATE = {record.ate:+.3f}")
        lines.append(f"  causal observations kept: {', '.join(self.causal_names)}")
        eliminated = ", ".join(CODE_NAMES[int(c)] for c in self.result.eliminated)
        lines.append(f"  eliminated (O^w):         {eliminated}")
        return "\n".join(lines)


def confounding_demo(num_episodes: int = 4000, seed: int = 0) -> ConfoundingDemo:
    """Run the demo (a few seconds on a CPU)."""
    episodes = sample_episodes(num_episodes, seed=seed)
    with torch.random.fork_rng():
        estimator = EffectEstimator(pad_episodes(episodes), 2, PredictorConfig(seed=seed))
        result = t_hci(estimator)
    return ConfoundingDemo(
        num_episodes,
        naive_conditional(episodes, DOOR_OPEN, TV),
        backdoor_adjusted(episodes, DOOR_OPEN, TV, [KEY, BALL]),
        result,
    )


def door_deciders_kept(result: CIResult) -> bool:
    """True when T-HCI dropped the TV and kept the key or the ball (its complement)."""
    causal = set(np.asarray(result.causal).tolist())
    return TV not in causal and bool(causal & {KEY, BALL})

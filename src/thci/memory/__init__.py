"""Memory modules behind one interface (:class:`Memory`), chosen by name with ``--method``.

See docs/baselines.md for the baselines (``nm``, ``wmg``) and ablations (``sai``, ``hai``,
``oracle``) and their defaults.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from thci.config import TrainConfig
from thci.errors import ThciError
from thci.memory.attention import HardAttentionMemory, SoftAttentionMemory
from thci.memory.base import NOISE, Memory
from thci.memory.memoryless import NoMemory
from thci.memory.neural_map import NeuralMap
from thci.memory.oracle import OracleMemory
from thci.memory.recurrent import RecurrentMemory
from thci.memory.wmg import BABYAI_FACTOR_SIZE, WorkingMemoryGraph, babyai_factors


@dataclass(frozen=True)
class MemorySpec:
    """What a memory is built from (the relevant fields of the run's config and spaces).

    Attributes:
        input_size: D of the encoder's features. hidden_size: recurrent width.
        observation_size: D of a flat observation (WMG embeds it itself).
        babyai_observations: the observations are thci's flat BabyAI view (WMG factors).
        window: past steps SAI and HAI attend to. hai_read: HAI's read, "max" or "mean".
        nm_map_size, nm_channels: the Neural Map.
        wmg_memos, wmg_layers, wmg_heads, wmg_head_size: the Working Memory Graph.
    """

    input_size: int
    hidden_size: int
    observation_size: int = 0
    babyai_observations: bool = False
    # the defaults are the command line's (documented in TrainConfig)
    window: int = TrainConfig.history_window
    hai_read: str = TrainConfig.hai_read
    nm_map_size: int = TrainConfig.nm_map_size
    nm_channels: int = TrainConfig.nm_channels
    wmg_memos: int = TrainConfig.wmg_memos
    wmg_layers: int = TrainConfig.wmg_layers
    wmg_heads: int = TrainConfig.wmg_heads
    wmg_head_size: int = TrainConfig.wmg_head_size


def _wmg(spec: MemorySpec) -> Memory:
    factored = spec.babyai_observations
    return WorkingMemoryGraph(
        spec.observation_size,
        spec.wmg_memos,
        spec.wmg_layers,
        spec.wmg_heads,
        spec.wmg_head_size,
        babyai_factors if factored else None,
        BABYAI_FACTOR_SIZE if factored else 0,
    )


MEMORIES: dict[str, Callable[[MemorySpec], Memory]] = {
    "lstm": lambda s: RecurrentMemory(s.input_size, s.hidden_size, "lstm"),
    "gru": lambda s: RecurrentMemory(s.input_size, s.hidden_size, "gru"),
    "mlp": lambda s: NoMemory(s.input_size),
    "nm": lambda s: NeuralMap(s.input_size, s.nm_map_size, s.nm_channels),
    "wmg": _wmg,
    "sai": lambda s: SoftAttentionMemory(s.input_size, s.hidden_size, s.window),
    "hai": lambda s: HardAttentionMemory(s.input_size, s.hidden_size, s.window, s.hai_read),
    "oracle": lambda s: OracleMemory(s.input_size, s.hidden_size),
}


def make_memory(method: str, input_size: int, hidden_size: int, **options: Any) -> Memory:
    """The memory module registered as `method`; `options` are :class:`MemorySpec` fields."""
    if method not in MEMORIES:
        raise ThciError(f"unknown method {method!r}: choose one of {', '.join(MEMORIES)}")
    return MEMORIES[method](MemorySpec(input_size, hidden_size, **options))


__all__ = [
    "MEMORIES",
    "NOISE",
    "HardAttentionMemory",
    "Memory",
    "MemorySpec",
    "NeuralMap",
    "NoMemory",
    "OracleMemory",
    "RecurrentMemory",
    "SoftAttentionMemory",
    "WorkingMemoryGraph",
    "make_memory",
]

"""Memory modules behind one interface (:class:`Memory`), chosen by name with ``--method``."""

from __future__ import annotations

from collections.abc import Callable

from thci.errors import ThciError
from thci.memory.base import Memory
from thci.memory.memoryless import NoMemory
from thci.memory.recurrent import RecurrentMemory

# name -> constructor(input_size, hidden_size)
MEMORIES: dict[str, Callable[[int, int], Memory]] = {
    "lstm": lambda d, h: RecurrentMemory(d, h, "lstm"),
    "gru": lambda d, h: RecurrentMemory(d, h, "gru"),
    "mlp": lambda d, h: NoMemory(d),
}


def make_memory(method: str, input_size: int, hidden_size: int) -> Memory:
    """The memory module registered as `method`."""
    if method not in MEMORIES:
        raise ThciError(f"unknown method {method!r}: choose one of {', '.join(MEMORIES)}")
    return MEMORIES[method](input_size, hidden_size)


__all__ = ["MEMORIES", "Memory", "NoMemory", "RecurrentMemory", "make_memory"]

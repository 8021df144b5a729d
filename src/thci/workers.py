"""Worker processes that do not outlive the process that started them.

`thci bench` trains runs in worker processes and a T-HCI run computes its CI rounds in one. If
the parent is killed (SIGKILL, a closed terminal), a worker would otherwise go on training or
fitting for minutes, holding a run's lock and a core. On Linux the kernel can deliver a signal
to a child when its parent dies (prctl PR_SET_PDEATHSIG); elsewhere this is a no-op.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys

PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """Process initializer: ask for SIGTERM when the parent process dies (Linux only)."""
    if not sys.platform.startswith("linux"):
        return
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() == 1:  # the parent died before the request was made
        os.kill(os.getpid(), signal.SIGTERM)

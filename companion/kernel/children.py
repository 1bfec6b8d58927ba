"""Child processes that never outlive their parent (Linux: ``PR_SET_PDEATHSIG``)."""

from __future__ import annotations

import signal
import sys


def die_with_parent() -> None:
    """In the child before exec: SIGTERM when the parent dies, however it dies (Linux only).

    Without it an interrupted or killed run left simulators, autopilots and render workers running.
    """
    if sys.platform != "linux":
        return
    import ctypes  # noqa: PLC0415

    pr_set_pdeathsig = 1
    ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGTERM)

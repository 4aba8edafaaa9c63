"""Child processes of the simulator (``rig sim`` itself, its CAN responder) end with the
thread that started them, so a crashed test or simulator leaves none behind (one at
SCHED_FIFO would keep a CPU busy)."""

from __future__ import annotations

import signal


def die_with_parent() -> None:
    """``preexec_fn`` of a child: SIGTERM when the parent thread ends (Linux
    ``PR_SET_PDEATHSIG``; ignored elsewhere)."""
    try:
        import ctypes
        PR_SET_PDEATHSIG = 1
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    except Exception:  # noqa: BLE001 - best effort
        pass

"""Asking Linux to run a timing-critical thread on time.

The bus master, its serial reader and the simulator (which plays hardware) live on
waits of fractions of a millisecond, on machines that do other work too.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import threading

#: prctl(2)'s PR_SET_NAME and PR_SET_TIMERSLACK.
_PR_SET_NAME = 15
_PR_SET_TIMERSLACK = 29
_COMM_MAX = 15  # bytes of a thread's name Linux keeps (comm), without the NUL


def tighten_timers(nice: int) -> None:
    """Wake the calling thread on time, and give it more of a busy CPU.

    Its timer slack (by default up to 50 µs added to every sleep, to batch wake-ups)
    becomes 1 ns; its niceness becomes ``nice`` (a higher scheduling weight, which
    Linux allows to root or with CAP_SYS_NICE).  Elsewhere, or if refused, sleeps are
    simply a little longer and the thread runs at the process's priority.

    Linux also learns the thread's name (Python 3.11 keeps it to itself), so that
    ``ps -L``, ``top -H`` and ``/proc/PID/task/*/comm`` show "bus" and "serial …",
    and an operator can pin it to a core with ``taskset -p`` (docs/deployment.md,
    "Small boxes")."""
    name = threading.current_thread().name.encode(errors="replace")[:_COMM_MAX]
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_NAME, ctypes.c_char_p(name), 0, 0, 0)
        libc.prctl(_PR_SET_TIMERSLACK, 1, 0, 0, 0)
    with contextlib.suppress(OSError, AttributeError):
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)

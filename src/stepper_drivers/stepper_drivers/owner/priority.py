"""The bus owner thread's real-time priority (owner_thread_priority)."""

from __future__ import annotations

import os
import threading
from typing import Callable

# The refusal of SCHED_FIFO is told once per process (every bus owner of a node asks for it).
_lock = threading.Lock()
_refusal_told = False


def set_priority(priority: int, on_event: Callable[[str, str, str], None], name: str) -> None:
    """SCHED_FIFO at `priority` for the calling thread (0: not): the owner then runs as soon as
    a command wakes it, not when the scheduler gets round to it (docs/benchmarks.md: the
    owner's wake-up was most of the command path's tail). A refusal is not an error: the bus
    works as well, only later on a loaded machine; the first owner of the process that is
    refused says so, once."""
    global _refusal_told
    if not priority:
        return
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        with _lock:
            told, _refusal_told = _refusal_told, True
        if not told:
            on_event(
                'warning', name,
                f'owner_thread_priority {priority}: SCHED_FIFO refused ({exc.strerror}): '
                'the bus owners run on the normal scheduler; allow it with an rtprio limit '
                f'of at least {priority} for this user in /etc/security/limits.conf (or '
                'CAP_SYS_NICE), or set owner_thread_priority: 0')

"""Child processes that end with the process that started them, even when it is killed
with SIGKILL and has no chance to stop them itself (Linux's parent-death signal)."""
from __future__ import annotations

import ctypes
import os
import signal
import threading
from typing import Callable

PR_SET_PDEATHSIG = 1


def die_with_parent(sig: int = signal.SIGTERM) -> Callable[[], None] | None:
    """A ``preexec_fn`` for ``subprocess.Popen``: the child gets ``sig`` when we die.

    Linux sends the signal when the *thread* that forked the child ends, not the process,
    so children must be started from the main thread (which lives as long as the process).
    Returns None where there is no ``prctl`` (not Linux): there the parent's own clean-up
    is all there is.
    """
    if threading.current_thread() is not threading.main_thread():
        raise RuntimeError(
            "A child that must die with this process has to be started from the main thread: "
            "Linux would stop it as soon as the starting thread ends."
        )
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl  # looked up here, not after fork
    except (OSError, AttributeError):
        return None
    parent = os.getpid()

    def arm() -> None:
        prctl(PR_SET_PDEATHSIG, int(sig))
        if os.getppid() != parent:  # we died between fork and prctl: nobody would signal
            os.kill(os.getpid(), sig)

    return arm

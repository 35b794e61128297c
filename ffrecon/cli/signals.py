"""Ctrl-C and SIGTERM on the command line: held while native libraries load, SIGTERM ended like Ctrl-C, and a
process that leaves while COLMAP computes beside it leaving at once."""

from __future__ import annotations

import contextlib
import os
import signal
import sys


def leave_if_work_beside(exit_code: int) -> None:
    """After a second Ctrl-C the run stops without waiting for COLMAP's current step in the thread beside
    (ffrecon.concurrency); a process that finishes normally while pycolmap computes in another thread is
    aborted by the C++ runtime, so it leaves at once instead (the staging folder is already as it stays)."""
    from ffrecon.concurrency import work_beside_running

    if work_beside_running():
        leave_now(exit_code)


@contextlib.contextmanager
def blocked_in_the_kernel():
    """SIGINT and SIGTERM blocked by the kernel (left pending) while glog may own them: pycolmap's import
    installs glog's native handler part-way through its initialisation, and a signal arriving after that
    was handled by glog (a stack dump, the process killed: reproduced by SIGTERM 0.25 s after start on a
    loaded machine). Blocked before numpy and OpenCV load, because the threads they start (OpenBLAS's)
    inherit the mask: a signal that reached such a thread went to glog's handler too (seen once in 40
    tries). At the end Python's handlers are put back over glog's, then the main thread unblocks, so a
    pending signal reaches the Python handler in force (held by :func:`interrupts_deferred`)."""
    held = {signal.SIGINT, signal.SIGTERM}
    before = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        for sig in held:
            handler = signal.getsignal(sig)
            if handler is not None:
                signal.signal(sig, handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


# The signals that ended the command (SIGTERM or Ctrl-C while sigterm_as_ctrl_c holds): a KeyboardInterrupt raised
# inside a C extension's initialisation comes out as an ImportError ("initialization failed"); the command then
# reads it as the interruption it is (libraries a stage imports when it needs them, e.g. Open3D, load mid-run).
received: list[int] = []


def terminate(signum, frame) -> None:
    """SIGTERM ends the run like Ctrl-C: finished stages kept, one line said, no stack trace. Ctrl-C takes it too
    (as Python's own handler, and remembered in :data:`received`)."""
    received.append(signum)
    raise KeyboardInterrupt


def leave_now(exit_code: int) -> None:
    """Leave the process at once with ``exit_code`` (output flushed), without waiting for other threads."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(exit_code)


def import_native_libraries() -> None:
    """Import numpy, OpenCV, Pillow and pycolmap with Ctrl-C and SIGTERM held until done.

    Held, because a KeyboardInterrupt inside a C extension's initialisation becomes an ImportError with a
    traceback (:func:`~ffrecon.concurrency.interrupts_deferred`); a signal is then taken once the imports
    end. pycolmap's logging library (glog) installs, when pycolmap is imported, a SIGTERM handler that
    prints a native stack trace and kills the process, so pycolmap is imported in a block of its own, whose
    end puts the held handlers back (:func:`blocked_in_the_kernel`). numpy, OpenCV and Pillow load before it,
    in the order the package has always imported them: with pycolmap's bundled libraries loaded first,
    Pillow's PNG writer aborts in zlib's deflateEnd ("double free", reproduced with `ffrecon demo`).
    """
    from ffrecon.concurrency import interrupts_deferred

    with interrupts_deferred(), blocked_in_the_kernel():
        import cv2  # noqa: F401
        import numpy  # noqa: F401
        import PIL.Image  # noqa: F401
        import pycolmap  # noqa: F401


@contextlib.contextmanager
def sigterm_as_ctrl_c():
    """While a command runs, SIGTERM raises KeyboardInterrupt (:func:`terminate`); the handler before is put back
    at the end."""
    previous = signal.signal(signal.SIGTERM, terminate)
    ctrl_c = signal.getsignal(signal.SIGINT)
    if ctrl_c is signal.default_int_handler:
        signal.signal(signal.SIGINT, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        if ctrl_c is signal.default_int_handler:
            signal.signal(signal.SIGINT, ctrl_c)


def take_sigterm_back() -> None:
    """SIGTERM as Ctrl-C again, after an import (pycolmap's, in ``ffrecon view``'s scene loading) that installed a
    handler of its own."""
    signal.signal(signal.SIGTERM, terminate)


def ignore_sigterm() -> None:
    """SIGTERM ignored while the interpreter shuts down (torch, numba and open3d take a moment), so that a
    finished command's exit code is not turned into a kill."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)

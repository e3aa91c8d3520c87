"""One thread for the numerics of a run, so that the same inputs give the same numbers everywhere.

A multi-threaded BLAS (or torch's intra-op pool) splits a reduction into as many partial sums as it
has threads: another thread count sums in another order, a last-bit difference follows, and a
planner's near-tie or a GP's optimiser can go the other way. The live controller, ``passt-mav
replay``, the demo's counterfactuals and the offline campaign therefore all run their numerics
under :func:`one_thread`, whatever ``OMP_NUM_THREADS`` or the machine's core count say.
"""

from __future__ import annotations

import contextlib
import functools
import sys
import threading
from collections.abc import Iterator

__all__ = ["one_thread", "single_threaded"]


_lock = threading.Lock()
_depth = 0  # blocks inside one_thread, all threads together
_local = threading.local()  # this thread's depth, and its settings before its outermost block


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """Within the block: one BLAS thread (threadpoolctl: OpenBLAS, MKL), one OpenMP thread and one torch
    intra-op thread (when torch is loaded; torch is not imported here: a run on DMD or persistence never
    loads it). Some of these settings are the calling thread's own, some the process's, so each thread's
    outermost block sets them all for itself, and the settings it found come back when it ends, unless
    another thread is still inside a block (a fleet's boats plan and absorb from threads of their own):
    then that thread keeps one thread, so that no block ever runs on more."""
    from threadpoolctl import threadpool_limits

    global _depth
    with _lock:
        mine = getattr(_local, "depth", 0)
        if mine == 0:
            torch = sys.modules.get("torch")
            prev = torch.get_num_threads() if torch is not None else None
            limits = threadpool_limits(1)
            if torch is not None and prev != 1:
                torch.set_num_threads(1)
            _local.saved = (limits, torch, prev)
        _local.depth = mine + 1
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            _local.depth -= 1
            if _local.depth == 0 and _depth == 0:
                limits, torch, prev = _local.saved
                if torch is not None and prev not in (None, 1):
                    torch.set_num_threads(prev)
                limits.restore_original_limits()


def single_threaded(fn):
    """Decorator: ``fn`` runs under :func:`one_thread`."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with one_thread():
            return fn(*args, **kwargs)

    return wrapper

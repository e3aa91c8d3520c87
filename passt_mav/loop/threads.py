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
from collections.abc import Iterator

__all__ = ["one_thread", "single_threaded"]


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """Within the block: one BLAS thread (threadpoolctl: OpenBLAS, MKL, OpenMP) and, when torch is
    loaded, one torch intra-op thread; the previous settings come back on exit. Torch is not imported
    here (a run on DMD or persistence never loads it)."""
    from threadpoolctl import threadpool_limits

    torch = sys.modules.get("torch")
    prev = torch.get_num_threads() if torch is not None else None
    try:
        if torch is not None and prev != 1:
            torch.set_num_threads(1)
        with threadpool_limits(1):
            yield
    finally:
        if torch is not None and prev != 1:
            torch.set_num_threads(prev)


def single_threaded(fn):
    """Decorator: ``fn`` runs under :func:`one_thread`."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with one_thread():
            return fn(*args, **kwargs)

    return wrapper

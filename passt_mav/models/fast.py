"""The fast path for KNODE training and batched prediction: ``torch.compile`` with a clean fallback.

Compiling the whole snapshot step (6 Euler sub-steps of the network plus the smoothing K)
with inductor gains little in training, because the step is dominated by convolutions that
eager mode already runs through oneDNN (``benchmarks/bench_models.py`` prints the ratio and
the fraction of the CPU's fp32 matmul rate each path reaches). The compiled step is exact to
fp32 rounding (checked against eager in ``tests/test_models.py``).

Compilation needs a C++ compiler and may fail on an unusual machine: any exception at
the first call falls back to the eager function, once, with a one-line warning.

Prediction (no gradients) compiles with inductor's ``freezing``: the weights become
constants and oneDNN convolutions get pre-packed weights; it deviates from eager by fp32
rounding. A first call per batch shape compiles for seconds, so only long roll-out work (the
campaign engine) turns it on (``KnodePredictor.fast_predict``).
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable

__all__ = ["compiled_or_eager"]


def compiled_or_eager(eager: Callable, module=None, *, warn=None, options: dict | None = None) -> Callable:
    """A function with ``eager``'s signature that runs ``torch.compile(eager)`` when it works.

    ``module``: the ``nn.Module`` whose parameters ``eager`` closes over (kept for
    reference; inductor guards on it). ``warn(msg)``: where the fallback is reported
    (default stderr). ``options``: inductor options (e.g. ``{"freezing": True}`` for
    inference: weights folded in as constants and convolution weights pre-packed for
    oneDNN; only valid while the weights do not change and under ``torch.no_grad``).
    """
    import torch

    state = {"fn": None}
    # inductor reads its config when a graph is compiled, which happens inside a call (the
    # first one, and again for a new input shape); torch.compile(options=...) did not
    # switch freezing on here (measured: aten convolutions, no pre-packed oneDNN ones),
    # so every call runs under the patched config instead
    import torch._inductor.config as inductor_config

    patch = (lambda: inductor_config.patch(options)) if options else contextlib.nullcontext

    def call(*args, **kw):
        if state["fn"] is None:
            try:
                fn = torch.compile(eager, dynamic=False)
                with patch():
                    out = fn(*args, **kw)
                state["fn"] = fn
                return out
            except Exception as exc:  # noqa: BLE001 - any compiler failure: run eager instead
                (warn or (lambda m: print(m, file=sys.stderr)))(
                    f"torch.compile unavailable ({type(exc).__name__}: {str(exc).splitlines()[0][:120]}); using the eager path"
                )
                state["fn"] = eager
        if state["fn"] is eager:
            return eager(*args, **kw)
        with patch():
            return state["fn"](*args, **kw)

    call.module = module
    call.is_compiled = lambda: state["fn"] is not None and state["fn"] is not eager
    return call

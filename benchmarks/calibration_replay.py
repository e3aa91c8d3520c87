"""Does the map's std hold the truth? A recorded run's legs replayed with the GP's own std and the map's.

Replays a run directory whose truth is known (``passt-mav demo``; any simulator run) through
:func:`passt_mav.analysis.replay.replay` (the same samples, the same leg step), once per variant of
the exported std, and prints each leg's 95 % interval coverage and NLPD
(:mod:`passt_mav.models.calibration`) against the truth at the estimate's time:

* ``raw``: the GP posterior's std (no background share, no forward check);
* ``forward+growth``: widened by the forward check and lead growth only (``unresolved_share=0``);
* ``share 0.25 fixed``: a fixed quarter of the background's variance kept (the share once tuned on the
  demo's truth), with the forward check;
* ``map`` (the default): the share estimated from the leg's held-out samples, with the forward check.

The estimates themselves are the same in every variant (only the std differs)::

    passt-mav demo --speedup 1000 --no-view --out runs/demo-cal
    python benchmarks/calibration_replay.py runs/demo-cal
"""

from __future__ import annotations

import argparse
import tempfile

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run_dir")
    args = ap.parse_args(argv)

    import passt_mav.reconstruction.gp as gpm
    from passt_mav.analysis.replay import replay
    from passt_mav.loop import legstep
    from passt_mav.loop.measurement import truth_at
    from passt_mav.models.calibration import calibration

    rows: list[tuple[float, float, float]] = []
    absorb = legstep.LegStep.absorb

    def scored(self, planned, recs, clock, *, strict=True):
        ab = absorb(self, planned, recs, clock, strict=strict)
        c = calibration(ab.state, ab.std, truth_at(self.field, ab.t_state))
        rows.append((c["coverage95"], c["nlpd"], ab.rmse_passt) if c else (np.nan, np.nan, np.nan))
        return ab

    kw, check = gpm.GPReconstructor.__init__.__kwdefaults__, gpm.GPReconstructor.forward_std_factor
    share = kw["unresolved_share"]

    def no_check(self, *a, **k):
        self.std_inflation_, self.std_check_ = 1.0, None
        return 1.0

    legstep.LegStep.absorb = scored
    try:
        for name, bu, fwd in (
            ("raw", 0.0, False),
            ("forward+growth", 0.0, True),
            ("share 0.25 fixed", 0.25, True),
            ("map", share, True),
        ):
            kw["unresolved_share"] = bu
            gpm.GPReconstructor.forward_std_factor = check if fwd else no_check
            rows.clear()
            with tempfile.TemporaryDirectory() as tmp:
                replay(args.run_dir, out=tmp)
            cov = " ".join(f"{c:.3f}" for c, _, _ in rows)
            nl = " ".join(f"{n:.3f}" for _, n, _ in rows)
            print(f"{name:>17}: coverage95 {cov} | nlpd {nl} | mean nlpd {np.nanmean([n for _, n, _ in rows]):.3f}")
        print("RMSE per leg (field units, every variant): " + " ".join(f"{r:.4f}" for _, _, r in rows))
    finally:
        legstep.LegStep.absorb = absorb
        kw["unresolved_share"], gpm.GPReconstructor.forward_std_factor = share, check
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

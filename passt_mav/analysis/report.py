"""The run report: one self-contained HTML page (figures embedded as base64 PNG) plus the PNG files.

:func:`load_run` gathers what a run directory (:mod:`passt_mav.runs.rundir`)
recorded; :func:`write_report` draws and writes it. Sections, in page order:

1. summary table (mission, status, times, field, grid, model, planner, seeds);
2. ``track_field.png``: the executed track over the truth current field (speed
   colour map) on lon/lat axes, with the planned waypoints;
3. ``legs.png``: per leg, planned path vs executed positions (the track split into
   legs by vehicle time, as the controller numbered its legs: :func:`_leg_windows`);
4. ``samples.png``: sample positions coloured by measured speed, with at most
   :data:`MAX_ARROWS` arrows of the mean velocity in spatial bins (:func:`binned_arrows`);
5. ``reconstruction.png``: the last reconstruction (``legs/NNN/estimate.nc``) vs
   the truth at its time, and the error; RMSE per leg in a table;
6. ``rmse.png``: RMSE over field time and per leg: PASST, the model alone and, where
   ``summary.json`` holds it, the lawnmower+GP counterfactual;
7. ``pod.png``: cumulative POD energy vs number of modes;
8. timings (planning, upload, leg duration) and link quality tables;
9. the telemetry log (``flight.tlog``): uploads, damage, mode changes.

Any part the run did not record is stated as "... not recorded" instead of drawn.
The page loads nothing from outside (no scripts, no URLs). Matplotlib runs with
the Agg backend.

Time axes are *field time*: seconds since the field's ``time_origin`` (drawn in
hours) for geographic fields, non-dimensional time for the cylinder.
"""

from __future__ import annotations

import datetime as _dt
import html
import json
import math
import sqlite3
from dataclasses import dataclass
from dataclasses import field as _dcfield
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from passt_mav.analysis.html_page import Page, pyplot
from passt_mav.errors import UserError
from passt_mav.loop.measurement import leg_number, sample_columns, truth_at
from passt_mav.loop.measurement import rmse as recon_rmse  # (the name tests and users know) the one RMSE rule
from passt_mav.runs.live import read_meta
from passt_mav.runs.records import RunRecords
from passt_mav.runs.rundir import RunDir, RunDirError
from passt_mav.units import MPS, SpeedUnit, run_speed_unit

__all__ = ["MAX_ARROWS", "Run", "binned_arrows", "load_run", "recon_rmse", "write_report"]

NOT_RECORDED = "not recorded"


# -- loading ------------------------------------------------------------------------------
@dataclass
class Run:
    """What a run directory recorded (None / empty where it did not).

    ``samples``: dict of arrays (``time_boot_ms``, ``utc``, ``lat``, ``lon``, ``u``,
    ``v`` m/s east/north, ``leg``, ``boot``: :func:`passt_mav.loop.measurement.sample_columns`);
    ``track``: ``(n, 2)`` lat/lon; ``leg_tracks``:
    leg index -> ``(n, 2)`` lat/lon executed positions; ``estimates``: leg index
    -> reconstruction FlowField; ``notes``: part -> why it is missing; ``damage``: what a damaged run
    lost (the store or the telemetry log unreadable or cut short), one phrase each (:func:`_damage`).
    """

    rundir: RunDir
    summary: dict[str, Any] | None
    legs: list[dict[str, Any]]
    field: Any = None
    grid: Any = None
    samples: dict[str, np.ndarray] | None = None
    samples_source: str | None = None
    tlog: Any = None
    track: np.ndarray | None = None
    track_source: str | None = None
    leg_tracks: dict[int, np.ndarray] = _dcfield(default_factory=dict)
    leg_tracks_source: str | None = None
    boat_tracks: dict[int, np.ndarray] = _dcfield(default_factory=dict)  # a fleet run: boat -> (n, 2) lat/lon
    estimates: dict[int, Any] = _dcfield(default_factory=dict)
    notes: dict[str, str] = _dcfield(default_factory=dict)
    damage: list[str] = _dcfield(default_factory=list)

    @property
    def root(self) -> Path:
        return self.rundir.root

    @property
    def in_progress(self) -> bool:
        return self.summary is None

    @cached_property
    def unit(self) -> SpeedUnit:
        """How the report shows field-derived speeds and RMSEs: m/s times the mission's velocity scale
        (:mod:`passt_mav.units`); the samples are in m/s already and are never scaled. Read once (the
        figures ask for it many times)."""
        meta = None if self.summary is not None else read_meta(self.rundir.root)
        return run_speed_unit(self.summary, meta, self.field.units if self.field is not None else "m s-1")

    @property
    def units(self) -> str:
        """The label of the field-derived speeds and RMSEs (``m/s``, or ``field units`` without a scale)."""
        return self.unit.label

    @property
    def time_origin(self) -> str | None:
        if self.field is not None:
            return self.field.time_origin
        return (self.summary or {}).get("field_time_origin")


def load_run(root: str | Path) -> Run:
    """Read everything a run directory holds (see :class:`Run`).

    Raises:
        RunDirError: ``root`` is missing, not a run directory, or its summary/leg
            JSON is invalid.
    """
    rd = RunDir(root)
    if not rd.root.exists():
        raise RunDirError(f"run directory not found: {rd.root}")
    if not rd.is_run_dir():
        raise RunDirError(f"{rd.root} is not a run directory (no summary.json, legs/, samples or flight.tlog)")
    recs = RunRecords(rd)
    # the summary's legs (those completed); while the first leg runs, the leg records on disk
    legs = (recs.summary.legs if recs.summary is not None else None) or recs.legs
    run = Run(rd, recs.summary_dict(), [x.as_dict() for x in sorted(legs, key=lambda x: x.index)])
    _load_field(run)
    _load_tlog(run)
    _load_samples(run)
    _load_tracks(run)
    _load_estimates(run)
    return run


def _load_field(run: Run) -> None:
    import geo

    s = run.summary or {}
    if isinstance(s.get("grid"), dict):
        try:
            run.grid = geo.grid_from_dict(s["grid"])
        except (geo.GeoError, TypeError) as exc:
            run.notes["grid"] = f"grid in summary.json is invalid: {exc}"
    spec = s.get("field")
    if not spec:
        run.notes["field"] = "truth field " + NOT_RECORDED
        return
    from passt_mav.fields.datasets import field_on_region, resolve_field

    spec = str(spec)
    if not spec.startswith("builtin:") and not Path(spec).is_absolute():
        spec = str(run.root / spec)
    seed = int((s.get("seeds") or {}).get("field", 0)) if isinstance(s.get("seeds"), dict) else 0
    try:
        run.field = resolve_field(spec, seed=seed)
    except UserError as exc:
        run.notes["field"] = f"truth field unavailable: {exc}"
        return
    if run.grid is None:
        run.grid = run.field.grid
        return
    try:  # the same rule as plan and run: a metric field takes the run's placement
        run.field = field_on_region(run.field, run.grid, source=str(s.get("field")))
    except UserError as exc:
        run.notes["field"] = f"truth field on another grid than the run: {exc}"
        run.field = None


def _load_tlog(run: Run) -> None:
    from passt_mav.runs.tlog import read_tlog

    for k, p in enumerate(run.rundir.boat_tlogs()):  # a fleet: one tlog per boat, each boat's track
        try:
            tl = read_tlog(p)
        except UserError as exc:
            run.notes[f"tlog{k}"] = f"boat {k}'s telemetry log unreadable: {exc}"
            continue
        if tl.track:
            run.boat_tracks[k] = np.array([(q.lat, q.lon) for q in tl.track], np.float64)
    if not run.rundir.tlog.exists():
        run.notes["tlog"] = (
            ("Telemetry log " + NOT_RECORDED)
            if not run.boat_tracks
            else f"a fleet run: one telemetry log per boat ({', '.join(p.name for p in run.rundir.boat_tlogs())})"
        )
        return

    try:
        run.tlog = read_tlog(run.rundir.tlog)
    except UserError as exc:
        run.notes["tlog"] = f"telemetry log unreadable: {exc}"


def _load_samples(run: Run) -> None:
    rd = run.rundir
    if rd.samples_db.exists():
        from passt_mav.runs.store import SampleStore  # resolved at call time (tests substitute it)

        try:
            store = SampleStore(rd.samples_db)
            try:
                recs = store.all()
            finally:
                store.close()
        except (UserError, sqlite3.DatabaseError) as exc:
            run.notes["samples_db"] = f"sample store unreadable: {exc}"
            run.damage.append(f"{rd.SAMPLES} unreadable ({_short(exc)})")
            recs = []
        if recs:
            run.samples, run.samples_source = sample_columns(recs), rd.SAMPLES
            _damage(run, rd.SAMPLES, len(recs))
            return
    if run.tlog is not None and run.tlog.samples:
        run.samples, run.samples_source = sample_columns(run.tlog.samples), rd.TLOG
        _damage(run, rd.TLOG, len(run.tlog.samples))


def _short(exc: BaseException) -> str:
    """The last clause of an error's first line (e.g. ``database disk image is malformed``)."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text.rsplit(": ", 1)[-1]


def _damage(run: Run, source: str, n: int) -> None:
    """Add to ``run.damage`` what the samples' ``source`` (``n`` of them) and the telemetry log lack against the
    run's own count (summary.json ``n_samples``) and legs: a store or a log cut short says so, with figures."""
    s = run.summary or {}
    want = s.get("n_samples")
    if isinstance(want, int) and n < want:
        run.damage.append(f"{source} holds {n} of the {want} samples the run recorded")
    tl = run.tlog
    done = [x for x in s.get("legs") or [] if x.get("status") == "complete"]
    if tl is not None and done:
        logged = sum(1 for x in tl.legs if x.complete)
        if logged < len(done):
            run.damage.append(f"{run.rundir.TLOG} ends early: {logged} of the {len(done)} complete legs in it")


#: one boot of the autopilot spans less than this many ms: (boot, time_boot_ms) -> one sortable key
_BOOT_SPAN_MS = 10**13


def _leg_windows(run: Run) -> tuple[dict[int, tuple[float, float]], str]:
    """Per controller leg index, the span ``[first, last]`` of vehicle time it covered, as
    ``boot * _BOOT_SPAN_MS + time_boot_ms`` keys; and where the spans come from.

    The controller's own records decide which positions belong to which leg, not the
    telemetry log's mission uploads: the log reader can miss an accepted upload (e.g.
    an INVALID_SEQUENCE ack for a re-sent item arriving after the last item) or end a
    leg early, and the n-th upload it saw is then not the controller's n-th leg.

    1. samples from the sample store carry the controller's leg number: a leg spans its
       first to its last sample, from its clock reading on when the leg recorded one;
    2. legs without such samples: from their clock reading (``clock_reading``: the
       vehicle time the controller planned the leg at) to the next leg's.
    Empty when neither was recorded.
    """
    starts: dict[int, float] = {}
    for n, leg in enumerate(run.legs):
        cr = leg.get("clock_reading")
        if isinstance(cr, dict) and isinstance(cr.get("time_boot_ms"), (int, float)):
            starts[int(leg.get("index", n))] = int(cr.get("boot") or 0) * _BOOT_SPAN_MS + float(cr["time_boot_ms"])
    spans: dict[int, tuple[float, float]] = {}
    s = run.samples
    from_store = s is not None and run.samples_source == run.rundir.SAMPLES
    if from_store:
        key = s["boot"] * _BOOT_SPAN_MS + s["time_boot_ms"]
        for i in np.unique(s["leg"]):
            if i >= 0:
                k = key[s["leg"] == i]
                lo = float(k.min())
                spans[int(i)] = (min(lo, starts.get(int(i), lo)), float(k.max()))
    n_store = len(spans)
    order = sorted(starts)
    for j, i in enumerate(order):
        if i not in spans:
            spans[i] = (starts[i], starts[order[j + 1]] if j + 1 < len(order) else math.inf)
    how = [
        f"{n_store} legs as numbered in {run.samples_source}" if n_store else "",
        f"{len(spans) - n_store} legs from their clock readings" if len(spans) > n_store else "",
    ]
    return spans, ", ".join(h for h in how if h)


def _load_tracks(run: Run) -> None:
    _load_run_tracks(run)
    if run.boat_tracks:
        run.track_source = (
            f"each boat's own telemetry log (flight_boatN.tlog, GLOBAL_POSITION_INT; "
            f"{sum(len(t) for t in run.boat_tracks.values())} points), one colour per boat"
        )


def _load_run_tracks(run: Run) -> None:
    tl = run.tlog
    if tl is not None and tl.track:
        run.track = np.array([(p.lat, p.lon) for p in tl.track], np.float64)
        run.track_source = f"{run.rundir.TLOG} GLOBAL_POSITION_INT ({len(tl.track)} points)"
        spans, how = _leg_windows(run)
        if spans:
            tb = np.array([p.time_boot_ms for p in tl.track], np.int64)
            key = np.array([p.boot for p in tl.track], np.int64) * _BOOT_SPAN_MS + tb  # the reader's boots
            for i, (lo, hi) in sorted(spans.items()):
                sel = (key >= lo) & (key <= hi)
                if sel.any():
                    run.leg_tracks[i] = run.track[sel]
            run.leg_tracks_source = f"positions from {run.rundir.TLOG} split by vehicle time ({how})"
            return
        # no record of the controller's legs: the log's accepted uploads, in order, stand for them
        idx = [int(leg.get("index", k)) for k, leg in enumerate(run.legs)] or list(range(len(tl.legs)))
        for k, lg in enumerate(tl.legs):
            if k < len(idx):
                pts = tl.leg_track(lg.index)
                if len(pts):
                    run.leg_tracks[idx[k]] = pts
        run.leg_tracks_source = f"positions from {run.rundir.TLOG}, legs as its accepted mission uploads"
    elif run.samples is not None:
        s = run.samples
        run.track = np.column_stack([s["lat"], s["lon"]])
        run.track_source = f"{run.samples_source} sample positions ({len(s['lat'])} points)"
        for i in np.unique(s["leg"]):
            if i >= 0:
                sel = s["leg"] == i
                run.leg_tracks[int(i)] = np.column_stack([s["lat"][sel], s["lon"][sel]])
        run.leg_tracks_source = f"sample positions from {run.samples_source}"


def _load_estimates(run: Run) -> None:
    from passt_mav.fields.field import load_field

    rd = run.rundir
    for i in rd.leg_indices():
        p = rd.estimate_file(i)
        if p.exists():
            try:
                run.estimates[i] = load_field(p)
            except UserError as exc:
                run.notes[f"estimate{i}"] = f"leg {i + 1} reconstruction unreadable: {exc}"


def _aspect(lat: np.ndarray) -> float:
    return 1.0 / max(0.05, math.cos(math.radians(float(np.nanmean(lat)))))


def _centres(grid) -> tuple[np.ndarray, np.ndarray]:
    """2-D cell-centre lat, lon ``(rows, cols)`` of any grid (metric grids are rotated on Earth)."""
    r, c = np.meshgrid(np.arange(grid.rows, dtype=float), np.arange(grid.cols, dtype=float), indexing="ij")
    return grid.fcell_to_latlon(r, c)


def _speed_map(ax, fig, grid, uv: np.ndarray, units: str, vmax: float | None = None, label: str = "speed"):
    lat, lon = _centres(grid)
    sp = np.hypot(uv[0], uv[1])
    vmax = vmax if vmax is not None else (float(np.nanmax(sp)) if np.isfinite(sp).any() else 1.0)
    ax.set_facecolor("0.85")
    pc = ax.pcolormesh(lon, lat, np.ma.masked_invalid(sp), shading="nearest", cmap="viridis", vmin=0.0, vmax=vmax)
    missing = ~np.isfinite(sp)
    if missing.any() and (~missing).any():
        # land (NaN in the field) is grey; its edge drawn between cell centres is the coastline
        ax.contour(lon, lat, missing.astype(float), levels=[0.5], colors="k", linewidths=1.2)
        ax.plot([], [], "k-", lw=1.2, label="coastline (land grey)")
    fig.colorbar(pc, ax=ax, label=f"{label} ({units})", shrink=0.85)
    ax.set_aspect(_aspect(lat))
    ax.set_xlabel("longitude (deg E)")
    ax.set_ylabel("latitude (deg N)")
    return pc


def _leg_time(leg: dict, key: str) -> float | None:
    x = leg.get(key)
    return float(x) if isinstance(x, (int, float)) and math.isfinite(x) else None


def _time_label(run: Run) -> tuple[float, str]:
    """(divisor, axis label) for field times."""
    origin = run.time_origin
    if run.field is not None:
        nondim = run.field.time_origin is None
    else:
        nondim = origin is None and run.grid is not None and run.grid.kind == "metric"
    if nondim:
        return 1.0, "non-dimensional field time"
    if origin:
        return 3600.0, f"field time (h since {origin})"
    return 3600.0, "field time (h)"


def _fig_track(run: Run, plt):
    fld = run.field
    t_end = [t for t in (_leg_time(leg, "t_end") for leg in run.legs) if t is not None]
    t = t_end[-1] if t_end else float(fld.times[0])
    k = int(np.argmin(np.abs(fld.times - t)))
    fig, ax = plt.subplots(figsize=(7.5, 6.0), constrained_layout=True)
    _speed_map(ax, fig, fld.grid, fld.data[k].astype(float) * run.unit.per_field_unit, run.units)
    for leg in run.legs:
        wp = np.asarray(leg.get("waypoints") or [], float).reshape(-1, 2)
        if len(wp):
            ax.plot(
                wp[:, 1],
                wp[:, 0],
                "w--",
                lw=1.0,
                marker="o",
                ms=3,
                mfc="white",
                mec="k",
                label="planned waypoints" if leg is run.legs[0] else None,
            )
    if run.boat_tracks:  # a fleet: every boat's track in its own colour
        colours = plt.get_cmap("tab10")
        sysids = {int(b.get("boat", -1)): b.get("sysid") for b in (run.summary or {}).get("boats") or []}
        for k, tr in sorted(run.boat_tracks.items()):
            c = colours((k + 3) % 10)  # (tab10's first colours are the legs')
            sid = f", sysid {sysids[k]}" if sysids.get(k) is not None else ""
            ax.plot(tr[:, 1], tr[:, 0], "-", color=c, lw=1.6, label=f"boat {k}{sid}")
            ax.plot(tr[0, 1], tr[0, 0], "^", color=c, mec="k", ms=8)
    elif run.track is not None and len(run.track):
        ax.plot(run.track[:, 1], run.track[:, 0], "-", color="tab:red", lw=1.6, label="executed track")
        ax.plot(run.track[0, 1], run.track[0, 0], "^", color="tab:red", mec="k", ms=8, label="start")
    div, lab = _time_label(run)
    ax.set_title(f"Track over the truth field, snapshot {k} ({lab} {fld.times[k] / div:.3g})", fontsize=10)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize=8, framealpha=0.8)
    return fig


def _fig_legs(run: Run, plt):
    fig, ax = plt.subplots(figsize=(7.5, 6.0), constrained_layout=True)
    colours = plt.get_cmap("tab10")
    lats = []
    for n, leg in enumerate(run.legs):
        i = int(leg.get("index", n))
        c = colours(n % 10)
        wp = np.asarray(leg.get("waypoints") or [], float).reshape(-1, 2)
        if len(wp):
            ax.plot(wp[:, 1], wp[:, 0], "--", color=c, marker="o", ms=4, lw=1.2, label=f"leg {i + 1} planned")
            ax.plot(wp[0, 1], wp[0, 0], "s", color=c, mec="k", ms=7)
            lats.append(wp[:, 0])
        ex = run.leg_tracks.get(i)
        if ex is not None and len(ex):
            ax.plot(ex[:, 1], ex[:, 0], "-", color=c, lw=2.2, alpha=0.7, label=f"leg {i + 1} executed")
            lats.append(ex[:, 0])
    if lats:
        ax.set_aspect(_aspect(np.concatenate(lats)))
    ax.set_xlabel("longitude (deg E)")
    ax.set_ylabel("latitude (deg N)")
    ax.grid(alpha=0.3)
    ax.set_title("Planned (dashed, square = start) vs executed path per leg", fontsize=10)
    ax.legend(loc="best", fontsize=8)
    return fig


#: most arrows the samples figure draws: more make a solid black blob at 10^4 samples
MAX_ARROWS = 300


def binned_arrows(lat, lon, u, v, max_arrows: int = MAX_ARROWS) -> tuple[np.ndarray, ...]:
    """Mean position and velocity of the samples in each occupied cell of a regular lon/lat
    binning, at most ``max_arrows`` cells.

    ``lat``, ``lon`` (deg), ``u``, ``v`` (any units; east/north): 1-D arrays of equal length.
    The bins are square on the ground (lon bins widened by 1/cos(lat)); the binning starts
    at 24 bins across the longer side and is made coarser until at most ``max_arrows`` bins
    hold samples. Returns ``(lat, lon, u, v, count)`` per occupied bin, NaN samples left out.
    """
    lat, lon, u, v = (np.asarray(x, np.float64).ravel() for x in (lat, lon, u, v))
    ok = np.isfinite(lat) & np.isfinite(lon) & np.isfinite(u) & np.isfinite(v)
    lat, lon, u, v = lat[ok], lon[ok], u[ok], v[ok]
    if lat.size == 0:
        return tuple(np.zeros(0) for _ in range(5))
    stretch = _aspect(lat)  # degrees of lon per degree of lat on the ground, inverted
    y, x = lat - lat.min(), (lon - lon.min()) / stretch
    extent = max(float(y.max()), float(x.max()), 1e-12)
    n = 24
    while True:
        size = extent / n * (1 + 1e-9)
        cell = np.floor(y / size).astype(np.int64) * (n + 1) + np.floor(x / size).astype(np.int64)
        keys, inv, count = np.unique(cell, return_inverse=True, return_counts=True)
        if len(keys) <= max_arrows or n == 1:
            break
        n = max(1, int(n * 0.8))
    mean = [np.bincount(inv, weights=w) / count for w in (lat, lon, u, v)]
    return (*mean, count)


def _fig_samples(run: Run, plt):
    s = run.samples
    sp = np.hypot(s["u"], s["v"])
    ok = np.isfinite(s["lat"]) & np.isfinite(s["lon"])
    la, lo = s["lat"][ok], s["lon"][ok]
    # the view is the samples' extent plus a margin: on the whole grid a track is a thin line
    pad_lat = max(0.08 * float(np.ptp(la)) if la.size else 0.0, 1e-3)
    pad_lon = max(0.08 * float(np.ptp(lo)) if lo.size else 0.0, 1e-3)
    centres = None
    if run.field is not None:
        g = run.field.grid
        centres = _centres(g)
        # the grid's cell size is the smallest margin
        pad_lat = max(pad_lat, float(np.nanmax(centres[0]) - np.nanmin(centres[0])) / max(g.rows - 1, 1))
        pad_lon = max(pad_lon, float(np.nanmax(centres[1]) - np.nanmin(centres[1])) / max(g.cols - 1, 1))
    # a figure as tall as the view (on the ground) needs: a wide view in a tall figure leaves
    # the axes a strip under a full-height colour bar
    wide = 1.0
    if la.size:
        wide = (float(np.ptp(lo)) + 2 * pad_lon) / _aspect(la) / (float(np.ptp(la)) + 2 * pad_lat)
    fig, ax = plt.subplots(figsize=(7.5, float(np.clip(5.8 / wide + 1.4, 3.6, 7.5))), constrained_layout=True)
    if centres is not None:
        ax.plot(centres[1].ravel(), centres[0].ravel(), "+", color="0.65", ms=4, mew=0.6, zorder=0)
    # small markers without edges: 10^4 of them still show their colours
    sc = ax.scatter(s["lon"], s["lat"], c=sp, cmap="plasma", s=5, linewidths=0, zorder=2, rasterized=True)
    fig.colorbar(sc, ax=ax, label=f"measured speed ({MPS})", shrink=0.85)
    blat, blon, bu, bv, _ = binned_arrows(s["lat"], s["lon"], s["u"], s["v"])
    bsp = np.hypot(bu, bv)
    vmax = float(bsp.max()) if bsp.size and bsp.max() > 0 else 1.0
    q = ax.quiver(
        blon,
        blat,
        bu,
        bv,
        angles="uv",
        scale_units="inches",
        scale=vmax / 0.35,
        width=0.0035,
        color="k",
        edgecolor="w",
        linewidth=0.5,
        zorder=3,
    )
    ax.quiverkey(
        q, 0.86, 1.015, vmax, f"{vmax:.2g} {MPS}", labelpos="W", coordinates="axes", fontproperties={"size": 8}
    )
    if la.size:
        ax.set_xlim(float(lo.min()) - pad_lon, float(lo.max()) + pad_lon)
        ax.set_ylim(float(la.min()) - pad_lat, float(la.max()) + pad_lat)
        ax.set_aspect(_aspect(la))
    ax.set_xlabel("longitude (deg E)")
    ax.set_ylabel("latitude (deg N)")
    ax.set_title(
        f"{len(sp)} samples coloured by measured speed; arrows: mean u, v of the samples\n"
        f"in each of {len(bu)} spatial bins",
        fontsize=10,
    )
    ax.grid(alpha=0.3)
    return fig


def _fmt_num(x: float, unit: str) -> str:
    """An RMSE after a leg (already in the report's unit) to 6 decimals with its unit, or "n/a"."""
    return f"{x:.6f} {unit}" if np.isfinite(x) else "n/a"


def _fmt_rmse(r: float | None, spec: str) -> str:
    return "n/a (no cell known in both)" if r is None else format(r, spec)


def _fig_recon(run: Run, plt, i: int, est, truth: np.ndarray | None):
    """The reconstruction after leg ``i`` beside the truth and the error (field states scaled to ``run.unit``)."""
    k = run.unit.per_field_unit
    e = est.data[0].astype(float) * k
    truth = None if truth is None else np.asarray(truth, float) * k
    panels = 3 if truth is not None else 1
    fig, axes = plt.subplots(1, panels, figsize=(5.2 * panels, 4.6), constrained_layout=True, squeeze=False)
    sp_e = np.hypot(e[0], e[1])
    vmax = float(np.nanmax(sp_e)) if np.isfinite(sp_e).any() else 1.0
    if truth is not None:
        sp_t = np.hypot(truth[0], truth[1])
        vmax = max(vmax, float(np.nanmax(sp_t)) if np.isfinite(sp_t).any() else 0.0)
        _speed_map(axes[0, 0], fig, est.grid, truth, run.units, vmax)
        axes[0, 0].set_title("truth", fontsize=10)
        _speed_map(axes[0, 1], fig, est.grid, e, run.units, vmax)
        axes[0, 1].set_title(f"reconstruction after leg {i + 1}", fontsize=10)
        err = e - truth
        _speed_map(axes[0, 2], fig, est.grid, err, run.units, label="|error|")
        axes[0, 2].set_title(f"error, RMSE {_fmt_rmse(recon_rmse(e, truth), '.3g')} {run.units}", fontsize=10)
    else:
        _speed_map(axes[0, 0], fig, est.grid, e, run.units, vmax)
        axes[0, 0].set_title(f"reconstruction after leg {i + 1} (no truth)", fontsize=10)
    return fig


def _series(xs) -> np.ndarray:
    return np.array([np.nan if x is None else float(x) for x in xs], float)


#: (summary key, line style, legend) of the RMSE curves, in drawing order
_RMSE_CURVES = (
    ("passt", "o-", "PASST"),
    ("model", "s--", "model alone (from the true initial state)"),
    ("random", "v-.", "random walk(s), same model + GP (counterfactual, offline; several: their mean)"),
    ("lawnmower", "^:", "lawnmower+GP (counterfactual, offline)"),
)


def _log_if_spread(ax, ys: np.ndarray) -> None:
    ys = ys[np.isfinite(ys) & (ys > 0)]
    if ys.size and ys.max() > 20 * ys.min():  # curves an order of magnitude apart: log scale shows all of them
        ax.set_yscale("log")


def _fig_rmse(run: Run, plt, over_time: dict | None, per_leg: dict[str, list]):
    """RMSE over field time (``over_time``: summary ``rmse``) and after each leg (``per_leg``:
    ``index`` -> leg numbers, ``passt``/``model``/``lawnmower`` -> RMSE per leg, NaN where not recorded)."""
    panels = (over_time is not None) + bool(per_leg)
    fig, axes = plt.subplots(1, panels, figsize=(6.0 * panels, 4.4), constrained_layout=True, squeeze=False)
    k = 0
    if over_time is not None:
        ax = axes[0, k]
        k += 1
        div, lab = _time_label(run)
        for key, style, name in _RMSE_CURVES:
            if key in over_time:
                y = _series(over_time[key]) * run.unit.per_field_unit
                # a curve on times of its own (``t_KEY``: a fleet's counterfactual, one value per round)
                t = _series(over_time.get(f"t_{key}", over_time["t"])) / div
                if t.shape != y.shape:
                    continue
                ok = np.isfinite(y) & np.isfinite(t)
                ax.plot(t[ok], y[ok], style, label=name)
        ax.set_xlabel(lab)
        ax.set_ylabel(f"RMSE ({run.units})")
        _log_if_spread(
            ax,
            np.concatenate([_series(over_time[c]) for c, _, _ in _RMSE_CURVES if c in over_time])
            * run.unit.per_field_unit,
        )
        ax.set_title("RMSE over time", fontsize=10)
        ax.grid(alpha=0.3)
    if per_leg:
        ax = axes[0, k]
        keys = [c for c in _RMSE_CURVES if np.isfinite(per_leg[c[0]]).any()]
        idx = np.arange(len(per_leg["index"]))
        w = 0.8 / max(len(keys), 1)
        for j, (key, _, name) in enumerate(keys):
            y = per_leg[key]
            bars = ax.bar(idx + (j - (len(keys) - 1) / 2) * w, np.nan_to_num(y, nan=0.0), w, label=name)
            ax.bar_label(bars, labels=["" if not np.isfinite(x) else f"{x:.2g}" for x in y], fontsize=7, padding=1)
        ax.set_xticks(idx, [f"leg {leg_number(i)}" for i in per_leg["index"]])
        ax.set_ylabel(f"RMSE ({run.units})")
        _log_if_spread(ax, np.concatenate([per_leg[c] for c, _, _ in keys]))
        ax.set_title("RMSE after each leg", fontsize=10)
        ax.grid(alpha=0.3, axis="y")
    # one legend for both panels, below them: inside, it hid the lawnmower's tall bars
    handles: dict[str, Any] = {}
    for ax in axes[0]:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    order = [name for _, _, name in _RMSE_CURVES if name in handles]
    fig.legend([handles[n] for n in order], order, loc="outside lower center", ncol=len(order), fontsize=8)
    return fig


def _fig_pod(run: Run, plt, pod: dict):
    fig, ax = plt.subplots(figsize=(6.5, 4.2), constrained_layout=True)
    for key, style, name in (("truth", "k-o", "truth"), ("passt", "o-", "PASST"), ("model", "s--", "model alone")):
        if key in pod:
            y = _series(pod[key])
            ax.plot(np.arange(1, len(y) + 1), y, style, label=name)
    ax.set_xlabel("number of POD modes")
    ax.set_ylabel("cumulative energy fraction")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("POD energy", fontsize=10)
    return fig


# -- HTML -----------------------------------------------------------------------------------------
def _fmt(x: Any) -> str:
    if x is None:
        return "&ndash;"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        return "&ndash;" if not math.isfinite(x) else f"{float(x):.4g}"
    return html.escape(str(x))


def _iso(s: Any) -> _dt.datetime | None:
    if not isinstance(s, str):
        return None
    try:
        d = _dt.datetime.fromisoformat(s.strip())
    except ValueError:
        return None
    return d if d.tzinfo else d.replace(tzinfo=_dt.UTC)


def write_report(run_dir: str | Path, out: str | Path | None = None, *, damage: list | None = None) -> Path:
    """Write ``report.html`` and the figure PNGs for ``run_dir``; returns the HTML path. ``damage``: a list
    that receives what a damaged run lost (the report's header says it too).

    ``out`` defaults to ``RUN_DIR/report``. Raises :class:`RunDirError` (a
    UserError) if ``run_dir`` is not a run directory.
    """
    run = load_run(run_dir)
    if damage is not None:
        damage.extend(run.damage)
    out_dir = Path(out) if out is not None else run.rundir.report_dir
    out_dir.mkdir(parents=True, exist_ok=True)
    for name in (
        "track_field.png",
        "legs.png",
        "reward.png",
        "samples.png",
        "reconstruction.png",
        "rmse.png",
        "calibration.png",
        "pod.png",
    ):
        (out_dir / name).unlink(missing_ok=True)  # a figure from an earlier report must not outlive its data
    plt = pyplot()
    page = Page(out_dir)
    s = run.summary or {}
    title = str(s.get("mission") or run.root.name)
    page.add(f"<h1>Run report: {html.escape(title)}</h1>")
    if run.in_progress:
        page.add(
            '<p class="status">No summary.json yet: the run is still in progress (or stopped before writing it). '
            "Shown: what the legs and logs recorded so far.</p>"
        )
    elif run.damage:  # never called complete: what is missing, in the header
        page.add(
            f'<p class="status">Status: damaged (recorded {html.escape(str(s.get("status", "unknown")))}): '
            f"{html.escape('; '.join(run.damage))}. Shown: what is still readable.</p>"
        )
    else:
        page.add(f'<p class="status">Status: {html.escape(str(s.get("status", "unknown")))}</p>')
    for leg in run.legs:  # the guard's alarms head the report: the run said so at the leg
        g = leg.get("guard") if isinstance(leg.get("guard"), dict) else {}
        if g.get("alarm") and isinstance(g.get("message"), str):
            page.add(f'<p class="status warn">{html.escape(g["message"])}</p>')
    _section_summary(page, run)
    _section_track(page, run, plt)
    _section_legs(page, run, plt)
    _section_reward(page, run, plt)
    _section_samples(page, run, plt)
    _section_recon(page, run, plt)
    _section_rmse(page, run, plt)
    _section_calibration(page, run, plt)
    _section_prior(page, run)
    _section_guard(page, run)
    _section_pod(page, run, plt)
    _section_timings(page, run)
    _section_tlog(page, run)
    gen = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    page.add(f'<p class="note">Written by passt-mav report from {html.escape(str(run.root))} at {gen}.</p>')
    return page.write(out_dir / "report.html", f"{title} - passt-mav report")


def _section_summary(page: Page, run: Run) -> None:
    s = run.summary or {}
    rows: list[tuple[str, str]] = []
    for key, label in (
        ("mission", "mission"),
        ("status", "status"),
        ("started_utc", "started (UTC)"),
        ("finished_utc", "finished (UTC)"),
    ):
        if key in s:
            rows.append((label, _fmt(s[key])))
    a, b = _iso(s.get("started_utc")), _iso(s.get("finished_utc"))
    if a and b:
        rows.append(("duration", f"{(b - a).total_seconds() / 60:.1f} min"))
    if "field" in s:
        rows.append(
            (
                "truth field",
                _fmt(s["field"]) + (f" ({html.escape(run.notes['field'])})" if "field" in run.notes else ""),
            )
        )
    g = run.grid
    if g is not None:
        desc = f"{g.rows} x {g.cols} cells, {g.kind}"
        if g.kind == "geographic":
            desc += f", lat {g.south:.4f}..{g.north:.4f}, lon {g.west:.4f}..{g.east:.4f}"
        else:
            desc += f", anchored at {g.anchor_lat:.4f}, {g.anchor_lon:.4f}, scale {g.scale:g}, rotation {g.rotation_deg:g} deg"
        rows.append(("grid", desc))
    if run.field is not None or run.grid is not None:
        div, lab = _time_label(run)
        rows.append(("time axis", html.escape(lab if div == 1.0 else f"seconds since {run.time_origin} (UTC)")))
        rows.append(("velocity units", html.escape(run.units)))
    for key in ("model", "planner", "reward"):
        if key in s:
            rows.append((key, _fmt(s[key])))
    if "seeds" in s:
        rows.append(("seeds", html.escape(json.dumps(s["seeds"], sort_keys=True))))
    rows.append(("legs", str(len(run.legs))))
    if run.samples is not None:
        rows.append(("samples", f"{html.escape(run.samples_source)} ({len(run.samples['u'])} samples)"))
    page.h2("Summary")
    page.table(rows)


def _section_track(page: Page, run: Run, plt) -> None:
    page.h2("Track over the current field")
    if run.field is None:
        page.missing("Track over the current field: " + run.notes.get("field", "truth field " + NOT_RECORDED))
        return
    page.figure(_fig_track(run, plt), "track_field.png", "track over the current field", plt)
    if run.track_source:
        page.note(f"Executed track: {run.track_source}.")
    else:
        page.note("Planned waypoints only: no positions were logged.")


def _section_legs(page: Page, run: Run, plt) -> None:
    page.h2("Legs: planned vs executed")
    if not any(leg.get("waypoints") for leg in run.legs):
        page.missing("Planned legs " + NOT_RECORDED)
        return
    page.figure(_fig_legs(run, plt), "legs.png", "planned vs executed path per leg", plt)
    page.note(
        "Legs are numbered from 1 here and on the console; the run directory's folders count from 0 "
        "(leg 1 is legs/000)."
    )
    if run.leg_tracks:
        page.note(f"Executed: {run.leg_tracks_source}.")
    else:
        page.missing("Executed track per leg " + NOT_RECORDED)


def _fig_reward(run: Run, plt, legs: list[dict]):
    """Per leg: the reward map it was planned on (grid cells, row 0 south) under its planned path."""
    n = len(legs)
    cols = min(n, 3)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.9 * rows), constrained_layout=True, squeeze=False)
    for ax in axes.ravel()[n:]:
        ax.set_visible(False)
    for ax, leg in zip(axes.ravel(), legs):
        q = np.asarray(leg["reward_map"], float)
        im = ax.imshow(q, origin="lower", cmap="magma", vmin=0.0, vmax=max(float(np.nanmax(q)), 1e-12))
        p = np.asarray(leg.get("path") or [], float).reshape(-1, 2)
        if len(p):
            ax.plot(p[:, 1], p[:, 0], "-", color="c", lw=1.8)
            ax.plot(p[0, 1], p[0, 0], "s", color="c", mec="k", ms=7)
        title = f"leg {leg_number(leg.get('index'))}" + (f", boat {leg['boat']}" if leg.get("boat") is not None else "")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("column (east)")
        ax.set_ylabel("row (north)")
    fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.8, label="reward (normalised)")
    return fig


def _section_reward(page: Page, run: Run, plt) -> None:
    page.h2("Why the boat went there: each leg's reward map under its path")
    legs = [leg for leg in run.legs if isinstance(leg.get("reward_map"), list) and leg["reward_map"]]
    if not legs:
        page.missing("Reward maps " + NOT_RECORDED)
        return
    page.figure(_fig_reward(run, plt, legs), "reward.png", "reward map per leg with the planned path", plt)
    reward = (run.summary or {}).get("reward")
    page.note(
        "Planned path cyan (square = start) over the map the planner maximised"
        + (f" (reward {html.escape(str(reward))})" if reward else "")
        + ": with variance_reduction, the error variance one sample there would remove from the next "
        "reconstruction under the GP's own prior; with speed, the predicted current speed."
    )


def _section_samples(page: Page, run: Run, plt) -> None:
    page.h2("Samples")
    if run.samples is None or len(run.samples["u"]) == 0:
        page.missing("Samples coloured by speed: samples " + NOT_RECORDED)
        return
    page.figure(_fig_samples(run, plt), "samples.png", "samples coloured by speed", plt)
    page.note(f"Source: {run.samples_source} ({len(run.samples['u'])} samples).")


def _section_recon(page: Page, run: Run, plt) -> None:
    page.h2("Reconstruction vs truth")
    if not run.estimates:
        page.missing("Reconstruction vs truth: reconstruction (estimate.nc) " + NOT_RECORDED)
        return
    rows, last = [], None
    for i, est in sorted(run.estimates.items()):
        truth = None
        if run.field is not None and est.grid == run.field.grid:
            truth = truth_at(run.field, float(est.times[-1]))
        if truth is not None:
            rmse = _fmt_rmse(run.unit(recon_rmse(est.data[-1], truth)), ".4g")
            rows.append((f"reconstruction RMSE vs truth, leg {i + 1}", f"{rmse} {html.escape(run.units)}"))
        last = (i, est.isel(time=est.n_times - 1), truth)
    i, est, truth = last
    page.figure(_fig_recon(run, plt, i, est, truth), "reconstruction.png", "reconstruction vs truth", plt)
    if rows:
        page.table(rows)
    else:
        page.missing(
            "Truth at the reconstruction times " + NOT_RECORDED + f" ({run.notes.get('field', 'outside the field')})"
        )


def _per_leg_rmse(run: Run) -> dict[str, Any]:
    """RMSE after each leg: ``index`` (list of leg numbers) and ``passt``, ``model``, ``random``,
    ``lawnmower`` (float arrays, NaN where not recorded); empty if no leg recorded any. The
    counterfactuals (``summary.json`` ``counterfactual.random`` / ``.lawnmower``, one value per
    leg in order, written by ``passt-mav demo``) are used only with one value per leg."""

    def num(x):
        return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else np.nan

    cf = (run.summary or {}).get("counterfactual") or {}
    out = {
        "index": [int(leg.get("index", n)) for n, leg in enumerate(run.legs)],
        "passt": np.array([num(leg.get("rmse_passt")) for leg in run.legs], float),
        "model": np.array([num(leg.get("rmse_model")) for leg in run.legs], float),
    }
    for key in ("random", "lawnmower"):
        vals = cf.get(key) if isinstance(cf, dict) else None
        if not isinstance(vals, list) or len(vals) != len(run.legs):
            vals = [None] * len(run.legs)
        out[key] = np.array([num(x) for x in vals], float)
    scale = run.unit.per_field_unit  # recorded in field units: shown in run.unit
    for key in ("passt", "model", "random", "lawnmower"):
        out[key] = out[key] * scale
    return out if any(np.isfinite(out[k]).any() for k, _, _ in _RMSE_CURVES) else {}


def _section_rmse(page: Page, run: Run, plt) -> None:
    page.h2("RMSE: PASST, model alone, random-walk and lawnmower counterfactuals")
    s = run.summary or {}
    over = s.get("rmse") if isinstance(s.get("rmse"), dict) and s["rmse"].get("t") else None
    per_leg = _per_leg_rmse(run)
    if over is None and not per_leg:
        page.missing("RMSE over time " + NOT_RECORDED + "; RMSE per leg " + NOT_RECORDED)
        return
    page.figure(_fig_rmse(run, plt, over, per_leg), "rmse.png", "RMSE over time and per leg", plt)
    if per_leg:
        u = html.escape(run.units)
        page.table(
            [
                (f"leg {leg_number(i)}", f"PASST {_fmt_num(p, u)}, model alone {_fmt_num(m, u)}")
                for i, p, m in zip(per_leg["index"], per_leg["passt"], per_leg["model"])
            ]
        )
    if over is None:
        page.missing("RMSE over time " + NOT_RECORDED)
    if isinstance(s.get("rmse_note"), str):
        page.note(s["rmse_note"] + ".")
    cf = s.get("counterfactual")
    if isinstance(cf, dict) and isinstance(cf.get("how_random"), str):
        page.note("Random-walk counterfactual: " + cf["how_random"] + ".")
    if isinstance(cf, dict) and isinstance(cf.get("how"), str):
        page.note("Lawnmower+GP counterfactual: " + cf["how"] + ".")
    elif not (over or {}).get("lawnmower"):
        page.note("No lawnmower+GP counterfactual for this run (passt-mav demo adds one to summary.json).")


def _fig_reliability(rows: list[tuple[int, dict]], plt):
    """The reliability diagram: per leg, the share of (cell, component) pairs whose truth lies inside the
    map's central p interval, against p (the diagonal: a map whose std is right)."""
    from passt_mav.models.calibration import RELIABILITY_LEVELS

    fig, ax = plt.subplots(figsize=(5.0, 4.6))
    ax.plot([0, 1], [0, 1], color="0.6", lw=1, ls="--", label="calibrated")
    for i, cal in rows:
        rel = cal.get("reliability")
        if isinstance(rel, list) and len(rel) == len(RELIABILITY_LEVELS):
            ax.plot(RELIABILITY_LEVELS, rel, marker="o", ms=3, lw=1.2, label=f"leg {leg_number(i)}")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("central interval probability p")
    ax.set_ylabel("share of the truth inside it")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    return fig


def _section_calibration(page: Page, run: Run, plt) -> None:
    """Does the map know how wrong it is? Per leg (where the truth is known, leg records ``calibration`` and
    ``baselines``, :mod:`passt_mav.loop.scoring`): the 95 % interval's coverage, the NLPD, the RMS of the
    standardised error, the map's RMSE beside the trivial maps', and the reliability diagram."""
    legs = [(int(leg.get("index", n)), leg) for n, leg in enumerate(run.legs)]
    cal_rows = [(i, leg["calibration"]) for i, leg in legs if isinstance(leg.get("calibration"), dict)]
    base_rows = {i: leg["baselines"] for i, leg in legs if isinstance(leg.get("baselines"), dict)}
    if not cal_rows and not base_rows:
        return  # the truth is unknown (a real vehicle), or a run recorded before these figures
    page.h2("Calibration: does the map know how wrong it is?")
    for i, b in sorted(base_rows.items()):
        if b.get("beaten_by"):
            names = ", ".join(
                {"zero": "zero current", "forecast_mean": "the forecast's time mean"}.get(k, k) for k in b["beaten_by"]
            )
            page.add(f'<p class="status warn">leg {leg_number(i)}: the map does not beat {html.escape(names)}</p>')
    scale = run.unit.per_field_unit
    u = html.escape(run.units)

    def num(x, f="{:.3f}", k=1.0):
        return f.format(k * float(x)) if isinstance(x, (int, float)) and not isinstance(x, bool) else "&ndash;"

    head = (
        "<tr><th>leg</th><th>coverage of the 95 % interval</th><th>NLPD (nats)</th><th>RMS standardised error</th>"
        f"<th>RMSE map ({u})</th><th>RMSE zero current ({u})</th><th>RMSE forecast time mean ({u})</th>"
        "<th>beats the trivial maps</th></tr>"
    )
    cal_by = dict(cal_rows)
    body = []
    for i, _ in legs:
        c, b = cal_by.get(i) or {}, base_rows.get(i) or {}
        if not c and not b:
            continue
        nl = c.get("nlpd")
        nl = None if not isinstance(nl, (int, float)) else float(nl) + float(np.log(scale))  # density in run.unit
        cells = [
            num(c.get("coverage95"), "{:.3f}"),
            num(nl, "{:.3f}"),
            num(c.get("z_rms"), "{:.2f}"),
            num(b.get("map"), "{:.4f}", scale),
            num(b.get("zero"), "{:.4f}", scale),
            num(b.get("forecast_mean"), "{:.4f}", scale),
            "&ndash;" if not b else ("no" if b.get("beaten_by") else "yes"),
        ]
        body.append(f"<tr><td>{leg_number(i)}</td>" + "".join(f'<td class="num">{x}</td>' for x in cells) + "</tr>")
    page.add(f"<table>{head}{''.join(body)}</table>")
    if cal_rows:
        page.figure(_fig_reliability(cal_rows, plt), "calibration.png", "reliability of the map's std per leg", plt)
    page.note(
        "Each leg's estimate is read as a Gaussian per cell and component (its mean and its posterior std, "
        "estimate.nc u_std/v_std) and scored against the truth at the estimate's time: coverage = share of "
        "(cell, component) pairs inside mean +- 1.96 std (0.95 when the std is right, lower when the map is "
        "overconfident); NLPD = mean negative log density of the truth (lower is better; it punishes overconfidence "
        "and timidity); RMS standardised error = 1 when right. The reliability diagram repeats the coverage for "
        "every central interval. The trivial maps: no current at all, and the time mean of the model's forecast "
        "from the mission's start; a map that does not beat them is not worth its samples."
    )


def _section_prior(page: Page, run: Run) -> None:
    """The prior blend per leg: the weight of each candidate prior (the forecast restarted from the
    estimate, the model alone, persistence) the leg's estimate used, and the leg's evidence for each
    (its samples' innovation log likelihood, nats), from summary.json ``legs[i].gp``."""
    rows = [
        (leg.get("index", n), leg["gp"])
        for n, leg in enumerate(run.legs)
        if isinstance(leg.get("gp"), dict) and isinstance(leg["gp"].get("prior_weights"), dict)
    ]
    if not rows:
        return  # no blend (gp.prior_blend off): the model's forecast was the prior on every leg
    page.h2("Prior per leg")
    names = list(rows[0][1]["prior_weights"])
    head = (
        "<tr><th>leg</th>"
        + "".join(f"<th>weight: {html.escape(k)}</th>" for k in names)
        + "".join(f"<th>log likelihood: {html.escape(k)} (nats)</th>" for k in names)
        + "</tr>"
    )
    body = []
    for i, gp in rows:
        w, ll = gp["prior_weights"], gp.get("prior_loglik") or {}
        cells = [f"{float(w[k]):.3f}" if isinstance(w.get(k), (int, float)) else "&ndash;" for k in names]
        cells += [f"{float(ll[k]):.1f}" if isinstance(ll.get(k), (int, float)) else "&ndash;" for k in names]
        body.append(f"<tr><td>{leg_number(i)}</td>" + "".join(f'<td class="num">{c}</td>' for c in cells) + "</tr>")
    page.add(f"<table>{head}{''.join(body)}</table>")
    page.note(
        "The prior mean of each leg's GP: the forecast restarted from the last estimate (model), the model alone "
        "from the mission's first state (open_loop) or persistence (the leg's first estimate held), weighed by how "
        "well each explained the legs' samples (gp.prior_blend: select takes the most probable alone, bma mixes "
        "them). Each is a whole-field forecast: where no sample reaches, the estimate is a forecast."
    )


def _section_guard(page: Page, run: Run) -> None:
    """The guard per leg (:mod:`passt_mav.loop.guard`): how far off, at the leg's own samples, the
    forecast restarted from the estimate and the model alone were (RMSE, m/s), and whether the leg fell
    back to the model alone, from summary.json ``legs[i].guard``. No truth is used."""
    rows = [(leg.get("index", n), leg["guard"]) for n, leg in enumerate(run.legs) if isinstance(leg.get("guard"), dict)]
    if not rows:
        return  # no guard (gp.guard off, or no model)
    page.h2("Guard: the estimate's forecast against the model alone")
    head = (
        "<tr><th>leg</th><th>restarted forecast at the samples (RMSE, m/s)</th>"
        "<th>model alone at the samples (RMSE, m/s)</th><th>background</th><th>alarm</th></tr>"
    )
    body = []
    for i, g in rows:
        a, b = g.get("rmse_loop_m_s"), g.get("rmse_open_loop_m_s")
        cells = [
            f"{a:.4f}" if isinstance(a, (int, float)) else "&ndash;",
            f"{b:.4f}" if isinstance(b, (int, float)) else "&ndash;",
            "model alone" if g.get("fallback") else "restarted forecast",
            "yes" if g.get("alarm") else "",
        ]
        body.append(f"<tr><td>{leg_number(i)}</td>" + "".join(f'<td class="num">{c}</td>' for c in cells) + "</tr>")
    page.add(f"<table>{head}{''.join(body)}</table>")
    page.note(
        "Before a leg's samples enter the estimate, the forecast restarted from the last estimate and the model "
        "alone (never re-initialised) are compared at them; the leg's background is the one that fits them better. "
        "Two legs running, or one by more than 10 %, where the model alone fits better raise the alarm "
        "'sampling is not helping'. Legs are numbered from 1."
    )


def _section_pod(page: Page, run: Run, plt) -> None:
    page.h2("POD energy")
    pod = (run.summary or {}).get("pod")
    if not isinstance(pod, dict) or not any(pod.get(k) for k in ("truth", "passt", "model")):
        page.missing("POD energy " + NOT_RECORDED)
        return
    page.figure(_fig_pod(run, plt, pod), "pod.png", "POD energy", plt)


def _section_timings(page: Page, run: Run) -> None:
    page.h2("Timings and link quality")
    keys = ("planning_s", "upload_s", "duration_s")
    if not any(k in leg for leg in run.legs for k in keys):
        page.missing("Timings (planning, upload, leg duration) " + NOT_RECORDED)
    else:
        head = (
            "<tr><th>leg</th><th>planning (s)</th><th>upload (s)</th><th>leg duration (s)</th><th>samples</th>"
            "<th>readings used</th><th>flown (vehicle s)</th><th>planned (vehicle s)</th></tr>"
        )
        body, tot = [], [0.0, 0.0, 0.0, 0]
        for n, leg in enumerate(run.legs):
            vals = [leg.get(k) for k in keys]
            for j, v in enumerate(vals):
                if isinstance(v, (int, float)):
                    tot[j] += float(v)
            ns = leg.get("n_samples")
            tot[3] += int(ns) if isinstance(ns, int) else 0
            body.append(
                "<tr><td>"
                + leg_number(leg.get("index", n))
                + "</td>"
                + "".join(f'<td class="num">{_fmt(v)}</td>' for v in vals + [ns])
                + f'<td class="num">{_readings_used(leg.get("readings"))}</td>'
                + "".join(
                    f'<td class="num">{_fmt(leg.get(k))}</td>'
                    for k in ("duration_vehicle_s", "planned_duration_vehicle_s")
                )
                + "</tr>"
            )
        body.append(
            "<tr><th>total</th>"
            + "".join(f'<td class="num">{_fmt(v)}</td>' for v in tot)
            + "<td></td><td></td><td></td></tr>"
        )
        page.add(f"<table>{head}{''.join(body)}</table>")
        page.note(
            "Flown: the leg's vehicle seconds from AUTO to its end; planned: what the controller expected "
            "(with planner.current_aware, the waypoints timed in the forecast current, the crab angle held "
            "against it; else at the mission's speed in still water). The overrun rule works from the planned figure."
        )
    links = [(leg.get("index", n), leg["link"]) for n, leg in enumerate(run.legs) if isinstance(leg.get("link"), dict)]
    tl = run.tlog
    if links:
        head = "<tr><th>leg</th><th>round trip (ms)</th><th>loss</th><th>messages</th><th>vehicle sends (B/s)</th></tr>"
        body = []
        for i, ln in links:
            loss = ln.get("loss")
            loss_s = f"{100 * float(loss):.1f} %" if isinstance(loss, (int, float)) else "&ndash;"
            body.append(
                f'<tr><td>{leg_number(i)}</td><td class="num">{_fmt(ln.get("rtt_ms"))}</td>'
                f'<td class="num">{loss_s}</td><td class="num">{_fmt(ln.get("messages"))}</td>'
                f'<td class="num">{_fmt(ln.get("vehicle_bytes_per_s"))}</td></tr>'
            )
        page.add(f"<table>{head}{''.join(body)}</table>")
    elif tl is not None and tl.link_loss is not None:
        page.note(
            f"Link (from {run.rundir.TLOG}): {tl.message_counts.get('_vehicle_frames', 0)} vehicle frames, "
            f"{tl.seq_lost} missing by sequence number ({100 * tl.link_loss:.1f} %)."
        )
    else:
        page.missing("Link quality " + NOT_RECORDED)


def _readings_used(r: Any) -> str:
    """'used / received (x %)' of a leg record's ``readings`` (placed on the track within the gap bound)."""
    if not isinstance(r, dict) or not r.get("received"):
        return "&ndash;"
    return f"{int(r['used'])} / {int(r['received'])} ({100.0 * r['used'] / r['received']:.0f} %)"


def _section_tlog(page: Page, run: Run) -> None:
    page.h2("Telemetry log")
    tl = run.tlog
    if tl is None:
        page.missing(run.notes.get("tlog", "Telemetry log " + NOT_RECORDED))
        return
    dur = (tl.utc_last - tl.utc_first) / 60 if tl.utc_first is not None else 0.0
    page.note(
        f"{run.rundir.TLOG}: {tl.n_messages} messages over {dur:.1f} min, vehicle system "
        f"{tl.vehicle_sysid if tl.vehicle_sysid is not None else 'unknown'}; "
        f"{len(tl.missions)} uploads, {tl.bad_frames} bad frames, {tl.skipped_bytes} bytes skipped."
    )
    leg_of = {lg.mission: lg for lg in tl.legs}
    items = []
    for m in tl.missions:
        state = "accepted" if m.accepted else ("no answer" if m.result is None else f"rejected (result {m.result})")
        line = f"mission {m.index + 1}: {len(m.items)} items, {m.n_waypoints} waypoints, {state}"
        lg = leg_of.get(m.index)
        if lg is not None:
            line += ", mission complete" if lg.complete else ", not completed"
        items.append(f"<li>{html.escape(line)}</li>")
    if items:
        page.add("<ul>" + "".join(items) + "</ul>")
    modes = [e.detail for e in tl.events if e.kind == "mode"]
    if modes:
        page.note("Modes: " + " \u2192 ".join(modes) + ".")
    if run.track_source:
        page.note(f"Track: {run.track_source}.")

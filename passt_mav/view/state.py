"""The live view's picture of a run, read from its run directory only (never from the mission's process).

:class:`RunState` reads what the controller writes (:mod:`passt_mav.runs.live`: ``events.jsonl``,
``live/*.json``; the summary, the leg records and the events through their schema
(:mod:`passt_mav.runs.records`); ``estimate.nc`` (with its posterior std ``u_std``/``v_std``); the sample
store, read-only) and turns it into one JSON-able snapshot for the page and into PNG rasters
(speed of the estimate, its posterior std, the reward map of the newest plan, land).
It works the same on a run in flight and on a finished one.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
from pathlib import Path

import numpy as np

from passt_mav.runs.commands import read_commands
from passt_mav.runs.live import read_meta, read_statuses
from passt_mav.runs.records import RunRecords, read_event_records
from passt_mav.runs.rundir import RunDir
from passt_mav.runs.store import SampleStore, SampleStoreError
from passt_mav.units import SpeedUnit, run_speed_unit

__all__ = ["RunState", "signature"]

log = logging.getLogger(__name__)

#: most points of one boat's track sent to the page; most arrows a side
MAX_TRACK = 600
MAX_ARROWS_SIDE = 24


def signature(root: Path) -> tuple:
    """(path, mtime_ns, size) of every file the view reads: a change means a new snapshot."""
    files = [root / "events.jsonl", root / "summary.json", root / "samples.sqlite", root / "samples.sqlite-wal"]
    files.append(root / "live" / "commands.jsonl")
    files += sorted((root / "live").glob("*.json")) + sorted((root / "legs").glob("*/leg.json"))
    files += sorted((root / "legs").glob("*/estimate.nc"))
    out = []
    for f in files:
        try:
            st = f.stat()
            out.append((f.name, f.parent.name, st.st_mtime_ns, st.st_size))
        except OSError:
            continue
    return tuple(out)


def _summary(rd: RunDir) -> dict:
    """``summary.json`` as a dict; empty while there is none, or while it cannot be read or does not fit its
    schema (the view keeps showing what it can)."""
    return RunRecords(rd, strict=False).summary_dict() or {}


class RunState:
    """Snapshots and rasters of the run in ``root`` (module docstring); thread-safe."""

    def __init__(self, root: str | Path):
        self.rd = RunDir(root)
        self.root = self.rd.root
        self._lock = threading.Lock()
        self._events: list[dict] = []
        self._ev_offset = 0
        self._samples: list[tuple] = []  # (id, lat, lon, u, v, leg, source)
        self._last_id = 0
        self._fields: dict = {}  # (kind, leg) -> (mtime, data)
        self._grid = None
        self._commands: list[dict] = []
        self._cmd_offset = 0

    def n_boats(self) -> int:
        """Boats of the run (its metadata; 1 before the controller wrote it)."""
        try:
            return max(1, int(self.meta().get("boats") or 1))
        except (TypeError, ValueError):
            return 1

    def finished(self) -> bool:
        """The run is over (summary.json has its end time)."""
        return bool(_summary(self.rd).get("finished_utc"))

    def _command_rows(self) -> list[dict]:
        """The operator's commands (newest 50) with the controller's answer: ``result`` the answering event's
        text, ``ok`` whether it was carried out (its level), None while pending."""
        new, self._cmd_offset = read_commands(self.root, self._cmd_offset)
        self._commands += new
        answers = {e["command_id"]: e for e in self._events if e.get("command_id")}
        out = []
        for c in self._commands[-50:]:
            a = answers.get(c.get("id"))
            out.append(
                {
                    **{k: c.get(k) for k in ("id", "utc", "boat", "action", "end_mode", "source")},
                    "result": None if a is None else a.get("text"),
                    "ok": None if a is None else a.get("level") != "warn",
                }
            )
        return out

    # -- pieces ------------------------------------------------------------------------------------
    def meta(self) -> dict:
        m = read_meta(self.root)
        if m is None:  # a run from before the live view: what the summary has
            s = _summary(self.rd)
            m = {
                "mission": s.get("mission"),
                "grid": s.get("grid"),
                "land": None,
                "boats": len(s.get("boats") or [1]),
                "legs_per_boat": s.get("legs_planned"),
                "geofence_margin_m": (s.get("config") or {}).get("geofence_margin_m", 0.0),
                "truth_known": s.get("rmse") is not None,
                "skill_warning": None,
            }
        return m

    def grid(self, meta: dict):
        if self._grid is None and meta.get("grid"):
            import geo

            self._grid = geo.grid_from_dict(meta["grid"])
        return self._grid

    def _new_samples(self) -> None:
        db = self.rd.samples_db
        if not db.exists():
            return
        try:
            with SampleStore(db, readonly=True) as store:
                new = store.since(self._last_id)
        except (SampleStoreError, sqlite3.Error) as exc:  # the writer holds the database a moment: next time
            log.debug("samples not read now: %s", exc)
            return
        if new:
            self._samples += [(i, x.lat, x.lon, x.u, x.v, x.leg, x.source) for i, x in new]
            self._last_id = new[-1][0]

    def _boat_of(self, statuses: dict, legs: list[dict]) -> dict[int, int]:
        """sysid -> boat, from the statuses and the leg records."""
        out = {int(s["sysid"]): b for b, s in statuses.items() if s.get("sysid")}
        out.update({int(r["sysid"]): int(r["boat"]) for r in legs if r.get("sysid") is not None and "boat" in r})
        return out

    def _leg_rows(self, grid, unit: SpeedUnit) -> list[dict]:
        """The legs for the page; their RMSEs (recorded in field units) in ``unit``."""
        out = []
        for rec in self._legs():
            # a leg the safety budget shortened before its upload flies only the start of its planned path
            path = (rec.get("budget_shortened") or {}).get("path") or rec.get("path") or []
            lat, lon = (
                grid.cell_to_latlon(np.array([p[0] for p in path]), np.array([p[1] for p in path]))
                if path and grid is not None
                else ([], [])
            )
            out.append(
                {
                    "index": int(rec.get("index", 0)),
                    "boat": int(rec.get("boat", 0)),
                    "sysid": rec.get("sysid"),
                    "status": rec.get("status"),
                    "path": [[round(float(a), 6), round(float(b), 6)] for a, b in zip(lat, lon)],
                    "waypoints": rec.get("waypoints") or [],
                    "t_start": rec.get("t_start"),
                    "t_end": rec.get("t_end"),
                    "rmse_passt": unit(rec.get("rmse_passt")),
                    "rmse_model": unit(rec.get("rmse_model")),
                    "guard": rec.get("guard"),
                    "n_samples": rec.get("n_samples"),
                    "approval": rec.get("approval"),
                    "has_reward": bool(rec.get("reward_map")),
                    "reward_range": _range(rec.get("reward_map")),
                }
            )
        return out

    def _legs(self) -> list[dict]:
        """The leg records on disk, by index (one that cannot be read or does not fit its schema is left out)."""
        return RunRecords(self.rd, strict=False).leg_dicts()

    # -- the snapshot --------------------------------------------------------------------------------
    def snapshot(self) -> dict:
        """Everything the page draws, as one JSON-able dict."""
        with self._lock:
            meta = self.meta()
            grid = self.grid(meta)
            new, self._ev_offset = read_event_records(self.root, self._ev_offset, strict=False)
            self._events += [e.as_dict() for e in new]
            self._new_samples()
            statuses = read_statuses(self.root)
            summary = _summary(self.rd)
            unit = run_speed_unit(summary, meta)
            legs = self._leg_rows(grid, unit)
            return {
                "meta": {k: v for k, v in meta.items() if k != "land"},
                "root": str(self.root),
                "status": summary.get("status") or "running",
                "finished": bool(summary.get("finished_utc")),
                "region": self._region(grid, meta),
                "boats": self._boats(statuses, legs, meta),
                "legs": legs,
                "events": self._events[-300:],
                "n_events": len(self._events),
                "estimate": self._estimate_info(grid, meta, legs, unit),
                # every speed and RMSE above is in this unit (m/s for a mission); samples are m/s as measured
                "units": unit.as_dict(),
                "rmse": _rmse(legs),
                "guard_warning": _guard_warning(legs),
                "n_samples": len(self._samples),
                "commands": self._command_rows(),
            }

    def _region(self, grid, meta: dict) -> dict | None:
        if grid is None:
            return None
        r, c = grid.shape
        lat, lon = grid.fcell_to_latlon(
            np.array([-0.5, r - 0.5, -0.5, r - 0.5]), np.array([-0.5, c - 0.5, c - 0.5, -0.5])
        )
        fence = grid.geofence(float(meta.get("geofence_margin_m") or 0.0))
        return {
            "bounds": [[float(lat.min()), float(lon.min())], [float(lat.max()), float(lon.max())]],
            "outline": grid.geofence(0.0).round(6).tolist(),
            "fence": np.asarray(fence).round(6).tolist(),
            "has_land": bool(meta.get("land")) and bool(np.any(meta["land"])),
        }

    def _boats(self, statuses: dict, legs: list[dict], meta: dict) -> list[dict]:
        n = max([int(meta.get("boats") or 1)] + [b + 1 for b in statuses])
        boat_of = self._boat_of(statuses, legs)
        flying = {b: s.get("leg") for b, s in statuses.items() if s.get("flying")}
        # each boat's current leg: the one it flies, else its newest
        current = {b: flying.get(b, max([r["index"] for r in legs if r["boat"] == b], default=-1)) for b in range(n)}
        tracks: dict[int, list] = {b: [] for b in range(n)}
        samples: dict[int, list] = {b: [] for b in range(n)}
        for _, lat, lon, u, v, leg, source in self._samples:
            try:
                b = boat_of.get(int(source.split(":")[1].split("/")[0]), 0) if n > 1 else 0
            except (IndexError, ValueError):
                b = 0
            if b not in tracks:
                continue
            tracks[b].append((lat, lon))
            if leg == current[b]:
                samples[b].append([round(lat, 6), round(lon, 6), round(u, 3), round(v, 3)])
        out = []
        for b in range(n):
            tr = tracks[b][:: max(1, len(tracks[b]) // MAX_TRACK + 1)] + tracks[b][-1:]
            st = statuses.get(b) or {}
            if st.get("lat") is not None:
                tr.append((st["lat"], st["lon"]))
            done = sum(1 for r in legs if r["boat"] == b and r["status"] == "complete")
            out.append(
                {
                    "boat": b,
                    "status": st,
                    "track": [[round(a, 6), round(o, 6)] for a, o in tr],
                    "samples": samples[b][-2000:],
                    "legs_done": done,
                }
            )
        return out

    def _leg_std(self, leg: int) -> np.ndarray | None:
        """The GP's posterior std (2, R, C) after ``leg`` (field units) from its ``estimate.nc``, or None."""
        from passt_mav.fields.field import load_std

        try:
            std = load_std(self.rd.estimate_file(leg))
        except (OSError, ValueError, KeyError):
            return None
        return None if std is None else std[-1]

    def _estimate_info(self, grid, meta: dict, legs: list[dict], unit: SpeedUnit) -> dict | None:
        """The newest estimate (else the newest forecast) as arrows, and which rasters exist; speeds (the
        arrows' u/v, ``vmax``, ``std_range``) in ``unit``."""
        if grid is None:
            return None
        est = [r["index"] for r in legs if self.rd.estimate_file(r["index"]).exists()]
        pred = [r["index"] for r in legs if self.rd.prediction_file(r["index"]).exists()]
        kind, leg = ("estimate", est[-1]) if est else (("forecast", pred[-1]) if pred else (None, None))
        reward = [r["index"] for r in legs if r["has_reward"]]
        std = self._leg_std(est[-1]) if est else None
        info = {
            "kind": kind,
            "leg": leg,
            "reward_leg": reward[-1] if reward else None,
            "reward_range": next((r["reward_range"] for r in legs if reward and r["index"] == reward[-1]), None),
            "std": std is not None,
            "std_range": None if std is None else _range(np.hypot(std[0], std[1]) * unit.per_field_unit),
        }
        if kind is None:
            return info
        uv = self.field_uv(kind, leg)
        if uv is None:
            return info
        uv = uv * np.float32(unit.per_field_unit)
        step = max(1, int(np.ceil(max(grid.shape) / MAX_ARROWS_SIDE)))
        rows, cols = np.mgrid[0 : grid.shape[0] : step, 0 : grid.shape[1] : step]
        lat, lon = grid.cell_to_latlon(rows.ravel(), cols.ravel())
        u, v = uv[0][rows, cols].ravel(), uv[1][rows, cols].ravel()
        ok = np.isfinite(u) & np.isfinite(v)
        speed = np.hypot(uv[0], uv[1])
        info.update(
            arrows=np.column_stack([lat[ok], lon[ok], u[ok], v[ok]]).round(5).tolist(),
            vmax=float(np.nanmax(speed)) if np.isfinite(speed).any() else 1.0,
            cell_m=float(grid.mean_cell_size_m) * step,
        )
        return info

    # -- fields and rasters ---------------------------------------------------------------------------
    def field_uv(self, kind: str, leg: int):
        """(2, R, C) of the estimate after ``leg`` (or the first snapshot of its forecast), cached by mtime."""
        path = self.rd.estimate_file(leg) if kind == "estimate" else self.rd.prediction_file(leg)
        try:
            mt = path.stat().st_mtime_ns
        except OSError:
            return None
        hit = self._fields.get((kind, leg))
        if hit and hit[0] == mt:
            return hit[1]
        try:
            from passt_mav.fields.field import load_field

            uv = np.asarray(load_field(path).data[0], np.float32)
        except Exception as exc:  # noqa: BLE001 - a file being written: the next change brings it
            log.debug("%s not read now: %s", path, exc)
            return None
        self._fields[(kind, leg)] = (mt, uv)
        return uv

    def raster(self, what: str, leg: int | None) -> bytes | None:
        """PNG (row 0 at the bottom) of ``what``: speed, std, reward, land. None when there is nothing."""
        with self._lock:
            meta = self.meta()
            grid = self.grid(meta)
            if grid is None:
                return None
            land = np.asarray(meta.get("land") or np.zeros(grid.shape), bool)
            if what == "land":
                return _png(np.where(land, 1.0, np.nan), "Greys", 0.0, 1.5, alpha=0.85)
            if leg is None:
                return None
            if what == "speed":
                uv = (
                    self.field_uv("estimate", leg)
                    if self.rd.estimate_file(leg).exists()
                    else self.field_uv("forecast", leg)
                )
                return None if uv is None else _png(np.hypot(uv[0], uv[1]), "viridis", vmin=0.0)
            if what == "std":
                std = self._leg_std(leg)
                if std is None:
                    return None
                return _png(np.where(land, np.nan, np.hypot(std[0], std[1])), "magma")
            if what == "reward":
                rec = RunRecords(self.rd, strict=False).leg(leg)
                q = np.asarray((rec.reward_map if rec is not None else None) or [], float)
                return None if q.ndim != 2 else _png(np.where(land | (q <= 0), np.nan, q), "inferno")
            return None


def _png(a: np.ndarray, cmap: str, vmin: float | None = None, vmax: float | None = None, alpha: float = 0.8) -> bytes:
    """A (R, C) array as an RGBA PNG, north up (row 0 is south), NaN transparent."""
    import io

    from matplotlib import colormaps
    from matplotlib.colors import Normalize
    from matplotlib.image import imsave

    a = np.asarray(a, float)
    fin = np.isfinite(a)
    lo = float(np.nanmin(a)) if vmin is None and fin.any() else (vmin or 0.0)
    hi = float(np.nanmax(a)) if vmax is None and fin.any() else (vmax or 1.0)
    rgba = colormaps[cmap](Normalize(lo, hi if hi > lo else lo + 1e-9)(np.where(fin, a, lo)))
    rgba[..., 3] = np.where(fin, alpha, 0.0)
    buf = io.BytesIO()
    imsave(buf, rgba[::-1], format="png")
    return buf.getvalue()


def _range(a) -> list[float] | None:
    """[min, max] of the finite positive values of ``a`` (what the rasters colour), None when there are none."""
    a = np.asarray(a if a is not None else [], float)
    a = a[np.isfinite(a) & (a > 0)]
    return [round(float(a.min()), 5), round(float(a.max()), 5)] if a.size else None


def _rmse(legs: list[dict]) -> dict:
    """RMSE of the estimate and of the model alone after each complete leg, in field-time order."""
    done = sorted(
        (r for r in legs if r["status"] == "complete" and r.get("rmse_passt") is not None),
        key=lambda r: (r.get("t_end") or 0.0, r["index"]),
    )
    return {
        "t": [r.get("t_end") for r in done],
        "passt": [r["rmse_passt"] for r in done],
        "model": [r.get("rmse_model") for r in done],
        "leg": [r["index"] for r in done],
    }


def _guard_warning(legs: list[dict]) -> str | None:
    """The banner: the guard's alarm (:mod:`passt_mav.loop.guard`: sampling is not helping) of the latest
    leg the guard scored (field-time order); None once a later leg is fine."""
    scored = sorted((r for r in legs if isinstance(r.get("guard"), dict)), key=lambda r: r.get("t_end") or 0.0)
    last = scored[-1]["guard"] if scored else {}
    return last.get("message") if last.get("alarm") else None

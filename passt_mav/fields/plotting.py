"""Figures of flow fields (matplotlib, Agg backend; file output only).

Imported lazily by ``passt-mav data show``; importing this module imports
matplotlib.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from passt_mav.errors import FieldError
from passt_mav.fields.field import FlowField

__all__ = ["plot_snapshot"]


def _time_label(field: FlowField, k: int) -> str:
    if field.time_origin is not None:
        return str(field.datetimes()[k].astype("datetime64[m]")).replace("T", " ") + " UTC"
    return f"t = {field.times[k]:.3g}"


def plot_snapshot(
    field: FlowField,
    time_index: int,
    out: str | Path,
    *,
    title: str | None = None,
    max_arrows: int = 16,
    dpi: int = 120,
) -> Path:
    """Speed colour map with velocity arrows of snapshot ``time_index``, saved to ``out``.

    Geographic fields are drawn on longitude/latitude axes (equal-distance aspect
    at the region's mid-latitude); metric fields on their data-frame x/y metres.
    Missing cells are left blank (grey background), never drawn as zero current.
    Arrows are thinned to at most ``max_arrows`` per side so the figure stays
    readable for large grids. Returns the path written.
    """
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    n = field.n_times
    if not -n <= time_index < n:
        raise FieldError(f"--time {time_index} is out of range: the field has {n} snapshots (0..{n - 1})")
    k = time_index % n
    u, v = field.data[k, 0].astype(float), field.data[k, 1].astype(float)
    speed = np.hypot(u, v)
    g = field.grid
    if field.is_geographic:
        X, Y = np.meshgrid(g.lons, g.lats)
        xlabel, ylabel = "longitude (deg E)", "latitude (deg N)"
        aspect = 1.0 / np.cos(np.radians(0.5 * (g.south + g.north)))
    else:
        X, Y = np.meshgrid(g.xs, g.ys)
        xlabel, ylabel = "x (m, data frame)", "y (m, data frame)"
        aspect = 1.0
    units = "m/s" if field.units in ("m s-1", "m/s") else ("non-dimensional" if field.units == "1" else field.units)

    fig, ax = plt.subplots(figsize=(7.0, 6.0), constrained_layout=True)
    ax.set_facecolor("0.85")
    masked = np.ma.masked_invalid(speed)
    finite = np.isfinite(speed)
    vmax = float(np.nanmax(speed)) if finite.any() else 1.0
    pc = ax.pcolormesh(X, Y, masked, shading="nearest", cmap="viridis", vmin=0.0, vmax=vmax)
    fig.colorbar(pc, ax=ax, label=f"speed ({units})", shrink=0.85)
    step_r = max(1, int(np.ceil(g.rows / max_arrows)))
    step_c = max(1, int(np.ceil(g.cols / max_arrows)))
    sl = (slice(None, None, step_r), slice(None, None, step_c))
    ok = finite[sl]
    if ok.any():
        # arrows in data units per unit speed; scale so the typical arrow spans ~1 thinned cell
        q = ax.quiver(
            X[sl][ok],
            Y[sl][ok],
            u[sl][ok],
            v[sl][ok],
            color="white",
            edgecolor="black",
            linewidth=0.3,
            pivot="middle",
            angles="uv",
            scale_units="inches",
            scale=max(vmax, 1e-9) / 0.35,
            width=0.004,
        )
        ref = round(vmax / 2, 2) or vmax / 2
        # below the axes, right of the x label: the title stays clear
        ax.quiverkey(q, 0.97, -0.09, ref, f"{ref:g} {units}", labelpos="W", coordinates="axes")
    ax.set_aspect(aspect)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    cov = float(finite.mean())
    ax.set_title(
        title
        or f"{field.attrs.get('title', 'flow field')}\n{_time_label(field, k)} (snapshot {k}/{n - 1}, "
        f"{cov:.0%} cells with data)",
        fontsize=10,
    )
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        fig.savefig(out, dpi=dpi, bbox_inches="tight")
    except ValueError as exc:  # unknown extension
        raise FieldError(f"cannot write figure {out}: {exc}") from None
    finally:
        plt.close(fig)
    return out

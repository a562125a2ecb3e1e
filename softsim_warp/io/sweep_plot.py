"""The figure of a sweep (``softsim sweep --plot``), drawn with matplotlib from the result rows.

* one varied key: one panel per metric, the metric over the key, one line per integrator (and dt,
  when several); exploded variants are crosses at the value they reached before exploding, and the
  explosion boundary (between the last value that completed and the first that exploded) is a
  dashed vertical line;
* two varied keys: one heat map per integrator over the two keys, coloured by ``metric``; exploded
  cells are hatched black, failed ones grey, and the boundary between completed and exploded cells
  is drawn as a thick line;
* ``--samples`` (points, not a grid): the same as scatter plots.

With ``--find-stable-dt`` the metric is ``stable_dt`` (log colour scale).
"""

from __future__ import annotations

import json
import math

import numpy as np

from ..core.methods import COLORS
from .outputs import save_atomic

LINE_METRICS = (
    ("energy_change_relative", "energy change / energy available"),
    ("max_speed", "largest speed [m/s]"),
    ("max_penetration", "largest penetration [m]"),
    ("com_y", "final centre of mass height [m]"),
    ("ref_position_error", "RMS error vs float64 RK4 [m]"),
)
STABLE_METRICS = (("stable_dt", "largest stable dt, scene [s]"),
                  ("stable_dt_jelly", "largest stable dt, free jelly [s]"))


def _key_value(v):
    """A column value as a number for an axis (JSON text of a list: its first number)."""
    if isinstance(v, bool):
        return float(v)
    if isinstance(v, (int, float)):
        return float(v)
    try:
        x = json.loads(v)
        while isinstance(x, list):
            x = x[0]
        return float(x)
    except (TypeError, ValueError, IndexError):
        return math.nan


def _series_key(row, keys):
    parts = [row["integrator"]]
    if "dt" not in keys:
        parts.append(f"dt={row['dt']:g}")
    return tuple(parts)


def _finite(x):
    return x is not None and isinstance(x, (int, float)) and math.isfinite(x)


def _log_axis(values):
    pos = [v for v in values if _finite(v) and v > 0]
    return len(pos) == len([v for v in values if _finite(v)]) and pos and max(pos) / min(pos) > 50


def plot_sweep(rows, keys, path, mode="run", metric=None, title="", sampled=False):
    """Draw the sweep's figure to ``path`` (atomically; the extension picks the format)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: PLC0415
    from matplotlib.figure import Figure  # noqa: PLC0415

    if not keys:
        keys = ["integrator"] if mode == "stable_dt" else ["dt"]
    if len(keys) == 1:
        fig = _lines(Figure, rows, keys[0], mode)
    else:
        fig = _maps(Figure, rows, keys[:2], mode, metric, sampled)
    FigureCanvasAgg(fig)
    if title:
        fig.suptitle(title)
    save_atomic(path, lambda tmp: fig.savefig(tmp, dpi=110), "--plot")


def _lines(Figure, rows, key, mode):
    # A metric that is 0 throughout (no penetration anywhere, say) gets no panel.
    metrics = STABLE_METRICS if mode == "stable_dt" else tuple(
        (m, label) for m, label in LINE_METRICS if any(_finite(r.get(m)) and r.get(m) != 0 for r in rows))
    fig = Figure(figsize=(7.5, 2.6 * len(metrics) + 0.6), layout="constrained")
    axes = fig.subplots(len(metrics), 1, sharex=True, squeeze=False)[:, 0]
    series = {}
    for r in rows:  # --find-stable-dt: the scene's dt is only the bisection's fallback start
        series.setdefault(_series_key(r, [key, "dt"] if mode == "stable_dt" else [key]), []).append(r)
    xs_all = [_key_value(r[key]) if key != "integrator" else 0.0 for r in rows]
    for ax, (m, label) in zip(axes, metrics):
        for skey, members in series.items():
            members = sorted(members, key=lambda r: _key_value(r[key]))
            color = COLORS.get(skey[0])
            x = np.array([_key_value(r[key]) for r in members])
            y = np.array([r.get(m) if _finite(r.get(m)) else np.nan for r in members], dtype=float)
            ok = np.array([r["status"] == "completed" for r in members])
            ax.plot(x[ok], y[ok], "o-", color=color, ms=4, lw=1.3, label=" ".join(skey))
            if (~ok).any():
                ax.plot(x[~ok], y[~ok], "x", color=color, ms=8, mew=2)
            # Explosion boundary: between the last completed value and the next exploded one.
            status = [r["status"] for r in members]
            for i in range(len(members) - 1):
                if {status[i], status[i + 1]} == {"completed", "exploded"}:
                    xb = math.sqrt(x[i] * x[i + 1]) if x[i] > 0 and x[i + 1] > 0 else 0.5 * (x[i] + x[i + 1])
                    ax.axvline(xb, color=color, ls="--", lw=1, alpha=0.8)
        if mode == "stable_dt" or _log_axis([r.get(m) for r in rows]):
            ax.set_yscale("log")
        ax.set_ylabel(label, fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
    if _log_axis(xs_all):
        axes[-1].set_xscale("log")
    axes[-1].set_xlabel(key)
    axes[0].legend(fontsize=7, loc="best")
    if mode != "stable_dt":
        axes[0].set_title("x: exploded (value at its last finite frame); dashed: explosion boundary", fontsize=8)
    return fig


def _maps(Figure, rows, keys, mode, metric, sampled):
    from matplotlib.colors import LogNorm  # noqa: PLC0415

    kx, ky = keys
    metric = metric or ("stable_dt" if mode == "stable_dt" else "energy_change_relative")
    panels = {}
    for r in rows:  # --find-stable-dt: the scene's dt is only the bisection's fallback start
        panels.setdefault(_series_key(r, keys + ["dt"] if mode == "stable_dt" else keys), []).append(r)
    n = len(panels)
    fig = Figure(figsize=(4.6 * n + 1.2, 4.4), layout="constrained")
    axes = fig.subplots(1, n, squeeze=False)[0]
    values = [r.get(metric) for r in rows if r["status"] == "completed" and _finite(r.get(metric))]
    log = mode == "stable_dt" or _log_axis(values)
    vmin, vmax = (min(values), max(values)) if values else (0.0, 1.0)
    norm = LogNorm(vmin=vmin, vmax=vmax) if log and values else None
    image = None
    for ax, (name, members) in zip(axes, panels.items()):
        label = " ".join(name)
        if sampled:
            x = [_key_value(r[kx]) for r in members]
            y = [_key_value(r[ky]) for r in members]
            ok = [r["status"] == "completed" and _finite(r.get(metric)) for r in members]
            c = [r.get(metric) for r, o in zip(members, ok) if o]
            image = ax.scatter([a for a, o in zip(x, ok) if o], [b for b, o in zip(y, ok) if o], c=c, norm=norm,
                               vmin=None if norm else vmin, vmax=None if norm else vmax, cmap="viridis", s=25)
            bad = [(a, b) for a, b, r in zip(x, y, members) if r["status"] == "exploded"]
            if bad:
                ax.plot(*zip(*bad), "kx", ms=7, mew=2, label="exploded")
                ax.legend(fontsize=7)
        else:
            xv = sorted({_key_value(r[kx]) for r in members})
            yv = sorted({_key_value(r[ky]) for r in members})
            grid = np.full((len(yv), len(xv)), np.nan)
            state = np.zeros((len(yv), len(xv)), dtype=int)  # 0 missing, 1 completed, 2 exploded, 3 failed
            for r in members:
                i, j = yv.index(_key_value(r[ky])), xv.index(_key_value(r[kx]))
                s = {"completed": 1, "exploded": 2}.get(r["status"], 3)
                state[i, j] = s
                if s == 1 and _finite(r.get(metric)):
                    grid[i, j] = r[metric]
            image = ax.imshow(grid, origin="lower", aspect="auto", cmap="viridis", norm=norm,
                              vmin=None if norm else vmin, vmax=None if norm else vmax,
                              extent=(-0.5, len(xv) - 0.5, -0.5, len(yv) - 0.5), interpolation="nearest")
            for (i, j), s in np.ndenumerate(state):
                if s == 2:
                    ax.add_patch(_rect(i, j, "black", "xx"))
                elif s == 3:
                    ax.add_patch(_rect(i, j, "0.6", None))
            # Boundary between completed and exploded neighbours.
            for i in range(len(yv)):
                for j in range(len(xv)):
                    if j + 1 < len(xv) and {state[i, j], state[i, j + 1]} == {1, 2}:
                        ax.plot([j + 0.5, j + 0.5], [i - 0.5, i + 0.5], color="red", lw=2.5)
                    if i + 1 < len(yv) and {state[i, j], state[i + 1, j]} == {1, 2}:
                        ax.plot([j - 0.5, j + 0.5], [i + 0.5, i + 0.5], color="red", lw=2.5)
            if grid.size <= 100:  # the values themselves, small enough to read
                for (i, j), v in np.ndenumerate(grid):
                    if np.isfinite(v):
                        ax.text(j, i, f"{v:.3g}", ha="center", va="center", fontsize=7, color="white",
                                bbox={"facecolor": "black", "alpha": 0.25, "lw": 0, "pad": 1})
            ax.set_xticks(range(len(xv)))
            ax.set_xticklabels([f"{v:.3g}" for v in xv], rotation=45, fontsize=7)
            ax.set_yticks(range(len(yv)))
            ax.set_yticklabels([f"{v:.3g}" for v in yv], fontsize=7)
        ax.set_xlabel(kx, fontsize=8)
        ax.set_ylabel(ky, fontsize=8)
        note = "" if sampled or mode == "stable_dt" else "  (hatched: exploded; red: boundary)"
        ax.set_title(label + note, fontsize=8)
    if image is not None:
        cb = fig.colorbar(image, ax=list(axes), shrink=0.9)
        cb.set_label(metric)
    return fig


def _rect(i, j, color, hatch):
    from matplotlib.patches import Rectangle  # noqa: PLC0415

    return Rectangle((j - 0.5, i - 0.5), 1, 1, facecolor=color if hatch is None else "none", edgecolor=color,
                     hatch=hatch, lw=0)

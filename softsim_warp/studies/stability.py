"""The largest stable step of each integrator, measured and predicted (``softsim stability SCENE`` reports it).

**Stable**, for one run, means all of:

1. every position and velocity stays finite (the speed bound of ``softsim run`` is not used: it is a
   heuristic for scenes, and a stiff lattice's own vibration can exceed it; condition 2 bounds the
   speed through the energy instead);
2. the energy ratio ``r(t) = (K + S) / (K0 + S0 + G0 - G(t))`` stays below ``R_MAX = 100``, where
   ``K`` is the kinetic and ``S`` the spring energy and ``G`` the gravity energy. The denominator is
   what energy conservation allows: the start's kinetic and spring energy plus the work gravity has
   done since. Damping, contact and friction only remove energy, so an exact solution keeps
   ``r <= 1``;
3. the energy does not keep growing: ``max r`` over the second half of the run is at most
   ``GROWTH = 2`` times ``max r`` over the first half. A bounded oscillation of the energy (the
   symplectic method's modified energy near its limit, or a stable method's transient) passes; an
   unstable mode, which multiplies its energy every step, fails.

Every run starts from the scene's initial state plus a seeded random displacement of every particle
(``PERTURBATION = 1e-3`` of the smallest rest spacing, no mean), so each mode, and an unstable one
in particular, starts from a known amplitude rather than from round-off (which would make the
result depend on the precision).

The largest stable step is bracketed (halving or doubling from the linear prediction, or from the
scene's dt) and bisected in log(dt) to a relative width of ``rtol``. It is measured on two systems:

* the **jelly**: the scene's jelly (``--jelly``, default the first) at full size, or with at most
  ``--lattice`` particles per axis at the same spacing, particle mass and springs, free (no
  gravity, no terrain), at rest, for ``steps`` steps. This is the system that the prediction
  (:func:`~softsim_warp.core.stability_model.predict_model_dt`: Lanczos on the jelly's own spring
  Jacobians, matrix-free in NumPy) linearises, so the two columns should agree; a finite run cannot see a growth slower than about ``ln(GROWTH)/steps``
  per step, so an instability that weak (euler on a nearly undamped mode) is reported as stable
  by the run.
* the **scene**: the scene as given (gravity, terrain, contact) for ``duration`` seconds.

Each is measured with the scene's damping and again with every ``kd = 0``. The map over ``ks`` sets
every spring type's ``ks`` to each value (``kd`` as in the scene) on the jelly.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass

import numpy as np

from ..core.methods import COLORS, IMPLICIT, NAMES
from ..core.model import NUMPY_SCALARS, build_model
from ..core.stability_model import free_jelly, predict_model_dt
from ..core.stability_model import free_jelly_model as lattice_model  # with free_jelly: the system measured
from ..core.stepper import make_integrator
from ..io.simulate import Simulator

R_MAX = 100.0
GROWTH = 2.0
PERTURBATION = 1.0e-3
SEED = 0
SAMPLES = 40
DEFAULT_STEPS = 1000
# Steps of one probe run at most: a dt whose run would need more counts as unstable, so a longer
# --steps, or a --duration longer than this many frame intervals, is refused up front (every probe
# would be "unstable" and every limit read "< MIN_DT").
MAX_PROBE_STEPS = 200_000
DEFAULT_KS = (1.0e2, 1.0e3, 1.0e4, 1.0e5, 1.0e6)
DEFAULT_RTOL = 0.02
MIN_DT = 1.0e-7


# ---------------------------------------------------------------------------------------------
# Systems


def predict(jelly_small: dict, methods, device=None) -> dict:
    """Linear prediction ``{method: dt}`` for a jelly dict (see :func:`free_jelly`), matrix-free (``device`` holds the model built for it)."""

    return predict_model_dt(lattice_model(jelly_small, device, "float64"), tuple(methods)).dt


def scene_model(scene, device, precision, undamped=False):
    """Model of the scene as given (with every kd set to 0 when ``undamped``)."""

    if undamped:
        scene = copy.copy(scene)
        scene.data = copy.deepcopy(scene.data)
        for j in scene.data["jelly"]:
            for p in j["springs"].values():
                p["kd"] = 0.0
    return build_model(scene, device=device, precision=precision)


def perturbation(model, amplitude=PERTURBATION, seed=SEED) -> np.ndarray:
    """Seeded random displacement ``(N, 3)`` [m]: ``amplitude`` times the smallest rest spacing, mean removed per jelly."""
    rng = np.random.default_rng(seed)
    out = np.zeros((model.particle_count, 3))
    for info in model.jellies:
        spacing = min((s for s in info.spacing if s > 0), default=1.0)
        d = rng.standard_normal((info.particle_count, 3)) * amplitude * spacing
        d -= d.mean(axis=0)
        out[info.particle_start : info.particle_start + info.particle_count] = d
    return out


# ---------------------------------------------------------------------------------------------
# One run


@dataclass
class Probe:
    """Outcome of one stability run."""

    dt: float
    steps: int
    stable: bool
    reason: str
    r_first: float
    r_second: float
    seconds: float


def probe(model, integrator, dt, steps, *, displacement=None, samples=SAMPLES, use_graph=True,
          on_warm_up=None) -> Probe:
    """Run ``steps`` steps of ``integrator`` at ``dt`` from the model's start plus ``displacement`` and judge stability.

    See the module docstring for the criterion. ``on_warm_up``: entered around the warm-up
    (``Simulator``'s), or None.
    """
    import warp as wp  # noqa: PLC0415

    t_start = time.perf_counter()
    chunk = max(1, math.ceil(steps / samples))
    n_chunks = math.ceil(steps / chunk)
    sim = Simulator(model, integrator, dt, fps=1.0, frames=1, use_graph=use_graph,
                    max_speed=math.inf, on_warm_up=on_warm_up)
    if displacement is not None:
        q0 = model.particle_q_host + displacement

        sim.states[0].particle_q.assign(q0.astype(NUMPY_SCALARS[model.precision]))
    m0 = sim.probe.measure(sim.state, 0, 0.0)
    base = m0.kinetic_energy + m0.spring_energy
    ratios = [1.0]
    reason = ""
    for c in range(1, n_chunks + 1):
        sim.advance(chunk)
        m = sim.probe.measure(sim.state, c, c * chunk * dt)
        if m.nonfinite:
            reason = f"non-finite state after {c * chunk} steps"
            break
        budget = base + (m0.gravity_energy - m.gravity_energy)
        r = (m.kinetic_energy + m.spring_energy) / max(budget, 1e-300)
        ratios.append(r)
        if r > R_MAX:
            reason = f"energy {r:.3g} times the budget after {c * chunk} steps"
            break
    wp.synchronize_device(model.device)
    half = max(1, len(ratios) // 2)
    r_first = max(ratios[:half])
    r_second = max(ratios[half:]) if len(ratios) > half else r_first
    if not reason and r_second > GROWTH * r_first:
        reason = f"energy grew {r_second / r_first:.3g}x from the first half of the run to the second"
    return Probe(dt, chunk * n_chunks, not reason, reason or "stable", r_first, r_second, time.perf_counter() - t_start)


def find_limit(is_stable, guess, min_dt=MIN_DT, max_dt=1.0, rtol=DEFAULT_RTOL) -> dict:
    """Bracket and bisect (in log dt) the largest ``dt`` for which ``is_stable(dt)`` holds.

    Returns:
        ``{"dt": largest stable dt found (0 if none above min_dt), "unstable_dt": smallest unstable dt
        found (inf if none up to max_dt), "bound": "" | ">=" | "<", "probes": [...]}``.
    """
    probes = []

    def check(h):
        ok = is_stable(h)
        probes.append((h, ok))
        return ok

    h = min(max(guess, min_dt), max_dt)
    lo, hi = None, None
    if check(h):
        lo = h
        while hi is None:
            if lo >= max_dt:
                return {"dt": lo, "unstable_dt": math.inf, "bound": ">=", "probes": probes}
            h = min(lo * 2.0, max_dt)
            if check(h):
                lo = h
            else:
                hi = h
    else:
        hi = h
        while lo is None:
            if hi <= min_dt:
                return {"dt": 0.0, "unstable_dt": hi, "bound": "<", "probes": probes}
            h = max(hi / 2.0, min_dt)
            if check(h):
                lo = h
            else:
                hi = h
    while hi / lo > 1.0 + rtol:
        mid = math.sqrt(lo * hi)
        if check(mid):
            lo = mid
        else:
            hi = mid
    return {"dt": lo, "unstable_dt": hi, "bound": "", "probes": probes}


def measure_limit(model, method, *, guess, steps=None, duration=None, max_dt, min_dt=MIN_DT, rtol=DEFAULT_RTOL,
                  max_steps=None, options=None, use_graph=True, on_warm_up=None) -> dict:
    """Largest stable dt of ``method`` on ``model``, by :func:`find_limit` over :func:`probe` runs.

    The run is ``steps`` steps, or ``duration`` seconds (``ceil(duration / dt)`` steps, at most
    ``max_steps``: a step that would need more is reported unstable-unresolved).

    Raises:
        ImportError: when the integrator is not available.
    """

    max_steps = MAX_PROBE_STEPS if max_steps is None else max_steps
    integ = make_integrator(method, model, options)
    disp = perturbation(model)
    # Compile once outside the timed probes.

    Simulator(model, integ, guess, 1.0, 1, use_graph=False, on_warm_up=on_warm_up).warm_up()
    notes = []

    def is_stable(h):
        n = steps if steps is not None else math.ceil(duration / h)
        if n > max_steps:
            notes.append(f"dt={h:.3g} s needs {n} steps > max_steps={max_steps}; counted unstable")
            return False
        return probe(model, integ, h, n, displacement=disp, use_graph=use_graph, on_warm_up=on_warm_up).stable

    out = find_limit(is_stable, guess, min_dt=min_dt, max_dt=max_dt, rtol=rtol)
    out["notes"] = notes
    return out


# ---------------------------------------------------------------------------------------------
# The whole report


def variant_stable_dt(scene, device, *, rtol=DEFAULT_RTOL, use_graph=True) -> dict:
    """The largest stable dt of a scene's integrator, as ``softsim sweep --find-stable-dt`` records it.

    ``_jelly`` columns: its first jelly, free and at rest, for :data:`DEFAULT_STEPS` steps; the plain
    columns: the scene as given, for at most a second (damping as in the scene). Both bisect from the
    linear prediction of the whole jelly; a prediction of 0 (no stable dt) skips the scene's run.
    """
    method = scene.sim["integrator"]
    precision = scene.sim["precision"]
    options = scene.data.get(IMPLICIT.name)
    max_dt = 1.0 / scene.sim["fps"]
    duration = min(scene.run_seconds(), 1.0)
    js = free_jelly(scene.jellies[0])
    p = float(predict(js, [method], device)[method])
    guess = _guess(p, scene.sim["dt"])
    free = lattice_model(js, device, precision)
    lattice = measure_limit(free, method, guess=guess, steps=DEFAULT_STEPS, max_dt=max_dt, rtol=rtol, options=options,
                            use_graph=use_graph)
    row = dict(stable_dt_jelly=lattice["dt"], unstable_dt_jelly=lattice["unstable_dt"], bound_jelly=lattice["bound"],
               predicted_dt=p, duration=duration)
    if p == 0.0:
        row.update(status="unstable", error="the linear analysis finds no stable dt; not measured in the scene")
        return row
    sc = scene_model(scene, device, precision)
    lim = measure_limit(sc, method, guess=guess, duration=duration, max_dt=max_dt, rtol=rtol, options=options,
                        use_graph=use_graph)
    row.update(status="completed", stable_dt=lim["dt"], unstable_dt=lim["unstable_dt"], bound=lim["bound"],
               probes=len(lim["probes"]))
    return row


def _guess(pred, fallback):
    return pred if (math.isfinite(pred) and pred > 0) else fallback


def analyse(scene, integrators=NAMES, *, ks_values=DEFAULT_KS, device=None, precision=None, steps=DEFAULT_STEPS,
            duration=None, rtol=DEFAULT_RTOL, scene_runs=True, max_dt=None, use_graph=True, lattice_max=None,
            jelly_index=0, log=None, progress=None, on_warm_up=None) -> dict:
    """Measured and predicted stability limits of every integrator; returns the JSON-ready report.

    Args:
        scene: validated scene.
        integrators: method names (a missing one is skipped with a note).
        ks_values: stiffnesses of the map [N/m] (empty: no map).
        device: Warp device.
        precision: precision of the runs (default the scene's; the prediction is always float64).
        steps: run length on the free jelly [steps].
        duration: run length in the scene [s] (default min(scene duration, 1 s)).
        rtol: relative width of the final bracket.
        scene_runs: also measure in the full scene (costlier).
        max_dt: largest step tried (default the frame interval 1/fps).
        use_graph: allow captured-graph replay.
        lattice_max: particles per axis of the free jelly, at most (None: the jelly's own size).
        jelly_index: which jelly of the scene is measured.
        log: callable taking a progress line.
        progress: callable ``progress(total)`` returning an object with ``update()`` and ``close()``
            (a tqdm bar), advanced once per measured limit.
        on_warm_up: entered around every run's warm-up (``Simulator``'s), or None.
    """
    import warp as wp  # noqa: PLC0415

    say = log or (lambda line: None)
    dev = wp.get_device(device)
    precision = precision or scene.sim["precision"]
    fps = scene.sim["fps"]
    max_dt = max_dt or 1.0 / fps
    duration = duration or min(scene.run_seconds(), 1.0)
    jelly = scene.jellies[jelly_index]
    options = scene.data.get(IMPLICIT.name)
    fallback = scene.sim["dt"]
    rows, skipped = [], {}
    available = []
    for method in integrators:
        try:
            make_integrator(method, lattice_model(free_jelly(jelly, max_n=2), dev, precision), options)
            available.append(method)
        except ImportError as e:
            skipped[method] = f"not available ({e})"
            say(f"{method}: skipped, not available ({e})")
    bar = progress(len(available) * (2 + len(ks_values))) if progress else None

    for undamped in (False, True):
        js = free_jelly(jelly, undamped=undamped, max_n=lattice_max)
        pred = predict(js, available, dev)
        lat = lattice_model(js, dev, precision)
        sc = scene_model(scene, dev, precision, undamped=undamped) if scene_runs else None
        for method in available:
            p = float(pred[method])
            row = {"integrator": method, "damping": "none" if undamped else "scene", "predicted": p}
            t0 = time.perf_counter()
            row["jelly"] = _clean(measure_limit(lat, method, guess=_guess(p, fallback), steps=steps, max_dt=max_dt,
                                                rtol=rtol, options=options, use_graph=use_graph,
                                                on_warm_up=on_warm_up))
            if sc is not None and p == 0.0:
                # Unstable at every dt (euler or midpoint without damping): a finite run only finds
                # how small a step hides the growth for `duration`, at up to max_steps per probe.
                row["scene_note"] = "not measured: the linear analysis finds no stable dt"
            elif sc is not None:
                row["scene"] = _clean(measure_limit(sc, method, guess=_guess(p, fallback), duration=duration,
                                                    max_dt=max_dt, rtol=rtol, options=options, use_graph=use_graph,
                                                    on_warm_up=on_warm_up))
            rows.append(row)
            say(f"{method:>10} {'undamped' if undamped else 'damped':>8}: predicted {_fmt_dt(p)}, jelly "
                f"{_fmt_limit(row['jelly'])}" + (f", scene {_fmt_limit(row['scene'])}" if "scene" in row else "")
                + f"  ({time.perf_counter() - t0:.1f} s)")
            if bar:
                bar.update()

    ks_map = []
    for ks in ks_values:
        js = free_jelly(jelly, ks=ks, max_n=lattice_max)
        pred = predict(js, available, dev)
        lat = lattice_model(js, dev, precision)
        for method in available:
            p = float(pred[method])
            m = _clean(measure_limit(lat, method, guess=_guess(p, fallback), steps=steps, max_dt=max_dt, rtol=rtol,
                                     options=options, use_graph=use_graph, on_warm_up=on_warm_up))
            ks_map.append({"ks": ks, "integrator": method, "predicted": p, "measured": m})
            say(f"ks={ks:g} {method:>10}: predicted {_fmt_dt(p)}, measured {_fmt_limit(m)}")
            if bar:
                bar.update()
    if bar:
        bar.close()

    js = free_jelly(jelly, max_n=lattice_max)
    return {
        "scene": scene.name,
        "source": scene.source,
        "device": str(dev),
        "precision": precision,
        "jelly": {"index": jelly_index, "resolution": js["resolution"], "size": js["size"], "particle_mass": js["particle_mass"],
                  "springs": js["springs"], "steps": steps},
        "scene_duration": duration if scene_runs else None,
        "max_dt": max_dt,
        "rtol": rtol,
        "definition": (
            f"stable: finite, r = (K + S) / (K0 + S0 + G0 - G) <= {R_MAX:g} "
            f"throughout and max r over the run's second half <= {GROWTH:g} x max r over its first half; "
            f"start = initial state + seeded random displacement of {PERTURBATION:g} x rest spacing; "
            f"jelly runs: {steps} steps of the free jelly at rest; scene runs: {duration:g} s of the scene "
            f"as given; 'none' damping: every kd = 0"
        ),
        "prediction": "linear stability analysis of the free jelly at rest, matrix-free (softsim_warp.core.stability_model)",
        "limits": rows,
        "ks_map": ks_map,
        "skipped": skipped,
    }


def _clean(limit: dict) -> dict:
    return {"dt": limit["dt"], "unstable_dt": limit["unstable_dt"], "bound": limit["bound"],
            "probes": len(limit["probes"]), "notes": limit.get("notes", [])}


def _fmt_dt(x):
    if math.isinf(x):
        return "inf"
    if x == 0:
        return "0 (always)"
    return f"{x:.3g}"


def _fmt_limit(m):
    if m["bound"] == ">=":
        return f">= {m['dt']:.3g}"
    if m["bound"] == "<":
        return f"< {m['unstable_dt']:.3g}"
    return f"{m['dt']:.3g}"


def format_table(report: dict) -> str:
    import textwrap  # noqa: PLC0415

    lat = report["jelly"]
    lines = [
        f"{report['scene']}: largest stable dt [s], {report['precision']} on {report['device']}",
        f"jelly {lat['index']}, {'x'.join(str(n) for n in lat['resolution'])} free, particle mass "
        f"{lat['particle_mass']:.4g} kg, {lat['steps']} steps; "
        + (f"scene runs {report['scene_duration']:g} s" if report["scene_duration"] else "no scene runs"),
        *textwrap.wrap("stable = " + report["definition"].split("stable: ", 1)[1], 110),
        "jelly: largest stable dt found - smallest unstable dt found (bisection from the prediction); "
        "ratio: their geometric mean / predicted",
        "",
        f"{'integrator':<11}{'damping':<9}{'predicted':>12}{'jelly':>22}{'ratio':>7}{'scene':>12}",
    ]
    for r in report["limits"]:
        m = r["jelly"]
        ratio = math.nan
        if 0 < r["predicted"] < math.inf and not m["bound"]:
            ratio = math.sqrt(m["dt"] * m["unstable_dt"]) / r["predicted"]
        lat_text = _fmt_limit(m) if m["bound"] else f"{m['dt']:.3g} - {m['unstable_dt']:.3g}"
        scene_text = _fmt_limit(r["scene"]) if "scene" in r else "-"
        lines.append(
            f"{r['integrator']:<11}{r['damping']:<9}{_fmt_dt(r['predicted']):>12}{lat_text:>22}"
            f"{'' if math.isnan(ratio) else f'{ratio:.2f}':>7}{scene_text:>12}"
        )
    if report["ks_map"]:
        methods = list(dict.fromkeys(m["integrator"] for m in report["ks_map"]))
        lines += ["", "map over ks (every spring type; free jelly runs): predicted / measured"]
        lines.append(f"{'ks [N/m]':>10}" + "".join(f"{m:>24}" for m in methods))
        for ks in dict.fromkeys(m["ks"] for m in report["ks_map"]):
            cells = []
            for meth in methods:
                e = next(m for m in report["ks_map"] if m["ks"] == ks and m["integrator"] == meth)
                cells.append(f"{_fmt_dt(e['predicted'])} / {_fmt_limit(e['measured'])}")
            lines.append(f"{ks:>10.3g}" + "".join(f"{c:>24}" for c in cells))
    for name, why in report["skipped"].items():
        lines.append(f"{name}: skipped: {why}")
    return "\n".join(lines)




def plot_report(report: dict, path):
    """Left: predicted vs measured limits per integrator; right (when the report has a ks map): stable dt over ks."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    if report["ks_map"]:
        fig, (ax_l, ax_m) = plt.subplots(1, 2, figsize=(13, 5.5))
    else:
        fig, ax_l = plt.subplots(1, 1, figsize=(7, 5.5))
        ax_m = None
    methods = list(dict.fromkeys(r["integrator"] for r in report["limits"]))
    max_dt = report["max_dt"]
    finite = [v for r in report["limits"] for v in (r["predicted"], r["jelly"]["dt"], r.get("scene", {}).get("dt", 0))
              if 0 < v < math.inf]
    floor = min(finite) / 10 if finite else max_dt * 1e-4
    # One column per integrator: x offsets for (damping) x (predicted, jelly, scene); a value of 0
    # (no stable dt) sits on the floor as a downward triangle, "stable up to max_dt" as an upward one.
    styles = {"predicted": ("_", 16, "predicted (linear)"), "jelly": ("o", 7, "measured, free jelly"),
              "scene": ("s", 7, "measured, scene")}
    for d_i, damping in enumerate(("scene", "none")):
        for k_i, key in enumerate(styles):
            marker, size, label = styles[key]
            for i, m in enumerate(methods):
                r = next((r for r in report["limits"] if r["integrator"] == m and r["damping"] == damping), None)
                if r is None or key not in r:
                    continue
                v = r[key] if key == "predicted" else r[key]["dt"]
                bound = "" if key == "predicted" else r[key]["bound"]
                mk = marker
                if v <= 0 or bound == "<":
                    v, mk = floor, "v"
                elif v >= max_dt or v == math.inf or bound == ">=":
                    v, mk = max_dt, "^"
                x = i + (d_i - 0.5) * 0.4 + (k_i - 1) * 0.1
                c = "k" if key == "predicted" else f"C{k_i}"
                ax_l.plot([x], [v], mk, color=c, ms=size if mk == marker else 9, mfc=c if damping == "scene" else "none",
                          mew=2)
    for k_i, key in enumerate(styles):
        marker, size, label = styles[key]
        c = "k" if key == "predicted" else f"C{k_i}"
        ax_l.plot([], [], marker, color=c, ms=size, mew=2, label=label)
    ax_l.plot([], [], "o", color="gray", label="filled: kd as in the scene (left)")
    ax_l.plot([], [], "o", color="gray", mfc="none", mew=2, label="open: kd = 0 (right)")
    ax_l.set_yscale("log")
    ax_l.set_xticks(range(len(methods)))
    ax_l.set_xticklabels(methods)
    ax_l.set_xlim(-0.6, len(methods) - 0.4)
    ax_l.set_ylim(floor / 2, max_dt * 3)
    ax_l.set_ylabel("largest stable dt [s]")
    ax_l.axhline(max_dt, color="gray", ls=":", lw=1)
    ax_l.set_title("largest stable dt (^: stable up to 1/fps; v: no stable dt)", fontsize=10)
    ax_l.legend(fontsize=7, loc="lower right")
    ax_l.grid(True, axis="y", which="both", alpha=0.3)

    if ax_m is not None:
        _plot_ks_map(ax_m, report, methods, max_dt)
    lat = report["jelly"]
    fig.suptitle(f"{report['scene']}: jelly {'x'.join(map(str, lat['resolution']))}, {report['precision']}, {report['device']}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_ks_map(ax_m, report, methods, max_dt):
    for m in methods:
        pts = [e for e in report["ks_map"] if e["integrator"] == m]
        if not pts:
            continue
        c = COLORS.get(m)
        ks = [e["ks"] for e in pts]
        pred = [min(e["predicted"], max_dt) for e in pts]
        ax_m.loglog(ks, pred, "-", color=c, alpha=0.6, label=f"{m} predicted")
        ok = [e for e in pts if not e["measured"]["bound"]]
        ax_m.loglog([e["ks"] for e in ok], [e["measured"]["dt"] for e in ok], "o", color=c, label=f"{m} measured")
        up = [e for e in pts if e["measured"]["bound"] == ">="]
        if up:
            ax_m.loglog([e["ks"] for e in up], [e["measured"]["dt"] for e in up], "^", color=c, mfc="none")
    ax_m.axhline(max_dt, color="gray", ls=":", lw=1)
    ax_m.set_xlabel("ks of every spring type [N/m]")
    ax_m.set_ylabel("largest stable dt [s]")
    ax_m.set_title("stable dt over ks (free jelly; open triangle: stable up to 1/fps)")
    ax_m.grid(True, which="both", alpha=0.3)
    ax_m.legend(fontsize=7, ncol=2)

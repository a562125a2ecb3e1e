"""Speed against error for each integrator and step size (``softsim accuracy SCENE`` reports it).

For each integrator and step ``dt`` the scene is run for ``--duration`` seconds and compared, frame by
frame, with a reference trajectory:

* **Reference.** rk4 in float64 at ``dt_ref`` (default: the smallest requested step / 8). rk4 is the
  highest-order method here, so at an eighth of the smallest step its error is ``8^4 = 4096`` times
  below rk4's own error at that step (on a smooth scene) and far below the first- and second-order
  methods'. To show that it converged, a second rk4 run at ``dt_ref / 2`` serves as the reference and
  the difference between the two is reported (``reference_self_error``): an upper estimate of the
  reference's own error (for a fourth-order method, the finer run's error is about 1/15 of it). The
  report flags it when it is not at least 10 times below the smallest error it measures.
* **Error.** ``RMS over the output frames 1..F and all particles of |x - x_ref|``, divided by the
  jelly size ``L`` (the longest edge of the largest jelly), so 1e-3 means "a thousandth of the
  jelly". Also the same RMS at the end time alone.
* **Cost.** Wall seconds per simulated second of the stepping alone: kernels are compiled, and
  graphs captured (as ``softsim run`` replays them, on CUDA and on the CPU), before the clock
  starts; copying frames to the host for the comparison is not counted.
* **Steps.** Frames are compared at the same times, so each ``dt`` is rounded to the nearest value
  that divides the frame interval ``1/fps`` (``n = round(1 / (fps dt))`` steps per frame); the report
  gives the step actually used.
* **Unstable runs** (non-finite state, a speed over the explosion bound or an energy overflow, judged
  as ``softsim run`` judges them: ``io.metrics.explosion_reason`` on the probe's reductions)
  are kept in the table and the plots, marked, with the time at which they stopped.

Contact makes every method first order near an impact, so convergence orders are measured on the
contact-free ``free_flight`` scene; contact scenes are shown separately (docs/ACCURACY.md).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..core.methods import COLORS, IMPLICIT, NAMES, REFERENCE
from ..core.model import build_model
from ..core.stepper import make_integrator
from ..io.metrics import explosion_reason
from ..io.simulate import Simulator

REFERENCE_METHOD = REFERENCE.name
REFERENCE_PRECISION = "float64"
# Default reference step relative to the smallest step measured (see the module docstring).
REFERENCE_DIVISOR = 8
# The reference counts as converged when its self-difference is this many times below the smallest
# error it is used to measure.
REFERENCE_MARGIN = 10.0
# Machine epsilon per precision: the fitted order ignores errors below 100 eps (round-off floor).
EPS = {"float32": float(np.finfo(np.float32).eps), "float64": float(np.finfo(np.float64).eps)}
ROUNDOFF_FACTOR = 100.0
# Errors above this fraction of the jelly are not in the asymptotic range; left out of the fit.
SATURATION = 0.1
# The fitted order uses this many of the smallest steps in range (the most asymptotic ones).
FIT_POINTS = 3




class ReferenceExploded(RuntimeError):
    """The reference run was unstable: no error can be measured against it (a smaller reference step helps)."""


# ---------------------------------------------------------------------------------------------
# Running one trajectory


@dataclass
class Trajectory:
    """One run's frames and cost.

    Attributes:
        integrator: method name.
        dt: step used [s] (divides the frame interval).
        precision: "float32" or "float64".
        steps_per_frame: steps between output frames.
        times: ``(F+1,)`` frame times [s].
        positions: ``(frames_done, N, 3)`` float64 particle positions [m], frame 0 included.
        step_seconds: wall seconds spent stepping (compilation and graph capture excluded).
        compile_seconds: wall seconds of the warm-up (kernel compilation and loading).
        exploded: the run stopped on a non-finite state or a speed above the bound.
        explosion: ``{"frame", "time", "reason"}`` when exploded.
        graph: whether steps were replayed from a captured graph.
    """

    integrator: str
    dt: float
    precision: str
    steps_per_frame: int
    times: np.ndarray
    positions: np.ndarray
    step_seconds: float
    compile_seconds: float
    exploded: bool = False
    explosion: dict | None = None
    graph: bool = False
    stats: dict = field(default_factory=dict)

    @property
    def frames_done(self) -> int:
        return self.positions.shape[0]

    @property
    def sim_time(self) -> float:
        return float(self.times[self.frames_done - 1]) if self.frames_done else 0.0


def steps_per_frame(dt: float, fps: float) -> int:
    """Whole number of steps per output frame closest to ``1 / (fps dt)`` (at least one)."""
    return max(1, round(1.0 / (fps * dt)))


def frame_dt(dt: float, fps: float) -> float:
    """``dt`` rounded so that it divides the frame interval ``1/fps`` exactly."""
    return 1.0 / (fps * steps_per_frame(dt, fps))


def jelly_size(scene) -> float:
    """Length scale of the error: the longest edge of the largest jelly [m]."""
    return max(max(j["size"]) for j in scene.jellies)


def run_trajectory(scene, integrator, dt, *, device=None, precision=None, fps=None, frames=None,
                   use_graph=True, max_speed=None, on_warm_up=None) -> Trajectory:
    """Run ``scene`` with ``integrator`` at (frame-rounded) ``dt`` and keep every frame's positions.

    Args:
        scene: a validated :class:`~softsim_warp.io.scene.Scene`.
        integrator: method name (``make_integrator`` name).
        dt: requested step [s]; rounded with :func:`frame_dt`.
        device: Warp device.
        precision: "float32"/"float64"; default the scene's.
        fps: frames per second of the comparison; default the scene's.
        frames: frames after frame 0; default the scene's.
        use_graph: replay each frame's steps from a captured graph, as ``softsim run`` does.
        max_speed: explosion speed bound [m/s]; default the scene's or the derived bound.
        on_warm_up: entered around the warm-up (``Simulator``'s), or None.

    Returns:
        A :class:`Trajectory`; on an explosion, the frames before it.

    Raises:
        ImportError: when the integrator's module is not available (``implicit`` before it lands).
    """
    import warp as wp  # noqa: PLC0415

    fps = float(fps or scene.sim["fps"])
    frames = int(frames if frames is not None else scene.frame_count())
    n = steps_per_frame(dt, fps)
    h = 1.0 / (fps * n)
    precision = precision or scene.sim["precision"]
    model = build_model(scene, device=device, precision=precision)
    integ = make_integrator(integrator, model, scene.data.get(IMPLICIT.name))
    graph = bool(use_graph)
    sim = Simulator(model, integ, h, fps, frames, use_graph=graph,
                    max_speed=max_speed if max_speed is not None else scene.sim.get("max_speed"), on_warm_up=on_warm_up)
    compile_seconds = sim.warm_up()
    if graph:
        # Capture the per-frame graphs now (one per buffer parity), then restart from frame 0, so
        # the timed loop only replays them.
        t0 = time.perf_counter()
        sim.advance(n)
        if n % 2:
            sim.advance(n)
        _restart(sim, model)
        wp.synchronize_device(model.device)
        compile_seconds += time.perf_counter() - t0
    reset_stats = getattr(integ, "reset_stats", None)
    if reset_stats is not None:
        reset_stats()

    times = np.arange(frames + 1) * (n * h)
    out = np.empty((frames + 1, model.particle_count, 3))
    out[0] = model.particle_q_host
    step_seconds = 0.0
    exploded, explosion = False, None
    done = 1
    for k in range(1, frames + 1):
        t0 = time.perf_counter()
        sim.advance(n)
        wp.synchronize_device(model.device)
        step_seconds += time.perf_counter() - t0
        # Judged as softsim run judges a frame: the probe's reductions on the device, one test.
        m = sim.probe.measure(sim.state, k, float(times[k]))
        reason = explosion_reason(m.nonfinite, m.max_speed, m.kinetic_energy, m.spring_energy, m.gravity_energy,
                                  m.total_energy, sim.max_speed, precision)
        if reason is not None:
            exploded = True
            explosion = {"frame": k, "time": float(times[k]), "reason": reason}
            break
        out[k] = sim.state.particle_q.numpy()  # the trajectory the errors are measured on
        done = k + 1
    return Trajectory(
        integrator=integ.name if isinstance(integrator, str) else str(integrator),
        dt=h,
        precision=precision,
        steps_per_frame=n,
        times=times,
        positions=out[:done],
        step_seconds=step_seconds,
        compile_seconds=compile_seconds,
        exploded=exploded,
        explosion=explosion,
        graph=graph,
        stats=dict(integ.stats()),
    )


def _restart(sim, model):
    """Put the simulator back at frame 0 (the model's initial state in buffer 0)."""
    import warp as wp  # noqa: PLC0415

    wp.copy(sim.states[0].particle_q, model.particle_q)
    wp.copy(sim.states[0].particle_qd, model.particle_qd)
    sim.current = 0
    sim.integrator.run.forget_contact_history()


# ---------------------------------------------------------------------------------------------
# Errors and orders


def frame_errors(run: Trajectory, ref: Trajectory, size: float) -> np.ndarray:
    """RMS over particles of |x - x_ref| / size at each frame the run reached, frame 0 included."""
    n = min(run.frames_done, ref.frames_done)
    diff = run.positions[:n] - ref.positions[:n]
    return np.sqrt((diff * diff).sum(axis=2).mean(axis=1)) / size


def trajectory_errors(run: Trajectory, ref: Trajectory, size: float) -> tuple[float, float]:
    """(RMS over frames 1..F and particles of |x - x_ref| / size, the same at the last frame).

    Both are ``inf`` for a run that did not reach the last frame.
    """
    if run.frames_done < ref.frames_done:
        return math.inf, math.inf
    if not np.allclose(run.times[: ref.frames_done], ref.times[: ref.frames_done], rtol=1e-9, atol=1e-12):
        raise ValueError("frames of the run and the reference are at different times")
    diff = run.positions[1:] - ref.positions[1 : run.frames_done]
    sq = (diff * diff).sum(axis=2)  # (F, N) squared distances
    rms = math.sqrt(float(sq.mean())) / size
    end = math.sqrt(float(sq[-1].mean())) / size
    return rms, end


def fit_order(dts, errors, floor=0.0, ceiling=SATURATION, points=FIT_POINTS):
    """Least-squares slope of log(error) against log(dt) over the smallest steps in the asymptotic range.

    Points with a non-finite error, an error at or below ``floor`` (reference or round-off limited) or
    above ``ceiling`` (not yet asymptotic) are left out; of the rest, the ``points`` smallest steps
    (the most asymptotic) are fitted.

    Returns:
        ``(order, used)``: the slope (``nan`` with fewer than two points) and the dts used.
    """
    pts = sorted((d, e) for d, e in zip(dts, errors) if math.isfinite(e) and floor < e <= ceiling)[:points]
    if len(pts) < 2:
        return math.nan, [d for d, _ in pts]
    x = np.log([d for d, _ in pts])
    y = np.log([e for _, e in pts])
    slope = float(np.polyfit(x, y, 1)[0])
    return slope, [d for d, _ in pts]


def pairwise_orders(dts, errors):
    """Local orders ``log(e_i / e_{i+1}) / log(dt_i / dt_{i+1})`` between successive finite points."""
    pts = sorted((d, e) for d, e in zip(dts, errors) if math.isfinite(e) and e > 0)
    out = []
    for (d0, e0), (d1, e1) in zip(pts, pts[1:]):
        out.append(math.log(e1 / e0) / math.log(d1 / d0))
    return out


# ---------------------------------------------------------------------------------------------
# The whole measurement


def measure(scene, integrators=NAMES, dts=None, *, device=None, precision=None, duration=None,
            reference_dt=None, fps=None, use_graph=True, log=None, progress=None, on_warm_up=None) -> dict:
    """Run every integrator at every step against the reference; return the report as a dict.

    Args:
        scene: validated scene.
        integrators: method names; one whose module is missing (``implicit`` before it lands) is
            skipped with a note in ``report["skipped"]``.
        dts: requested steps [s] for every integrator, or ``{integrator: steps}`` (default: the
            scene's dt times 2, 1, 1/2, 1/4, 1/8).
        device: Warp device.
        precision: precision of the runs under test (default the scene's); the reference is float64.
        duration: simulated time [s] (default the scene's).
        reference_dt: reference step [s] (default min(dts) / 8); a check run uses half of it.
        fps: frame rate of the comparison (default the scene's).
        use_graph: allow captured-graph replay.
        log: callable taking a progress line, or None.
        progress: callable ``progress(total)`` returning a bar with ``update()`` and ``close()``,
            advanced once per run (the two reference runs included), or None.
        on_warm_up: entered around every run's warm-up (``Simulator``'s), or None.

    Returns:
        A JSON-ready dict (see ``docs/ACCURACY.md`` for the fields).

    Raises:
        ReferenceExploded: when either reference run was unstable.
    """
    import warp as wp  # noqa: PLC0415

    say = log or (lambda line: None)
    fps = float(fps or scene.sim["fps"])
    duration = float(duration or scene.run_seconds())
    frames = max(1, round(duration * fps))
    precision = precision or scene.sim["precision"]
    if dts is None:
        dts = [scene.sim["dt"] * f for f in (2.0, 1.0, 0.5, 0.25, 0.125)]
    per_method = dts if isinstance(dts, dict) else {name: dts for name in integrators}
    per_method = {name: sorted({frame_dt(d, fps) for d in per_method[name]}, reverse=True) for name in integrators}
    smallest_dt = min(min(v) for v in per_method.values())
    size = jelly_size(scene)
    ref_dt = frame_dt(reference_dt if reference_dt else smallest_dt / REFERENCE_DIVISOR, fps)
    dev = wp.get_device(device)

    bar = progress(2 + sum(len(v) for v in per_method.values())) if progress else None
    tick = bar.update if bar else (lambda: None)
    say(f"reference: {REFERENCE_METHOD} {REFERENCE_PRECISION} at dt={ref_dt:.4g} s and {ref_dt / 2:.4g} s")
    ref_coarse = run_trajectory(scene, REFERENCE_METHOD, ref_dt, device=dev, precision=REFERENCE_PRECISION,
                                fps=fps, frames=frames, use_graph=use_graph, on_warm_up=on_warm_up)
    tick()
    ref = run_trajectory(scene, REFERENCE_METHOD, ref_dt / 2, device=dev, precision=REFERENCE_PRECISION,
                         fps=fps, frames=frames, use_graph=use_graph, on_warm_up=on_warm_up)
    tick()
    if ref.exploded or ref_coarse.exploded:
        raise ReferenceExploded(
            f"the reference run ({REFERENCE_METHOD}, {REFERENCE_PRECISION}, dt={ref_dt:g} s) exploded: "
            f"{(ref.explosion or ref_coarse.explosion)['reason']}; pass a smaller --reference-dt"
        )
    ref_self, ref_self_end = trajectory_errors(ref_coarse, ref, size)

    runs, skipped = [], {}
    for name in integrators:
        for dt in per_method[name]:
            try:
                tr = run_trajectory(scene, name, dt, device=dev, precision=precision, fps=fps, frames=frames,
                                    use_graph=use_graph, on_warm_up=on_warm_up)
            except ImportError as e:
                skipped[name] = f"not available ({e})"
                say(f"{name}: skipped, not available ({e})")
                break
            rms, end = trajectory_errors(tr, ref, size)
            per_frame = frame_errors(tr, ref, size)
            sim_time = tr.sim_time if tr.sim_time > 0 else tr.dt
            row = {
                "integrator": name,
                "dt": tr.dt,
                "steps_per_frame": tr.steps_per_frame,
                "steps": tr.steps_per_frame * (tr.frames_done - 1),
                "stable": not tr.exploded,
                "explosion": tr.explosion,
                "sim_seconds": tr.sim_time,
                "step_seconds": tr.step_seconds,
                "wall_per_sim_second": tr.step_seconds / sim_time if tr.frames_done > 1 else math.nan,
                "compile_seconds": tr.compile_seconds,
                "graph": tr.graph,
                "rms_error": rms,
                "end_error": end,
                "error_per_frame": [float(e) for e in per_frame],
            }
            if tr.stats:
                row["stats"] = tr.stats
            runs.append(row)
            status = "ok" if row["stable"] else f"UNSTABLE at t={tr.explosion['time']:.3g} s"
            say(f"{name:>10} dt={tr.dt:.4g}  {row['wall_per_sim_second']:.3g} s/s  err={rms:.3g}  {status}")
            tick()

    finite = [r["rms_error"] for r in runs if math.isfinite(r["rms_error"]) and r["rms_error"] > 0]
    smallest = min(finite) if finite else math.nan
    floor_precision = ROUNDOFF_FACTOR * EPS[precision]
    floor = max(REFERENCE_MARGIN * ref_self, floor_precision)
    orders = {}
    for name in dict.fromkeys(r["integrator"] for r in runs):
        rows = [r for r in runs if r["integrator"] == name]
        d = [r["dt"] for r in rows]
        e = [r["rms_error"] for r in rows]
        order, used = fit_order(d, e, floor=floor)
        orders[name] = {"order": order, "dts_fitted": used, "pairwise": pairwise_orders(d, e)}

    return {
        "scene": scene.name,
        "source": scene.source,
        "device": str(dev),
        "precision": precision,
        "duration": frames / fps,
        "fps": fps,
        "frames": frames,
        "particles": int(ref.positions.shape[1]),
        "size": size,
        "error_definition": (
            "RMS over output frames 1..F and all particles of |x - x_ref|, divided by the jelly size L "
            "(longest edge of the largest jelly); end_error: the same RMS at the last frame only"
        ),
        "cost_definition": (
            "wall seconds of stepping per simulated second; kernels compiled and graphs captured before "
            "timing; frame copies to the host not counted"
        ),
        "reference": {
            "integrator": REFERENCE_METHOD,
            "precision": REFERENCE_PRECISION,
            "dt": ref_dt / 2,
            "check_dt": ref_dt,
            "self_error": ref_self,
            "self_error_end": ref_self_end,
            "smallest_error": smallest,
            "margin": smallest / ref_self if ref_self > 0 else math.inf,
            "converged": bool(ref_self * REFERENCE_MARGIN <= smallest) if finite else True,
            "note": (
                f"reference = {REFERENCE_METHOD} {REFERENCE_PRECISION} at dt/2; self_error is its RMS "
                f"difference to the run at dt, an upper estimate of its own error"
            ),
        },
        "fit": {
            "floor": floor,
            "ceiling": SATURATION,
            "note": (
                f"orders are least-squares slopes of log(rms_error) vs log(dt) over the {FIT_POINTS} smallest "
                f"stable steps with {floor:.3g} < error <= {SATURATION:g} (floor = max({REFERENCE_MARGIN:g} x "
                f"reference self_error, {ROUNDOFF_FACTOR:g} x eps of {precision}))"
            ),
        },
        "orders": orders,
        "runs": runs,
        "skipped": skipped,
    }


# ---------------------------------------------------------------------------------------------
# Output: table and plots


def format_table(report: dict) -> str:
    """The report as a plain-text table."""
    ref = report["reference"]
    lines = [
        f"{report['scene']}: {report['particles']} particles, {report['duration']:g} s at {report['fps']:g} fps, "
        f"{report['precision']} on {report['device']}; error = RMS position error / jelly size "
        f"{report['size']:g} m",
        f"reference: {ref['integrator']} {ref['precision']} dt={ref['dt']:.4g} s; difference to dt={ref['check_dt']:.4g} s: "
        f"{ref['self_error']:.3g} ({ref['margin']:.3g}x below the smallest error {ref['smallest_error']:.3g})"
        + ("" if ref["converged"] else "  WARNING: not converged; pass a smaller --reference-dt"),
        "",
        f"{'integrator':<11}{'dt [s]':>11}{'steps':>8}{'wall s/sim s':>14}{'RMS error':>12}{'end error':>12}  status",
    ]
    for r in report["runs"]:
        status = "ok" if r["stable"] else f"UNSTABLE (stopped at t={r['explosion']['time']:.3g} s: {r['explosion']['reason']})"
        lines.append(
            f"{r['integrator']:<11}{r['dt']:>11.4g}{r['steps']:>8d}{r['wall_per_sim_second']:>14.4g}"
            f"{_fmt(r['rms_error']):>12}{_fmt(r['end_error']):>12}  {status}"
        )
    lines.append("")
    lines.append("fitted order (slope of log error vs log dt; " + report["fit"]["note"].split("over ", 1)[1] + "):")
    for name, o in report["orders"].items():
        pw = ", ".join(f"{p:.2f}" for p in o["pairwise"])
        lines.append(f"  {name:<11}{_fmt(o['order'], '.2f'):>6}   (pairwise: {pw})")
    for name, why in report["skipped"].items():
        lines.append(f"  {name:<11}skipped: {why}")
    return "\n".join(lines)


def _fmt(x, spec=".3g"):
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    if isinstance(x, float) and math.isinf(x):
        return "unstable"
    return format(x, spec)




def plot_report(report: dict, path, title=None):
    """Work-precision (error vs wall time) and convergence (error vs dt) side by side in one figure.

    Unstable runs are drawn as crosses on a band above the largest finite error, labelled
    "unstable", at their dt (convergence) or cost up to the explosion (work-precision).
    """
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    runs = report["runs"]
    finite = [r["rms_error"] for r in runs if math.isfinite(r["rms_error"]) and r["rms_error"] > 0]
    top = max(finite) * 10 if finite else 1.0
    bottom = min(finite + [report["reference"]["self_error"] or top]) / 3 if finite else 1e-3
    fig, (ax_wp, ax_cv, ax_t) = plt.subplots(1, 3, figsize=(17, 5))
    for name in report["orders"]:
        rows = sorted((r for r in runs if r["integrator"] == name), key=lambda r: r["dt"])
        c = COLORS.get(name, None)
        ok = [r for r in rows if r["stable"] and math.isfinite(r["rms_error"])]
        bad = [r for r in rows if r not in ok]
        order = report["orders"][name]["order"]
        label = f"{name} (order {order:.2f})" if math.isfinite(order) else name
        if ok:
            ax_wp.loglog([r["wall_per_sim_second"] for r in ok], [r["rms_error"] for r in ok], "o-", color=c, label=name)
            for r in ok:
                ax_wp.annotate(f"{r['dt']:.2g}", (r["wall_per_sim_second"], r["rms_error"]), fontsize=7,
                               xytext=(3, 3), textcoords="offset points", color=c)
            ax_cv.loglog([r["dt"] for r in ok], [r["rms_error"] for r in ok], "o-", color=c, label=label)
        for r in bad:
            w = r["wall_per_sim_second"] if math.isfinite(r["wall_per_sim_second"]) else None
            if w:
                ax_wp.loglog([w], [top], "x", color=c, markersize=9, mew=2)
                ax_wp.annotate(f"{r['dt']:.2g} unstable", (w, top), fontsize=7, xytext=(3, -10),
                               textcoords="offset points", color=c)
            ax_cv.loglog([r["dt"]], [top], "x", color=c, markersize=9, mew=2)
            ax_cv.annotate("unstable", (r["dt"], top), fontsize=7, xytext=(3, -10), textcoords="offset points", color=c)
    # Error over time at each integrator's smallest stable step: where the error comes from (an
    # impact shows as a jump).
    for name in report["orders"]:
        ok = [r for r in runs if r["integrator"] == name and r["stable"] and r.get("error_per_frame")]
        if ok:
            r = min(ok, key=lambda r: r["dt"])
            e = np.asarray(r["error_per_frame"][1:])
            t = np.arange(1, e.size + 1) / report["fps"]
            ax_t.semilogy(t, np.maximum(e, 1e-300), color=COLORS.get(name), label=f"{name}, dt={r['dt']:.2g}")
    ax_t.set_xlabel("time [s]")
    ax_t.set_ylabel("RMS position error / jelly size")
    ax_t.set_title("error over time (smallest stable dt)")
    ax_t.grid(True, which="both", alpha=0.3)
    ax_t.legend(fontsize=8)
    ref = report["reference"]
    from matplotlib.ticker import NullFormatter  # noqa: PLC0415

    for ax in (ax_wp, ax_cv):
        ax.xaxis.set_minor_formatter(NullFormatter())  # decade labels only; minor ones overlap
        ax.axhline(ref["self_error"], color="gray", ls=":", lw=1)
        ax.set_ylim(bottom, top * 3)
        ax.grid(True, which="both", alpha=0.3)
        ax.set_ylabel("RMS position error / jelly size")
    ax_cv.annotate(f"reference self-difference {ref['self_error']:.2g}", (0.02, ref["self_error"]),
                   xycoords=("axes fraction", "data"), fontsize=7, color="gray", xytext=(0, 2), textcoords="offset points")
    ax_wp.set_xlabel("wall seconds per simulated second")
    ax_cv.set_xlabel("dt [s]")
    ax_wp.set_title("work-precision (labels: dt [s]; x: unstable)")
    ax_cv.set_title("convergence (fitted order in legend)")
    ax_wp.legend(fontsize=8)
    ax_cv.legend(fontsize=8)
    fig.suptitle(title or f"{report['scene']}: {report['particles']} particles, {report['duration']:g} s, "
                 f"{report['precision']}, {report['device']}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

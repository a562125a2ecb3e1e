"""Run summaries: the metrics file's summary, the one-line report, the explosion message."""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..core.stability_model import predict_jelly_dt


def energy_floor(model, metrics) -> float:
    """The energy change [J] that rounding alone can make in a run: a change this small is not a gain.

    The energies are sums over every particle and spring in the model's precision (epsilon ``eps``):
    their sum rounds by about ``eps`` times the energy held (kinetic + spring + |gravity|, the most
    seen in any frame), and a jelly at rest vibrates by the rounding of its coordinates (``eps R``,
    R the largest coordinate reached), which springs of total stiffness ``sum ks`` turn into up to
    ``eps^2 R^2 sum ks / 2`` of energy -- the 3e-11 J "gain" of a float32 jelly at rest in zero gravity.
    """
    if not metrics:
        return 0.0
    eps = float(np.finfo(np.float64 if model.precision == "float64" else np.float32).eps)
    held = max(abs(m.kinetic_energy) + abs(m.spring_energy) + abs(m.gravity_energy) for m in metrics)
    q0 = np.asarray(model.particle_q_host, dtype=np.float64)
    c0 = np.asarray(metrics[0].com, dtype=np.float64)
    moved = max(float(np.linalg.norm(np.asarray(m.com, dtype=np.float64) - c0)) for m in metrics)
    reach = (float(np.abs(q0).max()) if q0.size else 0.0) + moved
    ks = float(np.sum(np.abs(model.spring_stiffness_host)))
    floor = eps * held + 0.5 * (eps * reach) ** 2 * ks
    return floor if math.isfinite(floor) else math.inf


def _moves(motion: dict) -> bool:
    """A pin's or a terrain entry's motion keys move it (a velocity, a spin or keyframes)."""
    spin = motion.get("spin") or {}
    return bool(any(float(c) != 0.0 for c in motion.get("velocity", (0.0, 0.0, 0.0)))
                or float(spin.get("degrees_per_second", 0.0)) != 0.0 or motion.get("keyframes"))


def pins_drive(scene) -> bool:
    """The scene has pins or terrain that move (a velocity, a spin, keyframes, an animated mesh):
    they do work on the jellies, so their energy may rise without any fault of the integrator."""
    data = scene.data
    if any(_moves(pin) for pin in data.get("pin", [])):
        return True
    return any(_moves(t.get("motion") or {}) or t.get("animated")
               for kind in ("plane", "sphere", "bowl", "mesh") for t in data.get(kind, []))


def energy_drift(metrics, floor: float = 0.0) -> tuple[float, float]:
    """(E_end - E_0 [J], that change relative to the energy available above the lowest state reached).

    The gravity energy's zero is arbitrary, so the relative drift divides by E_0 minus the lowest
    gravity energy seen: the energy the jelly could give up by falling plus what it started with.
    The relative change is NaN where that energy is nothing but rounding (a jelly at rest that has not
    moved yet; ``floor``: :func:`energy_floor`), since any change divided by it is meaningless.
    """
    if len(metrics) < 2:
        return 0.0, 0.0
    e0, e1 = metrics[0].total_energy, metrics[-1].total_energy
    lowest = min(m.gravity_energy for m in metrics)
    scale = e0 - lowest
    if not scale > max(1e-9 * max(abs(e0), abs(e1), abs(lowest), 1e-300), floor):
        return e1 - e0, math.nan
    return e1 - e0, (e1 - e0) / scale


def summary_dict(scene, model, integrator, simulator, result, device) -> dict:
    floor = energy_floor(model, result.metrics)
    drift, rel = energy_drift(result.metrics, floor)
    step_seconds = getattr(result, "step_seconds", result.wall_seconds)
    return {
        "scene": scene.name,
        "source": scene.source,
        "integrator": integrator.name,
        "precision": model.precision,
        "dt": simulator.dt,
        "dt_auto": bool(scene.sim.get("_dt_auto")),
        "fps": simulator.fps,
        "device": str(device),
        "warp_version": wp.config.version,
        "particles": model.particle_count,
        "springs": model.spring_count,
        "steps": result.steps,
        "frames": result.frames_written,
        "sim_time": result.sim_time,
        "wall_seconds": result.wall_seconds,
        "step_seconds": step_seconds,
        "compile_seconds": result.compile_seconds,
        "particle_steps_per_second": model.particle_count * result.steps / step_seconds if step_seconds > 0 else 0.0,
        "energy_drift": drift,
        "energy_drift_relative": rel,
        "energy_rounding": floor,
        "pins_drive": pins_drive(scene),
        "max_speed_bound": simulator.max_speed,
        "exploded": result.exploded,
        "explosion": result.explosion,
        "interrupted": result.interrupted,
        **integrator.stats(),
        **profile_stats(simulator),
    }


def profile_stats(simulator) -> dict:
    """A profiled run's ``time_*`` keys (core/profile.py); none for a run without ``profile``."""
    if simulator.profile is None:
        return {}
    return {**simulator.profile.stats(), "time_notes": simulator.integrator.profile_notes()}


def profile_table(s: dict) -> str:
    """The ``time_*`` keys of a profiled run's summary as a table: seconds, milliseconds a step, share."""
    steps, total = s["time_steps"], s["time_total_s"]
    lines = [
        f"profile: {steps} steps of {s['integrator']} on {s['device']}, {total:.4g} s "
        "(each part between device synchronises, kernels launched one by one)",
        f"  {'part':<20} {'seconds':>10} {'ms/step':>10} {'share':>7}",
    ]
    rows = list(s["time_parts_s"].items()) + [("total", total)]
    for name, seconds in rows:
        per_step = 1e3 * seconds / steps if steps else 0.0
        share = 100.0 * seconds / total if total > 0 else 0.0
        lines.append(f"  {name:<20} {seconds:>10.4f} {per_step:>10.3f} {share:>6.1f}%")
    lines += [f"  note: {note}" for note in s["time_notes"]]
    return "\n".join(lines)


def summary_line(s: dict, out) -> str:
    """The end-of-run line: how the run ended, what it did, how fast, and where the energy went.

    Energy lost is what damping, friction and inelastic contact take (expected in a damped scene);
    energy gained is the warning sign of a step too large for the method."""
    status = s.get("status", "complete")
    ended = "" if status == "complete" else f"{status.upper()}: "
    drift, rel = s["energy_drift"], s["energy_drift_relative"]
    rel = None if rel is None else 100 * rel
    if s["frames"] < 2:
        energy = ""  # one frame: no change to report
    elif drift is not None and abs(drift) <= s.get("energy_rounding", 0.0):
        energy = f"; energy change {drift:.3g} J, within the rounding of the energy sums ({s['energy_rounding']:.2g} J)"
    elif rel is None or not math.isfinite(rel):  # no energy to compare with (JSON writes NaN as null)
        energy = f"; energy change {drift:.4g} J"
    elif s.get("pins_drive"):  # the pins' work is in the change: neither a loss nor a gain of the method
        energy = f"; energy change {drift:+.4g} J ({rel:+.1f}%), including the work of the driven pins and moving terrain"
    elif drift <= 0:
        energy = f"; {abs(drift):.4g} J ({abs(rel):.1f}% of the energy available) dissipated by damping, friction and contact"
    else:
        energy = f"; energy GAINED {drift:.4g} J ({rel:+.1f}%): the integrator adds energy, try a smaller dt"
    frames = f"{s['frames']} frame" + ("" if s["frames"] == 1 else "s")
    return (
        f"{ended}{s['scene']}: {frames}, {s['steps']} steps of {s['integrator']} at dt={s['dt']:g} s"
        f"{' (auto)' if s.get('dt_auto') else ''} in "
        f"{s['wall_seconds']:.2f} s ({s['particle_steps_per_second']:.3g} particle-steps/s){energy} -> {out}"
    )


def predicted_stable_dt(scene, method, jelly=0, device=None) -> float | None:
    """Largest dt predicted stable for jelly ``jelly`` of the scene: a linear analysis of the whole
    jelly, free and at rest, matrix-free in NumPy (:mod:`softsim_warp.core.stability_model`)."""
    try:
        return predict_jelly_dt(scene.jellies[jelly], (method,), device).dt[method]
    except Exception:  # noqa: BLE001 - a prediction is advice; never let it hide the explosion itself
        return None


def explosion_message(scene, model, result) -> str:
    """The exit-3 message: frame, time, integrator, dt, what was seen, the stable dt predicted for the
    jelly that exploded, and the frames kept. Also stores the prediction in ``result.explosion``."""
    e = result.explosion
    sim = scene.sim
    k = e.get("jelly", 0)
    which = f" (jelly.{k})" if len(scene.jellies) > 1 else ""
    text = (
        f"{scene.source}: simulation exploded at frame {e['frame']} (t = {e['time']:.4g} s) with integrator "
        f"{sim['integrator']} at dt = {sim['dt']:g} s: {e['reason']}{which}"
    )
    if e.get("overflow"):
        # A smaller dt would not help: the speeds, masses, gravity or heights are beyond the precision.
        e["predicted_stable_dt"] = None
        kept = f"frames 0-{result.frames_written - 1} were kept" if result.frames_written else "no frame was kept"
        return (f"{text}; the scene's velocities, masses, gravity or positions are too large for "
                f"{model.precision} arithmetic; {kept}")
    pred = predicted_stable_dt(scene, sim["integrator"], k, model.device)
    e["predicted_stable_dt"] = pred if pred is not None and np.isfinite(pred) else None
    if pred is None:
        text += "; no stability prediction is available for this jelly"
    elif pred == 0.0:
        text += f"; the linear analysis predicts {sim['integrator']} unstable at every dt for this jelly (an undamped mode)"
    elif np.isfinite(pred):
        text += f"; largest dt predicted stable for this jelly: {pred:.3g} s"
    kept = f"frames 0-{result.frames_written - 1} were kept" if result.frames_written else "no frame was kept"
    return f"{text}; {kept}"

"""Pins: particles held fixed or driven along a path.

A pinned particle has mass 0 (inverse mass 0): no force accelerates it and the terrain contact
leaves it alone, yet its springs pull on the rest of the jelly with its position and velocity. A
*held* pin keeps its particles where they start, at rest; a *driven* pin moves them along the path
of ``kernels/pins.py`` (a velocity, a spin about a centre, keyframed offsets). Every integrator
calls :func:`drive` at the start of its step; it launches nothing for a model without driven pins.

The pin clock counts the steps taken (``t = steps * dt``); it is each integrator's own
(``RunState.pin_clock``), and ``Stepper.warm_up`` restarts it after its warm-up step
(``RunState.reset``).
"""

from __future__ import annotations

import numpy as np
import warp as wp
from ..kernels import pins as pins_kernels

FACES = ("-x", "+x", "-y", "+y", "-z", "+z")
INTERPOLATIONS = ("linear", "smooth")


def select_particles(shape, points, face=None, box=None, indices=None) -> np.ndarray:
    """Local indices (lattice order) of a jelly's particles selected by a face, a box or a list.

    Args:
        shape: the jelly's particles per axis.
        points: the jelly's start positions ``(N, 3)`` [m].
        face: one of :data:`FACES`: the lattice layer at index 0 (``-``) or n - 1 (``+``) of that
            lattice axis (the jelly's own axes, before its rotation).
        box: ``(min, max)`` corners [m] in world coordinates: the particles that start inside.
        indices: local particle indices.
    """
    n = int(np.prod(shape))
    if face is not None:
        axis = "xyz".index(face[1])
        ijk = np.stack(np.unravel_index(np.arange(n), shape), axis=1)
        layer = 0 if face[0] == "-" else shape[axis] - 1
        return np.flatnonzero(ijk[:, axis] == layer)
    if box is not None:
        lo, hi = np.asarray(box[0], dtype=np.float64), np.asarray(box[1], dtype=np.float64)
        return np.flatnonzero(np.all((points >= lo) & (points <= hi), axis=1))
    return np.unique(np.asarray(indices, dtype=np.int64))


class PinDrive:
    """Device arrays of the driven pins of a model (``Model.pins``): which particles, their start
    positions and each pin's path; the clock is a run's (``RunState.pin_clock``)."""

    def __init__(self, pins: list, q0: np.ndarray, device, scalar, vec3):
        particles, pin_of, start = [], [], []
        key_first, key_count, key_t, key_v = [], [], [], []
        for p_i, pin in enumerate(pins):
            particles.append(pin["particles"])
            pin_of.append(np.full(len(pin["particles"]), p_i, dtype=np.int32))
            start.append(q0[pin["particles"]])
            key_first.append(len(key_t))
            key_count.append(len(pin["key_times"]))
            key_t.extend(pin["key_times"])
            key_v.extend(pin["key_offsets"])
        np_scalar = np.float64 if scalar == wp.float64 else np.float32

        def arr(values, dtype, np_dtype):
            return wp.array(np.asarray(values, dtype=np_dtype), dtype=dtype, device=device)

        self.count = int(sum(len(p) for p in particles))
        self.particle = arr(np.concatenate(particles), wp.int32, np.int32)
        self.pin = arr(np.concatenate(pin_of), wp.int32, np.int32)
        self.start = arr(np.concatenate(start), vec3, np_scalar)
        self.velocity = arr([p["velocity"] for p in pins], vec3, np_scalar)
        self.spin = arr([p["spin"] for p in pins], vec3, np_scalar)
        self.center = arr([p["center"] for p in pins], vec3, np_scalar)
        self.key_first = arr(key_first, wp.int32, np.int32)
        self.key_count = arr(key_count, wp.int32, np.int32)
        self.smooth = arr([int(p["interpolation"] == "smooth") for p in pins], wp.int32, np.int32)
        self.key_time = arr(key_t or [0.0], scalar, np_scalar)
        self.key_value = arr(np.reshape(key_v or [[0.0, 0.0, 0.0]], (-1, 3)), vec3, np_scalar)


def drive(model, run, state, dt):
    """Put the driven pins of ``model`` on their paths at the step's start in ``state`` and give them
    the velocity that lands them on the path at its end; then advance the pin clock of ``run`` (the
    integrator's ``RunState``). A no-op (no launch) without driven pins."""
    pins = model.pins
    if pins is None:
        return
    h = model.scalar(dt)
    wp.launch(
        pins_kernels.drive_pins,
        dim=pins.count,
        inputs=[run.pin_clock, h, pins.particle, pins.pin, pins.start, pins.velocity, pins.spin, pins.center,
                pins.key_first, pins.key_count, pins.smooth, pins.key_time, pins.key_value],
        outputs=[state.particle_q, state.particle_qd],
        device=model.device,
    )
    wp.launch(pins_kernels.advance_pin_clock, dim=1, inputs=[run.pin_clock], device=model.device)


def make_motion(velocity=(0.0, 0.0, 0.0), spin=(0.0, 0.0, 0.0), center=None, key_times=(), key_offsets=(),
                interpolation="linear") -> dict:
    """A motion of ``kernels/pins.py`` as a pin or a moving terrain primitive stores it, checked
    (ValueError); ``center`` None is left for the caller to fill in. ``driven``: whether it moves."""
    times = np.asarray(key_times, dtype=np.float64).ravel()
    offsets = np.asarray(key_offsets, dtype=np.float64).reshape(-1, 3)
    if times.size != offsets.shape[0]:
        raise ValueError(f"key_times has {times.size} entries, key_offsets {offsets.shape[0]}")
    if times.size > 1 and np.any(np.diff(times) <= 0):
        raise ValueError(f"key_times must be strictly increasing (got {times.tolist()})")
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be linear or smooth (got {interpolation!r})")
    motion = {
        "velocity": np.asarray(velocity, dtype=np.float64),
        "spin": np.asarray(spin, dtype=np.float64),
        "center": None if center is None else np.asarray(center, dtype=np.float64),
        "key_times": times.tolist(),
        "key_offsets": offsets.tolist(),
        "interpolation": interpolation,
    }
    motion["driven"] = bool(np.any(motion["velocity"]) or np.any(motion["spin"]) or times.size)
    return motion


def motion_transform(motion: dict, t: float):
    """The rigid map of a motion at ``t`` on the host, float64: ``(R (3, 3), T (3,))`` with a point
    that starts at ``X`` at ``R X + T`` (:func:`path_position` of the origin and the axes)."""
    moved = path_position(motion, np.vstack([np.zeros(3), np.eye(3)]), t)
    return (moved[1:] - moved[0]).T, moved[0]


def path_position(pin: dict, x0: np.ndarray, t: float) -> np.ndarray:
    """The path of ``kernels/pins.py`` on the host, float64: where particles starting at ``x0``
    (``(3,)`` or ``(N, 3)``) are at ``t``; ``pin`` as :meth:`ModelBuilder.add_pin` stores it."""
    c = np.asarray(pin["center"], dtype=np.float64)
    w = np.asarray(pin["spin"], dtype=np.float64) * t
    angle = np.linalg.norm(w)
    r = np.asarray(x0, dtype=np.float64) - c
    if angle > 0:
        k = w / angle
        r = r * np.cos(angle) + np.cross(k, r) * np.sin(angle) + (r @ k)[..., None] * k * (1 - np.cos(angle))
    return c + np.asarray(pin["velocity"]) * t + _offset(pin, t) + r


def _offset(pin, t):
    times = np.asarray(pin["key_times"], dtype=np.float64)
    values = np.asarray(pin["key_offsets"], dtype=np.float64).reshape(-1, 3)
    if times.size == 0:
        return np.zeros(3)
    if t <= times[0]:
        return values[0]
    if t >= times[-1]:
        return values[-1]
    k = int(np.searchsorted(times, t, side="left")) - 1
    t0, t1 = times[k], times[k + 1]
    u = (t - t0) / (t1 - t0)
    p0, p1 = values[k], values[k + 1]
    if pin["interpolation"] != "smooth":
        return p0 + (p1 - p0) * u
    m0 = (p1 - values[k - 1]) / (t1 - times[k - 1]) if k > 0 else (p1 - p0) / (t1 - t0)
    m1 = (values[k + 2] - p0) / (times[k + 2] - t0) if k + 2 < times.size else (p1 - p0) / (t1 - t0)
    h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
    return p0 * h00 + m0 * h10 * (t1 - t0) + p1 * h01 + m1 * h11 * (t1 - t0)

"""Small model factories shared by the tests."""

import numpy as np

from softsim_warp import ModelBuilder, make_integrator
from softsim_warp.core.lattice import SPRING_TYPE_NAMES


def jelly_builder(shape=(3, 3, 3), size=0.2, mass=0.01, ks=100.0, kd=0.0, gravity=(0.0, 0.0, 0.0), **kw):
    b = ModelBuilder(gravity=gravity)
    springs = {name: {"ks": ks, "kd": kd} for name in SPRING_TYPE_NAMES}
    b.add_jelly(shape, size, mass, springs, **kw)
    return b


def run_steps(model, method, dt, steps, state=None, options=None):
    """Advance ``steps`` steps from ``state`` (default: the model's initial state); returns the final state."""
    integ = make_integrator(method, model, options)
    a = state if state is not None else model.state()
    b = model.state()
    for _ in range(steps):
        integ.step(a, b, dt)
        a, b = b, a
    return a


def energies(model, state):
    """(kinetic, spring) energy in float64 from host copies."""
    q = state.particle_q.numpy().astype(np.float64)
    v = state.particle_qd.numpy().astype(np.float64)
    m = model.particle_mass_host
    ke = 0.5 * np.sum(m * np.sum(v * v, axis=1))
    p = model.spring_indices_host
    stretch = np.linalg.norm(q[p[:, 0]] - q[p[:, 1]], axis=1) - model.spring_rest_host
    se = 0.5 * np.sum(model.spring_stiffness_host * stretch**2)
    return ke, se


def sigterm_after_first_frame(monkeypatch, delay: float) -> dict:
    """Send this process SIGTERM ``delay`` seconds after the first frame is written to USD (inside a
    long frame that follows); the returned dict gets the send time as ``"t"`` (perf_counter)."""
    import os
    import signal
    import threading
    import time

    from softsim_warp.io.usd import UsdWriter

    first = threading.Event()
    real = UsdWriter.write_frame

    def write_frame(self, frame, *a, **kw):
        real(self, frame, *a, **kw)
        if frame == 0:
            first.set()

    monkeypatch.setattr(UsdWriter, "write_frame", write_frame)
    sent = {}

    def kill():
        if first.wait(300):
            time.sleep(delay)
            sent["t"] = time.perf_counter()
            os.kill(os.getpid(), signal.SIGTERM)

    sent["thread"] = threading.Thread(target=kill, daemon=True)
    sent["thread"].start()
    return sent


def rate_about_y(x, v):
    """Least-squares rate [rad/s] at which particles at ``x`` with velocities ``v`` turn about the y
    axis through the origin (v_xz = omega (z, -x)), and the radius of their centre [m]."""
    r = x[:, [0, 2]]
    tangent = np.stack([r[:, 1], -r[:, 0]], axis=1)
    return float((tangent * v[:, [0, 2]]).sum() / (tangent**2).sum()), float(np.linalg.norm(r.mean(axis=0)))

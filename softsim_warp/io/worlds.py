"""Several variants of a scene as worlds of one model: built together, stepped in the same launches.

``softsim compare`` and ``softsim sweep`` both batch variants this way. A world shares no
particles, springs or terrain with another, and each world's explosion bound and metrics are what a
single run of its variant would compute: on the CPU a world of a batch steps bit for bit like that
single run (tests/test_sweep_batch.py), as long as the batch uses one integrator (the stage count and
the contact filter between stages are per model).
"""

from __future__ import annotations

import types

import numpy as np

from ..core.model import ModelBuilder, populate, terrain_anchors
from .metrics import speed_bound


def make_builder(datas):
    """A builder holding each validated scene dict of ``datas`` as world 0, 1, ... (gravity of the first)."""
    builder = ModelBuilder(datas[0]["simulation"]["gravity"])
    for w, data in enumerate(datas):
        populate(builder, data, world=w)
    return builder


def _world_bounds(model) -> list[tuple[int, int]]:
    """Index of the first and of the last jelly of each world in ``model.jellies``."""
    first, last = {}, {}
    for k, j in enumerate(model.jellies):
        first.setdefault(j.world, k)
        last[j.world] = k
    return [(first[w], last[w]) for w in range(model.world_count)]


def world_ranges(model) -> list[tuple[int, int]]:
    """``(first particle, end)`` of each world of ``model`` (populate adds a world's jellies one after another)."""
    out = []
    for a, b in _world_bounds(model):
        first, last = model.jellies[a], model.jellies[b]
        out.append((first.particle_start, last.particle_start + last.particle_count))
    return out


def world_jellies(model) -> list[tuple[int, int]]:
    """``(first jelly, end)`` of each world in ``model.jellies`` (a world's jellies are consecutive)."""
    return [(a, b + 1) for a, b in _world_bounds(model)]


def world_speed_bound(model, start, end, world):
    """The explosion speed bound a single run of this world's variant would use (see ``metrics.speed_bound``)."""

    # Made once for all worlds of a batch: each world's particle box (its least and largest
    # coordinates), its fastest particle's initial velocity as the device holds it, and its terrain.
    def inputs():
        ranges = world_ranges(model)
        starts = np.array([a for a, _ in ranges])
        q, qd = model.particle_q_host, model.particle_qd.numpy()
        consecutive = all(b == a2 for (_, b), a2 in zip(ranges, [*starts[1:], q.shape[0]]))
        if consecutive and q.shape[0]:
            lo, hi = np.minimum.reduceat(q, starts, axis=0), np.maximum.reduceat(q, starts, axis=0)
        else:
            lo = np.array([q[a:b].min(axis=0) for a, b in ranges])
            hi = np.array([q[a:b].max(axis=0) for a, b in ranges])
        speed = np.linalg.norm(qd, axis=1)  # row by row: each world's values as its own run computes them
        fastest = [a + int(np.argmax(speed[a:b])) for a, b in ranges]
        by_world = {}
        for kind in ("planes", "bowls", "spheres"):
            for item in getattr(model, kind):
                by_world.setdefault(item["world"], {"planes": [], "bowls": [], "spheres": []})[kind].append(item)
        return dict(zip(starts.tolist(), zip(lo, hi, fastest))), qd, by_world

    boxes, velocities, by_world = model.derived("world_bound_inputs", inputs)
    lo, hi, fastest = boxes[start]
    terrain = by_world.get(world, {"planes": [], "bowls": [], "spheres": []})
    qd = velocities[fastest : fastest + 1]
    # speed_bound reads only these host-side fields; this view holds one world's share of them: the
    # box's two corners stand for its particles (the same extremes), the fastest particle for all
    # of them (the same largest speed).
    view = types.SimpleNamespace(
        particle_q_host=np.stack([lo, hi]),
        planes=terrain["planes"],
        bowls=terrain["bowls"],
        spheres=terrain["spheres"],
        meshes=[],  # (a batch's meshes are left out of the bound, as they were before the Model was declared)
        terrain_anchor_points=terrain_anchors(terrain["bowls"], terrain["spheres"]),
        particle_qd=types.SimpleNamespace(numpy=lambda: qd),
        particle_count=end - start,
        gravity_host=model.gravity_host,
    )
    return speed_bound(view)


def probe_arrays(probe) -> dict:
    """The per-jelly arrays of ``probe``'s last ``measure`` on the host (one copy each per frame)."""
    return {
        "ke": probe.kinetic.numpy().astype(np.float64),
        "ge": probe.gravity_energy.numpy().astype(np.float64),
        "se": probe.spring_energy.numpy().astype(np.float64),
        "mom": probe.moment.numpy().astype(np.float64),
        "vmax": probe.max_speed.numpy().astype(np.float64),
        "bad": probe.nonfinite.numpy(),
        "mass": probe.jelly_mass,
    }


def world_frame(arrays, jellies) -> dict:
    """One world's whole-scene metrics from :func:`probe_arrays`.

    ``jellies``: the world's ``(first, end)`` jelly range. The sums are taken over the same values
    in the same order as ``MetricsProbe.measure`` takes them for a model holding that world alone,
    so they agree with a single run bit for bit.
    """
    a, b = jellies
    ke, ge, se = arrays["ke"][a:b], arrays["ge"][a:b], arrays["se"][a:b]
    mom, vmax, bad = arrays["mom"][a:b], arrays["vmax"][a:b], arrays["bad"][a:b]
    mass = arrays["mass"][a:b].sum()
    return {
        "com": (mom.sum(axis=0) / mass).tolist() if mass > 0 else [0.0, 0.0, 0.0],
        "kinetic_energy": float(ke.sum()),
        "spring_energy": float(se.sum()),
        "gravity_energy": float(ge.sum()),
        "total_energy": float(ke.sum() + se.sum() + ge.sum()),
        "max_speed": float(vmax.max()) if len(vmax) else 0.0,
        "nonfinite": int(bad.sum()),
    }


def world_columns(arrays, jellies) -> dict:
    """:func:`world_frame` of every world at once, as one array per quantity (``com`` [worlds, 3], the
    others [worlds]): the host's share of a batch's frame is a few NumPy operations, not a loop over
    worlds. Vectorised when each world has one jelly (the sums over one jelly are that jelly's values,
    so the result is the same bit for bit); worlds of several jellies are summed by :func:`world_frame`."""
    if not all(b - a == 1 for a, b in jellies):
        frames = [world_frame(arrays, j) for j in jellies]
        cols = {key: np.array([f[key] for f in frames], dtype=np.float64) for key in frames[0] if key != "nonfinite"}
        cols["nonfinite"] = np.array([f["nonfinite"] for f in frames], dtype=np.int64)
        return cols
    idx = np.array([a for a, _ in jellies])
    ke, ge, se = arrays["ke"][idx], arrays["ge"][idx], arrays["se"][idx]
    mass = arrays["mass"][idx]
    with np.errstate(divide="ignore", invalid="ignore"):
        com = np.where(mass[:, None] > 0, arrays["mom"][idx] / mass[:, None], 0.0)
    return {"com": com, "kinetic_energy": ke, "spring_energy": se, "gravity_energy": ge, "total_energy": ke + se + ge,
            "max_speed": arrays["vmax"][idx], "nonfinite": arrays["bad"][idx].astype(np.int64)}

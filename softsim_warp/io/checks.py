"""Checks of a scene as a whole, run by :func:`softsim_warp.io.scene.validate` after the schema.

The schema checks each value alone; these check what only the whole scene shows:

* every number is representable in the scene's precision (a stiffness of 1e39 is finite in the
  TOML file but infinite in float32, and a mass of 1e-40 is zero there, so 1/m is infinite);
* neighbouring particles are farther apart than the precision can resolve at their position;
* the scene fits in host memory before anything is built (:mod:`softsim_warp.io.resources`);
* no jelly starts inside terrain: every terrain type registers a signed-distance function in
  :data:`TERRAIN_SDF`, evaluated in NumPy on the jelly's initial particles.
"""

from __future__ import annotations

import math

import numpy as np

from ..core.model import rotation_matrix
from ..core.voxelize import mesh_lattice
from .mesh_scene import mesh_signed_distance_entry
from .resources import check_host_build

# Normal range of each precision: a non-zero value outside it becomes 0 or inf on the device.
PRECISION_RANGE = {
    "float32": (float(np.finfo(np.float32).tiny), float(np.finfo(np.float32).max)),
    "float64": (float(np.finfo(np.float64).tiny), float(np.finfo(np.float64).max)),
}
PRECISION_EPS = {"float32": float(np.finfo(np.float32).eps), "float64": float(np.finfo(np.float64).eps)}

# Particles per chunk when evaluating terrain distances, so a large jelly is checked in bounded memory.
_CHUNK = 1 << 18


def plane_signed_distance(plane: dict, points: np.ndarray) -> np.ndarray:
    """Signed distance [m] of ``points`` (N, 3) to a validated ``[[plane]]`` (unit normal), +inf over its hole.

    Positive on the side the normal points to; a point over the hole passes through the plane,
    as in ``kernels/contact.py: plane_distance``, so it can never be inside it.
    """
    n = np.asarray(plane["normal"], dtype=np.float64)
    phi = (points - np.asarray(plane["point"], dtype=np.float64)) @ n
    hole = plane.get("hole")
    if hole:
        r = points - np.asarray(hole["center"], dtype=np.float64)
        r = r - np.outer(r @ n, n)
        phi = np.where(np.einsum("ij,ij->i", r, r) < hole["radius"] ** 2, np.inf, phi)
    return phi


def sphere_signed_distance(sphere: dict, points: np.ndarray) -> np.ndarray:
    """Signed distance [m] to a solid ``[[sphere]]``, positive outside (``kernels/contact.py: sphere_distance``)."""
    return np.linalg.norm(points - np.asarray(sphere["center"], dtype=np.float64), axis=1) - sphere["radius"]


def bowl_signed_distance(bowl: dict, points: np.ndarray) -> np.ndarray:
    """Signed distance [m] to a ``[[bowl]]`` shell, positive inside its sphere, +inf at or above the cut.

    As ``kernels/contact.py: bowl_distance``. The bowl is a shell: both sides are free space, so
    it is listed in :data:`SHELLS` and a jelly may start on either side, but not across it.
    """
    phi = bowl["radius"] - np.linalg.norm(points - np.asarray(bowl["center"], dtype=np.float64), axis=1)
    cut = bowl.get("cut_height", math.inf)
    return np.where(points[:, 1] >= cut, np.inf, phi)


# Scene key of each terrain type -> signed distance of points to one entry (positive = free space,
# +inf where the entry does not collide). A new terrain type adds its function here.
TERRAIN_SDF = {"plane": plane_signed_distance, "sphere": sphere_signed_distance, "bowl": bowl_signed_distance,
               "mesh": mesh_signed_distance_entry}
# Terrain types that are thin shells: particles behind them (phi < 0) pass through, so a jelly is
# wrong only when the shell cuts it, some particles in front and some behind.
SHELLS = {"bowl"}


def jelly_points(jelly: dict, chunk: int = _CHUNK):
    """Yield a validated jelly's initial particle positions [m] in chunks of at most ~``chunk`` rows.

    Same placement as ``ModelBuilder.add_jelly``: the lattice centred on the origin, rotated, then
    moved to ``center``.
    """

    shape = [int(n) for n in jelly["resolution"]]
    size = jelly["size"]
    center = np.asarray(jelly["center"], dtype=np.float64)
    rows = max(1, chunk // max(shape[1] * shape[2], 1))
    # Extreme but finite float64 scenes may overflow to inf here; that is no error (and NumPy's
    # warning would break the one-line answer).
    with np.errstate(all="ignore"):
        axes = [np.linspace(-0.5 * s, 0.5 * s, n) * f if n > 1 else np.zeros(1)
                for n, s, f in zip(shape, size, _initial_scale(jelly))]
        rot = rotation_matrix(jelly["rotation"]["axis"], jelly["rotation"]["degrees"])
        # x = center + R (a_i, b_j, c_k) = center + a_i R[:, 0] + b_j R[:, 1] + c_k R[:, 2], by
        # broadcasting (an (N, 3) @ (3, 3) product is many times slower in NumPy).
        ey = axes[1][None, :, None, None] * rot[:, 1]
        ez = axes[2][None, None, :, None] * rot[:, 2]
    # A mesh jelly is its box lattice with the points outside the mesh left out (io/mesh_scene.py).
    inside = mesh_lattice(jelly)[1].reshape(shape[0], -1) if "mesh" in jelly else None
    for i0 in range(0, shape[0], rows):
        with np.errstate(all="ignore"):
            ex = axes[0][i0 : i0 + rows, None, None, None] * rot[:, 0]
            pts = ((ex + center) + ey + ez).reshape(-1, 3)
        yield pts if inside is None else pts[inside[i0 : i0 + rows].ravel()]


def _check_precision(value, key, ctx, lo, hi, precision):
    if isinstance(value, dict):
        for k, v in value.items():
            _check_precision(v, f"{key}.{k}" if key else k, ctx, lo, hi, precision)
    elif isinstance(value, list):
        for i, v in enumerate(value):
            # Vectors are reported whole; lists of tables by index.
            _check_precision(v, f"{key}.{i}" if isinstance(v, dict) else key, ctx, lo, hi, precision)
    elif isinstance(value, float) and value != 0.0 and not lo <= abs(value) <= hi:
        ctx.fail(
            key,
            f"is outside the range of {precision} ({lo:.3g} to {hi:.3g} in magnitude); "
            f'use a value in range or simulation.precision = "float64"',
            value,
        )


def _initial_scale(jelly) -> list:
    """The jelly's per-axis initial scale (1 where not given)."""
    scale = jelly.get("initial_scale")
    if scale is None:
        return [1.0, 1.0, 1.0]
    return [float(c) for c in (scale if isinstance(scale, (list, tuple)) else [scale] * 3)]


def _check_spacing(jelly, key, ctx, precision):
    """Neighbours must stay distinct after rounding positions to the precision: the rest spacing
    (the springs' rest lengths) and the starting one, which ``initial_scale`` shrinks."""
    scale = _initial_scale(jelly)
    extent = max(abs(c) for c in jelly["center"]) + 0.5 * math.sqrt(
        sum(s * s * max(1.0, abs(f)) ** 2 for s, f in zip(jelly["size"], scale)))
    resolution = PRECISION_EPS[precision] * max(extent, 1e-300)
    for n, s, f in zip(jelly["resolution"], jelly["size"], scale):
        if n > 1 and s / (n - 1) <= 4 * resolution:
            # 4 ulps: below that, rest lengths are mostly rounding error and spring forces noise.
            ctx.fail(
                f"{key}.size",
                f"particle spacing {s / (n - 1):.3g} m is below the {precision} resolution at this position "
                f"(4 x eps x {extent:.3g} m = {4 * resolution:.3g} m)",
                jelly["size"],
            )
        if n > 1 and abs(f) * s / (n - 1) <= 4 * resolution:
            # Scaled below the resolution, the start positions collapse onto each other (a crushed
            # jelly of 1e-20 would start as a flat disc, not re-expand).
            ctx.fail(
                f"{key}.initial_scale",
                f"the starting particle spacing {abs(f) * s / (n - 1):.3g} m is below the {precision} resolution at "
                f"this position (4 x eps x {extent:.3g} m = {4 * resolution:.3g} m)",
                jelly["initial_scale"],
            )


def check_terrain_overlap(data: dict, ctx):
    """Fail if a jelly starts inside terrain: a particle with negative signed distance to a solid (plane,
    sphere), or particles on both sides of a shell (bowl)."""
    terrain = [(kind, i, entry) for kind, sdf in TERRAIN_SDF.items() for i, entry in enumerate(data.get(kind, []))]
    if not terrain:
        return
    for j, jelly in enumerate(data["jelly"]):
        for kind, i, entry in terrain:
            sdf = TERRAIN_SDF[kind]
            inside, deepest, front = 0, 0.0, 0
            for pts in jelly_points(jelly):
                with np.errstate(all="ignore"):  # overflow is no error here (see jelly_points)
                    phi = sdf(entry, pts)
                bad = phi < 0.0
                front += int(((phi >= 0.0) & np.isfinite(phi)).sum())
                if bad.any():
                    inside += int(bad.sum())
                    deepest = max(deepest, float(-phi[bad].min()))
            total = math.prod(jelly["resolution"])
            if kind in SHELLS:
                if inside and front:
                    ctx.fail(
                        f"jelly.{j}.center",
                        f"jelly starts across the shell of {kind}.{i}: {inside} of {total} particles are behind it "
                        f"and {front} in front, up to {deepest:.4g} m behind; move the jelly or the {kind}",
                        jelly["center"],
                    )
                continue
            if inside:
                ctx.fail(
                    f"jelly.{j}.center",
                    f"jelly starts inside terrain: {inside} of {total} particles are inside {kind}.{i}, "
                    f"the deepest by {deepest:.4g} m; move the jelly or the terrain",
                    jelly["center"],
                )


def check_scene(data: dict, ctx):
    """All whole-scene checks; ``ctx.fail(key, message, value)`` raises the one-line error."""
    precision = data["simulation"]["precision"]
    lo, hi = PRECISION_RANGE[precision]
    # Size first: a huge resolution makes total_mass / particles underflow, and the answer must
    # name the resolution, not the particle_mass derived from it.
    check_host_build(data, ctx.source)
    _check_precision(data, "", ctx, lo, hi, precision)
    for j, jelly in enumerate(data["jelly"]):
        _check_spacing(jelly, f"jelly.{j}", ctx, precision)
    check_terrain_overlap(data, ctx)


def jelly_box(jelly: dict):
    """(centre, axes as columns, half extents) of a box jelly's lattice at the start, or None for a
    mesh jelly (its particles are a voxelised subset of the box: left out of the overlap check)."""
    if "mesh" in jelly:
        return None
    rot = rotation_matrix(jelly["rotation"]["axis"], jelly["rotation"]["degrees"])
    half = 0.5 * np.abs(np.asarray(jelly["size"], dtype=np.float64) * np.asarray(_initial_scale(jelly)))
    return np.asarray(jelly["center"], dtype=np.float64), rot, half


def box_overlap(a, b) -> float:
    """Depth [m] by which two oriented boxes ``(centre, axes, half extents)`` interpenetrate along
    their least separating axis (the separating-axis test over the 15 axes of two boxes): > 0 when
    they overlap, <= 0 when they are apart or only touch."""
    (ca, ra, ha), (cb, rb, hb) = a, b
    t = cb - ca
    axes = [ra[:, i] for i in range(3)] + [rb[:, i] for i in range(3)]
    for i in range(3):
        for j in range(3):
            c = np.cross(ra[:, i], rb[:, j])
            n = np.linalg.norm(c)
            if n > 1e-9:  # parallel edges give no new axis
                axes.append(c / n)
    depth = math.inf
    for axis in axes:
        reach = np.abs(ra.T @ axis) @ ha + np.abs(rb.T @ axis) @ hb
        depth = min(depth, float(reach - abs(t @ axis)))
    return depth


def jelly_overlaps(data: dict) -> list:
    """Pairs ``(i, j, depth)`` of box jellies whose lattices start interpenetrating (``i < j``).

    Two jellies that start inside each other are held together by contact (or, without it, pass
    through each other fused into one shape); touching (depth within rounding of the sizes) is fine.
    """
    boxes = [jelly_box(j) for j in data["jelly"]]
    pairs = []
    for i, a in enumerate(boxes):
        for j in range(i + 1, len(boxes)):
            b = boxes[j]
            if a is None or b is None:
                continue
            depth = box_overlap(a, b)
            tol = 1e-9 * max(float(a[2].max()), float(b[2].max()), 1e-300)
            if depth > tol:
                pairs.append((i, j, depth))
    return pairs


def overlap_warning(data: dict, source: str) -> str | None:
    """The one-line warning for jellies that start overlapping (:func:`jelly_overlaps`), or None."""
    pairs = jelly_overlaps(data)
    if not pairs:
        return None
    i, j, depth = pairs[0]
    more = f" (and {len(pairs) - 1} more overlapping pairs)" if len(pairs) > 1 else ""
    return (f"warning: {source}: jelly.{j}.center: jelly.{j} starts overlapping jelly.{i} by {depth:.3g} m; "
            f"they may stay fused; move one of them{more} (got {list(data['jelly'][j]['center'])})")

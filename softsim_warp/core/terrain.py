"""Static meshes of the curved terrain (bowls and spheres) for the USD stage; host-side NumPy.

Both are latitude-longitude meshes measured from the sphere's lowest point: a polar angle
``theta`` (0 at the bottom, pi at the top) and an azimuth. A bowl keeps the rings below its cut
height and ends in a ring exactly on the cut, so its rim meets a plane at that height; a sphere
keeps all of them and closes at the top.
"""

from __future__ import annotations

import math

import numpy as np


def _cap(center, radius, theta_max, rings, segments, inward):
    """Spherical cap from the bottom pole up to polar angle ``theta_max`` (pi: the whole sphere).

    Returns ``(points (V, 3), counts (F,), indices)``: triangles at the poles, quads elsewhere,
    wound so that the face normal points into the sphere when ``inward`` (the side a bowl's
    particles touch) and out of it otherwise.
    """
    center = np.asarray(center, dtype=np.float64)
    closed = theta_max >= math.pi - 1e-12
    n_rings = rings - 1 if closed else rings  # a closed sphere ends in a top pole, not a ring
    thetas = np.linspace(0.0, theta_max, rings + 1)[1 : n_rings + 1]
    phis = np.linspace(0.0, 2.0 * math.pi, segments, endpoint=False)
    st, ct = np.sin(thetas)[:, None], np.cos(thetas)[:, None]
    ring_pts = np.stack(
        [st * np.cos(phis), -ct * np.ones_like(phis), st * np.sin(phis)], axis=-1
    ).reshape(-1, 3)
    pts = [center + radius * np.array([[0.0, -1.0, 0.0]]), center + radius * ring_pts]
    if closed:
        pts.append(center + radius * np.array([[0.0, 1.0, 0.0]]))
    points = np.concatenate(pts)

    def ring(k, j):  # vertex index of ring k (0-based), segment j
        return 1 + k * segments + (j % segments)

    counts, indices = [], []
    # Increasing azimuth (x towards z) seen from below is clockwise, so (pole, j, j+1) faces
    # down and out of the sphere at the bottom; reversed it faces in.
    for j in range(segments):
        counts.append(3)
        indices += [0, ring(0, j), ring(0, j + 1)]
    for k in range(n_rings - 1):
        for j in range(segments):
            counts.append(4)
            indices += [ring(k, j), ring(k + 1, j), ring(k + 1, j + 1), ring(k, j + 1)]
    if closed:
        top = len(points) - 1
        for j in range(segments):
            counts.append(3)
            indices += [top, ring(n_rings - 1, j + 1), ring(n_rings - 1, j)]
    counts = np.array(counts, dtype=np.int64)
    indices = np.array(indices, dtype=np.int64)
    if inward:
        # Reverse every face's winding.
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        indices = np.concatenate([indices[s : s + c][::-1] for s, c in zip(starts, counts)])
    return points, counts, indices


def bowl_mesh(center, radius, cut_height, rings=16, segments=48):
    """The part of a sphere's surface below ``cut_height`` (``inf``: all of it), normals inward.

    Returns ``(points (V, 3), counts (F,), indices)``.
    """
    cy = float(np.asarray(center, dtype=np.float64)[1])
    # The cut plane y = cy - R cos(theta_max).
    c = (cy - float(cut_height)) / float(radius) if math.isfinite(cut_height) else -1.0
    theta_max = math.acos(min(max(c, -1.0), 1.0))
    return _cap(center, radius, theta_max, rings, segments, inward=True)


def sphere_mesh(center, radius, rings=16, segments=32):
    """A closed sphere, normals outward. Returns ``(points (V, 3), counts (F,), indices)``."""
    return _cap(center, radius, math.pi, rings, segments, inward=False)

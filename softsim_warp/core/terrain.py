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


def fan_triangles(counts, indices) -> np.ndarray:
    """Triangles ``(T, 3)`` of a polygon mesh, each face split as a fan from its first vertex.

    The fan keeps every face's winding, so the triangles face the way the polygons do.
    """
    counts = np.asarray(counts, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    per_face = np.maximum(counts - 2, 0)
    face = np.repeat(np.arange(counts.size), per_face)
    # Within each face, triangle k is (v0, v_{k+1}, v_{k+2}).
    k = np.arange(face.size) - (np.cumsum(per_face) - per_face)[face]
    s = starts[face]
    return np.stack([indices[s], indices[s + k + 1], indices[s + k + 2]], axis=1)


def face_normals(points, counts, indices) -> np.ndarray:
    """Unit normal of each polygon by the right-hand rule (its vector area, normalised), ``(F, 3)``."""
    points = np.asarray(points, dtype=np.float64)
    counts = np.asarray(counts, dtype=np.int64)
    tris = fan_triangles(counts, indices)
    area = np.cross(points[tris[:, 1]] - points[tris[:, 0]], points[tris[:, 2]] - points[tris[:, 0]])
    face = np.repeat(np.arange(counts.size), np.maximum(counts - 2, 0))
    n = np.stack([np.bincount(face, area[:, k], minlength=counts.size) for k in range(3)], axis=1)
    return _unit(n)


def vertex_normals(points, triangles) -> np.ndarray:
    """Area-weighted unit vertex normals ``(V, 3)`` from fan ``triangles`` (see :func:`fan_triangles`).

    A vertex no face touches with area (isolated or degenerate) gets +y, so every normal is a unit
    vector as USD asks.
    """
    points = np.asarray(points, dtype=np.float64)
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    area = np.cross(points[b] - points[a], points[c] - points[a])
    v = points.shape[0]
    n = np.zeros((v, 3))
    for k in range(3):
        n[:, k] = (
            np.bincount(a, area[:, k], minlength=v) + np.bincount(b, area[:, k], minlength=v)
            + np.bincount(c, area[:, k], minlength=v)
        )
    return _unit(n)


def signed_volume(points, triangles) -> float:
    """Volume enclosed by a closed triangle mesh [m^3]; positive when its faces wind outward."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    return float(np.einsum("ij,ij->i", p[t[:, 0]], np.cross(p[t[:, 1]], p[t[:, 2]])).sum() / 6.0)


def _unit(n):
    length = np.linalg.norm(n, axis=1)
    out = np.tile([0.0, 1.0, 0.0], (n.shape[0], 1))
    ok = length > 0
    out[ok] = n[ok] / length[ok, None]
    return out

"""Lattice geometry of a jelly: particle positions, spring stencils and the surface.

Everything here is host-side NumPy, run once when a model is built. Particle ``(i, j, k)`` of an
``nx x ny x nz`` lattice has index ``(i * ny + j) * nz + k`` (the seed's ``i*n^2 + j*n + k``).
"""

from __future__ import annotations

import numpy as np

from ..kernels.lattice import BENDING, SHEAR, SPRING_TYPE_NAMES, STENCILS, STRUCTURAL  # noqa: F401 - re-exported


def lattice_index(i, j, k, shape):
    """Flat particle index of lattice coordinate ``(i, j, k)``."""
    nx, ny, nz = shape
    return (np.asarray(i) * ny + np.asarray(j)) * nz + np.asarray(k)


def lattice_points(shape, size):
    """Rest positions of an ``nx x ny x nz`` lattice spanning ``size`` and centred on the origin.

    Args:
        shape: particles per axis ``(nx, ny, nz)``, each >= 1.
        size: edge lengths ``(sx, sy, sz)`` [m]; an axis with one particle has no extent.

    Returns:
        ``(nx*ny*nz, 3)`` float64 positions [m].
    """
    axes = []
    for n, s in zip(shape, size):
        axes.append(np.linspace(-0.5 * s, 0.5 * s, n) if n > 1 else np.zeros(1))
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    return grid.reshape(-1, 3)


def lattice_springs(shape):
    """Spring pairs of a lattice, each pair once, grouped by type.

    Returns:
        ``(pairs, types)``: ``(S, 2)`` int32 particle indices and ``(S,)`` int32 spring types
        (``STRUCTURAL``, ``SHEAR``, ``BENDING``), in type order.
    """
    shape = tuple(int(n) for n in shape)
    i, j, k = np.meshgrid(*(np.arange(n) for n in shape), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    pairs, types = [], []
    for spring_type, stencil in STENCILS.items():
        for di, dj, dk in stencil:
            i2, j2, k2 = i + di, j + dj, k + dk
            ok = (i2 >= 0) & (i2 < shape[0]) & (j2 >= 0) & (j2 < shape[1]) & (k2 >= 0) & (k2 < shape[2])
            a = lattice_index(i[ok], j[ok], k[ok], shape)
            b = lattice_index(i2[ok], j2[ok], k2[ok], shape)
            pairs.append(np.stack([a, b], axis=1))
            types.append(np.full(a.shape[0], spring_type))
    return np.concatenate(pairs).astype(np.int32), np.concatenate(types).astype(np.int32)


def spring_counts(shape):
    """Number of springs of each type, ``{name: count}``, without building the pair list."""
    counts = {}
    for spring_type, stencil in STENCILS.items():
        total = 0
        for off in stencil:
            total += int(np.prod([max(n - abs(o), 0) for n, o in zip(shape, off)]))
        counts[SPRING_TYPE_NAMES[spring_type]] = total
    return counts


def surface_quads(shape):
    """Boundary faces of the lattice as quads of particle indices, wound outward.

    Returns:
        ``(Q, 4)`` int32 particle indices. Quads on a flat axis (one particle thick) appear once per side.
    """
    shape = tuple(int(n) for n in shape)
    quads = []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        nu, nv = shape[u], shape[v]
        if nu < 2 or nv < 2:
            continue
        a, b = np.meshgrid(np.arange(nu - 1), np.arange(nv - 1), indexing="ij")
        a, b = a.ravel(), b.ravel()
        for side in (0, shape[axis] - 1):
            corners = []
            for da, db in ((0, 0), (1, 0), (1, 1), (0, 1)):
                c = [None, None, None]
                c[axis] = np.full_like(a, side)
                c[u] = a + da
                c[v] = b + db
                corners.append(lattice_index(*c, shape))
            q = np.stack(corners, axis=1)
            # (u, v, axis) is a right-handed cycle when v == (u + 1) % 3; flip so normals point out.
            outward_positive = side == shape[axis] - 1
            right_handed = v == (u + 1) % 3
            if outward_positive != right_handed:
                q = q[:, ::-1]
            quads.append(q)
            if shape[axis] == 1:
                quads.append(q[:, ::-1])
                break
    if not quads:
        return np.zeros((0, 4), dtype=np.int32)
    return np.concatenate(quads).astype(np.int32)

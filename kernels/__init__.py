"""Warp kernels of softsim-warp, installed as ``softsim_warp.kernels``.

Each topic module builds its kernels for one scalar type (``wp.float32`` or ``wp.float64``) from a
single source, so every kernel exists in both precisions. :func:`get_kernels` returns the set for a
precision, built once and cached.
"""

from __future__ import annotations

import functools
import types

import warp as wp

from . import contact, implicit, integration, lattice, mesh, metrics, multigrid, particle_contact, pins, springs

wp.set_module_options({"enable_backward": False})


@functools.lru_cache(maxsize=None)
def get_kernels(scalar) -> types.SimpleNamespace:
    """All kernels and functions for ``scalar`` (``wp.float32`` or ``wp.float64``), as one namespace."""
    ns = types.SimpleNamespace(scalar=scalar, vec3=wp.types.vector(3, scalar))
    for topic in (springs, integration, contact, metrics, implicit, lattice, pins, mesh, multigrid, particle_contact):
        for name, obj in topic.build(scalar).items():
            setattr(ns, name, obj)
    return ns

"""Types for kernels written once for both precisions.

A kernel or ``wp.func`` annotates its floating-point arguments with :data:`Float` (a scalar),
:data:`vec3` or :data:`mat33`, or arrays of them, and makes its constants from an argument's type
(``type(rest)(0.5)``, ``type(x)(type(rest)(0.0))``). :func:`both_precisions` then declares its
float32 and float64 overloads when the module is imported, so a module always compiles the same
set of kernels, whatever a process launches first, and no kernel is added to a module that is
already loaded (which would recompile it, and cannot happen inside a graph capture).
"""

from __future__ import annotations

import warp as wp

Float = wp.Float
"""A floating-point scalar: float32 or float64, fixed per overload."""
vec3 = wp.types.vector(3, Float)
mat33 = wp.types.matrix((3, 3), Float)

PRECISIONS = (wp.float32, wp.float64)


def concrete(t, scalar):
    """``t`` with :data:`Float` replaced by ``scalar`` (arrays, vectors and matrices of it too)."""
    if t is Float:
        return scalar
    if wp.types.is_array(t):
        return type(t)(dtype=concrete(t.dtype, scalar), ndim=t.ndim)
    if getattr(t, "_wp_scalar_type_", None) is Float:
        shape = t._shape_
        return wp.types.vector(shape[0], scalar) if len(shape) == 1 else wp.types.matrix(shape, scalar)
    return t


def is_generic(t) -> bool:
    return concrete(t, wp.float32) is not t


def both_precisions(kernel):
    """Declare ``kernel``'s float32 and float64 overloads (a decorator, above ``@wp.kernel``).

    Each overload gets a key of its own (``<kernel>_float32``, ``<kernel>_float64``): Warp 1.19's CPU
    graph capture registers a launched kernel by its key and module, so the two overloads of one
    kernel launched in one captured graph (a float32 run and its float64 reference, measured
    together) would otherwise replay one through the other's function: wrong values or a crash.
    """
    for scalar in PRECISIONS:
        overload = wp.overload(
            kernel, {name: concrete(t, scalar) for name, t in kernel.adj.arg_types.items() if is_generic(t)}
        )
        overload.key = f"{kernel.key}_{scalar.__name__}"
    return kernel

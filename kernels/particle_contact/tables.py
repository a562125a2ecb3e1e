"""Loads and stores of the contact tables, and the records the velocity passes exchange.

The passes wait on a chain of dependent loads (list slot, partner, partner's values), so their hot
loads and stores address the tables from the data pointer with the element size a constant: Warp's
``a[i]`` wraps a negative index and multiplies by the array's run-time 64-bit strides. Every table
here is contiguous (the hook allocates them; core/particle_contact.py), and a 2-d table is
slot-major, ``[slot, particle]``, so a warp reads one slot of its particles in one coalesced load.
The 1-d loads of the particle state are integration's (``load_contiguous`` and its kin).
"""

import warp as wp

from ..precision import Float, vec3

wp.set_module_options({"enable_backward": False})

vec4 = wp.types.vector(4, Float)


# Native snippets cannot be generic in their types, so each is declared for float32 and for float64
# under one name: Warp picks the overload from the argument types.
for _scalar, _ctype in ((wp.float32, "float"), (wp.float64, "double")):
    _vec3 = wp.types.vector(3, _scalar)
    _vec4 = wp.types.vector(4, _scalar)

    @wp.func_native(
        f"typedef {_ctype} T; struct alignas(4 * sizeof(T)) Quad {{ T x, y, z, w; }};\n"
        "const Quad q = reinterpret_cast<const Quad*>(a.data)[i];\n"
        "return wp::vec_t<4, T>(q.x, q.y, q.z, q.w);"
    )
    def load_vec4(a: wp.array(dtype=_vec4), i: int) -> _vec4:
        """``a[i]`` of a contiguous vec4 array as one aligned load (the array starts aligned to its
        element: the hook checks)."""

    @wp.func_native(
        f"typedef {_ctype} T; struct alignas(4 * sizeof(T)) Quad {{ T x, y, z, w; }};\n"
        "Quad q; q.x = value[0]; q.y = value[1]; q.z = value[2]; q.w = value[3];\n"
        "reinterpret_cast<Quad*>(a.data)[i] = q;"
    )
    def store_vec4(a: wp.array(dtype=_vec4), i: int, value: _vec4):
        """``a[i] = value`` of a contiguous vec4 array as one aligned store."""

    @wp.func_native(f"(({_ctype}*)a.data)[s * a.shape[1] + i] = value;")
    def set_scalar_entry(a: wp.array2d(dtype=_scalar), s: int, i: int, value: _scalar):
        """``a[s, i] = value`` of a contiguous scalar table."""

    @wp.func_native(
        f"const {_ctype}* t = (const {_ctype}*)a.data + 3 * (s * a.shape[1] + i);\n"
        f"return wp::vec_t<3, {_ctype}>(t[0], t[1], t[2]);"
    )
    def vec3_entry(a: wp.array2d(dtype=_vec3), s: int, i: int) -> _vec3:
        """``a[s, i]`` of a contiguous vec3 table."""

    @wp.func_native(
        f"{_ctype}* t = ({_ctype}*)a.data + 3 * (s * a.shape[1] + i);\n"
        "t[0] = value[0]; t[1] = value[1]; t[2] = value[2];"
    )
    def set_vec3_entry(a: wp.array2d(dtype=_vec3), s: int, i: int, value: _vec3):
        """``a[s, i] = value`` of a contiguous vec3 table."""


del _scalar, _ctype, _vec3, _vec4


@wp.func_native("return ((const int*)a.data)[s * a.shape[1] + i];")
def int_entry(a: wp.array2d(dtype=wp.int32), s: int, i: int) -> int:
    """``a[s, i]`` of a contiguous int32 table from its data pointer."""


@wp.func_native("((int*)a.data)[s * a.shape[1] + i] = value;")
def set_int_entry(a: wp.array2d(dtype=wp.int32), s: int, i: int, value: int):
    """``a[s, i] = value`` of a contiguous int32 table."""


@wp.func
def record(v: vec3, w: Float):
    """(v, w) as one vec4: an entry of the passes' records (a velocity with a count or an inverse
    mass), or a contact sphere (a position with its contact radius)."""
    return wp.vector(v[0], v[1], v[2], w)


@wp.func
def record_vector(r: vec4):
    """The vector of a record entry: its first three components (a velocity, a position)."""
    return wp.vector(r[0], r[1], r[2])


@wp.func
def split_inv_mass(current: vec4, initial: vec4):
    """A particle's split inverse mass from its two record entries (find_particle_contacts): its
    number of contacts (``current[3]``) times its inverse mass (``initial[3]``)."""
    return current[3] * initial[3]

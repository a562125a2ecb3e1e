"""Scene files: TOML loading, ``--set`` overrides, validation against a schema, built-in scenes.

A scene is validated as a whole after overrides are applied, so a value given on the command line
is checked exactly like one in the file. Every problem is reported as a :class:`SceneError` that
names the file, the dotted key, what is allowed and the value given.
"""

from __future__ import annotations

import codecs
import copy
import difflib
import json
import math
import os
import re
import sys
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from ..core import methods
from ..core.errors import COMMAND_LINE, SceneError
from ..core.mesh_assets import UNITS, UP_AXES, meters_per_unit
from ..core.model import jelly_points
from ..core.pins import FACES, INTERPOLATIONS, select_particles
from .checks import check_scene
from .mesh_scene import resolve_meshes

INTEGRATORS = methods.NAMES  # the public name (softsim_warp.INTEGRATORS)
PRECISIONS = ("float32", "float64")

# Arrays and tables nested deeper than this are refused before anything recursive sees them (the
# TOML parser, copying, validation and the error message all recurse; a scene needs 4 levels).
MAX_NESTING = 100
# Integers must fit in a signed 64-bit integer (counts and frame numbers are sized by it).
INT_MAX = 2**63 - 1
# Upper bounds of the iteration counts (each runs every step): far above what converges (contact:
# 1-4 Jacobi passes; Newton: 1-3 solves; CG: 200 by default, 2000 in the hardest tests) and low
# enough that a mistyped count is refused instead of making every step take hours.
MAX_CONTACT_ITERATIONS = 100
MAX_NEWTON_ITERATIONS = 100
MAX_CG_ITERATIONS = 10_000
# A scene file is a few kilobytes of settings; a larger one is a mistake (and would take long to parse).
MAX_SCENE_BYTES = 16 * 2**20


# ---------------------------------------------------------------------------------------------
# Values shown in error messages: bounded in depth, length and digits, so that formatting them
# (which recurses) cannot fail whatever the value is, a cyclic Python structure included.


class _Shown:
    """A stand-in that prints as the given text (``errors.format_value`` uses ``str`` for it)."""

    def __init__(self, text):
        self.text = text

    def __str__(self):
        return self.text

    __repr__ = __str__


def _safe_str(value) -> str:
    try:
        return str(value)
    except ValueError:  # an int beyond sys.get_int_max_str_digits()
        if isinstance(value, int):
            return f"<integer of {value.bit_length()} bits>"
        return f"<{type(value).__name__}>"
    except Exception:  # noqa: BLE001 - an object of the Python API whose __str__ fails
        return f"<{type(value).__name__}>"


_SHOW_DEPTH = 64
_SHOW_ITEMS = 100
_SHOW_NODES = 500


def shown(value):
    """``value`` made safe to format: nesting cut at 64 levels, containers at 100 items, 500 nodes in all.

    The message is cut to 200 characters anyway, so ordinary values print exactly as before.
    """
    budget = [_SHOW_NODES]

    def walk(v, depth):
        budget[0] -= 1
        if budget[0] < 0 or depth > _SHOW_DEPTH:
            return _Shown("...")
        if isinstance(v, (str, bool, float)) or v is None:
            return v
        if isinstance(v, int):
            text = _safe_str(v)
            return v if text[:1] != "<" else _Shown(text)
        if isinstance(v, (list, tuple)):
            items = [walk(x, depth + 1) for x, _ in zip(v, range(_SHOW_ITEMS))]
            if len(v) > _SHOW_ITEMS:
                items.append(_Shown("..."))
            return items if isinstance(v, list) else tuple(items)
        if isinstance(v, dict):
            out = {}
            for i, (k, x) in enumerate(v.items()):
                if i >= _SHOW_ITEMS:
                    out[_Shown("...")] = _Shown("...")
                    break
                out[k if isinstance(k, str) else _Shown(_safe_str(k))] = walk(x, depth + 1)
            return out
        return _Shown(_safe_str(v))

    return walk(value, 0)


def _fail(source, key, message, *value):
    """Raise the one-line :class:`SceneError`, with the value made safe to print."""
    raise SceneError(source, key, message, *(shown(v) for v in value))


# ---------------------------------------------------------------------------------------------
# Schema: each field knows how to check and normalise one value.


class Field:
    def __init__(self, default=None, required=False, doc=""):
        self.default = default
        self.required = required
        self.doc = doc

    def check(self, value, key, ctx):  # pragma: no cover - overridden
        raise NotImplementedError


def _is_number(value):
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _finite(value) -> bool:
    """``math.isfinite`` for a number; an integer too large for a float is not finite."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


class Float(Field):
    def __init__(self, default=None, lo=None, hi=None, lo_open=False, hi_open=False, auto=False, **kw):
        super().__init__(default, **kw)
        self.lo, self.hi, self.lo_open, self.hi_open = lo, hi, lo_open, hi_open
        self.auto = auto  # the string "auto" is also accepted, and kept for validate() to resolve

    def allowed(self):
        parts = []
        if self.lo is not None:
            parts.append(f"{'>' if self.lo_open else '>='} {self.lo:g}")
        if self.hi is not None:
            parts.append(f"{'<' if self.hi_open else '<='} {self.hi:g}")
        return "a finite number" + (" " + " and ".join(parts) if parts else "")

    def check(self, value, key, ctx):
        if self.auto and value == "auto":
            return value
        if not _is_number(value) or not _finite(value):
            ctx.fail(key, f"must be {self.allowed()}", value)
        v = float(value)
        if self.lo is not None and (v < self.lo or (self.lo_open and v == self.lo)):
            ctx.fail(key, f"must be {self.allowed()}", value)
        if self.hi is not None and (v > self.hi or (self.hi_open and v == self.hi)):
            ctx.fail(key, f"must be {self.allowed()}", value)
        return v


class Int(Field):
    """An integer, at least ``lo``; ``hi``: an upper bound (iteration counts: each has one, so a
    typo like 1e9 is refused rather than run for ever)."""

    def __init__(self, default=None, lo=None, hi=None, **kw):
        super().__init__(default, **kw)
        self.lo = lo
        self.hi = hi

    def check(self, value, key, ctx):
        # 3.0 reads as 3; a float beyond 2^53 is not an exact integer and stays a float (rejected).
        if isinstance(value, float) and value.is_integer() and abs(value) <= 2.0**53:
            value = int(value)
        what = "must be an integer" + (f" >= {self.lo}" if self.lo is not None else "")
        if not isinstance(value, int) or isinstance(value, bool) or (self.lo is not None and value < self.lo):
            ctx.fail(key, what, value)
        if self.hi is not None and value > self.hi:
            ctx.fail(key, f"{what} and <= {self.hi:,}", value)
        if abs(value) > INT_MAX:
            ctx.fail(key, f"{what} and below 2^63", value)
        return int(value)


class Choice(Field):
    def __init__(self, choices, default=None, **kw):
        super().__init__(default, **kw)
        self.choices = tuple(choices)

    def check(self, value, key, ctx):
        if not isinstance(value, str) or value not in self.choices:
            ctx.fail(key, "must be one of " + ", ".join(self.choices), value)
        return value


class Bool(Field):
    """true or false; with ``auto``, also the string "auto"."""

    def __init__(self, default=None, auto=False, **kw):
        super().__init__(default, **kw)
        self.auto = auto

    def check(self, value, key, ctx):
        if isinstance(value, bool) or (self.auto and value == "auto"):
            return value
        ctx.fail(key, 'must be "auto", true or false' if self.auto else "must be true or false", value)


class Text(Field):
    def check(self, value, key, ctx):
        if not isinstance(value, str):
            ctx.fail(key, "must be a string", value)
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:  # a lone surrogate: undecodable bytes of a command-line argument
            ctx.fail(key, "must be valid Unicode text (it holds bytes that are not UTF-8)", value)
        return value


class Units(Field):
    """A mesh file's length unit: a name in ``mesh_assets.UNITS`` or a finite number of metres per unit > 0."""

    def check(self, value, key, ctx):
        try:
            meters_per_unit(value, ctx.source, key)
        except SceneError as e:
            ctx.fail(key, e.message, value)
        return value if isinstance(value, str) else float(value)


class Vec3(Field):
    def __init__(self, default=None, nonzero=False, lo=None, lo_open=False, scalar_ok=False, **kw):
        super().__init__(default, **kw)
        self.nonzero, self.lo, self.lo_open, self.scalar_ok = nonzero, lo, lo_open, scalar_ok

    def check(self, value, key, ctx):
        if self.scalar_ok and _is_number(value):
            value = [value] * 3
        what = "a list of 3 finite numbers" + (" or one number" if self.scalar_ok else "")
        if not isinstance(value, list) or len(value) != 3 or not all(_is_number(c) for c in value):
            ctx.fail(key, f"must be {what}", value)
        if not all(_finite(c) for c in value):
            ctx.fail(key, f"must be {what}", value)
        if self.lo is not None and any(c < self.lo or (self.lo_open and c == self.lo) for c in value):
            ctx.fail(key, f"components must be {'>' if self.lo_open else '>='} {self.lo:g}", value)
        if self.nonzero and all(c == 0 for c in value):
            ctx.fail(key, "must not be the zero vector", value)
        return [float(c) for c in value]


class Int3(Field):
    def check(self, value, key, ctx):
        given = value
        if isinstance(value, int) and not isinstance(value, bool):
            value = [value] * 3
        if (
            not isinstance(value, list)
            or len(value) != 3
            or not all(isinstance(c, int) and not isinstance(c, bool) for c in value)
            or min(value) < 1
        ):
            ctx.fail(key, "must be an integer >= 1 or a list of 3 such integers", given)
        if max(value) > INT_MAX:
            ctx.fail(key, "must be an integer >= 1 or a list of 3 such integers, each below 2^63", given)
        return list(value)


class Table(Field):
    def __init__(self, fields, optional=False, **kw):
        super().__init__(None, **kw)
        self.fields = fields
        self.optional = optional

    def check(self, value, key, ctx):
        if not isinstance(value, dict):
            ctx.fail(key, "must be a table", value)
        out = {}
        for name in value:
            if name not in self.fields:
                # Keys of an in-memory scene need not be strings; only strings can be near a field name.
                near = difflib.get_close_matches(name, list(self.fields), n=1) if isinstance(name, str) else []
                hint = f"; did you mean '{near[0]}'?" if near else f"; allowed: {', '.join(self.fields)}"
                ctx.fail(_join(key, name), "unknown key" + hint, value[name])
        for name, spec in self.fields.items():
            sub = _join(key, name)
            if name in value:
                out[name] = spec.check(value[name], sub, ctx)
            elif isinstance(spec, Table) and not spec.optional:
                out[name] = spec.check({}, sub, ctx)
            elif spec.required:
                ctx.fail(sub, "is required")
            elif spec.default is not None:
                out[name] = copy.deepcopy(spec.default)
        return out


class IntList(Field):
    def check(self, value, key, ctx):
        if (not isinstance(value, list) or not value
                or not all(isinstance(c, int) and not isinstance(c, bool) and 0 <= c <= INT_MAX for c in value)):
            ctx.fail(key, "must be a non-empty list of integers >= 0", value)
        return list(value)


class TableList(Field):
    def __init__(self, item: Table, min_len=0, **kw):
        super().__init__(None, **kw)
        self.item = item
        self.min_len = min_len

    def check(self, value, key, ctx):
        if isinstance(value, dict):  # a single [table] where [[table]] was meant
            value = [value]
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            ctx.fail(key, "must be an array of tables ([[" + key + "]])", value)
        if len(value) < self.min_len:
            ctx.fail(key, f"needs at least {self.min_len} entr{'y' if self.min_len == 1 else 'ies'}", len(value))
        return [self.item.check(v, f"{key}.{i}", ctx) for i, v in enumerate(value)]


_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")
_KEY_PART_CHARS = 64


def key_part(name) -> str:
    """One part of a dotted key as TOML writes it: bare if it can be, else quoted.

    Inside quotes ':' is written as the TOML escape \\u003a, so that the ': ' separators of an
    error line stay unambiguous whatever a misspelt key contains. A part longer than 64 characters
    is cut, ending in "..." (so quoted).
    """
    name = name if isinstance(name, str) else _safe_str(name)
    if len(name) > _KEY_PART_CHARS:  # a key of a megabyte makes a line nobody reads
        name = name[: _KEY_PART_CHARS - 3] + "..."
    if _BARE_KEY.fullmatch(name):
        return name
    return '"' + json.dumps(name)[1:-1].replace(":", "\\u003a") + '"'


def _join(key, name):
    return f"{key}.{key_part(name)}" if key else key_part(name)


SPRING = Table(
    {
        "ks": Float(lo=0, required=True, doc="spring stiffness [N/m]"),
        "kd": Float(0.0, lo=0, doc="damper coefficient along the spring [N s/m]"),
    },
    optional=True,
)

MESH_TRANSFORM = Table(
    {
        "translate": Vec3([0.0, 0.0, 0.0], doc="[m]"),
        "rotation": Table({"axis": Vec3([0.0, 1.0, 0.0], nonzero=True), "degrees": Float(0.0)}),
        "scale": Vec3([1.0, 1.0, 1.0], lo=0, lo_open=True, scalar_ok=True, doc="per-axis factor, applied first"),
    },
    optional=True,
)

# An OBJ, STL or PLY file's axes and units (a USD file states its own upAxis and metersPerUnit).
UP_AXIS = Choice(UP_AXES, doc="an OBJ/STL/PLY file's up axis (default Y); a Z-up asset is stood upright")
UNITS_KEY = Units(doc=f"an OBJ/STL/PLY file's unit: {', '.join(UNITS)} or metres per unit (default m)")

# A prescribed motion (core/pins.py, kernels/pins.py): a pin's keys, and a terrain entry's ``motion``.
MOTION_FIELDS = {
    "velocity": Vec3([0.0, 0.0, 0.0], doc="[m/s]"),
    "spin": Table(
        {
            "axis": Vec3([0.0, 1.0, 0.0], nonzero=True),
            "degrees_per_second": Float(0.0),
            "center": Vec3(doc="[m]; default a pin's particles' mean start position, a terrain entry's point or center"),
        },
        optional=True,
    ),
    "keyframes": TableList(
        Table({"time": Float(required=True, doc="[s]"), "offset": Vec3(required=True, doc="[m]")})
    ),
    "interpolation": Choice(INTERPOLATIONS, "linear", doc="between keyframes: linear or smooth"),
}
# Terrain that moves: the pin's motion keys in one table (core/contact.py TerrainMotion).
MOTION = Table(MOTION_FIELDS, optional=True, doc="the entry moves as a pin does: velocity, spin, keyframes")

SCHEMA = Table(
    {
        "name": Text(doc="scene name"),
        "description": Text("", doc="one line shown by `softsim scenes`"),
        "simulation": Table(
            {
                "integrator": Choice(methods.NAMES, methods.DEFAULT.name),
                "dt": Float(1.0e-3, lo=0, lo_open=True, auto=True,
                            doc='step size [s]; "auto": the largest the stability prediction allows (io/stable_step.py)'),
                "duration": Float(lo=0, lo_open=True, doc="simulated time [s]"),
                "frames": Int(lo=1, doc="output frames after the first"),
                "fps": Float(60.0, lo=0, lo_open=True, doc="output frames per second"),
                "gravity": Vec3([0.0, -9.8, 0.0], doc="[m/s^2]"),
                "precision": Choice(PRECISIONS, "float32"),
                "contact_epsilon": Float(
                    0.01, lo=0, doc="layer within which surfaces are tested [m]; a particle touches within 0.1 % of it"
                ),
                "contact_velocity_epsilon": Float(0.01, lo=0, doc="resting-contact speed tolerance [m/s]"),
                "restitution_threshold_steps": Float(
                    1.0, lo=0, doc="approaches slower than this many steps of pressing impulse are inelastic [1]"
                ),
                "max_speed": Float(lo=0, lo_open=True, doc="speed treated as an explosion [m/s]"),
                # Contact between jellies (core/particle_contact.py, docs/CONTACT.md).
                "jelly_contact": Bool("auto", auto=True, doc='"auto": on with two or more jellies'),
                "jelly_contact_thickness": Float(
                    lo=0, lo_open=True, doc="distance at which two particles touch [m]; absent: the lattice spacing"
                ),
                "jelly_contact_friction": Float(0.5, lo=0, doc="Coulomb coefficient between jellies [1]"),
                "jelly_contact_restitution": Float(0.0, lo=0, hi=1, doc="restitution between jellies [1]"),
                "jelly_contact_iterations": Int(
                    1, lo=1, hi=MAX_CONTACT_ITERATIONS, doc="Jacobi iterations of the contact impulses per step"
                ),
            }
        ),
        "jelly": TableList(
            Table(
                {
                    "resolution": Int3(doc="particles per axis; a mesh jelly: cells along its longest side"),
                    "size": Vec3(lo=0, lo_open=True, scalar_ok=True, doc="edge lengths [m]; a mesh jelly: its longest side"),
                    "mesh": Text(doc="a mesh file (USD, OBJ, STL, PLY) enclosing a volume, voxelised into the jelly, relative to the scene file"),
                    "mesh_prim": Text(doc="prim path in a USD file: a Mesh, or every Mesh under it (default: every Mesh under the default prim)"),
                    "up_axis": UP_AXIS,
                    "units": UNITS_KEY,
                    "spacing": Float(lo=0, lo_open=True, doc="a mesh jelly's largest lattice spacing [m] (instead of resolution)"),
                    "center": Vec3([0.0, 0.0, 0.0], doc="[m]"),
                    "rotation": Table(
                        {
                            "axis": Vec3([0.0, 1.0, 0.0], nonzero=True),
                            "degrees": Float(0.0),
                        }
                    ),
                    "velocity": Vec3([0.0, 0.0, 0.0], doc="[m/s]"),
                    "angular_velocity": Vec3([0.0, 0.0, 0.0], doc="about the centre [rad/s]"),
                    "initial_scale": Vec3(
                        scalar_ok=True,
                        doc="per-axis scale of the lattice at the start (rest lengths unscaled): "
                        "> 1 stretched, < 1 crushed, negative mirrored; nonzero",
                    ),
                    "particle_mass": Float(lo=0, lo_open=True, doc="[kg]"),
                    "total_mass": Float(lo=0, lo_open=True, doc="[kg]"),
                    "springs": Table(
                        {"structural": SPRING, "shear": SPRING, "bending": SPRING},
                    ),
                    "self_contact": Bool(False, doc="the jelly collides with itself"),
                }
            ),
            min_len=1,
            required=True,
        ),
        # Settings of the implicit integrator, in the table named after it (make_integrator's
        # options); absent keys take ImplicitIntegrator's defaults.
        methods.IMPLICIT.name: Table(
            {
                "newton_iterations": Int(lo=1, hi=MAX_NEWTON_ITERATIONS, doc="linear solves per step (default 1)"),
                "cg_tolerance": Float(lo=0, lo_open=True, hi=1, hi_open=True, doc="CG stops at |r| <= tol |b| (1e-4)"),
                "cg_max_iterations": Int(lo=1, hi=MAX_CG_ITERATIONS, doc="CG iteration cap per solve (default 200)"),
                "linearization": Choice(("predictor", "baraff_witkin"), doc="where forces are linearised (predictor)"),
                "preconditioner": Choice(
                    ("auto", "multigrid", "jacobi"),
                    doc="CG preconditioner: multigrid (one lattice jelly), jacobi (3x3 blocks) or auto",
                ),
            },
            optional=True,
        ),
        "plane": TableList(
            Table(
                {
                    "point": Vec3([0.0, 0.0, 0.0], doc="a point on the plane [m]"),
                    "normal": Vec3([0.0, 1.0, 0.0], nonzero=True, doc="normalised on load"),
                    "restitution": Float(0.5, lo=0, hi=1),
                    "friction": Float(0.3, lo=0),
                    "hole": Table(
                        {
                            "center": Vec3([0.0, 0.0, 0.0]),
                            "radius": Float(lo=0, lo_open=True, required=True),
                        },
                        optional=True,
                    ),
                    "size": Float(20.0, lo=0, lo_open=True, doc="edge of the drawn square [m]"),
                    "motion": MOTION,
                }
            )
        ),
        # Curved terrain (see model.ModelBuilder.add_bowl / add_sphere).
        "bowl": TableList(
            Table(
                {
                    "center": Vec3(required=True, doc="sphere centre [m]"),
                    "radius": Float(lo=0, lo_open=True, required=True, doc="sphere radius [m]"),
                    "cut_height": Float(doc="the bowl exists where y < cut_height [m]; absent: the whole sphere"),
                    "restitution": Float(0.5, lo=0, hi=1),
                    "friction": Float(0.3, lo=0),
                    "motion": MOTION,
                }
            )
        ),
        "sphere": TableList(
            Table(
                {
                    "center": Vec3(required=True, doc="[m]"),
                    "radius": Float(lo=0, lo_open=True, required=True, doc="[m]"),
                    "restitution": Float(0.5, lo=0, hi=1),
                    "friction": Float(0.3, lo=0),
                    "motion": MOTION,
                }
            )
        ),
        # Particles held fixed or driven along a path (core/pins.py); exactly one of face, box, particles.
        "pin": TableList(
            Table(
                {
                    "jelly": Int(0, lo=0, doc="the jelly whose particles are pinned"),
                    "face": Choice(FACES, doc="a face of the jelly's lattice, along its own axes"),
                    "box": Table(
                        {"min": Vec3(required=True, doc="[m]"), "max": Vec3(required=True, doc="[m]")},
                        optional=True,
                    ),
                    "particles": IntList(doc="lattice indices (i ny + j) nz + k"),
                    **MOTION_FIELDS,
                }
            )
        ),
        # Triangle-mesh terrain from a file (core/mesh_terrain.py, io/mesh_scene.py).
        "mesh": TableList(
            Table(
                {
                    "path": Text(required=True, doc="USD, OBJ, STL or PLY file, relative to the scene file"),
                    "prim": Text(doc="prim path in a USD file: a Mesh, or every Mesh under it; default: the default prim's Meshes with CollisionAPI, else all of them"),
                    "up_axis": UP_AXIS,
                    "units": UNITS_KEY,
                    "restitution": Float(0.5, lo=0, hi=1),
                    "friction": Float(0.3, lo=0),
                    "thickness": Float(0.1, lo=0, lo_open=True, doc="how far behind its surface a mesh pushes particles out [m]"),
                    "transform": MESH_TRANSFORM,
                    "motion": MOTION,
                    "animated": Bool(False, doc="follow the USD asset's time-sampled points and transforms"),
                }
            )
        ),
    }
)


class _Context:
    def __init__(self, source):
        self.source = source

    def fail(self, key, message, *value):
        _fail(self.source, key, message, *value)


# ---------------------------------------------------------------------------------------------


@dataclass
class Scene:
    """A validated scene: plain dictionaries with every default filled in."""

    data: dict
    source: str = "<scene>"
    name: str = "scene"
    overrides: list = field(default_factory=list)

    @property
    def sim(self) -> dict:
        return self.data["simulation"]

    @property
    def jellies(self) -> list:
        return self.data["jelly"]

    @property
    def planes(self) -> list:
        return self.data.get("plane", [])

    def frame_count(self) -> int:
        """Output frames after frame 0: ``frames`` if given, else ``duration * fps`` rounded up (the
        last frame shorter, ending at the duration: :meth:`end_time`)."""
        sim = self.sim
        if "frames" in sim:
            return sim["frames"]
        return _duration_frames(sim["duration"], sim["fps"], sim["dt"])[0]

    def end_time(self):
        """The run's last time [s] when ``duration`` is not a whole number of frames, else None
        (every frame, the last too, ends a whole 1/fps after the one before)."""
        sim = self.sim
        if "frames" in sim:
            return None
        return _duration_frames(sim["duration"], sim["fps"], sim["dt"])[1]

    def run_seconds(self) -> float:
        """Simulated seconds of the whole run: the duration, or frames / fps."""
        end = self.end_time()
        return end if end is not None else self.frame_count() / self.sim["fps"]


def _duration_frames(duration: float, fps: float, dt: float) -> tuple:
    """(frames after frame 0, end time or None) of a run of ``duration`` seconds.

    A whole number of frames (up to rounding: 0.1 * 30 is 3.0000000000000004) gives that many and
    no end time. Otherwise the frames are rounded up and the last one ends at the duration -- unless
    at this dt the duration's step is no later than the frame before's, which then ends the run."""
    n = duration * fps
    if abs(n - round(n)) <= 1e-9 * max(1.0, abs(n)):
        return max(1, round(n)), None
    frames = max(1, math.ceil(n))
    if frames > 1 and round(duration / dt) <= round((frames - 1) / (fps * dt)):
        return frames - 1, None
    return frames, duration


def builtin_dir():
    return resources.files("softsim_warp.scenes")


def builtin_scenes() -> dict:
    """``{name: description}`` of the scenes shipped with the package."""
    out = {}
    for entry in sorted(builtin_dir().iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".toml"):
            data = tomllib.loads(entry.read_text())
            out[entry.name[:-5]] = data.get("description", "")
    return out


def _scene_file(p: Path, shown_as: str):
    """``(path, read)`` of a scene file on disk, refused unless it is a regular file of sane size."""
    if p.is_dir():
        raise SceneError(shown_as, "scene", "is a directory, not a scene file", shown_as)
    if not p.exists():
        raise SceneError(shown_as, "scene", "no such scene file", shown_as)
    if not p.is_file():
        # A FIFO or device would block or never end when read.
        raise SceneError(
            shown_as, "scene", "is not a regular file (a pipe, socket or device); give a scene file", shown_as
        )
    size = p.stat().st_size
    if size > MAX_SCENE_BYTES:
        raise SceneError(
            shown_as, "scene", f"file too large for a scene: {size} B, at most {MAX_SCENE_BYTES // 2**20} MiB", shown_as
        )
    return p, p.read_bytes


def resolve_scene_path(name_or_path: str):
    """A scene argument is a path if it names an existing file or ends in .toml, else a built-in name.

    Returns:
        ``(path, read)``: the path shown in messages and a callable returning the file's bytes.
    """
    if "\0" in name_or_path:
        shown_as = name_or_path.replace("\0", "\\0")
        raise SceneError(shown_as, "scene", "a file name cannot contain a NUL character", name_or_path)
    p = Path(name_or_path)
    try:
        if p.suffix == ".toml" or p.exists() or "/" in name_or_path:
            if not p.is_absolute():
                try:
                    os.getcwd()
                except FileNotFoundError:
                    raise SceneError(name_or_path, "scene", "is a relative path and the current directory no longer "
                                     "exists (it was deleted); cd to an existing directory or give an absolute path",
                                     name_or_path) from None
            return _scene_file(p, name_or_path)
        entry = builtin_dir() / f"{name_or_path}.toml"
        found = entry.is_file()
    except OSError as e:  # a name too long, a directory without search permission
        raise SceneError(name_or_path, "scene", f"cannot read the file: {e.strerror or e}", name_or_path) from None
    if not found:
        names = list(builtin_scenes())
        near = difflib.get_close_matches(name_or_path, names, n=1)
        hint = f"; did you mean '{near[0]}'?" if near else ""
        raise SceneError(
            name_or_path, "scene", f"no such scene file or built-in scene; built-ins: {', '.join(names)}{hint}", name_or_path
        )
    return Path(f"{name_or_path}.toml"), entry.read_bytes


def read_scene_data(name_or_path: str) -> tuple[Path, str, dict]:
    """Find, read and parse a scene file or built-in scene; returns ``(path, source, data)``."""
    path, read = resolve_scene_path(name_or_path)
    source = str(path)
    try:
        raw = read()
    except OSError as e:
        raise SceneError(source, "scene", f"cannot read the file: {e.strerror}", str(path)) from None
    # A UTF-8 byte-order mark (Windows editors write one) is not part of the TOML text.
    raw = raw.removeprefix(codecs.BOM_UTF8)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        line = raw[: e.start].count(b"\n") + 1
        raise SceneError(source, f"line {line}", "TOML files must be UTF-8 text", raw[e.start : e.start + 4]) from None
    return path, source, parse_toml(text, source)


_TOML_POSITION = re.compile(r"^(.*) \(at (line (\d+), column \d+|end of document)\)$", re.S)

# What can hold '[' or '{' without opening an array or table: strings (four kinds) and comments;
# everything else is skipped. Used only to measure nesting, so it need not validate anything.
_NEST_TOKENS = re.compile(
    '"""(?:[^"\\\\]|\\\\.|"(?!""))*(?:"{3,5}|\\Z)'  # multi-line basic string
    "|'''(?:[^']|'(?!''))*(?:'{3,5}|\\Z)"  # multi-line literal string
    '|"(?:[^"\\\\\\n]|\\\\.)*"?'  # basic string
    "|'[^'\\n]*'?"  # literal string
    "|#[^\\n]*"  # comment
    "|[\\[\\]{}]",
    re.S,
)


def nesting_overflow(text: str, limit: int = MAX_NESTING):
    """Offset in TOML ``text`` of the first '[' or '{' opening level ``limit + 1``; None if none does.

    Python's TOML parser recurses once or more per level and fails with RecursionError some
    hundreds of levels down; this finds such nesting without recursing.
    """
    if text.count("[") + text.count("{") <= limit:
        return None
    depth = 0
    for m in _NEST_TOKENS.finditer(text):
        c = m.group()
        if c == "[" or c == "{":
            depth += 1
            if depth > limit:
                return m.start()
        elif c == "]" or c == "}":
            depth = max(depth - 1, 0)
    return None


def _position(text: str, pos: int) -> tuple[str, str]:
    """``("line L, column C", the text of that line)`` for offset ``pos``."""
    start = text.rfind("\n", 0, pos) + 1
    end = text.find("\n", pos)
    line = text.count("\n", 0, pos) + 1
    return f"line {line}, column {pos - start + 1}", text[start : len(text) if end < 0 else end]


def _long_number(text: str):
    """Offset of the first run of digits longer than Python reads as an integer; None if none."""
    limit = sys.get_int_max_str_digits()
    m = re.search("[0-9][0-9A-Fa-fxob_]{%d,}" % limit, text) if limit else None
    return m.start() if m else None


_TOO_DEEP = f"arrays and inline tables nested deeper than {MAX_NESTING} levels"
_TOO_DEEP_FOR_PARSER = "arrays and inline tables nested too deeply for the TOML parser"


def _too_long_message() -> str:
    return f"number too long: an integer may have at most {sys.get_int_max_str_digits()} digits"


def parse_toml(text: str, source: str) -> dict:
    """Parse TOML; a syntax error names its line and column and shows that line."""
    pos = nesting_overflow(text)
    if pos is not None:
        where, line = _position(text, pos)
        raise SceneError(source, where, _TOO_DEEP, line)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        m = _TOML_POSITION.match(str(e))
        lines = text.splitlines() or [""]
        if m is None:  # a message without a position: name the whole file
            raise SceneError(source, "(file)", f"TOML syntax error: {e}", lines[-1]) from None
        what, where, line = m.group(1), m.group(2), m.group(3)
        shown_line = lines[min(int(line), len(lines)) - 1] if line else lines[-1]
        raise SceneError(source, where, f"TOML syntax error: {what[:1].lower()}{what[1:]}", shown_line) from None
    except RecursionError:  # not expected below MAX_NESTING levels; the parser's own limit
        deepest = max(text.split("\n"), key=lambda s: s.count("[") + s.count("{"))
        raise SceneError(source, "(file)", _TOO_DEEP_FOR_PARSER, deepest) from None
    except ValueError as e:  # an integer literal of more digits than Python converts
        pos = _long_number(text)
        if pos is None:
            raise SceneError(source, "(file)", f"TOML cannot be read: {e}", text.split("\n")[-1]) from None
        where, line = _position(text, pos)
        raise SceneError(source, where, _too_long_message(), line) from None


MAX_KEY_PARTS = 16
_INDEX = re.compile(r"[0-9]+")


def _index(part: str):
    """A list index written in ASCII digits as an int (an absurdly long one as 2^63), else None.

    ``str.isdigit`` is no test: it holds for '²' and for Arabic-Indic digits, which ``int`` then
    reads or refuses.
    """
    if not _INDEX.fullmatch(part):
        return None
    digits = part.lstrip("0") or "0"
    return int(digits) if len(digits) <= 18 else 2**63


def _set_key(parts) -> str:
    return "--set " + ".".join(key_part(p) for p in parts)


def parse_override(item: str, source=COMMAND_LINE):
    """Split ``a.b.0.c=VALUE``; VALUE is read as a TOML value, or as a bare string if it is not one."""
    if not isinstance(item, str):  # the Python API's load_scene(name, overrides)
        raise SceneError(source, "--set", "expected KEY=VALUE text, such as simulation.dt=0.001", shown(item))
    if "=" not in item:
        raise SceneError(source, "--set", "expected KEY=VALUE, such as simulation.dt=0.001", item)
    key, raw = item.split("=", 1)
    key = key.strip()
    parts = key.split(".")
    if not key or any(not part for part in parts):
        raise SceneError(source, "--set", "expected a dotted key such as simulation.dt before '='", item)
    if len(parts) > MAX_KEY_PARTS:
        raise SceneError(source, "--set", f"expected a dotted key of at most {MAX_KEY_PARTS} parts", item)
    if nesting_overflow(raw) is not None:
        raise SceneError(source, _set_key(parts), _TOO_DEEP, raw)
    try:
        doc = tomllib.loads(f"v = {raw}")
    except tomllib.TOMLDecodeError:
        doc = None
    except RecursionError:  # not expected below MAX_NESTING levels
        raise SceneError(source, _set_key(parts), _TOO_DEEP_FOR_PARSER, raw) from None
    except ValueError:  # an integer literal of more digits than Python converts
        raise SceneError(source, _set_key(parts), _too_long_message(), raw) from None
    # One value only: "1\nx = 2" is not the number 1.
    value = doc["v"] if doc is not None and list(doc) == ["v"] else raw.strip()
    try:
        repr(value)  # a hexadecimal integer of thousands of digits is read, but Python cannot print it
    except ValueError:
        raise SceneError(source, _set_key(parts), _too_long_message(), raw) from None
    return key, value


def apply_override(data: dict, key: str, value, source=COMMAND_LINE):
    """Set ``data[a][b][0][c] = value`` for the dotted key ``a.b.0.c``; creates missing tables.

    A list index is ASCII digits. Keys come from ``parse_override``; a key given here directly is
    held to the same rules.
    """
    parts = key.split(".") if isinstance(key, str) else []
    if not parts or any(not part for part in parts) or len(parts) > MAX_KEY_PARTS:
        raise SceneError(
            source, "--set", f"expected a dotted key such as simulation.dt of at most {MAX_KEY_PARTS} parts", shown(key)
        )
    node = data
    for depth, part in enumerate(parts):
        last = depth == len(parts) - 1
        if isinstance(node, list):
            index = _index(part)
            if index is None or index >= len(node):
                n = len(node)
                if depth and all(isinstance(v, dict) for v in node):
                    what = f"the scene has {n} {key_part(parts[depth - 1])} table{'' if n == 1 else 's'}"
                else:
                    what = f"the list has {n} entr{'y' if n == 1 else 'ies'}"
                message = "expected an index (digits 0-9)" if index is None else "index out of range"
                raise SceneError(source, _set_key(parts[: depth + 1]), f"{message}; {what}", part)
            if last:
                node[index] = value
            else:
                node = node[index]
            continue
        if not isinstance(node, dict):
            raise SceneError(
                source, _set_key(parts[: depth + 1]), "cannot set a key inside a value that is not a table", shown(node)
            )
        if last:
            node[part] = value
        else:
            if part not in node:
                # "jelly.0..." on a scene without jellies cannot be created; a new table can.
                if _index(parts[depth + 1]) is not None:
                    raise SceneError(
                        source,
                        _set_key(parts[: depth + 1]),
                        f"index out of range; the scene has no {key_part(part)} tables",
                        parts[depth + 1],
                    )
                node[part] = {}
            node = node[part]


# Keys that replace each other: overriding one drops the other from the file's values.
EXCLUSIVE = {"simulation.duration": "simulation.frames", "simulation.frames": "simulation.duration"}


def apply_overrides(data: dict, items, source=COMMAND_LINE):
    """Apply ``[(dotted_key, value), ...]`` in order; returns the list applied."""
    for key, value in items:
        other = EXCLUSIVE.get(key) if isinstance(key, str) else None
        if other:
            table, _, name = other.rpartition(".")
            node = data.get(table)
            if isinstance(node, dict):
                node.pop(name, None)
        apply_override(data, key, value, source)
    return list(items)


def _unit(v):
    """``v / |v|`` without overflow or underflow: scaled by its largest component first (v != 0)."""
    big = max(abs(c) for c in v)
    v = [c / big for c in v]
    length = math.sqrt(sum(c * c for c in v))
    return [c / length for c in v]


def validate(data: dict, source: str, base=None) -> dict:
    """Check ``data`` against the schema and the whole-scene checks; ``base`` is the directory that
    relative mesh paths start from (default: the scene file's, or the built-in scenes' folder)."""
    ctx = _Context(source)
    out = SCHEMA.check(data, "", ctx)
    resolve_meshes(out, ctx, base)
    sim = out["simulation"]
    if "duration" in sim and "frames" in sim:
        ctx.fail("simulation.frames", "give simulation.duration or simulation.frames, not both", sim["frames"])
    if "duration" not in sim and "frames" not in sim:
        ctx.fail("simulation.duration", "is required (or give simulation.frames)")
    for i, jelly in enumerate(out["jelly"]):
        key = f"jelly.{i}"
        for name in ("resolution", "size"):
            if name not in jelly:
                ctx.fail(f"{key}.{name}", "is required (or give mesh)")
        count = jelly["resolution"][0] * jelly["resolution"][1] * jelly["resolution"][2]
        if count < 2:
            ctx.fail(f"{key}.resolution", "a jelly needs at least 2 particles", jelly["resolution"])
        if "particle_mass" in jelly and "total_mass" in jelly:
            both = {"particle_mass": jelly["particle_mass"], "total_mass": jelly["total_mass"]}
            ctx.fail(f"{key}.particle_mass", "give exactly one of particle_mass and total_mass, not both", both)
        if "particle_mass" not in jelly and "total_mass" not in jelly:
            ctx.fail(f"{key}.particle_mass", "is required (or give total_mass)")
        if "total_mass" in jelly:
            jelly["particle_mass"] = jelly.pop("total_mass") / count
        if "initial_scale" in jelly and any(c == 0.0 for c in jelly["initial_scale"]):
            # A zero axis would put particles on top of each other: springs without a direction.
            ctx.fail(f"{key}.initial_scale", "components must be nonzero (negative mirrors the lattice)",
                     jelly["initial_scale"])
    for plane in out.get("plane", []):
        plane["normal"] = _unit(plane["normal"])
    for jelly in out["jelly"]:
        jelly["rotation"]["axis"] = _unit(jelly["rotation"]["axis"])
    for i, bowl in enumerate(out.get("bowl", [])):
        bottom = bowl["center"][1] - bowl["radius"]
        if "cut_height" in bowl and bowl["cut_height"] <= bottom:
            ctx.fail(f"bowl.{i}.cut_height", f"must be above the bowl's lowest point center.y - radius = {bottom:g}",
                     bowl["cut_height"])
    for i, pin in enumerate(out.get("pin", [])):
        _check_pin(pin, f"pin.{i}", out["jelly"], ctx)
    for kind in ("plane", "bowl", "sphere", "mesh"):
        for i, entry in enumerate(out.get(kind, [])):
            moving = [name for name in ("motion", "animated") if entry.get(name)]
            if "motion" in entry:
                _check_motion(entry["motion"], f"{kind}.{i}.motion", ctx)
            if moving and not methods.method(sim["integrator"]).explicit:
                ctx.fail(f"{kind}.{i}.{moving[0]}", "the implicit integrator does not take moving terrain; "
                         "use an explicit integrator", sim["integrator"])
    # Checks of the scene as a whole (sizes, precision range, a jelly starting inside terrain);
    # see checks.py.

    check_scene(out, ctx)
    from .stable_step import resolve_auto  # noqa: PLC0415 - the stability prediction imports the model

    resolve_auto(out, ctx)
    return out


def _check_pin(pin: dict, key: str, jellies: list, ctx):
    """One pin: its jelly exists, exactly one selection that selects something, increasing key times;
    stores the selected lattice indices as ``pin["indices"]``."""
    if pin["jelly"] >= len(jellies):
        ctx.fail(f"{key}.jelly", f"the scene has jellies 0 to {len(jellies) - 1}", pin["jelly"])
    given = [name for name in ("face", "box", "particles") if name in pin]
    if len(given) != 1:
        ctx.fail(f"{key}.face", "give exactly one of face, box and particles to select the pinned particles",
                 {name: pin[name] for name in given} if given else "none")
    jelly = jellies[pin["jelly"]]
    if "mesh" in jelly:
        ctx.fail(f"{key}.jelly", "pins hold particles of box jellies only; this jelly is a mesh", pin["jelly"])
    shape = jelly["resolution"]
    count = shape[0] * shape[1] * shape[2]
    if "particles" in pin and max(pin["particles"]) >= count:
        ctx.fail(f"{key}.particles", f"indices must be below the jelly's {count} particles", max(pin["particles"]))
    points = jelly_points(shape, jelly["size"], jelly["center"], jelly["rotation"]["axis"],
                          jelly["rotation"]["degrees"], jelly.get("initial_scale"))
    box = (pin["box"]["min"], pin["box"]["max"]) if "box" in pin else None
    pin["indices"] = select_particles(shape, points, pin.get("face"), box, pin.get("particles")).tolist()
    if not pin["indices"]:
        ctx.fail(f"{key}.box", "selects no particle of the jelly at its start", pin["box"])
    _check_motion(pin, key, ctx)


def _check_motion(motion: dict, key: str, ctx):
    """A pin's or a terrain entry's motion keys: the spin axis normalised, key times increasing."""
    if "spin" in motion:
        motion["spin"]["axis"] = _unit(motion["spin"]["axis"])
    times = [k["time"] for k in motion.get("keyframes", [])]
    if any(b <= a for a, b in zip(times, times[1:])):
        ctx.fail(f"{key}.keyframes", "times must be strictly increasing", times)


def load_scene(name_or_path: str, overrides=()) -> Scene:
    """Load a scene file or a built-in scene by name, apply ``--set`` overrides and validate it."""
    path, source, data = read_scene_data(name_or_path)
    applied = apply_overrides(data, [parse_override(item) for item in overrides])
    validated = validate(data, source)
    return Scene(validated, source=source, name=validated.get("name", path.stem), overrides=applied)


def _copy_tree(value, source, path=()):
    """A copy of the dicts and lists in ``value`` (other values shared); nesting beyond MAX_NESTING,
    a cycle included, is a :class:`SceneError` (``copy.deepcopy`` would raise RecursionError)."""
    if isinstance(value, (dict, list)) and len(path) >= MAX_NESTING:
        key = ".".join(key_part(p) for p in path[:8]) + ("..." if len(path) > 8 else "")
        _fail(source, key, f"nested deeper than {MAX_NESTING} levels", value)
    if isinstance(value, dict):
        return {k: _copy_tree(v, source, path + (k,)) for k, v in value.items()}
    if isinstance(value, list):
        return [_copy_tree(v, source, path + (i,)) for i, v in enumerate(value)]
    return value


def scene_from_dict(data: dict, source="<dict>") -> Scene:
    """Validate an in-memory scene (the Python API's way to make one without a file)."""
    validated = validate(_copy_tree(data, source), source)
    return Scene(validated, source=source, name=validated.get("name", "scene"))

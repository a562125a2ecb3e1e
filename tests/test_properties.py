"""Property-based tests (hypothesis).

Scene loader: any mutation of a valid scene (keys deleted, values replaced by anything TOML can
hold: nan, inf, huge, negative, wrong types; unknown keys added, odd Unicode ones (superscript and
non-ASCII digits, combining marks) and, in a Python dict, keys that are not strings; values nested
thousands of levels deep or cyclic; text edits of the file; random ``--set``) either loads or
raises SceneError whose message is one line of the documented form, never another exception.

Spring forces: on random lattices with random states, coincident particles, and coordinates from
1e-6 to 1e6 m, the total internal force is zero to float32 rounding (momentum conservation: each
spring adds f to one particle and -f to the other) and no force is NaN or inf.
"""

import copy
import math
import os
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
import warp as wp
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from softsim_warp import eval_forces
from softsim_warp.io import scene
from softsim_warp.core.errors import SceneError
from softsim_warp.core.model import ModelBuilder

sys.path.insert(0, str(Path(__file__).parent))
import robustness_cases as rc  # noqa: E402

# 50 examples keep the suite fast; SOFTSIM_HYPOTHESIS_EXAMPLES=5000 hunts harder.
SETTINGS = settings(
    max_examples=int(os.environ.get("SOFTSIM_HYPOTHESIS_EXAMPLES", "50")),
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
BASE = tomllib.loads(rc.BASE)

# --- scene loader -----------------------------------------------------------------------------

# Characters that look like digits or separators to one Unicode rule or another: superscripts,
# Arabic-Indic, Devanagari, fullwidth and mathematical digits, roman numerals, fractions,
# combining marks, zero-width and control characters, the key separators of the error line.
ODD_CHARS = "0123456789²³¹٠١٣۴०१০߀０１𝟙Ⅻ½\u0301\u0308\u20dd\u200b\u200d\ufeff\x00\t\n.:=\"'\\ [{"

scalars = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-3, 12),
    st.sampled_from([0, -1, 2**31 - 1, 2**53, 10**12, -(2**63), 10**30, 2**63, 10**400, -(10**400)]),
    # More digits than str() converts; built on draw, since hypothesis cannot print it as a constant.
    st.just(5000).map(lambda n: 10**n),
    st.booleans(),
    st.text(max_size=8),
    st.sampled_from(["symplectic", "rk4", "implicit", "float64", "float32", "nan"]),
)
odd_text = st.text(alphabet=ODD_CHARS, min_size=1, max_size=6)
# Keys of an in-memory scene: any hashable, not only strings.
keys = st.one_of(
    st.text(min_size=1, max_size=8),
    odd_text,
    st.integers(),
    st.sampled_from([None, True, b"dt", ("jelly", 0), frozenset({1})]),
    st.just(5000).map(lambda n: 10**n),
    st.floats(),
)


def _nest(depth, kind, leaf):
    v = leaf
    for i in range(depth):
        v = [v] if kind == "list" or (kind == "mixed" and i % 2) else {"a": v}
    return v


def _cycle(kind):
    v = [] if kind == "list" else {}
    if kind == "list":
        v.append(v)
    else:
        v["a"] = v
    return v


deep_values = st.one_of(
    st.builds(_nest, st.integers(95, 5000), st.sampled_from(["list", "dict", "mixed"]), scalars),
    st.builds(_cycle, st.sampled_from(["list", "dict"])),
)
values = st.recursive(
    scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(keys, inner, max_size=3)),
    max_leaves=8,
)
# Mostly ordinary values, one in ten nested deeper than any parser or copy can recurse.
mutant_values = st.integers(0, 9).flatmap(lambda r: deep_values if r == 0 else values)


def _paths(node, prefix=(), max_depth=8):
    """Every (container path, key) in a parsed TOML tree, down to ``max_depth`` (values may be deep or cyclic)."""
    out = []
    if len(prefix) >= max_depth:
        return out
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for k, v in items:
        out.append((prefix, k))
        out += _paths(v, prefix + (k,), max_depth)
    return out


def _at(node, path):
    for k in path:
        node = node[k]
    return node


def _assert_one_line(err: SceneError):
    line = "error: " + err.line()
    assert "\n" not in line and "\r" not in line
    assert rc.LINE.match(line), line


def _load(data):
    try:
        loaded = scene.scene_from_dict(data, source="mutant.toml")
    except SceneError as e:
        _assert_one_line(e)
        event("refused: " + e.message.split(";")[0][:40])
        return None
    event("loaded")
    return loaded


@SETTINGS
@given(st.data())
def test_mutated_scene_loads_or_gives_one_line(data):
    doc = copy.deepcopy(BASE)
    for _ in range(data.draw(st.integers(1, 4), label="mutations")):
        paths = _paths(doc)
        op = data.draw(st.sampled_from(["delete", "replace", "add"]), label="op")
        if op == "add" or not paths:
            tables = [()] + [p + (k,) for p, k in paths if isinstance(_at(doc, p + (k,)), dict)]
            where = data.draw(st.sampled_from(tables), label="table")
            _at(doc, where)[data.draw(keys, label="key")] = data.draw(mutant_values, label="value")
            continue
        parent, key = data.draw(st.sampled_from(paths), label="path")
        container = _at(doc, parent)
        if op == "delete":
            del container[key]
        else:
            container[key] = data.draw(mutant_values, label="value")
    _load(doc)


# Text edits: any short text, odd Unicode, nesting beyond the limit, integers of thousands of digits.
deep_text = st.builds(
    lambda n, opener: opener * n, st.integers(95, 5000), st.sampled_from(["[", "{a=", "[{a=", "{", "x = ["])
)
inserts = st.one_of(
    st.text(max_size=6),
    odd_text,
    deep_text,
    st.builds(lambda n: "9" * n, st.sampled_from([19, 400, 4301, 6000])),
    st.sampled_from(["1e999", "-inf", "nan", "0x" + "f" * 5000, "[]", "{}"]),
)


@SETTINGS
@given(st.data())
def test_edited_scene_text_loads_or_gives_one_line(data):
    """Character-level edits of the TOML file: deletions, insertions and replacements anywhere."""
    text = rc.BASE
    for _ in range(data.draw(st.integers(1, 3), label="edits")):
        i = data.draw(st.integers(0, len(text)), label="at")
        j = data.draw(st.integers(i, min(len(text), i + 12)), label="to")
        text = text[:i] + data.draw(inserts, label="insert") + text[j:]
    try:
        scene.validate(scene.parse_toml(text, "edited.toml"), "edited.toml")
    except SceneError as e:
        _assert_one_line(e)


known_keys = [".".join(map(str, p + (k,))) for p, k in _paths(BASE)]


def _replace_part(key, i, odd):
    parts = key.split(".")
    parts[i % len(parts)] = odd
    return ".".join(parts)


override_keys = st.one_of(
    st.sampled_from(known_keys),
    st.text(alphabet="abcdefgjklmnoprstuvxyz0123456789._", min_size=0, max_size=20),
    # A known key with one part replaced by odd Unicode (jelly.².size, jelly.٣.size, ...).
    st.builds(_replace_part, st.sampled_from(known_keys), st.integers(0, 5), odd_text),
    st.text(alphabet=ODD_CHARS + "jely.s0", min_size=0, max_size=12),
    st.builds(lambda n: ".".join(["a"] * n), st.integers(10, 200)),
)
override_values = st.one_of(
    st.text(max_size=12),
    odd_text,
    st.builds(lambda n, o: o * n + "1" + "]}"[o == "{a="] * n, st.integers(95, 5000), st.sampled_from(["[", "{a="])),
    deep_text,
    st.sampled_from(["9" * 5000, "9" * 400, "1e999", "-inf", "nan", "1\nx = 2", "0x" + "f" * 5000]),
)


@SETTINGS
@given(st.lists(st.tuples(override_keys, st.sampled_from(["=", "", "=="]), override_values), max_size=3))
def test_random_overrides_load_or_give_one_line(items):
    doc = copy.deepcopy(BASE)
    try:
        for key, sep, raw in items:
            k, v = scene.parse_override(f"{key}{sep}{raw}")
            scene.apply_override(doc, k, v)
        scene.validate(doc, "scene.toml")
    except SceneError as e:
        _assert_one_line(e)


# --- spring forces ----------------------------------------------------------------------------

EPS32 = float(np.finfo(np.float32).eps)
# Where a float32 result falls below the smallest normal number, its error is absolute, not relative:
# up to that number with subnormals flushed to zero (as a device may), 2**-150 without. A spring's force
# takes fewer than 32 float32 operations, so each adds at most 32 TINY32 to what a relative bound allows.
TINY32 = float(np.finfo(np.float32).smallest_normal)
SPRING_OPS = 32


def _reference_spring_forces(q, qd, pairs, rest, ks, kd):
    """Per-spring force on the first particle, float64 NumPy, from the same float32 inputs."""
    d = q[pairs[:, 0]] - q[pairs[:, 1]]
    length = np.linalg.norm(d, axis=1)
    safe = np.where(length > 0, length, 1.0)
    dhat = d / safe[:, None]
    mag = ks * (length - rest) + kd * np.einsum("ij,ij->i", qd[pairs[:, 0]] - qd[pairs[:, 1]], dhat)
    return np.where(length[:, None] > 0, -mag[:, None] * dhat, 0.0)


@SETTINGS
@given(
    res=st.tuples(st.integers(1, 4), st.integers(1, 4), st.integers(1, 4)).filter(lambda r: math.prod(r) >= 2),
    scale=st.sampled_from([1e-6, 1e-3, 1.0, 1e3]),
    offset=st.sampled_from([0.0, 1e6, -1e6]),
    ks=st.lists(st.floats(0.0, 1e4), min_size=3, max_size=3),
    kd=st.lists(st.floats(0.0, 1e2), min_size=3, max_size=3),
    seed=st.integers(0, 2**32 - 1),
    coincide=st.floats(0.0, 0.5),
    deterministic=st.booleans(),
)
def test_spring_forces_conserve_momentum(device, res, scale, offset, ks, kd, seed, coincide, deterministic):
    rng = np.random.default_rng(seed)
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    springs = {name: {"ks": ks[t], "kd": kd[t]} for t, name in enumerate(("structural", "shear", "bending"))}
    b.add_jelly(res, [scale * (n - 1) for n in res], 1.0, springs, center=(offset, offset, -offset))
    model = b.finalize(device, deterministic=deterministic)
    n = model.particle_count
    # State: rest lattice, displaced by up to the spacing, some particles moved onto others.
    q = model.particle_q_host + rng.uniform(-scale, scale, size=(n, 3))
    hit = rng.random(n) < coincide
    q[hit] = q[rng.integers(0, n, size=int(hit.sum()))]
    qd = rng.normal(scale=10.0 * scale, size=(n, 3))
    q32, qd32 = q.astype(np.float32), qd.astype(np.float32)
    f = wp.empty(n, dtype=model.vec3, device=device)
    f.fill_(wp.nan)  # poisoned: every particle must be written
    eval_forces(
        model, wp.array(q32, dtype=model.vec3, device=device), wp.array(qd32, dtype=model.vec3, device=device), f
    )
    f = f.numpy().astype(np.float64)
    assert np.isfinite(f).all()

    pairs = model.spring_indices_host
    if len(pairs) == 0:
        assert (f == 0).all()
        return
    fs = _reference_spring_forces(
        q32.astype(np.float64),
        qd32.astype(np.float64),
        pairs,
        model.spring_rest_length.numpy().astype(np.float64),
        model.spring_stiffness.numpy().astype(np.float64),
        model.spring_damping.numpy().astype(np.float64),
    )
    k_max = np.bincount(pairs.ravel(), minlength=n).max()
    # Exactly, sum_i f_i = sum_s (f_s - f_s) = 0. In float32 each particle's sum of k terms errs by at
    # most (k - 1) eps sum |terms|, and each term by a few eps of |f_s|; every spring is in two particles'
    # sums: |sum_i f_i| <= 2 (k_max + 2) eps sum_s |f_s|, per component, and the underflow of each
    # spring's operations (TINY32) on top. The float64 host sum adds nothing of that order.
    underflow = 2 * SPRING_OPS * TINY32 * len(pairs)
    bound = 2 * (k_max + 2) * EPS32 * np.abs(fs).sum(axis=0) + underflow
    total = f.sum(axis=0)
    assert (np.abs(total) <= bound).all(), (total, bound)
    # And each particle's force is its springs' (a kernel that wrote zeros would pass the sum). In
    # float32 a spring's force errs by a few eps of the terms it subtracts, ks (|d| + rest) and
    # kd |v_rel|, and a particle's sum of k of them by (k - 1) eps of their magnitudes; each of its k
    # springs adds its underflow (TINY32) on top.
    ref = np.zeros((n, 3))
    np.add.at(ref, pairs[:, 0], fs)
    np.add.at(ref, pairs[:, 1], -fs)
    q64, qd64 = q32.astype(np.float64), qd32.astype(np.float64)
    d = np.linalg.norm(q64[pairs[:, 0]] - q64[pairs[:, 1]], axis=1)
    vrel = np.linalg.norm(qd64[pairs[:, 0]] - qd64[pairs[:, 1]], axis=1)
    terms = model.spring_stiffness.numpy() * (d + model.spring_rest_length.numpy()) + model.spring_damping.numpy() * vrel
    scale_i = np.zeros(n)
    np.add.at(scale_i, pairs[:, 0], terms)
    np.add.at(scale_i, pairs[:, 1], terms)
    err = np.abs(f - ref).max(axis=1)
    bound_i = (k_max + 8) * EPS32 * scale_i + k_max * SPRING_OPS * TINY32
    assert (err <= bound_i).all(), (err.max(), scale_i[err.argmax()])

"""Planning a sweep: ``--vary`` axes, the variants they make, and the batches that can share launches.

* **Axes** (:func:`parse_axis`): ``KEY=V1,V2,...`` lists and ``KEY=LO:HI:N[:log]`` ranges, ``*``
  expanded over the scene's tables (:func:`expand_key`).
* **Plan** (:func:`plan_sweep`): their product or a Latin hypercube (``--samples``), times
  ``--integrators`` and ``--dts``. Every variant is a scene dict validated like ``softsim run --set
  KEY=VALUE`` would validate it, before anything runs; a bad value is a one-line error.
* **Batches** (:func:`make_batches`): variants that can share launches -- the same ``[simulation]``
  table, the same integrator, the same lattice shapes and terrain types -- are cut into batches
  whose size follows from the memory each variant needs (:mod:`~softsim_warp.io.resources`). An
  implicit variant is a batch of its own: the implicit solver's iteration counts depend on every
  particle of its model.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import re
from dataclasses import dataclass, field

import numpy as np

from ...core import methods
from ...core.errors import CommandLineError, SceneError, UserError
from .. import scene as scene_mod
from ..checks import TERRAIN_SDF
from ..resources import available_host_bytes, estimate

# Values one axis may have, and variants one sweep may plan: beyond these a typo (1:2:1e9) is more
# likely than a wish.
MAX_AXIS_VALUES = 100_000
MAX_VARIANTS = 1_000_000
# Share of a worker's memory (device memory on CUDA, host memory on the CPU) one batch may take.
MEMORY_SHARE = 0.5
# Worlds in one batch at most (the per-frame host work grows with them).
MAX_BATCH = 4096


# ---------------------------------------------------------------------------------------------
# Axes


def split_values(text: str) -> list[str]:
    """Split ``1,2,[1,0,1]`` on the commas outside brackets and quotes."""
    parts, depth, quote, cur = [], 0, None, []
    for ch in text:
        if quote:
            quote = None if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            parts.append("".join(cur))
            cur = []
            continue
        cur.append(ch)
    parts.append("".join(cur))
    return [p.strip() for p in parts]


_RANGE = re.compile(r"^([^:\[\]{}\"',]+):([^:\[\]{}\"',]+):([^:\[\]{}\"',]+)(?::([A-Za-z]+))?$")


@dataclass
class Axis:
    """One varied key: its values (a list, or a range ``lo:hi:n`` linear or log)."""

    key: str
    """The key as given (may hold ``*``); also the column name."""
    values: list
    targets: list = field(default_factory=list)
    """The scene keys it sets (``*`` expanded)."""
    lo: float | None = None
    hi: float | None = None
    log: bool = False
    integer: bool = False
    flag: str = "--vary"

    @property
    def is_range(self) -> bool:
        return self.lo is not None


def _number(text: str, flag: str, key: str, what: str):
    try:
        value = scene_mod.parse_override(f"{key}={text}", source=flag)[1]
    except SceneError:
        value = None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise CommandLineError(flag, f"{key}: {what} must be a finite number", text)
    return value


def parse_axis(item: str, flag: str = "--vary", key: str | None = None) -> Axis:
    """``KEY=V1,V2,...``, ``KEY=LO:HI:N`` (N values, linear) or ``KEY=LO:HI:N:log`` as an :class:`Axis`.

    ``key`` given: ``item`` is only the values (``--dts``).
    """
    if key is None:
        if not isinstance(item, str) or "=" not in item:
            raise CommandLineError(flag, "expected KEY=V1,V2,... or KEY=LO:HI:N[:log]", item)
        key, raw = item.split("=", 1)
        key = key.strip()
        if not key or any(not p.strip() for p in key.split(".")):
            raise CommandLineError(flag, "expected a dotted key such as jelly.0.springs.structural.ks before '='", item)
    else:
        raw = item
    raw = raw.strip()
    if not raw:
        raise CommandLineError(flag, f"{key}: no values", item)
    m = _RANGE.match(raw)
    if m:
        lo = _number(m.group(1).strip(), flag, key, "the range's start")
        hi = _number(m.group(2).strip(), flag, key, "the range's end")
        n_text = m.group(3).strip()
        n = scene_mod._index(n_text)
        if n is None or n < 1:
            raise CommandLineError(flag, f"{key}: the range's count N in LO:HI:N must be an integer >= 1", n_text)
        if n > MAX_AXIS_VALUES:
            raise CommandLineError(flag, f"{key}: at most {MAX_AXIS_VALUES} values per axis", n_text)
        scale = (m.group(4) or "lin").lower()
        if scale not in ("lin", "log"):
            raise CommandLineError(flag, f"{key}: the range's scale must be lin or log", m.group(4))
        log = scale == "log"
        if log and not (lo > 0 and hi > 0):
            raise CommandLineError(flag, f"{key}: a log range needs LO > 0 and HI > 0", raw)
        if n > 1 and lo == hi:
            raise CommandLineError(flag, f"{key}: a range of {n} values needs LO != HI", raw)
        if log:
            values = np.geomspace(lo, hi, n) if n > 1 else np.array([float(lo)])
        else:
            values = np.linspace(lo, hi, n) if n > 1 else np.array([float(lo)])
        integer = isinstance(lo, int) and isinstance(hi, int) and not log
        if integer and all(float(v).is_integer() for v in values):
            out = [int(round(v)) for v in values]
        else:
            integer = False
            # 15 significant digits: geomspace's 0.0020000000000000005 is the 0.002 meant.
            out = [float(f"{v:.15g}") for v in values]
        # The ends exactly as given (geomspace may round them).
        out[0] = type(out[0])(lo)
        if n > 1:
            out[-1] = type(out[-1])(hi)
        return Axis(key, out, lo=float(lo), hi=float(hi), log=log, integer=integer, flag=flag)
    values = []
    for text in split_values(raw):
        if not text:
            raise CommandLineError(flag, f"{key}: empty value in the list", raw)
        try:
            values.append(scene_mod.parse_override(f"{key}={text}", source=flag)[1])
        except SceneError as e:
            raise CommandLineError(flag, f"{key}: {e.message}", text) from None
    if len(values) > MAX_AXIS_VALUES:
        raise CommandLineError(flag, f"{key}: at most {MAX_AXIS_VALUES} values per axis", len(values))
    if len(set(map(_canonical, values))) != len(values):
        raise CommandLineError(flag, f"{key}: repeats a value", raw)
    numbers = [v for v in values if isinstance(v, (int, float)) and not isinstance(v, bool)]
    if len(numbers) == len(values) and any(isinstance(v, float) for v in values):
        values = [float(v) for v in values]  # one column type
    return Axis(key, values, flag=flag)


def _canonical(value) -> str:
    return json.dumps(value, sort_keys=True, default=str)


def expand_key(data: dict, key: str, flag: str = "--vary") -> list[str]:
    """The scene keys a key with ``*`` parts names: every table entry or list index there, in order.

    ``jelly.0.springs.*.ks`` names the ``ks`` of every spring type jelly 0 lists; ``*.*.friction``
    the friction of every terrain entry that sets one (only the tables whose file sets the last
    key, unless none does: then every table matched).
    """
    parts = key.split(".")
    if "*" not in parts:
        return [key]
    found = [([], data)]
    for depth, part in enumerate(parts[:-1]):
        nxt = []
        for prefix, node in found:
            if part == "*":
                if isinstance(node, dict):
                    nxt += [(prefix + [k], v) for k, v in node.items()]
                elif isinstance(node, list):
                    nxt += [(prefix + [str(i)], v) for i, v in enumerate(node)]
            elif isinstance(node, dict) and part in node:
                nxt.append((prefix + [part], node[part]))
            elif isinstance(node, list) and scene_mod._index(part) is not None and scene_mod._index(part) < len(node):
                nxt.append((prefix + [part], node[scene_mod._index(part)]))
        found = nxt
    if parts[-1] == "*":
        raise CommandLineError(flag, f"{key}: '*' may stand for a table or list entry, not the last part", key)
    # The tables that have the key in the file; when none has it (a default), every table matched.
    tables = [(prefix, node) for prefix, node in found if isinstance(node, dict)]
    keys = [".".join(prefix + [parts[-1]]) for prefix, node in tables if parts[-1] in node] or \
        [".".join(prefix + [parts[-1]]) for prefix, _ in tables]
    if not keys:
        raise CommandLineError(flag, f"{key}: no table of the scene matches", key)
    return keys


# ---------------------------------------------------------------------------------------------
# Plan


@dataclass
class SweepVariant:
    """One variant: its position in the plan, identity, column values and validated scene dict."""

    index: int
    id: str
    values: dict
    """Column -> value: each axis, then ``integrator`` and ``dt``."""
    data: dict
    reference: dict | None = None
    """The float64 RK4 copy for ``--reference`` (validated)."""

    @property
    def integrator(self) -> str:
        return self.data["simulation"]["integrator"]


def latin_hypercube(axes: list[Axis], samples: int, seed: int) -> list[tuple]:
    """``samples`` points, one value per axis each: every axis's range (or list) split into
    ``samples`` equal strata, each stratum used once, in an order shuffled per axis.

    A range draws uniformly inside its stratum (in log space for a log range; rounded for an integer
    range); a list maps the stratum to an entry (lists longer than ``samples`` are thinned evenly).
    """
    rng = np.random.default_rng(seed)
    columns = []
    for axis in axes:
        u = (rng.permutation(samples) + rng.random(samples)) / samples
        if axis.is_range:
            if axis.log:
                vals = np.exp(math.log(axis.lo) + u * (math.log(axis.hi) - math.log(axis.lo)))
            else:
                vals = axis.lo + u * (axis.hi - axis.lo)
            col = [int(round(v)) for v in vals] if axis.integer else [float(v) for v in vals]
        else:
            col = [axis.values[min(int(x * len(axis.values)), len(axis.values) - 1)] for x in u]
        columns.append(col)
    return list(zip(*columns)) if columns else [()] * samples


def plan_sweep(base: dict, source: str, axes: list[Axis], integrators=None, samples=None, seed=0, mode="run",
               blame=None) -> list[SweepVariant]:
    """Every variant of the sweep, validated (one-line error for the first bad one).

    Args:
        base: the scene's raw dict with ``--set`` and flag overrides applied (not yet validated).
        source: the scene's name for messages.
        axes: ``--vary`` and ``--dts`` axes, in column order.
        integrators: method names, or None for the scene's own.
        samples: draw this many Latin-hypercube points of the axes instead of their product.
        seed: the Latin hypercube's seed.
        mode: ``"run"``, ``"reference"`` (runs plus a float64 RK4 reference each) or ``"stable_dt"``;
            part of each variant's identity, so rows of one mode never stand in for another's.
        blame: ``SceneError -> UserError`` mapping an error to the flag that set the value.
    """
    blame = blame or (lambda e: e)
    keys = [a.key for a in axes]
    if len(set(keys)) != len(keys):
        dup = next(k for k in keys if keys.count(k) > 1)
        raise CommandLineError("--vary", f"{dup}: given twice; list all its values in one --vary", dup)
    for a in axes:
        if a.key in ("simulation.integrator",):
            raise CommandLineError(a.flag, "vary the integrator with --integrators", a.key)
        a.targets = expand_key(base, a.key, a.flag)
        # A range of integers samples integers only for a key whose scene value is an integer (a
        # resolution), not for one that happens to be given as 0:1.
        a.integer = a.integer and all(_is_int(_lookup(base, t)) for t in a.targets)
        if samples is None and not a.values:
            raise CommandLineError(a.flag, f"{a.key}: no values", a.key)
    if samples is not None:
        points = latin_hypercube(axes, samples, seed)
    else:
        count = math.prod(len(a.values) for a in axes) * len(integrators or [None])
        if count > MAX_VARIANTS:
            raise CommandLineError("--vary", f"the product has {count} variants, at most {MAX_VARIANTS} allowed; "
                                   "use --samples N", count)
        points = list(itertools.product(*[a.values for a in axes]))
    variants = []
    for point in points:
        for integrator in integrators or [None]:
            data = copy.deepcopy(base)
            items = []
            if integrator is not None:
                items.append(("simulation.integrator", integrator))
            for axis, value in zip(axes, point):
                items += [(t, value) for t in axis.targets]
            try:
                scene_mod.apply_overrides(data, items, source="--vary")
                validated = scene_mod.validate(data, source)
                sim = validated["simulation"]
                if sim["dt"] > 1.0 / sim["fps"]:
                    raise SceneError(source, "simulation.dt",
                                     f"must not exceed the frame interval 1/fps = {1.0 / sim['fps']:g} s", sim["dt"])
            except SceneError as e:
                raise _blame_axis(blame(e), axes, point) from None
            reference = None
            if mode == "reference":
                ref = copy.deepcopy(data)
                scene_mod.apply_overrides(ref, [("simulation.integrator", methods.REFERENCE.name), ("simulation.precision", "float64")])
                try:
                    reference = scene_mod.validate(ref, source)
                except SceneError as e:
                    raise CommandLineError("--reference", f"the float64 RK4 copy: {e.message}", e.value) from None
            values = {a.key: v for a, v in zip(axes, point) if a.key != "simulation.dt"}
            values["integrator"] = validated["simulation"]["integrator"]
            values["dt"] = float(validated["simulation"]["dt"])
            ident = hashlib.sha256(_canonical({"mode": mode, "scene": validated}).encode()).hexdigest()[:20]
            variants.append(SweepVariant(len(variants), ident, values, validated, reference))
    ids = [v.id for v in variants]
    if len(set(ids)) != len(ids):
        # Two points gave the same scene (a range rounded to repeated integers, a list sampled twice).
        seen, kept = set(), []
        for v in variants:
            if v.id not in seen:
                seen.add(v.id)
                kept.append(v)
        for i, v in enumerate(kept):
            v.index = i
        variants = kept
    return variants


def _lookup(data, key):
    node = data
    for part in key.split("."):
        if isinstance(node, dict) and part in node:
            node = node[part]
        elif isinstance(node, list) and scene_mod._index(part) is not None and scene_mod._index(part) < len(node):
            node = node[scene_mod._index(part)]
        else:
            return None
    return node


def _is_int(value) -> bool:
    if isinstance(value, list):
        return bool(value) and all(_is_int(v) for v in value)
    return isinstance(value, int) and not isinstance(value, bool)


def _blame_axis(error: UserError, axes, point) -> UserError:
    """A scene error about a varied key, reported under ``--vary`` with the key and value."""
    key = getattr(error, "key", None)
    if isinstance(key, str):
        key = key.removeprefix("--set ")
    for axis, value in zip(axes, point):
        if key is not None and any(key == t or key.startswith(t + ".") or t.startswith(key + ".")
                                   for t in axis.targets):
            return CommandLineError(axis.flag, f"{axis.key}: {error.message}", value)
    return error


# ---------------------------------------------------------------------------------------------
# Batches


def group_key(v: SweepVariant) -> str:
    """Variants with equal keys can be worlds of one model: one clock, one integrator, like lattices and terrain."""
    data = v.data
    sim = dict(data["simulation"])
    shapes = [list(j["resolution"]) for j in data["jelly"]]
    terrain = {kind: len(data.get(kind, [])) for kind in TERRAIN_SDF}
    key = {"simulation": sim, "shapes": shapes, "terrain": terrain, "reference": v.reference is not None}
    if not methods.method(sim["integrator"]).explicit:  # an implicit variant runs alone
        key["alone"] = v.id
    return _canonical(key)


def variant_bytes(v: SweepVariant, is_cuda: bool) -> int:
    """Memory one world of ``v`` needs while its batch runs (and its reference copy beside it)."""
    total = 0
    for data in (v.data, v.reference):
        if data is None:
            continue
        est = estimate(data)
        host, device = est.on(is_cuda)
        total += device if is_cuda else host
    return total


def batch_size(variants: list[SweepVariant], workers: int, is_cuda: bool, budget: int | None, limit: int | None) -> int:
    """Worlds per batch for one group: what fits in ``MEMORY_SHARE`` of ``budget`` bytes and
    ``MAX_BATCH``; within that ``limit`` (``--batch``) when given, else no more than spreads the
    group over the workers (twice over on the CPU, so a slow batch does not leave a worker idle at
    the end)."""
    per = max(variant_bytes(v, is_cuda) for v in variants)
    fit = max(1, int(MEMORY_SHARE * budget // per)) if budget else MAX_BATCH
    spread = limit or math.ceil(len(variants) / max(1, workers * (1 if is_cuda else 2)))
    return max(1, min(fit, spread, MAX_BATCH))


def make_batches(variants: list[SweepVariant], workers: int, is_cuda: bool, budget: int | None = None,
                 limit: int | None = None) -> list[list[SweepVariant]]:
    """Variants cut into batches of one group each, in plan order within a group."""
    groups = {}
    for v in variants:
        groups.setdefault(group_key(v), []).append(v)
    out = []
    for members in groups.values():
        if not methods.method(members[0].integrator).explicit:
            out += [[v] for v in members]
            continue
        size = batch_size(members, workers, is_cuda, budget, limit)
        out += [members[i: i + size] for i in range(0, len(members), size)]
    return out


def memory_budget(device_name: str, workers: int) -> int | None:
    """Bytes one worker may use: the device's free memory shared by the workers on it, or host memory."""
    if device_name.startswith("cuda"):
        try:
            import warp as wp  # noqa: PLC0415

            dev = wp.get_device("cuda:0" if device_name == "cuda" else device_name)
            # --device cuda: one worker per GPU (dask-cuda); cuda:N: the workers share that GPU.
            return int(dev.free_memory) // (1 if device_name == "cuda" else max(1, workers))
        except Exception:  # noqa: BLE001 - a remote cluster's devices may not be visible here
            return None
    avail = available_host_bytes()
    return avail // max(1, workers) if avail else None

"""Parameter sweeps: many variants of one scene, batched as worlds, run as Dask tasks, kept as rows.

The pieces, in the order ``softsim sweep`` uses them:

* **Plan** (:func:`parse_axis`, :func:`plan_sweep`): ``--vary KEY=...`` axes (lists, linear or
  log ranges), their product or a Latin hypercube (``--samples``), times ``--integrators`` and
  ``--dts``. Every variant is a scene dict validated like ``softsim run --set KEY=VALUE`` would
  validate it, before anything runs; a bad value is a one-line error.
* **Batches** (:func:`make_batches`): variants that can share launches -- the same ``[simulation]``
  table (dt, fps, duration, precision, ...), the same integrator, the same lattice shapes and the
  same terrain types -- are cut into batches whose size follows from the memory each variant needs
  (:mod:`~softsim_warp.io.resources`). An implicit variant is a batch of its own: the implicit
  solver's iteration counts depend on every particle of its model.
* **Tasks** (:func:`run_batch`, in a Dask worker): one model holds the batch's variants as worlds
  (:mod:`~softsim_warp.io.worlds`, what ``softsim compare`` does) and one launch of each kernel
  steps them all. Each world is judged frame by frame as ``softsim run`` judges its run: the same
  explosion bound and the same metrics, so on the CPU a row equals a single run bit for bit.
* **Rows** (:class:`RowStore`): each finished task's rows go to a part file at once (written to a
  temporary and renamed); the results file (Parquet, or CSV by extension) is rewritten atomically
  from all parts every few seconds and at the end. A sweep stopped by Ctrl-C, a lost worker or a
  lost scheduler keeps every finished row, and ``--resume`` runs only the missing ones. A results
  file that existed before a sweep (not a ``--resume`` of it) is replaced only by the complete
  table: until then the rows go to ``<stem>.partial<ext>`` beside it.
* **Engine** (:func:`start_cluster`, :func:`run_tasks`): a ``distributed.LocalCluster`` of worker
  processes (one thread each), or an existing cluster at ``--scheduler``; a task whose worker dies
  is rerun elsewhere by the scheduler.

The row schema is documented in docs/SWEEP.md.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import os
import re
import shutil
import time
import types
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.errors import CommandLineError, SceneError, UserError
from . import scene as scene_mod
from .checks import SHELLS, TERRAIN_SDF
from .outputs import commit, discard, is_stream, kept_partial_path, save_atomic, target_of
from .resources import available_host_bytes, estimate

# Values one axis may have, and variants one sweep may plan: beyond these a typo (1:2:1e9) is more
# likely than a wish.
MAX_AXIS_VALUES = 100_000
MAX_VARIANTS = 1_000_000
# Seconds between rewrites of the results file while tasks finish (parts are written at once).
CONSOLIDATE_SECONDS = 5.0
# Seconds between a task's asks whether the sweep was stopped (each ask is a round trip to the scheduler).
STOP_POLL_SECONDS = 0.2
# In a sweep's parts folder: this sweep may not replace --out until it is complete (RowStore.keep_out).
KEEP_OUT_MARK = "keep-out"
# Share of a worker's memory (device memory on CUDA, host memory on the CPU) one batch may take.
MEMORY_SHARE = 0.5
# Worlds in one batch at most (the per-frame host work grows with them).
MAX_BATCH = 4096
RESULT_SUFFIXES = (".parquet", ".csv")
SWEEP_EXTRA = "pip install 'softsim-warp[sweep]' (dask, distributed, pyarrow)"


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
                scene_mod.apply_overrides(ref, [("simulation.integrator", "rk4"), ("simulation.precision", "float64")])
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
    if sim["integrator"] == "implicit":
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
        if members[0].integrator == "implicit":
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


# ---------------------------------------------------------------------------------------------
# One batch, in a worker


def penetration(data: dict, q: np.ndarray, jelly_ranges) -> float:
    """Largest depth [m] of a particle inside terrain in the positions ``q`` (one world, float64).

    Solid terrain (planes, spheres): the largest ``-phi`` over particles with signed distance
    ``phi < 0``. A shell (a bowl) has free space on both sides, so a particle behind it is not by
    itself inside anything; a jelly that the shell cuts, some particles on each side, penetrates by
    the smaller of its deepest excursions on the two sides (0 when it lies on one side).
    """
    worst = 0.0
    for kind, sdf in TERRAIN_SDF.items():
        for entry in data.get(kind, []):
            if kind in SHELLS:
                for a, b in jelly_ranges:
                    phi = sdf(entry, q[a:b])
                    phi = phi[np.isfinite(phi)]
                    if phi.size and phi.min() < 0 < phi.max():
                        worst = max(worst, float(min(-phi.min(), phi.max())))
            else:
                phi = sdf(entry, q)
                phi = phi[np.isfinite(phi)]
                if phi.size and phi.min() < 0:
                    worst = max(worst, float(-phi.min()))
    return worst


# Terrain keys that do not move the surface: entries that differ only in these share one distance evaluation.
_NOT_GEOMETRY = ("restitution", "friction", "size")


def shared_surfaces(datas: list[dict]) -> dict:
    """``{(kind, entry): True}`` for each terrain entry whose surface is the same in every world."""
    out = {}
    for kind in TERRAIN_SDF:
        count = len(datas[0].get(kind, []))
        for e in range(count):
            if any(len(d.get(kind, [])) != count for d in datas):
                out[(kind, e)] = False
                continue
            shape = {_canonical({k: v for k, v in d[kind][e].items() if k not in _NOT_GEOMETRY}) for d in datas}
            out[(kind, e)] = len(shape) == 1
    return out


def batch_penetration(datas: list[dict], q: np.ndarray, ranges, jelly_ranges, shared=None) -> np.ndarray:
    """:func:`penetration` of every world of a batch: ``q`` holds all worlds' particles, ``ranges``
    each world's ``(first, end)`` and ``jelly_ranges`` each world's jelly ranges (world-local).

    A terrain entry whose surface is the same in every world (only restitution or friction vary, say)
    is evaluated once over all particles; otherwise world by world. ``shared``: :func:`shared_surfaces`
    of ``datas`` (computed when not given).
    """
    shared = shared_surfaces(datas) if shared is None else shared
    worlds = len(datas)
    worst = np.zeros(worlds)
    q64 = None
    starts = np.array([a for a, _ in ranges])
    for kind, sdf in TERRAIN_SDF.items():
        count = len(datas[0].get(kind, []))
        for e in range(count):
            if not shared[(kind, e)]:
                for w, (a, b) in enumerate(ranges):
                    if e >= len(datas[w].get(kind, [])):
                        continue
                    worst[w] = max(worst[w], penetration({kind: [datas[w][kind][e]]}, q[a:b].astype(np.float64),
                                                         jelly_ranges[w]))
                continue
            if q64 is None:
                q64 = q.astype(np.float64)
            phi = sdf(datas[0][kind][e], q64)
            finite = np.isfinite(phi)
            if kind in SHELLS:
                jstart = np.array([a + ja for (a, _), js in zip(ranges, jelly_ranges) for ja, _ in js])
                jworld = np.array([w for w, js in enumerate(jelly_ranges) for _ in js])
                lo = np.minimum.reduceat(np.where(finite, phi, np.inf), jstart)
                hi = np.maximum.reduceat(np.where(finite, phi, -np.inf), jstart)
                depth = np.where((lo < 0) & (hi > 0), np.minimum(-lo, hi), 0.0)
                np.maximum.at(worst, jworld, depth)
            else:
                depth = np.maximum.reduceat(np.where(finite, -phi, -np.inf), starts)
                worst = np.maximum(worst, depth)
    return np.maximum(worst, 0.0)


class _World:
    """What one world of a batch accumulates frame by frame (what ``Simulator.run`` records for a run)."""

    def __init__(self, bound):
        self.bound = bound
        self.frames = []  # per frame written: namespace(total_energy, gravity_energy, com, max_speed)
        self.exploded = None
        self.steps = 0
        self.sim_time = 0.0
        self.penetration = 0.0
        self.ref_error = 0.0
        self.ref_com_error = None
        self.ref_exploded = None


class _Batch:
    """A batch's model, integrator and stepper, with each world's ranges and explosion bound."""

    def __init__(self, datas, device, use_graph):
        from ..core.integrators import ExplicitIntegrator  # noqa: PLC0415
        from ..core.stepper import make_integrator  # noqa: PLC0415
        from .simulate import Simulator  # noqa: PLC0415
        from .worlds import make_builder, world_jellies, world_ranges, world_speed_bound  # noqa: PLC0415

        sim = datas[0]["simulation"]
        self.datas = datas
        self.model = make_builder(datas).finalize(device, sim["precision"])
        method = sim["integrator"]
        if method == "implicit":
            self.integrator = make_integrator("implicit", self.model, datas[0].get("implicit"))
        else:
            self.integrator = ExplicitIntegrator(self.model, [method] * len(datas))
        first = scene_mod.Scene(datas[0])
        frames = first.frame_count()
        self.sim = Simulator(self.model, self.integrator, sim["dt"], sim["fps"], frames, use_graph=use_graph,
                             max_speed=math.inf, end_time=first.end_time())
        self.frames = frames
        self.ranges = world_ranges(self.model)
        self.jellies = world_jellies(self.model)
        # Jelly particle ranges inside each world (for the shell test of penetration).
        self.world_jelly_ranges = []
        for w, (a, _) in enumerate(self.ranges):
            ja, jb = self.jellies[w]
            self.world_jelly_ranges.append([(j.particle_start - a, j.particle_start - a + j.particle_count)
                                            for j in self.model.jellies[ja:jb]])
        self.worlds = []
        for w, data in enumerate(datas):
            bound = data["simulation"].get("max_speed")
            a, b = self.ranges[w]
            self.worlds.append(_World(float(bound) if bound is not None else world_speed_bound(self.model, a, b, w)))
        self.shared = shared_surfaces(datas)
        # Penetration is measured into terrain only: without any, the positions are never read.
        self.has_terrain = any(d.get(kind) for d in datas for kind in TERRAIN_SDF)
        self.done_steps = 0
        self.step_seconds = 0.0
        self.stop = None  # asked between chunks of a long frame (stop_check): the sweep was stopped

    def launch_frame(self, k: int):
        """Launch the steps up to frame ``k``: asynchronous on CUDA, so the host can work meanwhile."""
        target = self.sim.step_of_frame(k)
        if not self.sim.advance_frame(target - self.done_steps, stop=self.stop):
            raise TaskStopped("the sweep was stopped, or the worker lost its scheduler")
        self.done_steps = target

    def read_frame(self, k: int, positions=True):
        """Measure the frame the launched steps reach (synchronises) and copy it to the host:
        ``(step, time, positions, probe arrays)``; the positions are None unless ``positions``."""
        from .worlds import probe_arrays  # noqa: PLC0415

        t = self.done_steps * self.sim.dt
        self.sim.probe.measure(self.sim.state, k, t)
        q = self.sim.state.particle_q.numpy() if positions else None
        return self.done_steps, t, q, probe_arrays(self.sim.probe)


def _record_frame(world: _World, frame: dict, k: int, step: int, t: float) -> bool:
    """Judge and record frame ``k`` of a world as ``Simulator.run`` does; False once it has exploded."""
    if frame["nonfinite"] or frame["max_speed"] > world.bound:
        world.steps = step
        world.exploded = {
            "frame": k,
            "time": t,
            "reason": (f"{frame['nonfinite']} particles with non-finite state" if frame["nonfinite"]
                       else f"max speed {frame['max_speed']:.4g} m/s exceeds the bound {world.bound:.4g} m/s"),
        }
        return False
    world.frames.append(types.SimpleNamespace(total_energy=frame["total_energy"],
                                              gravity_energy=frame["gravity_energy"], com=frame["com"],
                                              max_speed=frame["max_speed"]))
    world.steps = step
    world.sim_time = t
    return True


class TaskStopped(Exception):
    """The client stopped the sweep while this task ran, or the worker could not ask (``stop_check``).
    Raised out of the task, not returned as no rows: a task that stopped gives no row, and when the
    client still listens it counts the task's variants as lost, for ``--resume``."""


def stop_check(name: str | None):
    """In a task: a callable that is true once the client has set the sweep's stop event ``name``
    (``run_tasks``), or the worker has lost its scheduler. It asks the scheduler at most every
    STOP_POLL_SECONDS, the first time that long after the task started, so a task of short frames
    never asks. None without a name."""
    if not name:
        return None
    seen = {"at": time.perf_counter(), "set": False, "event": None}

    def stop():
        now = time.perf_counter()
        if not seen["set"] and now - seen["at"] >= STOP_POLL_SECONDS:
            seen["at"] = now
            try:
                if seen["event"] is None:
                    from distributed import Event, get_worker  # noqa: PLC0415

                    get_worker()  # ValueError outside a worker
                    seen["event"] = Event(name)
                seen["set"] = seen["event"].is_set()
            except ValueError:  # not in a worker (a task run directly): nothing can stop it
                seen["at"] = math.inf
            except Exception:  # noqa: BLE001 - the worker lost its scheduler (closing): no one takes the rows
                seen["set"] = True
        return seen["set"]

    return stop


def _simulate(variants: list[dict], device, use_graph=True, stop=None) -> list[dict]:
    """Run one batch (all of one group) as worlds of one model; one result dict per variant.
    ``stop``: asked between chunks of a long frame; when true the task ends (``TaskStopped``)."""
    from .runinfo import energy_drift  # noqa: PLC0415
    from .worlds import world_frame, world_frames  # noqa: PLC0415

    batch = _Batch([v["data"] for v in variants], device, use_graph)
    batch.stop = stop
    ref = None
    if variants[0].get("reference") is not None:
        ref = _Batch([v["reference"] for v in variants], device, use_graph)
        ref.stop = stop
    t_compile = time.perf_counter()
    batch.sim.warm_up()
    if ref is not None:
        ref.sim.warm_up()
    compile_seconds = time.perf_counter() - t_compile
    alive = [True] * len(variants)
    ref_alive = [True] * len(variants)
    # Frame k+1's steps are launched before frame k is judged on the host: on CUDA the host work
    # (metrics per world, terrain distances) overlaps the device's; on the CPU launches run at once.
    t_start = time.perf_counter()
    for b in (batch, ref):
        if b is not None:
            b.launch_frame(0)
    for k in range(batch.frames + 1):
        # The positions come to the host only for what reads them: penetration, the reference error.
        step, t, q, arrays = batch.read_frame(k, positions=batch.has_terrain or ref is not None)
        if ref is not None:
            _, _, q_ref, ref_arrays = ref.read_frame(k)
        if k < batch.frames:
            for b in (batch, ref):
                if b is not None:
                    b.launch_frame(k + 1)
        frames = world_frames(arrays, batch.jellies)
        depth = None
        if batch.has_terrain:
            depth = batch_penetration(batch.datas, q, batch.ranges, batch.world_jelly_ranges, batch.shared)
        for w, world in enumerate(batch.worlds):
            if not alive[w]:
                continue
            frame = frames[w]
            alive[w] = _record_frame(world, frame, k, step, t)
            if not alive[w]:
                continue
            if depth is not None:
                world.penetration = max(world.penetration, float(depth[w]))
            if ref is not None and ref_alive[w]:
                a, b = batch.ranges[w]
                qw = q[a:b].astype(np.float64)
                rframe = world_frame(ref_arrays, ref.jellies[w])
                rworld = ref.worlds[w]
                ref_alive[w] = _record_frame(rworld, rframe, k, step, t)
                if ref_alive[w]:
                    d = qw - q_ref[a:b]
                    world.ref_error = max(world.ref_error, float(np.sqrt(np.mean(np.einsum("ij,ij->i", d, d)))))
                    world.ref_com_error = float(np.linalg.norm(np.asarray(frame["com"]) - np.asarray(rframe["com"])))
                else:
                    world.ref_exploded = rworld.exploded
        if not any(alive):
            break
    batch.step_seconds = time.perf_counter() - t_start
    particles = [b - a for a, b in batch.ranges]
    work = sum(n * w.steps for n, w in zip(particles, batch.worlds))
    out = []
    for w, (v, world) in enumerate(zip(variants, batch.worlds)):
        drift, rel = energy_drift(world.frames)
        last = world.frames[-1] if world.frames else None
        row = {
            "variant_id": v["id"],
            "status": "exploded" if world.exploded else "completed",
            "explosion_time": world.exploded["time"] if world.exploded else None,
            "explosion_frame": world.exploded["frame"] if world.exploded else None,
            "explosion_reason": world.exploded["reason"] if world.exploded else None,
            "error": None,
            "steps": world.steps,
            "frames": len(world.frames),
            "sim_time": world.sim_time,
            "particles": particles[w],
            "batch_size": len(variants),
            "wall_seconds": batch.step_seconds,
            "compile_seconds": compile_seconds,
            "particle_steps_per_second": work / batch.step_seconds if batch.step_seconds > 0 else 0.0,
            "energy_start": world.frames[0].total_energy if world.frames else None,
            "energy_end": last.total_energy if last else None,
            "energy_change": drift,
            "energy_change_relative": rel,
            "com_x": last.com[0] if last else None,
            "com_y": last.com[1] if last else None,
            "com_z": last.com[2] if last else None,
            "max_speed": max(f.max_speed for f in world.frames) if world.frames else None,
            "max_penetration": world.penetration,
        }
        if ref is not None:
            rworld = ref.worlds[w]
            row["ref_status"] = "exploded" if rworld.exploded else "completed"
            row["ref_position_error"] = world.ref_error if world.frames else None
            row["ref_com_error"] = world.ref_com_error
        out.append(row)
    return out


def _failed(v: dict, error: BaseException, batch_size: int) -> dict:
    return {"variant_id": v["id"], "status": "failed", "error": f"{type(error).__name__}: {error}".strip(),
            "batch_size": batch_size}


_WARP_READY = False


def _init_warp():
    global _WARP_READY
    import warp as wp  # noqa: PLC0415

    if not _WARP_READY:
        # As commands.common.init_warp: Warp's banner and missing-driver notice (written by native
        # code to descriptor 2) would repeat once per worker; they are held back.
        from ..core.native_output import held_stderr  # noqa: PLC0415

        wp.config.quiet = True
        wp.config.log_level = wp.LOG_WARNING
        with held_stderr():
            wp.init()
        _WARP_READY = True
    return wp


def _test_hooks(spec, phase):
    """Test seam (tests/test_sweep.py): with SOFTSIM_SWEEP_TEST_DIR set, a task marks its start and
    end there (``<task>.<pid>.running`` / ``.done``) and, at start, waits ``SOFTSIM_SWEEP_TEST_DELAY``
    seconds, so a test can kill a worker while it holds a task. Unset, it costs an environment lookup."""
    folder = os.environ.get("SOFTSIM_SWEEP_TEST_DIR")
    if not folder:
        return
    name = Path(folder) / f"{spec['task']}.{os.getpid()}"
    if phase == "start":
        name.with_suffix(name.suffix + ".running").write_text("")
        time.sleep(float(os.environ.get("SOFTSIM_SWEEP_TEST_DELAY", "0")))
    else:
        name.with_suffix(name.suffix + ".done").write_text("")


def run_batch(spec: dict) -> list[dict]:
    """A Dask task: simulate the batch ``spec["variants"]`` on ``spec["device"]``; one result per variant.

    A batch that fails as a whole is rerun variant by variant, so one bad variant fails alone.
    """
    _test_hooks(spec, "start")
    wp = _init_warp()
    device = wp.get_device(spec["device"])
    variants = spec["variants"]
    use_graph = spec.get("use_graph", True)
    stop = stop_check(spec.get("stop_event"))
    try:
        rows = _simulate(variants, device, use_graph, stop)
    except TaskStopped:
        raise
    except Exception as e:  # noqa: BLE001 - a variant's failure is its row's result
        if len(variants) == 1:
            rows = [_failed(variants[0], e, 1)]
        else:
            rows = []
            for v in variants:
                try:
                    rows += _simulate([v], device, use_graph, stop)
                except TaskStopped:
                    raise
                except Exception as e1:  # noqa: BLE001
                    rows.append(_failed(v, e1, len(variants)))
    host = os.uname().nodename
    for r in rows:
        r["device"] = str(device)
        r["worker"] = f"{host}:{os.getpid()}"
    _test_hooks(spec, "end")
    return rows


def task_spec(batch: list[SweepVariant], device: str, number: int, use_graph=True) -> dict:
    """What a task needs: plain data only (it travels to the worker)."""
    return {
        "task": f"task{number:06d}",
        "device": device,
        "use_graph": use_graph,
        "variants": [{"id": v.id, "data": v.data, "reference": v.reference} for v in batch],
    }


# ---------------------------------------------------------------------------------------------
# Rows


def require(module: str):
    """Import an optional dependency of the sweep, or a one-line error saying how to install it."""
    import importlib  # noqa: PLC0415

    try:
        return importlib.import_module(module)
    except ImportError:
        raise CommandLineError("sweep", f"needs the '{module.split('.')[0]}' package: {SWEEP_EXTRA}") from None


RESULT_COLUMNS = [
    ("device", "string"), ("precision", "string"), ("status", "string"),
    ("explosion_time", "float64"), ("explosion_frame", "int64"), ("explosion_reason", "string"), ("error", "string"),
    ("steps", "int64"), ("frames", "int64"), ("sim_time", "float64"), ("particles", "int64"), ("batch_size", "int64"),
    ("wall_seconds", "float64"), ("compile_seconds", "float64"), ("particle_steps_per_second", "float64"),
    ("energy_start", "float64"), ("energy_end", "float64"), ("energy_change", "float64"),
    ("energy_change_relative", "float64"), ("com_x", "float64"), ("com_y", "float64"), ("com_z", "float64"),
    ("max_speed", "float64"), ("max_penetration", "float64"), ("worker", "string"),
]
REFERENCE_COLUMNS = [("ref_status", "string"), ("ref_position_error", "float64"), ("ref_com_error", "float64")]
STABLE_COLUMNS = [
    ("device", "string"), ("precision", "string"), ("status", "string"), ("error", "string"),
    ("stable_dt", "float64"), ("unstable_dt", "float64"), ("bound", "string"), ("probes", "int64"),
    ("duration", "float64"), ("predicted_dt", "float64"),
    ("stable_dt_jelly", "float64"), ("unstable_dt_jelly", "float64"), ("bound_jelly", "string"),
    ("wall_seconds", "float64"), ("worker", "string"),
]


def _arrow_type(pa, values):
    """The Arrow type of a varied key's column: int64, float64, bool or string (JSON text for lists)."""
    if all(isinstance(v, bool) for v in values):
        return pa.bool_()
    if all(isinstance(v, int) and not isinstance(v, bool) for v in values):
        return pa.int64()
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        return pa.float64()
    return pa.string()


def column_value(value, kind):
    if kind == "string" and not isinstance(value, str):
        return _canonical(value)
    return value


def make_schema(axes: list[Axis], variants: list[SweepVariant], mode: str, meta: dict):
    """The results' Arrow schema: identity, varied keys, integrator and dt, then the mode's columns."""
    pa = require("pyarrow")
    fields = [pa.field("variant_id", pa.string()), pa.field("index", pa.int64())]
    for a in axes:
        if a.key == "simulation.dt":
            continue
        fields.append(pa.field(a.key, _arrow_type(pa, [v.values[a.key] for v in variants] or a.values)))
    fields += [pa.field("integrator", pa.string()), pa.field("dt", pa.float64())]
    if mode == "stable_dt":
        cols = STABLE_COLUMNS
    else:
        cols = RESULT_COLUMNS + (REFERENCE_COLUMNS if mode == "reference" else [])
    fields += [pa.field(name, getattr(pa, kind)()) for name, kind in cols]
    return pa.schema(fields, metadata={"softsim:sweep": json.dumps(meta, sort_keys=True, default=str)})


class RowStore:
    """The results of one sweep on disk: part files as tasks finish, one consolidated file.

    Parts live in the hidden folder ``.<name>.parts`` beside the results file; each is written to a
    temporary and renamed, so a part is whole or absent. :meth:`consolidate` rewrites the results
    file atomically from the rows it had, the parts and nothing else; after a complete sweep the
    parts are removed. Rows are told apart by ``variant_id``; a later row of an id replaces none.

    A file at ``out`` that existed before this sweep (and is not being resumed) is another result:
    it is replaced only by the complete table. Until then (``keep_out``) the consolidated rows go to
    ``<stem>.partial<ext>`` beside it (:func:`~softsim_warp.io.outputs.kept_partial_path`), and the
    parts folder says so (:data:`KEEP_OUT_MARK`), so that ``--resume`` reads that file and the
    parts, leaves ``out`` alone until the table is complete, and then removes the partial file.
    """

    def __init__(self, out, schema, resume=False):
        self.pa = require("pyarrow")
        self.pq = require("pyarrow.parquet")
        self.out = Path(out)
        self.schema = schema
        target = target_of(self.out)
        self.parts = target.with_name(f".{target.name}.parts")
        self.partial = kept_partial_path(self.out)
        self.rows = {}  # variant_id -> row dict
        self._part = 0
        self._last = time.monotonic()
        self._own_partial = False  # the partial file holds this sweep's rows (read or written here)
        if resume:
            self.keep_out = (self.parts / KEEP_OUT_MARK).exists()
            self._load()
        elif self.parts.exists():
            raise CommandLineError("--out", f"the rows of an unfinished sweep are in '{self.parts}': add --resume to "
                                   "finish that sweep, or remove the folder to start again", str(out))
        else:
            self.keep_out = target.exists() and not is_stream(target)

    @property
    def results(self) -> Path:
        """Where the rows are consolidated while the sweep is not complete: ``out``, or its partial file."""
        return self.partial if self.keep_out else self.out

    def _read(self, path):
        if path.suffix == ".csv":
            csv = require("pyarrow.csv")
            types_ = {f.name: f.type for f in self.schema}
            table = csv.read_csv(path, convert_options=csv.ConvertOptions(column_types=types_))
        else:
            table = self.pq.read_table(path)
        return table

    def _load(self):
        sources = []
        if self.results.exists():
            sources.append(self.results)
        if self.parts.exists():
            sources += sorted(self.parts.glob("part-*.parquet"))
        want = set(self.schema.names)
        for path in sources:
            try:
                table = self._read(path)
            except Exception as e:  # noqa: BLE001 - a damaged file is the user's to look at
                raise CommandLineError("--resume", f"cannot read '{path}': {e}", str(path)) from None
            if set(table.column_names) != want:
                missing = sorted(want - set(table.column_names)) or sorted(set(table.column_names) - want)
                raise CommandLineError("--resume", f"'{path}' holds rows of another sweep (columns differ: "
                                       f"{', '.join(missing[:4])}); use another --out or run without --resume",
                                       str(path))
            for row in table.to_pylist():
                self.rows.setdefault(row["variant_id"], row)
            self._own_partial |= path == self.partial
            m = re.match(r"part-(\d+)", path.stem)
            if m:
                self._part = max(self._part, int(m.group(1)) + 1)

    def done_ids(self) -> set:
        return set(self.rows)

    def add(self, rows: list[dict]):
        """Keep ``rows`` (one task's): written to a new part file before this returns."""
        rows = [r for r in rows if r["variant_id"] not in self.rows]
        if not rows:
            return
        self.parts.mkdir(exist_ok=True)
        mark = self.parts / KEEP_OUT_MARK
        if self.keep_out and not mark.exists():  # before the first part: --resume must know
            note = f"'{self.out.name}' predates this sweep: its rows go to '{self.partial.name}' until it is complete"
            mark.write_text(note + "\n")
        table = self._table(rows)
        path = self.parts / f"part-{self._part:06d}.parquet"
        self._part += 1
        tmp = self.parts / f".{path.stem}.partial-{os.getpid()}.parquet"
        try:
            self.pq.write_table(table, tmp)
        except BaseException:
            discard(tmp)
            raise
        commit(tmp, path, "--out")
        for r in rows:
            self.rows[r["variant_id"]] = r

    def _table(self, rows):
        names = self.schema.names
        kinds = {f.name: ("string" if f.type == self.pa.string() else "") for f in self.schema}
        cols = {n: [column_value(r.get(n), kinds[n]) if r.get(n) is not None else None for r in rows] for n in names}
        return self.pa.Table.from_pydict(cols, schema=self.schema)

    def due(self) -> bool:
        return time.monotonic() - self._last >= CONSOLIDATE_SECONDS

    def consolidate(self, final=False):
        """Rewrite the results file from every row kept, in plan order.

        ``final`` (the table is complete) writes ``out`` itself and then removes the parts and the
        partial file of a ``keep_out`` sweep (when it held this sweep's rows); otherwise the rows go
        to :attr:`results`.
        """
        rows = sorted(self.rows.values(), key=lambda r: (r["index"], r["variant_id"]))
        table = self._table(rows)
        path = self.out if final else self.results
        if self.out.suffix == ".csv":
            csv = require("pyarrow.csv")
            save_atomic(path, lambda tmp: csv.write_csv(table, tmp), "--out")
        else:
            save_atomic(path, lambda tmp: self.pq.write_table(table, tmp), "--out")
        self._last = time.monotonic()
        self._own_partial |= path == self.partial
        if final:
            if self._own_partial:
                discard(self.partial)
            if self.parts.exists():
                shutil.rmtree(self.parts, ignore_errors=True)


def read_results(path):
    """The rows of a results file as a list of dicts (Parquet or CSV)."""
    path = Path(path)
    if path.suffix == ".csv":
        return require("pyarrow.csv").read_csv(path).to_pylist()
    return require("pyarrow.parquet").read_table(path).to_pylist()


# ---------------------------------------------------------------------------------------------
# Engine


@dataclass
class Cluster:
    client: object
    cluster: object | None
    workers: int
    dashboard: str | None
    address: str
    device: str
    """The device name each task uses (``cuda:0`` on a dask-cuda worker, which sees its own GPU)."""

    def close(self):
        try:
            self.client.close(timeout=10)
        except Exception:  # noqa: BLE001 - closing a lost scheduler's client
            pass
        if self.cluster is not None:
            try:
                self.cluster.close(timeout=10)
            except Exception:  # noqa: BLE001
                pass


SCHEDULER_SCHEMES = ("tcp", "tls", "ws", "wss")
SCHEDULER_EXPECTED = "expected a scheduler address tcp://HOST:PORT (or tls://, ws://, wss://; tcp:// may be left out)"


def check_scheduler_address(address: str) -> str:
    """``--scheduler``'s address as ``scheme://HOST:PORT``, or a one-line error saying what is wrong.

    The form distributed's ``Client`` connects to: ``[SCHEME://]HOST:PORT``, SCHEME one of
    :data:`SCHEDULER_SCHEMES` (tcp when left out), an IPv6 host in brackets, PORT from 1 to 65535.
    Only the form is checked; whether a scheduler answers there is :func:`start_cluster`'s to find.
    """
    text = str(address).strip()
    scheme, sep, rest = text.partition("://")
    if not sep:
        scheme, rest = "tcp", text
    if rest.startswith("["):  # [::1]:8786
        host, close, port = rest[1:].partition("]")
        port = port[1:] if close and port.startswith(":") else None
    else:
        host, colon, port = rest.rpartition(":")
        host, port = (host, port) if colon else (rest, None)
    if not text:
        why = "empty"
    elif scheme.lower() not in SCHEDULER_SCHEMES:
        why = f"unknown scheme '{scheme}'"
    elif "/" in rest or any(c.isspace() for c in rest):
        why = "not HOST:PORT after the scheme"
    elif not host:
        why = "no host"
    elif not port:
        why = "no port"
    elif not (port.isdecimal() and 1 <= int(port) <= 65535):
        why = "the port must be an integer from 1 to 65535"
    else:
        return f"{scheme.lower()}://{rest}"  # distributed knows the schemes in lower case
    raise CommandLineError("--scheduler", f"{why}; {SCHEDULER_EXPECTED}", address)


def default_workers(device: str) -> int:
    if device.startswith("cuda"):
        return 1
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def start_cluster(device: str, workers: int | None = None, scheduler: str | None = None, gpus: int = 0) -> Cluster:
    """A Dask client: on ``scheduler``'s cluster, else on a new local cluster of worker processes.

    Locally, each worker is a process with one thread. ``device == "cuda"`` (every GPU) with several
    GPUs starts ``dask_cuda.LocalCUDACluster``, one worker per GPU, each seeing its GPU as cuda:0.
    """
    import logging  # noqa: PLC0415

    distributed = require("distributed")
    dashboard_ok = _has_bokeh()
    if scheduler:
        scheduler = check_scheduler_address(scheduler)
        try:
            client = distributed.Client(scheduler, timeout="30s")
        except (OSError, TimeoutError) as e:
            why = str(e).replace(": ", ", ") or type(e).__name__  # the line keeps its four ': '-separated parts
            raise CommandLineError("--scheduler", f"cannot reach the scheduler ({why})", scheduler) from None
        except ValueError as e:  # an address distributed cannot parse after all
            why = str(e).replace(": ", ", ")  # the line keeps its four ': '-separated parts
            raise CommandLineError("--scheduler", f"{SCHEDULER_EXPECTED} ({why})", scheduler) from None
        n = len(client.scheduler_info().get("workers", {}))
        dashboard = client.dashboard_link if dashboard_ok else None
        task_device = "cuda:0" if device == "cuda" else device
        return Cluster(client, None, n, dashboard, scheduler, task_device)
    # preload: this module's dask_setup runs in each local worker process (Ctrl-C is the client's).
    kwargs = {"threads_per_worker": 1, "dashboard_address": ":0" if dashboard_ok else None,
              "silence_logs": logging.ERROR, "preload": [__name__]}
    if device == "cuda" and gpus > 1:
        try:
            from dask_cuda import LocalCUDACluster  # noqa: PLC0415
        except ImportError:
            raise CommandLineError("--device", f"cuda (every GPU, {gpus} here) needs dask-cuda: pip install dask-cuda; "
                                   "or name one GPU, cuda:N", device) from None
        cluster = LocalCUDACluster(n_workers=workers or gpus, **kwargs)
        task_device = "cuda:0"
    else:
        n = workers or default_workers(device)
        cluster = distributed.LocalCluster(n_workers=n, processes=True, scheduler_port=0, **kwargs)
        task_device = "cuda:0" if device == "cuda" else device
    client = distributed.Client(cluster)
    # Warp starts in every worker now, not in its first task (a start-up cost, not a task's).
    client.run(_start_worker)
    n = len(cluster.workers)
    dashboard = client.dashboard_link if dashboard_ok else None
    return Cluster(client, cluster, n, dashboard, cluster.scheduler_address, task_device)


def _start_worker():
    _init_warp()


def dask_setup(worker):
    """Preloaded into each local worker process: a Ctrl-C in the terminal (or the terminal closed:
    SIGHUP) reaches every process of the group, and the client alone handles it (it stops, keeps
    the rows and closes the cluster)."""
    import signal  # noqa: PLC0415

    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGHUP, signal.SIG_IGN)
    except ValueError:  # not the main thread: leave it
        pass


def _has_bokeh() -> bool:
    import importlib.util  # noqa: PLC0415

    return importlib.util.find_spec("bokeh") is not None


@dataclass
class Outcome:
    done: int = 0
    failed: int = 0
    lost: list = field(default_factory=list)  # variant ids whose task was lost or raised (no rows)
    errors: list = field(default_factory=list)  # what those tasks raised
    interrupted: bool = False
    scheduler_lost: str | None = None


def run_tasks(cluster: Cluster, fn, specs: list[dict], on_rows, stop_requested=None, progress=None) -> Outcome:
    """Submit ``fn(spec)`` for each spec and hand each finished task's rows to ``on_rows`` as they come.

    A task whose worker died is rerun by the scheduler (up to its ``allowed-failures``); one it gave
    up on, or one that raised outside a variant (a device missing on that worker, say), is reported
    in ``Outcome.lost`` and ``errors`` and gives no rows, so ``--resume`` runs it again: only a
    variant's own failure is a row. Stops early, cancelling what is still queued, when
    ``stop_requested()`` says so or the scheduler is lost.
    """
    distributed = require("distributed")
    client = cluster.client
    outcome = Outcome()
    futures = {}
    # Set when the sweep stops: a running task reads it between chunks of a long frame and ends
    # (stop_check), so its worker is free and the cluster closes at once.
    stop_event = f"softsim-stop-{os.getpid()}-{time.time_ns()}"
    for spec in specs:
        spec = {**spec, "stop_event": stop_event}
        f = client.submit(fn, spec, key=f"softsim-{spec['task']}-{os.getpid()}-{time.time_ns()}", pure=False)
        futures[f.key] = (f, spec)
    pending = {f for f, _ in futures.values()}
    ac = distributed.as_completed(list(pending))
    try:
        while pending:
            if stop_requested is not None and stop_requested():
                outcome.interrupted = True
                try:
                    distributed.Event(stop_event, client=client).set()
                except Exception:  # noqa: BLE001 - a lost scheduler: its tasks are gone anyway
                    pass
                break
            if not ac.has_ready():
                if ac.is_empty():
                    break
                time.sleep(0.05)
                continue
            for f in ac.next_batch(block=False):
                pending.discard(f)
                _, spec = futures.pop(f.key)  # the result is released once read
                ids = [v["id"] for v in spec["variants"]]
                if f.status == "finished":
                    rows = f.result()
                    on_rows(rows)
                    outcome.done += len(rows)
                    outcome.failed += sum(r["status"] == "failed" for r in rows)
                elif f.status == "error":
                    exc = f.exception()
                    outcome.lost += ids
                    outcome.errors.append(f"{type(exc).__name__}: {exc}".strip())
                else:  # cancelled or lost: the scheduler went away
                    outcome.lost += ids
                    outcome.scheduler_lost = f"task {spec['task']} was {f.status}"
                if progress is not None:
                    progress.update(len(ids))
            if outcome.scheduler_lost:
                break
    except (OSError, TimeoutError) as e:  # the connection to the scheduler broke
        outcome.scheduler_lost = str(e) or type(e).__name__
    finally:
        if pending:
            try:
                client.cancel(list(pending), force=True)
            except Exception:  # noqa: BLE001 - a lost scheduler cannot cancel
                pass
    return outcome

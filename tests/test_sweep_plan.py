"""Planning a sweep (softsim_warp/io/sweep/plan.py): axes, ranges, Latin hypercubes and batches."""

from __future__ import annotations

import pytest

pytest.importorskip("distributed")
pq = pytest.importorskip("pyarrow.parquet")

import numpy as np  # noqa: E402

from softsim_warp.io import sweep as engine  # noqa: E402
from softsim_warp.io.sweep import latin_hypercube, parse_axis  # noqa: E402


def test_ranges_lists_and_wildcards():
    a = parse_axis("x=1:5:5")
    assert a.values == [1, 2, 3, 4, 5] and all(isinstance(v, int) for v in a.values)
    a = parse_axis("x=0.1:0.2:3")
    assert a.values == [0.1, pytest.approx(0.15), 0.2]
    a = parse_axis("x=1e2:1e6:5:log")
    assert a.values[0] == 100.0 and a.values[-1] == 1e6
    np.testing.assert_allclose(np.diff(np.log10(a.values)), 1.0)
    assert parse_axis("x=1,2.5,[1,0,1]").values == [1, 2.5, [1, 0, 1]]
    assert parse_axis("x=1,2.5").values == [1.0, 2.5]  # one column type
    base = {"jelly": [{"springs": {"structural": {"ks": 1}, "bending": {"ks": 2}}}, {"springs": {"shear": {}}}]}
    # Only the tables whose file sets the key; when none does, every table matched.
    assert engine.expand_key(base, "jelly.*.springs.*.ks") == ["jelly.0.springs.structural.ks",
                                                               "jelly.0.springs.bending.ks"]
    assert engine.expand_key(base, "jelly.*.springs.*.kd") == [
        "jelly.0.springs.structural.kd", "jelly.0.springs.bending.kd", "jelly.1.springs.shear.kd"]


def test_latin_hypercube_uses_each_stratum_once():
    axes = [parse_axis("a=0.0:1.0:2"), parse_axis("b=1:100:2:log"), parse_axis("c=x,y,z,w")]
    n = 8
    pts = latin_hypercube(axes, n, seed=3)
    assert len(pts) == n
    a = np.array([p[0] for p in pts])
    b = np.log10([p[1] for p in pts]) / 2.0  # log range mapped to [0, 1]
    for col in (a, b):
        assert sorted(np.floor(col * n).astype(int)) == list(range(n))
    assert sorted(p[2] for p in pts) == sorted(["x", "y", "z", "w"] * 2)
    assert latin_hypercube(axes, n, seed=3) == pts


def test_batches_group_what_can_share_a_launch():
    from softsim_warp.io import scene as scene_mod

    _, source, base = scene_mod.read_scene_data("seed_bowl")
    axes = [parse_axis("jelly.0.resolution=3,4"), parse_axis("jelly.0.springs.*.ks=1000,2000,3000")]
    variants = engine.plan_sweep(base, source, axes, ["euler", "implicit"])
    assert len(variants) == 12 and len({v.id for v in variants}) == 12
    batches = engine.make_batches(variants, workers=1, is_cuda=True)
    for b in batches:
        assert len({engine.group_key(v) for v in b}) == 1
    explicit = [b for b in batches if b[0].integrator == "euler"]
    assert sorted(len(b) for b in explicit) == [3, 3]  # one per lattice shape
    assert all(len(b) == 1 for b in batches if b[0].integrator == "implicit")
    # A memory budget bounds the batch.
    per = engine.variant_bytes(variants[0], True)
    small = engine.make_batches(variants, workers=1, is_cuda=True, budget=int(4 * per / engine.MEMORY_SHARE) + 1)
    assert max(len(b) for b in small) <= 4 and sum(map(len, small)) == 12

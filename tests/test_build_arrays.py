"""Models built as arrays: what ``ModelBuilder`` records for a whole lattice jelly
(no spring list, no ``detect_lattice``) gives the model a spring-by-spring loop builds.

The reference here is built one spring at a time, in Python loops over every lattice point and
stencil offset, from the lattice's definition (``lattice_index``, ``STENCILS``): it shares no code
with the recorded path's slicing (``rest_tables``) or its lazily made list (``LatticeSprings.arrays``).
"""

from __future__ import annotations

import copy
import itertools

import numpy as np
import pytest

import softsim_warp.core.lattice_model as lattice_model
import softsim_warp.core.model as model_mod
from softsim_warp.studies.bench_contact import pile_positions
from softsim_warp.core import lattice
from softsim_warp.core.lattice_model import LatticeSprings, detect_lattice, recorded_lattice
from softsim_warp.core.model import ModelBuilder, build_model, jelly_points, populate
from softsim_warp.io import scene as scene_mod
from softsim_warp.io.sweep import parse_axis, plan_sweep
from softsim_warp.io.worlds import make_builder

SPRINGS = {"structural": {"ks": 80.0, "kd": 0.3}, "shear": {"ks": 60.0, "kd": 0.2}, "bending": {"ks": 20.0}}


def loop_springs(shape, rest_pose, start, springs, keep=None):
    """Every spring of a lattice jelly, one at a time: ``{(a, b, type): (rest, ks, kd)}`` with global
    particle indices; ``keep``: the kept lattice points of a masked jelly (renumbered in order)."""
    nx, ny, nz = shape
    number = {}
    for p in range(nx * ny * nz):
        if keep is None or keep[p]:
            number[p] = len(number)
    out = {}
    for t, stencil in lattice.STENCILS.items():
        params = springs.get(lattice.SPRING_TYPE_NAMES[t])
        if params is None:
            continue
        for di, dj, dk in stencil:
            for i, j, k in itertools.product(range(nx), range(ny), range(nz)):
                i2, j2, k2 = i + di, j + dj, k + dk
                if not (0 <= i2 < nx and 0 <= j2 < ny and 0 <= k2 < nz):
                    continue
                a, b = (i * ny + j) * nz + k, (i2 * ny + j2) * nz + k2
                if a not in number or b not in number:
                    continue
                d = rest_pose[a] - rest_pose[b]
                rest = float(np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]))
                out[(number[a] + start, number[b] + start, t)] = (rest, float(params["ks"]), float(params.get("kd", 0.0)))
    return out


def model_springs(model):
    """The model's spring list as ``{(a, b, type): (rest, ks, kd)}`` (made on first access here)."""
    pairs, types = model.spring_indices_host, model.spring_type_host
    rest, ks, kd = model.spring_rest_host, model.spring_stiffness_host, model.spring_damping_host
    out = {(int(a), int(b), int(t)): (float(r), float(s), float(d))
           for (a, b), t, r, s, d in zip(pairs, types, rest, ks, kd)}
    assert len(out) == model.spring_count == len(pairs)  # no spring twice
    return out


def assert_springs_match(model, expected):
    got = model_springs(model)
    assert got.keys() == expected.keys()
    for key, (rest, ks, kd) in expected.items():
        g_rest, g_ks, g_kd = got[key]
        assert (g_ks, g_kd) == (ks, kd)
        assert g_rest == pytest.approx(rest, rel=1e-14, abs=1e-15)


def expected_springs(data_list, model):
    """The loop-built springs of every jelly of ``model`` whose scene dicts are ``data_list`` (one per world)."""
    expected = {}
    jellies = [j for data in data_list for j in data["jelly"]]
    assert len(jellies) == len(model.jellies)
    for j, info in zip(jellies, model.jellies):
        pose = jelly_points(j["resolution"], j["size"], j["center"], j["rotation"]["axis"], j["rotation"]["degrees"])
        keep = None
        if info.lattice_index is not None:
            keep = np.zeros(int(np.prod(info.shape)), dtype=bool)
            keep[info.lattice_index] = True
        expected.update(loop_springs(tuple(j["resolution"]), pose, info.particle_start, j["springs"], keep))
    return expected


def assert_particles_match(model, data_list):
    """Start positions, velocities, masses, jelly and world of each particle, from the scene dicts."""
    q = model.particle_q_host
    qd = model.particle_qd.numpy()
    jelly_of, world_of = model.particle_jelly.numpy(), model.particle_world.numpy()
    k = 0
    for w, data in enumerate(data_list):
        for j in data["jelly"]:
            info = model.jellies[k]
            a, b = info.particle_start, info.particle_start + info.particle_count
            pts = jelly_points(j["resolution"], j["size"], j["center"], j["rotation"]["axis"], j["rotation"]["degrees"],
                               j.get("initial_scale"))
            if info.lattice_index is not None:
                pts = pts[info.lattice_index]
            np.testing.assert_array_equal(q[a:b], pts)
            v = np.asarray(j["velocity"]) + np.cross(np.asarray(j["angular_velocity"]), pts - np.asarray(j["center"]))
            moving = model.particle_mass_host[a:b] > 0  # pinned particles start on their path (at rest here)
            np.testing.assert_array_equal(qd[a:b][moving], v[moving].astype(np.float32))
            assert np.all(jelly_of[a:b] == k) and np.all(world_of[a:b] == w)
            assert info.world == w
            k += 1
    assert k == len(model.jellies) and model.particle_count == q.shape[0]


def seed_batch(worlds):
    _, source, base = scene_mod.read_scene_data("seed_bowl")
    return [v.data for v in plan_sweep(base, source, [parse_axis(f"jelly.0.springs.*.ks=1000:8000:{worlds}")])]


def pile(count, rotate=False):
    _, source, base = scene_mod.read_scene_data("seed_plane")
    jelly = dict(base["jelly"][0], resolution=[5, 5, 5], size=2.0)  # spacing 0.5
    data = copy.deepcopy(base)
    data["jelly"] = []
    for n, c in enumerate(pile_positions(count, 5, 0.5)):  # on y = 0, the plane at y = -1
        j = dict(copy.deepcopy(jelly), center=list(c))
        if rotate:  # a little, each jelly about its own axis, so that they stay apart
            j["rotation"] = {"axis": [1.0, n % 3, 1.0], "degrees": 0.5 * n}
        data["jelly"].append(j)
    return scene_mod.validate(data, source)


def list_built(builder):
    """The same builder with its spring list read out: the lattice is then searched (detect_lattice)."""
    builder._pairs  # noqa: B018 - reading the lists gives up the records
    assert builder.lattice_records() is None
    return builder


def assert_layouts_equal(a, b):
    for field in ("start", "shape", "types", "rest", "ks", "kd", "world"):
        x, y = getattr(a, field), getattr(b, field)
        assert x.dtype == y.dtype and np.array_equal(x, y), field


def test_batch_equals_loop_built():
    datas = seed_batch(6)
    builder = make_builder(datas)
    model = builder.finalize("cpu", "float32")
    assert model.world_count == 6 and model.lattice is not None
    assert not model.has_derived("spring_indices_host")  # not made until read
    assert_particles_match(model, datas)
    assert_springs_match(model, expected_springs(datas, model))
    # The jellies' starts, and one ks per world as varied.
    ks = model.lattice.layout.ks
    assert np.array_equal(ks[:, 0], [d["jelly"][0]["springs"]["structural"]["ks"] for d in datas])
    # The recorded tables are detect_lattice's on the spring list, to the bit.
    searched = detect_lattice(list_built(make_builder(datas)))[0]
    assert_layouts_equal(model.lattice.layout, searched)


@pytest.mark.parametrize("rotate", [False, True])
def test_pile_equals_loop_built(rotate):
    data = pile(12, rotate)
    model = build_model(scene_mod.Scene(data), device="cpu")
    assert len(model.jellies) == 12 and model.lattice is not None and model.particle_contact is not None
    assert_particles_match(model, [data])
    assert_springs_match(model, expected_springs([data], model))
    b = ModelBuilder(data["simulation"]["gravity"])
    populate(b, data)
    layout, reason = detect_lattice(list_built(b))
    assert reason == "lattice"
    assert_layouts_equal(model.lattice.layout, layout)
    # The contact particles of jellies sharing a shape are each jelly's own.
    hook = model.particle_contact
    index, jelly = hook.contact_index.numpy(), hook.contact_jelly.numpy()
    assert np.all(model.particle_jelly.numpy()[index] == jelly)
    assert len(set(index.tolist())) == index.size


def test_float64_rotated_rest_lengths_are_the_lists_medians():
    """Rest lengths of a rotated lattice vary in their last bits; the table holds the list's median."""
    b = ModelBuilder()
    for n in range(5):
        b.add_jelly((5, 4, 6), (0.7, 0.3, 1.1), 0.1, SPRINGS, center=(1e3 * n, 0.1, -7.0), axis=(1.0, 2.0, 3.0),
                    degrees=33.0 + n)
    b.add_jelly((1, 2, 2), 0.5, 0.1, SPRINGS)  # too thin for some offsets and for bending
    recorded, _ = recorded_lattice(b)
    searched, _ = detect_lattice(list_built(b))
    assert np.ptp(b._rest[0]) > 0.0  # the lengths of one offset differ: which one is the median matters
    assert_layouts_equal(recorded, searched)
    assert recorded.types[-1] == 0b011 and recorded.ks[-1, 2] == 0.0  # no bending spring fits: no bending type


def test_masked_and_pinned_jellies_equal_loop_built():
    """A mesh jelly (masked lattice) beside a whole one, and a pinned jelly: the spring list as the
    loop builds it, the lattice tables as the search finds them."""
    mesh = scene_mod.load_scene("mesh_drop", ["simulation.duration=0.1"])
    model = build_model(mesh, device="cpu")
    assert model.jellies[0].lattice_index is not None
    assert_particles_match(model, [mesh.data])
    assert_springs_match(model, expected_springs([mesh.data], model))

    hang = scene_mod.load_scene("hang", ["simulation.duration=0.1"])
    model = build_model(hang, device="cpu")
    assert model.pinned_count > 0 and model.lattice is not None
    assert_particles_match(model, [hang.data])
    assert_springs_match(model, expected_springs([hang.data], model))
    pinned = np.concatenate([np.asarray(p["indices"]) for p in hang.data["pin"]])
    assert np.all(model.particle_mass_host[pinned] == 0.0)


def test_finalize_uses_the_records_not_the_search(monkeypatch):
    """A batch and a many-jelly scene take the lattice path from what the builder recorded:
    detect_lattice is not called and no spring list is made, for the model or its first steps."""

    def refuse(*_):
        raise AssertionError("called")

    monkeypatch.setattr(model_mod, "detect_lattice", refuse)
    monkeypatch.setattr(lattice_model, "detect_lattice", refuse)
    monkeypatch.setattr(LatticeSprings, "arrays", refuse)
    import softsim_warp as ss

    for model in (make_builder(seed_batch(4)).finalize("cpu", "float32"),
                  build_model(scene_mod.Scene(pile(8)), device="cpu")):
        assert model.lattice is not None and model.lattice_reason == "lattice"
        integrator = ss.make_integrator("symplectic", model)
        s0, s1 = model.state(), model.state()
        integrator.step(s0, s1, 1e-3)
        assert np.all(np.isfinite(s1.particle_q.numpy()))
        assert not model.has_derived("spring_indices_host") and not model.has_derived("spring_indices")


def test_spring_list_made_on_demand_equals_the_lists():
    """The lazily made list is the one reading the builder's lists gives (the old eager list), in
    the same order: jellies in turn, each type in turn (what --springs output reads by range)."""
    datas = seed_batch(3)
    lazy = make_builder(datas).finalize("cpu", "float64")
    eager = list_built(make_builder(datas)).finalize("cpu", "float64")
    for name in ("spring_indices_host", "spring_type_host", "spring_rest_host", "spring_stiffness_host",
                 "spring_damping_host"):
        a, b = getattr(lazy, name), getattr(eager, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    for info in lazy.jellies:
        types = lazy.spring_type_host[info.spring_start : info.spring_start + info.spring_count]
        assert np.all(np.diff(types) >= 0) and info.spring_count == sum(lattice.spring_counts(info.shape).values())
    assert np.array_equal(lazy.spring_indices.numpy(), eager.spring_indices.numpy())
    # force_path="springs" makes the device list at once from the records.
    springs = make_builder(datas).finalize("cpu", "float32", force_path="springs")
    assert springs.lattice is None and np.array_equal(springs.spring_indices.numpy(), eager.spring_indices.numpy())


def test_extra_springs_or_edited_lists_fall_back_to_the_search():
    """A spring added by hand, or the lists edited, and the builder no longer vouches for its lattices."""
    b = ModelBuilder()
    b.add_jelly((3, 3, 3), 1.0, 0.1, SPRINGS)
    assert b.lattice_records() is not None
    b.add_spring([0], [26], 5.0, 0.0)
    assert b.lattice_records() is None
    m = b.finalize("cpu")
    assert m.lattice is None and "belong to no jelly" in m.lattice_reason
    b = ModelBuilder()
    b.add_jelly((3, 3, 3), 1.0, 0.1, SPRINGS)
    b._rest[0] = b._rest[0] * np.linspace(0.9, 1.1, len(b._rest[0]))
    assert b.finalize("cpu").lattice is None


def test_varying_rest_lengths_refused_as_the_search_refuses():
    """A lattice placed so far out that its springs' lengths differ beyond REST_TOLERANCE (the
    rounding of its positions): the records refuse it with the search's reason, and the model keeps
    the spring list."""
    def build():
        b = ModelBuilder()
        b.add_jelly((3, 3, 3), 1.0, 0.1, SPRINGS)
        b.add_jelly((4, 3, 3), 1e-3, 0.1, SPRINGS, center=(1e9, 0.0, 0.0), degrees=10.0)
        return b

    recorded = recorded_lattice(build())
    searched = detect_lattice(list_built(build()))
    assert recorded[0] is None and searched[0] is None
    assert recorded[1] == searched[1] and "Jelly_1: rest lengths of offset" in recorded[1]
    m = build().finalize("cpu")
    assert m.lattice is None and m.lattice_reason == searched[1] and m.spring_count == len(m.spring_indices_host)

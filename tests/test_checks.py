"""Whole-scene checks: jelly-in-terrain by signed distance (planes, holes, registered terrain types),
the particle positions they use, and extreme-but-finite values."""

import copy
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from softsim_warp import build_model, checks, load_scene, scene_from_dict
from softsim_warp.errors import SceneError

sys.path.insert(0, str(Path(__file__).parent))
import robustness_cases as rc  # noqa: E402

BASE = tomllib.loads(rc.BASE)


def _with(**jelly):
    d = copy.deepcopy(BASE)
    d["jelly"][0].update(jelly)
    return d


@pytest.mark.parametrize("res", [[3, 3, 3], [7, 1, 4], [10, 10, 10]])
def test_check_points_are_the_model_particles(res):
    """The check sees the particles the model will have (same lattice, rotation, centre), in any chunking."""
    scene = load_scene("jelly_drop", [f"jelly.0.resolution={res}"])
    model = build_model(scene, device="cpu")
    for chunk in (1, 17, 1 << 18):
        pts = np.concatenate(list(checks.jelly_points(scene.jellies[0], chunk=chunk)))
        np.testing.assert_allclose(pts, model.particle_q_host, rtol=0, atol=1e-14)


def test_touching_the_plane_is_allowed():
    """Signed distance exactly 0 (the bottom face on the plane) is not inside: only phi < 0 is."""
    scene_from_dict(_with(center=[0.0, 0.25, 0.0]))  # size 0.5: the bottom layer at y = 0
    with pytest.raises(SceneError, match=r"9 of 27 particles are inside plane.0, the deepest by 1e-06 m"):
        scene_from_dict(_with(center=[0.0, 0.25 - 1e-6, 0.0]))


def test_particles_over_the_hole_pass_through():
    """A jelly below the plane but within its hole is not inside it (it falls through the hole)."""
    d = _with(center=[0.0, -1.0, 0.0])
    d["plane"][0]["hole"] = {"center": [0.0, 0.0, 0.0], "radius": 1.0}
    scene_from_dict(d)
    # Hole moved to x = 0.9: the layer x = -0.25 (9 particles) is 1.15 m or more from its axis.
    d["plane"][0]["hole"]["center"] = [0.9, 0.0, 0.0]
    with pytest.raises(SceneError, match=r"jelly.0.center: jelly starts inside terrain: 9 of 27 particles"):
        scene_from_dict(d)


def test_registered_terrain_types_are_checked(monkeypatch):
    """Each terrain type adds a signed-distance function; a sphere obstacle here stands in for the terrain branch."""

    def sphere(entry, pts):
        return np.linalg.norm(pts - np.asarray(entry["center"]), axis=1) - entry["radius"]

    monkeypatch.setitem(checks.TERRAIN_SDF, "sphere", sphere)
    data = scene_from_dict(BASE).data
    # Centre of a lattice cell of spacing 0.25: its 8 corners are sqrt(3) * 0.125 = 0.217 m away.
    data["sphere"] = [{"center": [0.125, 1.125, 0.125], "radius": 0.1}]
    ctx = type("Ctx", (), {"source": "s.toml", "fail": lambda self, *a: (_ for _ in ()).throw(SceneError("s.toml", *a))})()
    checks.check_terrain_overlap(data, ctx)  # no particle inside
    data["sphere"][0]["radius"] = 0.3  # holds the cell's 8 corners; the next particles are 0.415 m away
    with pytest.raises(SceneError, match=r"8 of 27 particles are inside sphere.0"):
        checks.check_terrain_overlap(data, ctx)


def test_normals_and_axes_of_extreme_size_are_normalised():
    """[1e300, 1e300, 0] is a fine direction: normalising it must not overflow to a zero vector."""
    d = copy.deepcopy(BASE)
    d["simulation"]["precision"] = "float64"
    d["plane"][0]["normal"] = [0.0, 1e300, 0.0]
    d["jelly"][0]["rotation"] = {"axis": [1e-300, 0.0, 1e-300], "degrees": 30.0}
    s = scene_from_dict(d)
    assert s.planes[0]["normal"] == [0.0, 1.0, 0.0]
    np.testing.assert_allclose(s.jellies[0]["rotation"]["axis"], [2**-0.5, 0.0, 2**-0.5], rtol=1e-15)


def test_float64_scene_accepts_what_float32_cannot_hold():
    d = _with(particle_mass=1e-40)
    with pytest.raises(SceneError, match="outside the range of float32"):
        scene_from_dict(d)
    d["simulation"]["precision"] = "float64"
    scene_from_dict(d)

"""Whole-scene checks: jelly-in-terrain by signed distance (planes, holes, registered terrain types),
the particle positions they use, and extreme-but-finite values."""

import copy
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from softsim_warp import build_model, load_scene, scene_from_dict
from softsim_warp.io import checks
from softsim_warp.core.errors import SceneError

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


class _Ctx:
    source = "s.toml"

    def fail(self, *args):
        raise SceneError(self.source, *args)


def test_registered_terrain_types_are_checked(monkeypatch):
    """Each terrain type adds a signed-distance function: a new type ("blob", a ball) is checked once registered."""

    def blob(entry, pts):
        return np.linalg.norm(pts - np.asarray(entry["center"]), axis=1) - entry["radius"]

    monkeypatch.setitem(checks.TERRAIN_SDF, "blob", blob)
    data = scene_from_dict(BASE).data
    # Centre of a lattice cell of spacing 0.25: its 8 corners are sqrt(3) * 0.125 = 0.217 m away.
    data["blob"] = [{"center": [0.125, 1.125, 0.125], "radius": 0.1}]
    checks.check_terrain_overlap(data, _Ctx())  # no particle inside
    data["blob"][0]["radius"] = 0.3  # holds the cell's 8 corners; the next particles are 0.415 m away
    with pytest.raises(SceneError, match=r"8 of 27 particles are inside blob.0"):
        checks.check_terrain_overlap(data, _Ctx())


def test_sphere_and_bowl_distances_match_the_contact_kernels():
    """The NumPy signed distances are the kernels' (kernels/contact.py), sign and cut included."""
    import warp as wp  # noqa: PLC0415

    from softsim_warp.kernels import contact as contact_kernels  # noqa: PLC0415

    rng = np.random.default_rng(5)
    pts = rng.uniform(-2, 2, size=(200, 3))
    center, radius, cut = np.array([0.1, -0.2, 0.3]), 1.3, 0.25

    @wp.kernel
    def distances(
        x: wp.array(dtype=wp.vec3d),
        c: wp.vec3d,
        r: wp.float64,
        cut: wp.float64,
        sphere: wp.array(dtype=wp.float64),
        bowl: wp.array(dtype=wp.float64),
    ):
        i = wp.tid()
        phi_s, n_s = contact_kernels.sphere_distance(x[i], c, r)
        phi_b, n_b = contact_kernels.bowl_distance(x[i], c, r, cut)
        sphere[i] = phi_s
        bowl[i] = phi_b

    sphere = wp.zeros(len(pts), dtype=wp.float64, device="cpu")
    bowl = wp.zeros(len(pts), dtype=wp.float64, device="cpu")
    wp.launch(
        distances,
        dim=len(pts),
        inputs=[wp.array(pts, dtype=wp.vec3d, device="cpu"), wp.vec3d(*center), radius, cut],
        outputs=[sphere, bowl],
        device="cpu",
    )
    np.testing.assert_allclose(
        checks.sphere_signed_distance({"center": center, "radius": radius}, pts), sphere.numpy(), rtol=0, atol=1e-12
    )
    ours = checks.bowl_signed_distance({"center": center, "radius": radius, "cut_height": cut}, pts)
    theirs = bowl.numpy()
    above = pts[:, 1] >= cut
    assert np.isinf(ours[above]).all() and (theirs[above] >= 1e30).all()
    np.testing.assert_allclose(ours[~above], theirs[~above], rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "center, ok",
    [
        ([0.0, 1.0, 0.0], True),  # the whole jelly inside the bowl's sphere, below the cut
        ([3.0, 1.0, 0.0], True),  # wholly outside: behind the shell, where the bowl lets it pass
        ([0.0, 2.45, 0.0], True),  # wholly above the cut: no bowl there
        ([1.05, 1.0, 0.0], False),  # the shell (radius 1.2) runs through the jelly
    ],
)
def test_bowl_shell_must_not_cut_the_jelly(center, ok):
    data = scene_from_dict(_with(center=center)).data
    data["bowl"] = [{"center": [0.0, 1.0, 0.0], "radius": 1.2, "cut_height": 2.2}]
    if ok:
        checks.check_terrain_overlap(data, _Ctx())
    else:
        with pytest.raises(
            SceneError, match=r"jelly starts across the shell of bowl.0: \d+ of 27 particles are behind"
        ):
            checks.check_terrain_overlap(data, _Ctx())


def test_builtin_scenes_pass_the_checks():
    from softsim_warp import builtin_scenes, load_scene  # noqa: PLC0415

    for name in builtin_scenes():
        load_scene(name)


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

"""``softsim compare`` (one world per variant, one stage) and ``softsim preview``.

The comparison's promise is that a copy is the same simulation as a single run of its variant:
the worlds of a batch share launches but no particles, springs or terrain, so each copy must
agree with ``softsim run`` to float32 rounding.
"""

import json
import math

import numpy as np
import pytest

from softsim_warp.commands import cli
from softsim_warp.io.sweep import split_values
from softsim_warp.studies.compare import prim_token, rigid_deviation, short_keys

# A small version of the 2023 scene: 4^3 particles, long enough to hit the hole's rim (t = 1.34 s)
# and slide into the bowl, at 20 frames per second.
SMALL = ["--set", "jelly.0.resolution=4", "--set", "simulation.fps=20"]
DURATION = ["--duration", "1.6"]
F32 = np.finfo(np.float32).eps


def _points(path, prim):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    attr = UsdGeom.Points(stage.GetPrimAtPath(prim)).GetPointsAttr()
    frames = range(int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode()) + 1)
    return np.array([np.asarray(attr.Get(f), dtype=np.float64) for f in frames])


def _assert_float32_equal(a, b):
    # float32 rounding: a few units in the last place of the largest coordinate.
    assert a.shape == b.shape
    scale = max(np.abs(a).max(), 1.0)
    np.testing.assert_allclose(a, b, rtol=0, atol=8 * F32 * scale)


def test_compare_stage_copies_names_and_single_run_agreement(tmp_path):
    out = tmp_path / "cmp.usda"
    metrics = tmp_path / "cmp.json"
    plot = tmp_path / "cmp.png"
    rc = cli.main(["compare", "seed_bowl", *SMALL, *DURATION, "--out", str(out), "--metrics", str(metrics),
                   "--plot", str(plot), "--quiet"])
    assert rc == 0
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(out))
    names = ["euler", "implicit", "midpoint", "rk4"]  # the default set, in the report's order
    assert [p.GetName() for p in stage.GetPrimAtPath("/World").GetChildren()] == names
    offsets = []
    for name in names:
        for child in ("Jelly_0/Particles", "Jelly_0/Surface", "Plane_0", "Bowl_0"):
            assert stage.GetPrimAtPath(f"/World/{name}/{child}").IsValid(), (name, child)
        m = UsdGeom.Xformable(stage.GetPrimAtPath(f"/World/{name}")).ComputeLocalToWorldTransform(0)
        offsets.append(np.array(m.ExtractTranslation()))
    # 2x2 grid, row by row: explicit Euler | implicit Euler over midpoint | RK4; a gap between cells.
    pitch = offsets[1][0] - offsets[0][0]
    np.testing.assert_allclose(offsets, [[0, 0, 0], [pitch, 0, 0], [0, 0, pitch], [pitch, 0, pitch]])
    # Each copy's plane is drawn one cell wide, so neighbours leave a gap between them.
    plane = np.array(UsdGeom.Mesh(stage.GetPrimAtPath("/World/euler/Plane_0")).GetPointsAttr().Get())
    width = plane[:, 0].max() - plane[:, 0].min()
    assert 0 < width < pitch
    del stage

    data = json.loads(metrics.read_text())
    assert [v["name"] for v in data["variants"]] == names
    for v in data["variants"]:
        assert len(v["frames"]) == 33 and v["exploded"] is None
        assert v["frames"][0]["deformation"] == pytest.approx(0.0, abs=1e-5)
        assert max(f["deformation"] for f in v["frames"]) > 0.01  # the landing squashes it
    assert plot.stat().st_size > 10_000

    # Each copy is the same simulation as a single run of its variant.
    for name in names:
        single = tmp_path / f"{name}.usda"
        assert cli.main(["run", "seed_bowl", *SMALL, *DURATION, "--integrator", name, "--out", str(single), "--quiet"]) == 0
        copy = _points(out, f"/World/{name}/Jelly_0/Particles")
        alone = _points(single, "/World/Jelly_0/Particles")
        assert alone[-1, :, 1].min() < 0.0  # the run got past the rim into the bowl, contact included
        _assert_float32_equal(copy, alone)


def test_compare_vary_product_names_and_agreement(tmp_path):
    out = tmp_path / "vary.usda"
    rc = cli.main(["compare", "seed_bowl", *SMALL, "--duration", "1.5", "--integrators", "euler,rk4",
                   "--vary", "jelly.0.springs.structural.ks=1000,4000", "--vary", "jelly.0.springs.shear.kd=10,60",
                   "--out", str(out), "--quiet"])
    assert rc == 0
    from pxr import Usd

    stage = Usd.Stage.Open(str(out))
    got = [p.GetName() for p in stage.GetPrimAtPath("/World").GetChildren()]
    expected = [f"{i}_ks_{k}_kd_{d}" for i in ("euler", "rk4") for k in (1000, 4000) for d in (10, 60)]
    assert got == expected
    del stage
    single = tmp_path / "single.usda"
    assert cli.main(["run", "seed_bowl", *SMALL, "--duration", "1.5", "--integrator", "rk4",
                     "--set", "jelly.0.springs.structural.ks=4000", "--set", "jelly.0.springs.shear.kd=10",
                     "--out", str(single), "--quiet"]) == 0
    _assert_float32_equal(_points(out, "/World/rk4_ks_4000_kd_10/Jelly_0/Particles"),
                          _points(single, "/World/Jelly_0/Particles"))


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--vary", "simulation.dt=0.001,0.002"], "command line: --vary: simulation.dt: every copy shares one clock"),
        (["--vary", "=1,2"], "command line: --vary: expected a dotted key such as simulation.dt before '=' (got '=1')"),
        (["--vary", "jelly.5.size=1,2"], "command line: --vary: jelly.5: index out of range"),
        (["--vary", "jelly.0.size=1,"], "command line: --vary: jelly.0.size: empty value in the list (got '1,')"),
        (["--integrators", "euler,bogus"], "--integrators: unknown integrator"),
        (["--integrators", "euler,euler"], "lists an integrator twice"),
        (["--vary", "jelly.0.springs.structural.ks=1,1"], "repeats a value"),
        (["--vary", "jelly.0.springs.structural.kz=1,2"], "unknown key; allowed: ks, kd"),
        (["--vary", "jelly.0.springs.structural.ks=-1,2"], "must be a finite number >= 0"),
    ],
)
def test_compare_bad_input_is_one_line(tmp_path, capsys, argv, needle):
    rc = cli.main(["compare", "seed_bowl", *argv, "--out", str(tmp_path / "x.usda"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and err[0].startswith("error: ") and needle in err[0], err


def test_rigid_deviation_closed_forms():
    rng = np.random.default_rng(1)
    rest = rng.normal(size=(50, 3))
    rest -= rest.mean(axis=0)
    mass = np.ones(50)
    # A rigid motion deviates by nothing.
    axis = np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + math.sin(0.7) * k + (1 - math.cos(0.7)) * k @ k
    assert rigid_deviation(rest, rest @ rot.T + [3.0, -1.0, 2.0], mass) == pytest.approx(0.0, abs=1e-12)
    # A uniform scaling by s about the centre: the best rigid fit is the rest pose itself, and the
    # residual is (s - 1) times each particle's distance from the centre: RMS = |s - 1| * RMS radius.
    s = 1.1
    rms_radius = math.sqrt(np.mean(np.sum(rest**2, axis=1)))
    assert rigid_deviation(rest, s * rest @ rot.T, mass) == pytest.approx((s - 1) * rms_radius, rel=1e-9)


def test_names_and_value_lists():
    assert split_values("1,2,[1,0,1], 'a,b'") == ["1", "2", "[1,0,1]", "'a,b'"]
    assert prim_token(0.5) == "0p5" and prim_token(1000.0) == "1000" and prim_token(-2) == "m2"
    assert prim_token([1.0, 0.0, 1.0]) == "1_0_1"
    assert short_keys(["jelly.0.springs.structural.ks", "jelly.0.springs.shear.ks", "jelly.0.center"]) == {
        "jelly.0.springs.structural.ks": "structural_ks",
        "jelly.0.springs.shear.ks": "shear_ks",
        "jelly.0.center": "center",
    }


def test_compare_with_implicit_runs_it_as_its_own_model(tmp_path):
    pytest.importorskip("softsim_warp.core.implicit")
    out = tmp_path / "imp.usda"
    assert cli.main(["compare", "seed_bowl", *SMALL, "--duration", "1.5", "--integrators", "euler,implicit",
                     "--out", str(out), "--quiet"]) == 0
    single = tmp_path / "single.usda"
    assert cli.main(["run", "seed_bowl", *SMALL, "--duration", "1.5", "--integrator", "implicit",
                     "--out", str(single), "--quiet"]) == 0
    _assert_float32_equal(_points(out, "/World/implicit/Jelly_0/Particles"), _points(single, "/World/Jelly_0/Particles"))


def test_preview_png_shows_the_jelly(tmp_path):
    usd = tmp_path / "drop.usdc"
    assert cli.main(["run", "seed_plane", "--set", "jelly.0.resolution=4", "--duration", "0.5", "--fps", "10",
                     "--out", str(usd), "--quiet"]) == 0
    png = tmp_path / "frame.png"
    assert cli.main(["preview", str(usd), "--png", str(png), "--time", "0.5"]) == 0
    from PIL import Image

    rgb = np.asarray(Image.open(png).convert("RGB"), dtype=np.float64) / 255.0
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    # The jelly is drawn in (1.0, 0.45, 0.08) times a Lambert factor: its hue survives shading,
    # g/r ~ 0.45 and b/r ~ 0.08, unlike the grey terrain (r = g = b) and the pale background.
    lit = r > 0.25
    jelly = lit & (np.abs(g / np.maximum(r, 1e-6) - 0.45) < 0.08) & (b / np.maximum(r, 1e-6) < 0.2)
    grey = (np.abs(r - g) < 0.02) & (np.abs(g - b) < 0.02) & (r < 0.9)
    assert jelly.sum() > 500, jelly.sum()
    assert grey.sum() > 500, grey.sum()


def test_preview_split_tiles_each_copy(tmp_path):
    out = tmp_path / "two.usdc"
    assert cli.main(["compare", "seed_plane", "--set", "jelly.0.resolution=4", "--duration", "0.6", "--fps", "10",
                     "--integrators", "euler,rk4", "--out", str(out), "--quiet"]) == 0
    png = tmp_path / "split.png"
    assert cli.main(["preview", str(out), "--png", str(png), "--split", "--size", "200x150"]) == 0
    from PIL import Image

    rgb = np.asarray(Image.open(png).convert("RGB"), dtype=np.float64) / 255.0
    assert rgb.shape[1] == 400  # two tiles side by side, one row
    r, g = rgb[..., 0], rgb[..., 1]
    jelly = (r > 0.25) & (np.abs(g / np.maximum(r, 1e-6) - 0.45) < 0.08)
    # Each half shows its own copy's jelly.
    assert jelly[:, :200].sum() > 50 and jelly[:, 200:].sum() > 50

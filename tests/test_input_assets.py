"""A scene's mesh files are inputs: no output may overwrite them, and an unreadable one is a one-line error.

Also the extensions of JSON outputs (reports, metrics): a JSON report is never written under a
``.usda`` name. Every case runs the real command in-process (``cli.main``) on real files and
checks the exit code (2), that stderr is one line naming the key and the file, and that the asset's
bytes are unchanged; all of them stop before any simulation.
"""

import os
import shutil
import sys
from pathlib import Path

import pytest
from pxr import Usd, UsdGeom

from softsim_warp.commands import cli
from softsim_warp.core.errors import CommandLineError
from softsim_warp.io.mesh_scene import scene_assets
from softsim_warp.io.outputs import JSON_SUFFIXES, Outputs
from softsim_warp.io.scene import load_scene
from tests.test_outputs import _one_line_error

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX files")

ASSETS = Path(__file__).resolve().parents[1] / "scenes" / "assets"
SIM = '[simulation]\nintegrator = "symplectic"\ndt = 1e-3\nframes = 2\nfps = 30\n'
SPRINGS = "springs.structural = { ks = 50.0, kd = 0.1 }\n"
BOX_JELLY = "[[jelly]]\nresolution = [3, 3, 3]\nsize = 0.2\ncenter = [0.0, 0.5, 0.0]\ntotal_mass = 0.1\n" + SPRINGS
PLANE = "[[plane]]\npoint = [0.0, 0.0, 0.0]\nnormal = [0.0, 1.0, 0.0]\n"


def _terrain_usd(path):
    """An open square of terrain, one Mesh prim."""
    stage = Usd.Stage.CreateNew(str(path))
    mesh = UsdGeom.Mesh.Define(stage, "/Terrain")
    mesh.CreatePointsAttr([(-4.0, 0.0, -4.0), (-4.0, 0.0, 4.0), (4.0, 0.0, 4.0), (4.0, 0.0, -4.0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    stage.GetRootLayer().Save()


def _terrain_scene(tmp_path, path="open.usda", name="mt.toml"):
    scene = tmp_path / name
    scene.write_text(SIM + BOX_JELLY + f'[[mesh]]\npath = "{path}"\n')
    return scene


def _jelly_scene(tmp_path, mesh="blob.usda", name="mj.toml"):
    scene = tmp_path / name
    scene.write_text(
        SIM + f'[[jelly]]\nmesh = "{mesh}"\nresolution = 4\ncenter = [0.0, 0.5, 0.0]\n'
        "total_mass = 0.1\n" + SPRINGS + PLANE
    )
    return scene


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    """tmp_path as the working directory, holding mt.toml (terrain open.usda, also linked as o.usda
    and hard-linked as h.usda) and mj.toml (a jelly of blob.usda)."""
    monkeypatch.chdir(tmp_path)
    _terrain_usd(tmp_path / "open.usda")
    shutil.copy(ASSETS / "blob.usda", tmp_path / "blob.usda")
    os.symlink("open.usda", tmp_path / "o.usda")
    os.link(tmp_path / "open.usda", tmp_path / "h.usda")
    _terrain_scene(tmp_path)
    _jelly_scene(tmp_path)
    return tmp_path


def _snapshot(directory):
    return {
        p.name: (p.read_bytes() if p.is_file() and not p.is_symlink() else os.readlink(p) if p.is_symlink() else None)
        for p in directory.iterdir()
    }


# ---------------------------------------------------------------------------------------------
# Mesh assets are inputs


OVERWRITES = [
    (["run", "mj.toml", "--out", "blob.usda"], "--out", "jelly.0.mesh", "blob.usda"),
    (["run", "mt.toml", "--out", "open.usda"], "--out", "mesh.0.path", "open.usda"),
    (["run", "mt.toml", "--out", "o.usda"], "--out", "mesh.0.path", "open.usda"),  # a symlink to the asset
    (["run", "mt.toml", "--out", "h.usda"], "--out", "mesh.0.path", "open.usda"),  # a hard link to it
    (["run", "mt.toml", "--out", "sub/../open.usda"], "--out", "mesh.0.path", "open.usda"),
    (["run", "mt.toml", "--out", "x.usda", "--metrics", "open.usda"], "--metrics", "mesh.0.path", "open.usda"),
    (["run", "mj.toml", "--out", "x.usda", "--preview", "blob.usda"], "--preview", "jelly.0.mesh", "blob.usda"),
    (["compare", "mt.toml", "--integrators", "symplectic", "--out", "open.usda"], "--out", "mesh.0.path", "open.usda"),
    (["compare", "mj.toml", "--integrators", "symplectic", "--out", "blob.usda"], "--out", "jelly.0.mesh", "blob.usda"),
    (
        ["compare", "mt.toml", "--integrators", "symplectic", "--out", "x.usda", "--metrics", "o.usda"],
        "--metrics",
        "mesh.0.path",
        "open.usda",
    ),
    (
        ["accuracy", "mt.toml", "--integrators", "symplectic", "--dts", "1e-3", "--out", "open.usda"],
        "--out",
        "mesh.0.path",
        "open.usda",
    ),
    (
        ["accuracy", "mj.toml", "--integrators", "symplectic", "--dts", "1e-3", "--plot", "blob.usda"],
        "--plot",
        "jelly.0.mesh",
        "blob.usda",
    ),
    (
        ["stability", "mt.toml", "--integrators", "symplectic", "--out", "open.usda"],
        "--out",
        "mesh.0.path",
        "open.usda",
    ),
    (
        ["stability", "mj.toml", "--integrators", "symplectic", "--out", "blob.usda"],
        "--out",
        "jelly.0.mesh",
        "blob.usda",
    ),
    (["bench", "--scene", "mt.toml", "--out", "open.usda"], "--out", "mesh.0.path", "open.usda"),
    (["bench", "--scene", "mj.toml", "--plot", "blob.usda"], "--plot", "jelly.0.mesh", "blob.usda"),
    # An overridden path is the file the run reads.
    (["run", "mt.toml", "--set", 'mesh.0.path="h.usda"', "--out", "h.usda"], "--out", "mesh.0.path", "h.usda"),
]


@pytest.mark.parametrize("argv, flag, key, asset", OVERWRITES, ids=[" ".join(c[0]) for c in OVERWRITES])
def test_outputs_never_overwrite_a_mesh_asset(workdir, capsys, argv, flag, key, asset):
    (workdir / "sub").mkdir()
    before = _snapshot(workdir)
    assert cli.main(argv + ["--quiet"]) == 2
    line = _one_line_error(capsys, f"{flag}: would overwrite the input {key}", str(workdir / asset))
    assert "Traceback" not in line
    assert _snapshot(workdir) == before  # the asset's bytes, and no output or temporary left


def test_sweep_output_never_overwrites_a_mesh_asset(workdir, capsys):
    pytest.importorskip("pyarrow")
    pytest.importorskip("distributed")
    before = _snapshot(workdir)
    argv = ["sweep", "mt.toml", "--vary", "simulation.dt=1e-3,5e-4", "--out", "open.usda", "--quiet"]
    assert cli.main(argv) == 2
    _one_line_error(capsys, "--out: would overwrite the input mesh.0.path", str(workdir / "open.usda"))
    assert _snapshot(workdir) == before


def test_a_run_with_mesh_assets_leaves_them_alone(workdir, capsys):
    before = {name: (workdir / name).read_bytes() for name in ("open.usda", "blob.usda")}
    assert cli.main(["run", "mt.toml", "--out", "out.usda", "--metrics", "m.json", "--quiet"]) == 0
    assert cli.main(["run", "mj.toml", "--out", "out2.usdc", "--quiet"]) == 0
    assert {name: (workdir / name).read_bytes() for name in before} == before
    assert (workdir / "out.usda").stat().st_size > 0 and (workdir / "m.json").stat().st_size > 0


def test_scene_assets_of_a_validated_scene(workdir):
    (workdir / "both.toml").write_text(
        SIM
        + '[[jelly]]\nmesh = "blob.usda"\nresolution = 4\ncenter = [0.0, 0.5, 0.0]\ntotal_mass = 0.1\n'
        + SPRINGS
        + BOX_JELLY.replace("0.5, 0.0]", "1.5, 0.0]")
        + '[[mesh]]\npath = "open.usda"\n[[mesh]]\npath = "o.usda"\n'
    )
    expected = [
        ("mesh.0.path", workdir / "open.usda"),
        ("mesh.1.path", workdir / "o.usda"),
        ("jelly.0.mesh", workdir / "blob.usda"),
    ]
    assert scene_assets(load_scene("both.toml").data) == expected
    # --set values count: the files the scene reads after them.
    changed = load_scene("both.toml", ['mesh.1.path="open.usda"']).data
    assert scene_assets(changed)[1] == ("mesh.1.path", workdir / "open.usda")
    assert scene_assets(load_scene("jelly_drop").data) == []


# ---------------------------------------------------------------------------------------------
# Unreadable mesh files


NOT_USD = b"hello"
BAD_USDA = b'#usda 1.0\ndef Mesh "A" {\n  point3f[] points = [(0,0\n'
BAD_FILES = [
    ("bad.usdc", NOT_USD, "cannot be read as USD (File too small"),
    ("bad.usda", BAD_USDA, "cannot be read as USD ("),
    ("bad.usd", NOT_USD, "cannot be read as USD ("),
    ("empty.usda", b"", "cannot be read as USD ("),
    ("bad.obj", NOT_USD, "the mesh has no faces"),
    ("bad.stl", NOT_USD, "the mesh has no faces"),
    ("bad.ply", NOT_USD, "cannot read the mesh"),
]


@pytest.mark.parametrize("name, content, message", BAD_FILES, ids=[c[0] for c in BAD_FILES])
@pytest.mark.parametrize("role", ["terrain", "jelly"])
def test_unreadable_mesh_file_is_a_one_line_error(tmp_path, monkeypatch, capsys, name, content, message, role):
    if name.endswith((".obj", ".stl", ".ply")):
        pytest.importorskip("trimesh")
    monkeypatch.chdir(tmp_path)
    (tmp_path / name).write_bytes(content)
    scene, key = (
        (_terrain_scene(tmp_path, name), "mesh.0.path")
        if role == "terrain"
        else (_jelly_scene(tmp_path, name), "jelly.0.mesh")
    )
    assert cli.main(["run", scene.name, "--out", "x.usdc", "--quiet"]) == 2
    line = _one_line_error(capsys, f"error: {scene.name}: {key}: {message}", str(tmp_path / name))
    if name.endswith((".usd", ".usda", ".usdc")):
        assert "give a USD file with a Mesh" in line and "pxrInternal" not in line
    assert (tmp_path / name).read_bytes() == content
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([name, scene.name])


# ---------------------------------------------------------------------------------------------
# Extensions of JSON outputs


EXTENSIONS = [
    (["accuracy", "mt.toml", "--integrators", "symplectic", "--dts", "1e-3", "--out", "a.usda"], "--out", "a.usda"),
    (["stability", "mt.toml", "--integrators", "symplectic", "--out", "s.usda"], "--out", "s.usda"),
    (["run", "mt.toml", "--out", "o2.usda", "--metrics", "m.usdc"], "--metrics", "m.usdc"),
    (["run", "mt.toml", "--out", "o2.usda", "--metrics", "m.txt"], "--metrics", "m.txt"),
    (
        ["compare", "mt.toml", "--integrators", "symplectic", "--out", "c.usdc", "--metrics", "m.usdc"],
        "--metrics",
        "m.usdc",
    ),
    (["compare", "mt.toml", "--integrators", "symplectic", "--out", "c.usdc", "--plot", "p.svg"], "--plot", "p.svg"),
]


@pytest.mark.parametrize("argv, flag, value", EXTENSIONS, ids=[" ".join(c[0]) for c in EXTENSIONS])
def test_json_outputs_need_a_json_extension(workdir, capsys, argv, flag, value):
    before = _snapshot(workdir)
    assert cli.main(argv + ["--quiet"]) == 2
    _one_line_error(capsys, f"command line: {flag}: unsupported file extension; use .", f"(got '{value}')")
    assert _snapshot(workdir) == before


def test_json_outputs_may_be_streams(tmp_path):
    """A device or FIFO takes JSON whatever its name; a USD or plot output still needs its extension."""
    fifo = tmp_path / "report.fifo"
    os.mkfifo(fifo)
    outputs = Outputs()
    assert outputs.add("--metrics", "/dev/null", JSON_SUFFIXES, streams=True) == Path("/dev/null")
    assert outputs.add("--out", str(fifo), JSON_SUFFIXES, streams=True) == fifo
    with pytest.raises(CommandLineError, match="unsupported file extension"):
        outputs.add("--plot", "/dev/null", (".png",))
    with pytest.raises(CommandLineError, match="unsupported file extension; use .json"):
        outputs.add("--out", str(tmp_path / "r.usda"), JSON_SUFFIXES, streams=True)
    assert fifo.is_fifo() and sorted(p.name for p in tmp_path.iterdir()) == ["report.fifo"]

"""`softsim preview` on unusual input: one-line errors, no output left behind, and GIFs streamed.

Every refused case goes through ``cli.main(["preview", ...])`` in-process: exit code 2, exactly one
stderr line (read at the file-descriptor level, so USD's own C++ diagnostics would show) that
starts with ``error:`` and names the file, and nothing left in the output folder (no GIF/PNG, no
hidden ``.*partial-*`` temporary, no lock). The stages are small and written with pxr here.
"""

import math
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

pytest.importorskip("pxr")
pytest.importorskip("matplotlib")

from softsim_warp.commands import cli
from softsim_warp.io import preview
from tests.test_preview import FPS, jelly_fraction, write_stage

SIZE = "96x72"


# --------------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------------


def _edit(path, fn):
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))
    fn(stage)
    stage.GetRootLayer().Save()
    return path


def _jelly_points(stage):
    from pxr import UsdGeom

    return UsdGeom.Mesh(stage.GetPrimAtPath("/World/Jelly_0/Surface")).GetPointsAttr()


def _usda(path, text):
    path.write_text("#usda 1.0\n" + textwrap.dedent(text))
    return path


def _preview(capfd, *argv):
    """Run ``softsim preview`` in-process; returns ``(exit code, stderr lines)``."""
    capfd.readouterr()
    rc = cli.main(["preview", *[str(a) for a in argv]])
    out, err = capfd.readouterr()
    assert out == ""
    return rc, [line for line in err.splitlines() if line.strip()]


def assert_refused(capfd, tmp_path, usd, *needles, flags=("--png", "--gif")):
    """Both --png and --gif are refused with one line naming the file; nothing is left behind."""
    outdir = tmp_path / "out"
    outdir.mkdir(exist_ok=True)
    for flag in flags:
        out = outdir / ("x.png" if flag == "--png" else "x.gif")
        rc, err = _preview(capfd, usd, flag, out, "--size", SIZE)
        assert rc == 2, err
        assert len(err) == 1, err
        assert err[0].startswith("error: "), err
        assert str(usd) in err[0], err
        for needle in needles:
            assert needle in err[0], err
        assert sorted(os.listdir(outdir)) == [], "output or temporary left behind"


def assert_rendered(capfd, tmp_path, usd, frames=None, png=True):
    """--png and --gif succeed with one line each; returns the PNG path and the GIF's frame count."""
    from PIL import Image

    png_path, gif_path = tmp_path / "x.png", tmp_path / "x.gif"
    if png:
        rc, err = _preview(capfd, usd, "--png", png_path, "--size", SIZE)
        assert (rc, len(err)) == (0, 1), err
        assert png_path.is_file()
    rc, err = _preview(capfd, usd, "--gif", gif_path, "--size", SIZE)
    assert (rc, len(err)) == (0, 1), err
    with Image.open(gif_path) as im:
        n = im.n_frames
    assert f"{n} frames" in err[0]
    if frames is not None:
        assert n == frames
    assert [p for p in os.listdir(tmp_path) if ".partial-" in p or p.endswith(".lock")] == []
    return png_path, n


@pytest.fixture
def small(tmp_path):
    """A softsim-layout stage: a jelly falling onto a plane over 3 frames."""
    return write_stage(tmp_path / "small.usda", np.linspace(2.0, 0.5, 3))


@pytest.mark.parametrize(
    "flags, line",
    [
        (["--frame", "99"], "--frame: out of range, allowed 0..2 (got 99)"),
        (["--time", "100"], "--time: out of range, allowed 0..0.0666667 s (got 100)"),
        (["--size", "0x0"], "--size: must be (width, height) in pixels, 16..8192 (got (0, 0))"),
    ],
)
def test_bad_value_names_its_flag_and_value(capfd, tmp_path, small, flags, line):
    """Every refusal reads ``<file>: <flag>: <what is wrong> (got <value>)``."""
    rc, err = _preview(capfd, small, "--png", tmp_path / "p.png", *flags)
    assert rc == 2 and err == [f"error: {small}: {line}"]


def test_missing_file_names_the_usd_and_its_path(capfd, tmp_path):
    path = tmp_path / "nope.usdc"
    rc, err = _preview(capfd, path, "--png", tmp_path / "p.png")
    assert rc == 2 and err == [f"error: {path}: usd: USD file not found (got '{path}')"]


# --------------------------------------------------------------------------------------------------
# Files that are not USD
# --------------------------------------------------------------------------------------------------


def test_text_file_is_not_usd(capfd, tmp_path):
    path = tmp_path / "notes.usda"
    path.write_text("this is not USD\n")
    assert_refused(capfd, tmp_path, path, "cannot open as USD")


def test_truncated_usdc_is_not_usd(capfd, tmp_path):
    good = write_stage(tmp_path / "good.usdc", np.linspace(2.0, 0.5, 3))
    data = good.read_bytes()
    for keep in (len(data) // 2, 100, 10):
        path = tmp_path / f"cut{keep}.usdc"
        path.write_bytes(data[:keep])
        assert_refused(capfd, tmp_path, path, "cannot open as USD")


def test_empty_file_is_not_usd(capfd, tmp_path):
    for name in ("empty.usdc", "empty.usda"):
        path = tmp_path / name
        path.write_bytes(b"")
        assert_refused(capfd, tmp_path, path, "cannot open as USD", "empty")


def test_folder_is_not_usd(capfd, tmp_path):
    path = tmp_path / "x.usdc"
    path.mkdir()
    assert_refused(capfd, tmp_path, path, "cannot open as USD", "folder")


def test_fifo_is_refused_without_blocking(capfd, tmp_path):
    path = tmp_path / "pipe.usda"
    os.mkfifo(path)  # opening it to read would wait for a writer forever
    assert_refused(capfd, tmp_path, path, "cannot open as USD", "not a regular file")


# --------------------------------------------------------------------------------------------------
# Stages with nothing to draw, or a broken time range
# --------------------------------------------------------------------------------------------------


def test_stage_without_drawable_geometry(capfd, tmp_path):
    cube = _usda(tmp_path / "cube.usda", 'def Xform "Root" {\n    def Cube "Box" {}\n}\n')
    assert_refused(capfd, tmp_path, cube, "nothing to draw", "Cube")
    empty = _usda(tmp_path / "nothing.usda", "")
    assert_refused(capfd, tmp_path, empty, "nothing to draw", "no geometry")


def test_points_of_the_wrong_type_or_malformed_faces(capfd, tmp_path):
    wrong = _usda(tmp_path / "wrong.usda", """\
        def Mesh "Thing"
        {
            int[] faceVertexCounts = [3]
            int[] faceVertexIndices = [0, 1, 2]
            float[] points.timeSamples = { 0: [1, 2, 3, 4], 1: [1, 2, 3] }
        }
        """)
    assert_refused(capfd, tmp_path, wrong, "nothing to draw", "/Thing.points holds FloatArray")
    text = _usda(tmp_path / "text.usda", 'def Mesh "Thing"\n{\n    string points = "hello"\n}\n')
    assert_refused(capfd, tmp_path, text, "nothing to draw", "/Thing.points")
    negative = _usda(tmp_path / "negative.usda", """\
        def Mesh "Thing"
        {
            int[] faceVertexCounts = [3]
            int[] faceVertexIndices = [0, -1, 2]
            point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
        }
        """)
    assert_refused(capfd, tmp_path, negative, "nothing to draw", "malformed")


@pytest.mark.parametrize(
    "start, end, needle",
    [
        (10, 0, "startTimeCode is after endTimeCode (got 10..0)"),
        (0, math.nan, "endTimeCode must be a finite number (got nan)"),
        (-math.inf, 2, "startTimeCode must be a finite number (got -inf)"),
        (0, math.inf, "endTimeCode must be a finite number (got inf)"),
    ],
)
def test_broken_time_range(capfd, tmp_path, small, start, end, needle):
    _edit(small, lambda s: (s.SetStartTimeCode(start), s.SetEndTimeCode(end)))
    assert_refused(capfd, tmp_path, small, needle)


@pytest.mark.parametrize("tcps", [0.0, -5.0, math.nan, math.inf])
def test_broken_time_codes_per_second(capfd, tmp_path, small, tcps):
    _edit(small, lambda s: s.SetTimeCodesPerSecond(tcps))
    assert_refused(capfd, tmp_path, small, "timeCodesPerSecond must be a finite number > 0")


def _poison_points(stage, change):
    """Apply ``change`` (in place, to a NumPy copy) to the jelly's points at every time sample."""
    from pxr import Vt

    attr = _jelly_points(stage)
    for t in attr.GetTimeSamples():
        v = np.array(attr.Get(t))
        change(v)
        attr.Set(Vt.Vec3fArray.FromNumpy(v.astype(np.float32)), t)


def test_points_never_finite_and_no_terrain(capfd, tmp_path, small):
    from pxr import Sdf

    def change(v):
        v[::2], v[1::2] = np.nan, np.inf

    def poison(stage):
        _poison_points(stage, change)
        stage.RemovePrim(Sdf.Path("/World/Plane_0"))

    _edit(small, poison)
    assert_refused(capfd, tmp_path, small, "nothing to draw", "NaN, inf")


def test_read_error_inside_a_frame_is_one_line(capfd, tmp_path, small, monkeypatch):
    """A damaged file may open and fail only when a frame's points are read."""
    from pxr import Tf

    real = preview._read

    class Damaged:
        def __init__(self, attr):
            self.attr = attr

        def Get(self, time):
            raise Tf.ErrorException("Error in 'crate' at line 1 in file x.cpp : 'corrupt data'")

        def GetPrim(self):
            return self.attr.GetPrim()

    def failing(path, attr, time, what="points"):
        if not time.IsEarliestTime() and time.GetValue() >= 1:
            attr = Damaged(attr)
        return real(path, attr, time, what)

    monkeypatch.setattr(preview, "_read", failing)
    assert_refused(capfd, tmp_path, small, "cannot read the points of /World/Jelly_0/Surface")


def test_error_while_the_gif_streams_leaves_nothing(capfd, tmp_path, monkeypatch):
    """A frame that fails halfway through the GIF: the partly written temporary is removed."""
    path = write_stage(tmp_path / "ten.usda", np.linspace(2.0, 0.5, 10))
    real, calls = preview._Renderer.render_rgb, []

    def render_rgb(self, frame):
        calls.append(frame)
        if len(calls) == 3 + 5:  # palette frames, then 4 frames written
            assert [p for p in os.listdir(tmp_path / "out") if ".partial-" in p], "not streaming"
            raise ValueError(f"{path}: cannot read the points of /World/Jelly_0/Surface (test)")
        return real(self, frame)

    monkeypatch.setattr(preview._Renderer, "render_rgb", render_rgb)
    assert_refused(capfd, tmp_path, path, "cannot read the points", flags=("--gif",))
    assert len(calls) == 8


# --------------------------------------------------------------------------------------------------
# Unusual stages that do render
# --------------------------------------------------------------------------------------------------


def test_static_stage_renders_one_frame(capfd, tmp_path):
    """No time samples at all: --png renders the stage, --gif a one-frame GIF."""
    path = tmp_path / "static.usda"
    write_stage(path, [0.5])

    def make_static(stage):
        attr = _jelly_points(stage)
        value = attr.Get(0)
        attr.Clear()
        attr.Set(value)
        stage.GetRootLayer().ClearStartTimeCode()
        stage.GetRootLayer().ClearEndTimeCode()

    from pxr import Usd

    _edit(path, make_static)
    assert _jelly_points(Usd.Stage.Open(str(path))).GetNumTimeSamples() == 0
    png, _ = assert_rendered(capfd, tmp_path, path, frames=1)
    assert jelly_fraction(png)[0] > 0.02  # the Jelly_0 mesh is drawn as jelly, not as grey terrain


def test_static_point_cloud_is_drawn(capfd, tmp_path):
    path = _usda(tmp_path / "cloud.usda", 'def Points "Cloud"\n{\n    point3f[] points = ['
                 + ", ".join(f"({i}, {i % 3}, 0)" for i in range(20)) + "]\n}\n")
    png, _ = assert_rendered(capfd, tmp_path, path, frames=1)
    assert jelly_fraction(png)[0] > 0.005


def test_other_prim_layout_renders(capfd, tmp_path):
    """No /World, no softsim names: a moving mesh anywhere is drawn as jelly, over a static one."""
    from pxr import Gf, Usd, UsdGeom, Vt

    path = tmp_path / "other.usdc"
    stage = Usd.Stage.CreateNew(str(path))
    stage.SetTimeCodesPerSecond(FPS)  # no start/end: the range comes from the samples
    ground = UsdGeom.Mesh.Define(stage, "/Root/Ground")
    ground.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(x, 0, z) for x, z in ((-3, -3), (3, -3), (3, 3), (-3, 3))]))
    ground.CreateFaceVertexCountsAttr([4])
    ground.CreateFaceVertexIndicesAttr([0, 3, 2, 1])
    thing = UsdGeom.Mesh.Define(stage, "/Root/Things/Thing")
    thing.CreateFaceVertexCountsAttr([4, 4])
    thing.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 3, 2, 1, 0])
    attr = thing.CreatePointsAttr()
    for t in range(5, 12):
        y = 2.0 - 0.2 * (t - 5)
        quad = [Gf.Vec3f(-1, y, 0), Gf.Vec3f(1, y, 0), Gf.Vec3f(1, y + 2, 0), Gf.Vec3f(-1, y + 2, 0)]
        attr.Set(Vt.Vec3fArray(quad), t)
    stage.GetRootLayer().Save()
    png, _ = assert_rendered(capfd, tmp_path, path, frames=7)
    assert jelly_fraction(png)[0] > 0.02


def test_nonfinite_points_are_left_out(capfd, tmp_path, small):
    def change(v):
        v[::7], v[3::11] = np.nan, np.inf
        v[5] = 3e38  # finite, absurd

    def poison(stage):
        _poison_points(stage, change)

    _edit(small, poison)
    png, _ = assert_rendered(capfd, tmp_path, small, frames=3)  # one line each: no RuntimeWarning
    assert jelly_fraction(png)[0] > 0.01


def test_huge_end_time_code_caps_the_gif(capfd, tmp_path, small, monkeypatch):
    """endTimeCode = 1e9: the PNG shows the last frame, the GIF is capped (stepped evenly) and quick."""
    from PIL import Image

    _edit(small, lambda s: s.SetEndTimeCode(1e9))
    monkeypatch.setattr(preview, "MAX_GIF_FRAMES", 40)  # the default (2000) would take seconds
    _, n = assert_rendered(capfd, tmp_path, small, frames=40)
    with Image.open(tmp_path / "x.gif") as im:
        im.seek(1)
        assert im.info["duration"] == 10 * preview.MAX_GIF_DELAY_CS  # GIF's longest delay, not an overflow


def test_many_time_samples_are_not_all_read(capfd, tmp_path, monkeypatch):
    """10^5 time samples: the camera is framed from at most BBOX_SAMPLES of them per prim."""
    from pxr import Gf, Sdf, Usd, UsdGeom, Vt

    n = 10**5
    path = tmp_path / "many.usdc"
    layer = Sdf.Layer.CreateNew(str(path))
    stage = Usd.Stage.Open(layer)
    stage.SetTimeCodesPerSecond(60)
    spec = UsdGeom.Points.Define(stage, "/Cloud").CreatePointsAttr().GetPath()
    with Sdf.ChangeBlock():
        for t in range(n):
            a = 0.01 * t
            layer.SetTimeSample(spec, t, Vt.Vec3fArray([Gf.Vec3f(math.sin(a), 1 + math.cos(a), 0), Gf.Vec3f(0, 0, 0)]))
    layer.Save()
    del stage, layer

    reads = []
    real = preview._Deforming.points
    monkeypatch.setattr(preview._Deforming, "points", lambda self, frame: reads.append(frame) or real(self, frame))
    monkeypatch.setattr(preview, "MAX_GIF_FRAMES", 30)
    assert_rendered(capfd, tmp_path, path, frames=30)
    # Per command: <= 2 * BBOX_SAMPLES to frame the camera (bracketing), 1 setup, the frames drawn.
    assert len(reads) <= 2 * (2 * preview.BBOX_SAMPLES + 1 + 3 + 30)


def test_gif_frames_are_computed_not_listed():
    frames, step = preview._gif_frames(0.0, 1e9, 30.0, 30.0, preview.MAX_GIF_FRAMES)
    assert isinstance(frames, range) and len(frames) == preview.MAX_GIF_FRAMES == 2000
    assert frames[0] == 0 and frames[-1] <= 1e9 < frames[-1] + step
    frames, step = preview._gif_frames(-1e308, 1e308, 24.0, 24.0, 2000)  # 2e308 codes: no overflow
    assert len(frames) == 2000
    frames, step = preview._gif_frames(0.0, 100.0, 30.0, 1e-300, 2000)  # tiny fps: one frame
    assert list(frames) == [0]
    frames, step = preview._gif_frames(0.3, 0.7, 30.0, 30.0, 2000)  # no integer code in range
    assert list(frames) == [0.3]
    delays = list(preview._gif_delays(100, 1, 30.0))
    assert sum(delays) == round(100 / 30 * 100)  # real time, in centiseconds
    assert list(preview._gif_delays(3, 10**300, 1e-300)) == [preview.MAX_GIF_DELAY_CS] * 3


# --------------------------------------------------------------------------------------------------
# Streaming GIF writer
# --------------------------------------------------------------------------------------------------


def test_streamed_gif_decodes_like_pillows(tmp_path):
    """The streamed writer's GIF decodes to the same frames as Pillow's own writer; identical
    consecutive frames are kept (Pillow would merge them), with their delays."""
    from PIL import Image

    rng = np.random.default_rng(0)
    h, w = 30, 40
    palette = rng.integers(0, 256, 3 * 200).tolist()
    frames = []
    base = rng.integers(0, 200, (h, w)).astype(np.uint8)
    for k in range(8):
        f = base.copy()
        f[5 + k : 12 + k, 3 * k : 3 * k + 9] = 10 + k  # a moving block
        frames.append(f)
    delays = [3, 4, 3, 3, 4, 3, 3, 4]
    ours = tmp_path / "ours.gif"
    assert preview._write_gif(ours, (w, h), palette, iter(frames), iter(delays)) == 8
    images = []
    for f in frames:
        im = Image.frombytes("P", (w, h), f.tobytes())
        im.putpalette(palette)
        images.append(im)
    theirs = tmp_path / "theirs.gif"
    images[0].save(theirs, save_all=True, append_images=images[1:], duration=[10 * d for d in delays], loop=0,
                   optimize=False)

    def decode(path):
        out = []
        with Image.open(path) as im:
            for i in range(im.n_frames):
                im.seek(i)
                out.append((np.asarray(im.convert("RGB")), im.info["duration"]))
        return out

    a, b = decode(ours), decode(theirs)
    assert len(a) == len(b) == 8
    for (fa, da), (fb, db) in zip(a, b):
        assert np.array_equal(fa, fb) and da == db

    same = tmp_path / "same.gif"
    assert preview._write_gif(same, (w, h), palette, iter([frames[0]] * 3), iter([5, 5, 5])) == 3
    c = decode(same)
    assert len(c) == 3 and all(np.array_equal(f, a[0][0]) and d == 50 for f, d in c)


MEMORY_PROBE = """
import resource, sys
import numpy as np
from softsim_warp.io.preview import render_gif
from tests.test_preview import write_stage
d, n = sys.argv[1], int(sys.argv[2])
warm = write_stage(d + "/warm.usdc", 1.0 + 0.5 * np.sin(0.1 * np.arange(5)))
clip = write_stage(d + "/clip.usdc", 1.0 + 0.5 * np.sin(0.1 * np.arange(n)))
render_gif(warm, d + "/warm.gif", size=(320, 240))  # imports, figure, caches: the baseline
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
count = render_gif(clip, d + "/clip.gif", size=(320, 240))
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(count, (after - before) * 1024)
"""


def test_gif_memory_does_not_grow_with_frames(tmp_path):
    """600 frames of 320x240: the peak memory (max RSS of a fresh process, after a warm-up GIF) grows
    by well under 20 frames' worth. Holding the frames (Pillow's save_all) took ~93 MB here, about
    400 RGB frames; the streamed writer ~2 MB. (tracemalloc does not see Pillow's image memory.)"""
    from PIL import Image

    n = 600
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.run([sys.executable, "-c", MEMORY_PROBE, str(tmp_path), str(n)], cwd=root,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    count, grown = (int(v) for v in proc.stdout.split()[-2:])
    assert count == n
    with Image.open(tmp_path / "clip.gif") as im:
        assert im.n_frames == n
    frame_bytes = 320 * 240 * 3
    assert grown < 20 * frame_bytes, f"peak memory grew by {grown / 1e6:.1f} MB for {n} frames"

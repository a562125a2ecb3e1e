"""Headless preview renderer: synthetic softsim-layout USD files rendered to PNG and GIF."""

import numpy as np
import pytest

pytest.importorskip("pxr")
pytest.importorskip("matplotlib")

from softsim_warp.io.preview import render_gif, render_png

FPS = 30
FRAMES = 10
SIZE = (320, 240)


def _cube_surface(n=4, size=1.0):
    """Points of an n^3 lattice centred on the origin and its boundary quads, wound outward."""
    axis = np.linspace(-0.5 * size, 0.5 * size, n)
    pts = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)

    def idx(i, j, k):
        return (i * n + j) * n + k

    quads = []
    for ax in range(3):
        for side in (0, n - 1):
            for a in range(n - 1):
                for b in range(n - 1):
                    q = []
                    for da, db in ((0, 0), (1, 0), (1, 1), (0, 1)):
                        c = [0, 0, 0]
                        c[ax] = side
                        c[(ax + 1) % 3] = a + da
                        c[(ax + 2) % 3] = b + db
                        q.append(idx(*c))
                    p = pts[q]
                    normal = np.cross(p[1] - p[0], p[2] - p[0])
                    if np.dot(normal, p.mean(axis=0)) < 0:  # make it point away from the centre
                        q = q[::-1]
                    quads.append(q)
    return pts, np.array(quads)


def write_stage(path, centers_y, plane_half=3.0, jelly_root="/World", root_translate=None, points_only=False):
    """A softsim-layout stage: a jelly whose centre moves through ``centers_y`` (one per frame) over a
    static ground quad at y = 0."""
    from pxr import Gf, Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    stage.SetTimeCodesPerSecond(FPS)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(len(centers_y) - 1)
    if jelly_root != "/World":
        xf = UsdGeom.Xform.Define(stage, jelly_root)
        if root_translate is not None:
            xf.AddTranslateOp().Set(Gf.Vec3d(*root_translate))
    pts, quads = _cube_surface()
    if points_only:
        prim = UsdGeom.Points.Define(stage, f"{jelly_root}/Jelly_0/Particles")
        prim.CreateWidthsAttr(Vt.FloatArray([0.15] * len(pts)))
    else:
        prim = UsdGeom.Mesh.Define(stage, f"{jelly_root}/Jelly_0/Surface")
        prim.CreateFaceVertexCountsAttr(Vt.IntArray([4] * len(quads)))
        prim.CreateFaceVertexIndicesAttr(Vt.IntArray(quads.ravel().tolist()))
    attr = prim.CreatePointsAttr()
    for frame, y in enumerate(centers_y):
        attr.Set(Vt.Vec3fArray.FromNumpy((pts + [0.0, y, 0.0]).astype(np.float32)), frame)
    plane = UsdGeom.Mesh.Define(stage, "/World/Plane_0")
    h = plane_half
    corners = [Gf.Vec3f(-h, 0, -h), Gf.Vec3f(h, 0, -h), Gf.Vec3f(h, 0, h), Gf.Vec3f(-h, 0, h)]
    plane.CreatePointsAttr(Vt.Vec3fArray(corners))
    plane.CreateFaceVertexCountsAttr(Vt.IntArray([4]))
    plane.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 3, 2, 1]))
    plane.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray([Gf.Vec3f(0.5, 0.5, 0.5)]))
    stage.GetRootLayer().Save()
    return path


def jelly_fraction(png_path):
    """Fraction of pixels of the jelly's orange hue (saturated, not too dark)."""
    from matplotlib.colors import rgb_to_hsv
    from matplotlib.image import imread

    rgb = imread(str(png_path))[..., :3].astype(np.float64)
    if rgb.max() > 1.0:
        rgb = rgb / 255.0
    hsv = rgb_to_hsv(rgb)
    mask = (hsv[..., 0] > 0.03) & (hsv[..., 0] < 0.11) & (hsv[..., 1] > 0.5) & (hsv[..., 2] > 0.15)
    return mask.mean(), rgb


@pytest.fixture(scope="module")
def landing(tmp_path_factory):
    """The jelly falls from y = 2 to rest on the ground (bottom at y = 0) over 10 frames."""
    path = tmp_path_factory.mktemp("preview") / "landing.usda"
    return write_stage(path, np.linspace(2.0, 0.5, FRAMES))


@pytest.fixture(scope="module")
def sinking(tmp_path_factory):
    """The jelly passes through a large opaque ground plane: above it at frame 0, below it at the end."""
    path = tmp_path_factory.mktemp("preview") / "sinking.usdc"
    return write_stage(path, np.linspace(1.5, -1.5, FRAMES), plane_half=8.0)


def test_png_shows_the_jelly(landing, tmp_path):
    out = tmp_path / "last.png"
    frame = render_png(landing, out, size=SIZE)
    assert frame == FRAMES - 1
    frac, rgb = jelly_fraction(out)
    assert rgb.shape[:2] == (SIZE[1], SIZE[0])
    assert frac > 0.02
    assert len(np.unique(rgb.reshape(-1, 3), axis=0)) > 20  # not one flat colour
    assert rgb.std() > 0.05


def test_jelly_under_an_opaque_plane_is_hidden(sinking, tmp_path):
    above, below = tmp_path / "above.png", tmp_path / "below.png"
    render_png(sinking, above, frame=0, size=SIZE)
    render_png(sinking, below, frame=FRAMES - 1, size=SIZE)
    assert jelly_fraction(above)[0] > 0.02
    assert jelly_fraction(below)[0] == 0.0


def test_world_transform_of_a_variant_is_applied(tmp_path):
    # In its own frame the jelly stays 1.5 m above the ground; its parent Xform moves it 3 m down,
    # so in the world it sinks from above the plane to under it.
    path = write_stage(
        tmp_path / "variant.usda",
        np.linspace(4.5, 1.5, FRAMES),
        plane_half=8.0,
        jelly_root="/World/Sunk",
        root_translate=(0.0, -3.0, 0.0),
    )
    render_png(path, tmp_path / "above.png", frame=0, size=SIZE)
    render_png(path, tmp_path / "below.png", size=SIZE)
    assert jelly_fraction(tmp_path / "above.png")[0] > 0.02
    assert jelly_fraction(tmp_path / "below.png")[0] == 0.0


def test_points_are_drawn_when_there_is_no_surface(tmp_path):
    path = write_stage(tmp_path / "points.usda", np.linspace(1.0, 0.5, 3), points_only=True)
    render_png(path, tmp_path / "p.png", size=SIZE)
    assert jelly_fraction(tmp_path / "p.png")[0] > 0.005


def test_frame_and_time_selection(landing, tmp_path):
    assert render_png(landing, tmp_path / "a.png", frame=4, size=SIZE) == 4
    assert render_png(landing, tmp_path / "b.png", time=0.1, size=SIZE) == pytest.approx(3.0)
    with pytest.raises(ValueError, match=r"frame: out of range, allowed 0\.\.9 \(got 10\)"):
        render_png(landing, tmp_path / "c.png", frame=10)
    with pytest.raises(ValueError, match=r"time: out of range, allowed 0\.\.0\.3 s \(got -1\)"):
        render_png(landing, tmp_path / "c.png", time=-1)
    with pytest.raises(ValueError, match="not both"):
        render_png(landing, tmp_path / "c.png", frame=1, time=0.1)
    assert not (tmp_path / "c.png").exists()


def test_missing_or_unreadable_file(tmp_path):
    missing = tmp_path / "nope.usd"
    with pytest.raises(ValueError, match="nope.usd"):
        render_png(missing, tmp_path / "x.png")
    with pytest.raises(ValueError, match="nope.usd"):
        render_gif(missing, tmp_path / "x.gif")
    garbage = tmp_path / "garbage.usda"
    garbage.write_text("this is not USD\n")
    with pytest.raises(ValueError, match="garbage.usda"):
        render_png(garbage, tmp_path / "x.png")


def test_gif_frames_and_real_time_duration(landing, tmp_path):
    from PIL import Image

    def frames_and_ms(path):
        with Image.open(path) as im:
            durations = []
            for i in range(im.n_frames):
                im.seek(i)
                durations.append(im.info["duration"])
            return im.n_frames, sum(durations), im.size

    out = tmp_path / "all.gif"
    assert render_gif(landing, out, size=SIZE) == FRAMES
    n, ms, size = frames_and_ms(out)
    assert (n, size) == (FRAMES, SIZE)
    assert ms == pytest.approx(1000.0 * FRAMES / FPS, abs=10)

    out = tmp_path / "half.gif"
    assert render_gif(landing, out, fps=15, size=SIZE) == FRAMES // 2
    n, ms, _ = frames_and_ms(out)
    assert n == FRAMES // 2
    assert ms == pytest.approx(1000.0 * FRAMES / FPS, abs=10)  # still real time

    out = tmp_path / "few.gif"
    assert render_gif(landing, out, size=SIZE, max_frames=4) == 4
    assert frames_and_ms(out)[0] == 4

    with pytest.raises(ValueError, match="fps"):
        render_gif(landing, tmp_path / "bad.gif", fps=0)

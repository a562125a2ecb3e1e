"""Headless previews of a softsim USD file: one frame to a PNG, or the whole clip to an animated GIF.

The renderer is a small software pipeline on top of matplotlib's Agg backend (no mplot3d, no GPU):

* every ``UsdGeom.Mesh`` is put in world space with ``UsdGeom.XformCache``; a mesh whose ``points``
  have more than one time sample is *jelly* (deforming; so is a mesh under a ``Jelly_*`` prim with
  one sample or none, a run that has written only frame 0), every other mesh is *terrain*. In a
  softsim output (a stage with ``Jelly_*`` prims) a mesh outside them is terrain even when its
  points are time-sampled (an animated mesh collider); terrain whose points or transforms are
  time-sampled (moving terrain) is read again at every frame drawn, where it stands then.
  ``UsdGeom.Points`` are drawn (as small squares) only when there is no deforming mesh at all (the
  deforming ones, or all of them when none deforms); ``BasisCurves`` and other prims are ignored;
  invisible, guide and proxy prims are skipped, and so are prims with malformed points or faces;
* a fixed perspective camera looks at the bounding box of the jelly over all frames (at most
  ``BBOX_SAMPLES`` time samples per prim) from an elevated 3/4 view, so a PNG of any frame and
  every frame of a GIF share one camera;
* terrain is clipped to a horizontal neighbourhood of that box (a 60 m plane does not dominate the
  view), subdivided near the jelly (so the painter's algorithm orders ground and jelly correctly),
  shaded once (two-sided Lambert, ``primvars:displayColor`` or grey) and projected once;
* each frame, the jelly faces are fan-triangulated, back-face culled (closed surfaces, winding
  checked by signed volume), Lambert shaded in orange, projected, depth-sorted together with the
  terrain triangles (far to near, by mean camera depth; terrain gets a depth bias of half a jelly
  edge, so a jelly resting on or slightly sunk into the ground is drawn on top of it) and drawn as
  one ``PolyCollection``; the terrain straight below each jelly is darkened (a soft contact shadow
  that fades with height, only on the topmost terrain), which shows whether a jelly rests or floats;
* GIF frames are blitted: the terrain-only picture is drawn once and restored, and only the jelly,
  its shadow and the terrain triangles that may cover them are painted again (same picture).

GIFs are streamed: each frame is rendered, mapped to the GIF's one palette and written to the file
before the next is rendered (only the previous frame's palette indices are kept, to write the
changed rectangle), so memory does not grow with the number of frames. A GIF has at most
``max_frames`` frames (default :data:`MAX_GIF_FRAMES`): a longer clip is stepped evenly, and the
frames to draw are computed arithmetically (a stage whose ``endTimeCode`` is 1e9 costs no more than
a short one).

Unusual stages (decisions):

* a stage with no time samples at all (static) renders its one frame, as a PNG or as a one-frame
  GIF; meshes under a ``Jelly_*`` prim are drawn as jelly even then;
* any layout is read: every ``UsdGeom.Mesh`` and ``UsdGeom.Points`` anywhere in the stage (a moving
  mesh at ``/Root/Thing`` is drawn as jelly; static points are drawn when nothing moves but them);
  a stage with nothing drawable is refused, saying what it holds;
* the time range is ``startTimeCode..endTimeCode``; one that is not authored comes from the time
  samples; a non-finite or inverted authored range, and a ``timeCodesPerSecond`` that is not a
  finite number > 0, are refused;
* at most :data:`BBOX_SAMPLES` time samples per prim are read to frame the camera (evenly spaced),
  so a file with 10^6 samples opens as fast as a short one;
* coordinates that are NaN, inf or beyond :data:`COORD_LIMIT` are not drawn (the frame's label
  says how many points were left out); a jelly with no finite point in any frame read is drawn
  as missing over the terrain, or refused when there is no terrain;
* a file that is not USD (text, truncated or empty, a folder, a FIFO) is refused with "cannot open
  as USD".

Public API: :func:`render_png` and :func:`render_gif`. Bad input (missing or unreadable file,
unusual stage as above, frame or time out of range, bad fps/size) raises ``ValueError`` with a
one-line message naming the file and the value and saying what is allowed.

matplotlib and pxr are imported lazily, inside the functions that need them.
"""

from __future__ import annotations

import math
import os
import stat
import struct
import sys

import numpy as np

from .outputs import save_atomic

__all__ = ["open_stage", "render_gif", "render_png"]

JELLY_RGB = np.array([1.0, 0.45, 0.08])
TERRAIN_RGB = np.array([0.70, 0.70, 0.70])
POINTS_RGB = np.array([0.95, 0.35, 0.10])
BACKGROUND_RGB = (0.955, 0.965, 0.98)
TEXT_RGB = (0.2, 0.2, 0.25)

AMBIENT, DIFFUSE = 0.38, 0.62
ELEVATION_DEG, AZIMUTH_DEG, HALF_FOV_DEG = 27.0, 35.0, 16.0
MAX_GIF_FPS = 30.0  # default cap on the GIF frame rate
MAX_GIF_FRAMES = 2000  # default cap on the number of GIF frames (a longer clip is stepped evenly)
MAX_GIF_DELAY_CS = 65535  # the longest delay a GIF frame can hold (16 bits of centiseconds)
BBOX_SAMPLES = 512  # at most this many time samples per prim are read to frame the camera
COORD_LIMIT = 1e30  # coordinates beyond this (or NaN, inf) are not drawn
MIN_GIF_FRAME_MS = 20  # browsers play GIF frames shorter than 20 ms at 100 ms
TERRAIN_TRIANGLE_BUDGET = 5000
SHADOW = 0.35  # darkening of the terrain right under a jelly at rest
EDGE_WIDTH = 0.5  # points; triangle outlines in the fill colour


# --------------------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------------------


def render_png(usd_path, png_path, frame=None, time=None, size=(800, 600)):
    """Render one frame of a softsim USD file to a PNG.

    Args:
        usd_path: the USD file (``.usd``, ``.usda``, ``.usdc``).
        png_path: the PNG to write (its folder must exist).
        frame: time code to render (the simulator writes one time code per frame); may be
            fractional (USD interpolates the points). Must lie in the stage's start..end range.
        time: alternatively, the time in seconds (``frame = time * timeCodesPerSecond``).
        size: image size ``(width, height)`` in pixels.

    Default (neither ``frame`` nor ``time``): the last frame (the only one of a static stage).
    Returns the frame (time code) rendered.
    """
    width, height = _check_size(usd_path, size)
    _check_out_dir(png_path)
    with np.errstate(all="ignore"):  # NaN and inf points are dropped, not warned about
        scene = _Scene(usd_path)
        if frame is not None and time is not None:
            raise ValueError(f"{scene.path}: frame: give frame or time, not both (got frame={frame}, time={time})")
        if time is not None:
            t = _as_number(scene.path, "time", time)
            lo, hi = scene.start / scene.fps, scene.end / scene.fps
            if not (lo - 1e-9 <= t <= hi + 1e-9):
                raise ValueError(f"{scene.path}: time: out of range, allowed {lo:g}..{hi:g} s (got {t:g})")
            frame = min(max(t * scene.fps, scene.start), scene.end)
        elif frame is not None:
            f = _as_number(scene.path, "frame", frame)
            if not (scene.start - 1e-9 <= f <= scene.end + 1e-9):
                raise ValueError(f"{scene.path}: frame: out of range, allowed {scene.start:g}..{scene.end:g} (got {frame:g})")
            frame = min(max(f, scene.start), scene.end)
        else:
            frame = scene.end
        renderer = _Renderer(scene, width, height)
        renderer.draw(frame)
        save_atomic(
            png_path,
            lambda tmp: renderer.fig.savefig(tmp, format="png", dpi=renderer.dpi, facecolor=BACKGROUND_RGB),
            "--png",
        )
    return frame


def render_gif(usd_path, gif_path, fps=None, size=(640, 480), max_frames=None, progress=None):
    """Render the whole clip of a softsim USD file to an animated GIF that plays in real time.

    Args:
        usd_path: the USD file.
        gif_path: the GIF to write (its folder must exist).
        fps: target GIF frame rate; default the stage's ``timeCodesPerSecond`` capped at 30.
            Every ``step = round(stage_fps / fps)``-th frame is drawn (at least 1, and at least
            enough to keep frames >= 20 ms, the shortest GIF delay browsers honour), and each GIF
            frame lasts ``step / stage_fps`` s, so the GIF's duration matches simulated time.
            (With a non-integer ratio the actual rate is ``stage_fps / step``.)
        size: image size ``(width, height)`` in pixels.
        max_frames: at most this many GIF frames (default :data:`MAX_GIF_FRAMES`); if the clip
            needs more, the step is increased (frames are skipped evenly, still covering the whole
            clip in real time, up to GIF's longest frame delay of 655.35 s).
        progress: callable ``progress(total)`` returning a bar with ``update()``, advanced once per
            frame drawn, or None.

    A static stage (no time samples) gives a one-frame GIF. Frames are rendered and written one
    at a time (see the module docstring). Returns the number of frames written.
    """
    width, height = _check_size(usd_path, size)
    _check_out_dir(gif_path)
    if max_frames is None:
        max_frames = MAX_GIF_FRAMES
    else:
        try:
            ok = not isinstance(max_frames, bool) and int(max_frames) == max_frames and max_frames >= 1
        except (TypeError, ValueError, OverflowError):
            ok = False
        if not ok:
            raise ValueError(f"{os.fspath(usd_path)}: max_frames: must be an integer >= 1 (got {max_frames!r})")
        max_frames = int(max_frames)
    with np.errstate(all="ignore"):  # NaN and inf points are dropped, not warned about
        scene = _Scene(usd_path)
        if fps is None:
            fps = min(scene.fps, MAX_GIF_FPS)
        else:
            fps = _as_number(scene.path, "fps", fps)
            if not fps > 0:
                raise ValueError(f"{scene.path}: fps: must be > 0 (got {fps:g})")
        frames, step = _gif_frames(scene.start, scene.end, scene.fps, fps, max_frames)

        from PIL import Image

        renderer = _Renderer(scene, width, height)
        # One palette for the whole GIF, from the first, middle and last frames (no flicker, fast mapping).
        samples = [renderer.render_rgb(frames[i]) for i in sorted({0, len(frames) // 2, len(frames) - 1})]
        mediancut = getattr(Image, "Quantize", Image).MEDIANCUT  # enums since Pillow 9.1
        no_dither = getattr(Image, "Dither", Image).NONE
        palette = Image.fromarray(np.concatenate(samples, axis=0)).quantize(
            colors=255, method=mediancut, dither=no_dither
        )
        del samples
        bar = progress(len(frames)) if progress else None

        def draw(f):
            image = np.asarray(Image.fromarray(renderer.render_rgb(f)).quantize(palette=palette, dither=no_dither))
            if bar is not None:
                bar.update()
            return image

        indexed = (draw(f) for f in frames)
        delays = _gif_delays(len(frames), step, scene.fps)
        written = []
        save_atomic(
            gif_path,
            lambda tmp: written.append(_write_gif(tmp, (width, height), palette.getpalette(), indexed, delays)),
            "--gif",
        )
    return written[0]


def _gif_frames(start, end, stage_fps, fps, max_frames):
    """The time codes a GIF draws and the step between them, computed arithmetically.

    The integer time codes in ``start..end`` (``[start]`` when there is none), every ``step``-th:
    ``step = round(stage_fps / fps)``, at least 1 and enough for frames of >= 20 ms, increased so
    that there are at most ``max_frames``. Returns ``(frames, step)``; ``frames`` is a ``range``
    (or a one-element list), never a list of every time code, however long the clip."""
    first, last = math.ceil(start - 1e-9), math.floor(end + 1e-9)
    if last < first:
        return [start], 1
    count = last - first + 1
    ratio = min(stage_fps / fps, count)  # fps may be tiny: no overflow in round()
    step = max(1, round(ratio), math.ceil(stage_fps * MIN_GIF_FRAME_MS / 1000.0 - 1e-9))
    step = min(step, count)
    if max_frames is not None and -(-count // step) > max_frames:
        step = -(-count // max_frames)
    return range(first, last + 1, step), step


def _gif_delays(count, step, stage_fps):
    """Frame delays in whole centiseconds (GIF's unit) whose running sum tracks real time
    (``step / stage_fps`` s per frame); each at most :data:`MAX_GIF_DELAY_CS`. A generator."""
    try:
        seconds = step / stage_fps
    except OverflowError:
        seconds = math.inf
    done = 0
    for i in range(1, count + 1):
        end = i * seconds * 100.0
        if not math.isfinite(end):
            yield MAX_GIF_DELAY_CS
            continue
        end = round(end)
        yield min(max(end - done, 0), MAX_GIF_DELAY_CS)
        done = end


def _write_gif(path, size, palette, frames, delays):
    """Write an animated GIF frame by frame; returns the number of frames written.

    ``palette``: the global colour table (``[r, g, b, ...]``, at most 256 colours); ``frames``: an
    iterable of ``(height, width)`` uint8 palette indices, consumed one at a time; ``delays``: an
    iterable of centiseconds. Pillow's ``save(save_all=True, append_images=...)`` keeps every frame
    in memory until the end (it merges identical frames), so the file is assembled here: the header,
    global colour table and loop extension, then per frame the rectangle that changed since the
    previous frame (a 1x1 unchanged pixel for an identical frame, so every frame and its delay are
    kept) encoded by Pillow's ``GifImagePlugin.getdata`` (graphic control extension with the delay,
    image descriptor, LZW data), then the trailer.
    """
    from PIL import GifImagePlugin, Image

    width, height = size
    table = bytes(int(v) for v in list(palette)[:768]).ljust(768, b"\0")
    count = 0
    previous = None
    with open(path, "wb") as f:
        # Logical screen: global colour table of 256 entries (flag, 8-bit colour resolution, size 2^8).
        f.write(b"GIF89a" + struct.pack("<HHBBB", width, height, 0xF7, 0, 0) + table)
        f.write(b"!\xff\x0bNETSCAPE2.0\x03\x01" + struct.pack("<H", 0) + b"\0")  # loop forever
        for index, delay in zip(frames, delays):
            index = np.asarray(index, dtype=np.uint8)
            if index.shape != (height, width):
                raise RuntimeError(f"GIF frame of shape {index.shape}, expected {(height, width)}")
            if previous is None:
                x0, y0, x1, y1 = 0, 0, width, height
            else:
                changed = index != previous
                rows = np.flatnonzero(changed.any(axis=1))
                if len(rows) == 0:
                    x0, y0, x1, y1 = 0, 0, 1, 1
                else:
                    cols = np.flatnonzero(changed.any(axis=0))
                    x0, y0, x1, y1 = int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1
            tile = Image.fromarray(np.ascontiguousarray(index[y0:y1, x0:x1]))
            for chunk in GifImagePlugin.getdata(tile, offset=(x0, y0), duration=10 * int(delay)):
                f.write(chunk)
            previous = index
            count += 1
        f.write(b";")
    return count


# --------------------------------------------------------------------------------------------------
# Argument checks
# --------------------------------------------------------------------------------------------------


def _as_number(path, name, value):
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: {name}: must be a number (got {value!r})") from None
    if not math.isfinite(out):
        raise ValueError(f"{path}: {name}: must be finite (got {value!r})")
    return out


def _check_size(usd_path, size):
    try:
        width, height = (int(v) for v in size)
        ok = all(int(v) == v for v in size) and 16 <= width <= 8192 and 16 <= height <= 8192
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"{os.fspath(usd_path)}: size: must be (width, height) in pixels, 16..8192 (got {size!r})")
    return width, height


def _check_out_dir(out_path):
    folder = os.path.dirname(os.path.abspath(os.fspath(out_path)))
    if not os.path.isdir(folder):
        raise ValueError(f"{os.fspath(out_path)}: output: the folder does not exist (got {folder!r})")


# --------------------------------------------------------------------------------------------------
# Scene: the stage's meshes in world space
# --------------------------------------------------------------------------------------------------


def _fan_triangulate(counts, indices):
    """Fan-triangulate polygons. Returns ``(tri, corner, face)``: point indices ``(T, 3)``, positions of
    the corners in ``indices`` ``(T, 3)`` (for faceVarying primvars) and the face of each triangle."""
    counts = np.asarray(counts, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]) if len(counts) else np.zeros(0, np.int64)
    ntri = np.maximum(counts - 2, 0)
    total = int(ntri.sum())
    face = np.repeat(np.arange(len(counts)), ntri)
    k = np.arange(total) - np.repeat(np.cumsum(ntri) - ntri, ntri) + 1
    start = offsets[face]
    corner = np.stack([start, start + k, start + k + 1], axis=1)
    return indices[corner], corner, face


def _is_closed(counts, indices):
    """True if every edge of the polygon mesh is shared by exactly two faces."""
    counts = np.asarray(counts, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    if len(indices) == 0:
        return False
    face = np.repeat(np.arange(len(counts)), counts)
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
    pos = np.arange(len(indices))
    nxt = offsets[face] + (pos - offsets[face] + 1) % counts[face]
    edges = np.sort(np.stack([indices[pos], indices[nxt]], axis=1), axis=1)
    _, mult = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(mult == 2))


def _transform(points, matrix):
    """Apply a USD (row-vector) 4x4 matrix to ``(N, 3)`` points."""
    return points @ matrix[:3, :3] + matrix[3, :3]


def _points_array(value):
    """``(N, 3)`` float64 points from an attribute value; empty for a missing or malformed value."""
    if value is None:
        return np.zeros((0, 3))
    try:
        out = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return np.zeros((0, 3))
    if out.size % 3 or (out.ndim > 1 and out.shape[-1] != 3):
        return np.zeros((0, 3))
    return out.reshape(-1, 3)


def _sane(points):
    """Mask of the rows of ``(N, 3)`` points that can be drawn: finite and within :data:`COORD_LIMIT`."""
    return np.all(np.abs(points) < COORD_LIMIT, axis=-1)  # False for NaN and inf too


def _read(path, attr, time, what="points"):
    """``attr.Get(time)``; a read error of a damaged file becomes a one-line ``ValueError``."""
    from pxr import Tf

    try:
        return attr.Get(time)
    except Tf.ErrorException as exc:
        raise ValueError(f"{path}: cannot read the {what} of {attr.GetPrim().GetPath()} ({_one_line(exc)})") from None


def _bbox_times(attr, start, end):
    """The time samples of ``attr`` in ``start..end`` to frame the camera with: all of them, or at most
    :data:`BBOX_SAMPLES` evenly spaced ones (found by bracketing, never by listing every sample)."""
    from pxr import Gf

    n = attr.GetNumTimeSamples()
    if n == 0:
        return [start]
    if n <= BBOX_SAMPLES:
        times = attr.GetTimeSamplesInInterval(Gf.Interval(start - 1e-9, end + 1e-9))
    else:
        times = set()
        for t in np.linspace(start, end, BBOX_SAMPLES):
            times.update(v for v in attr.GetBracketingTimeSamples(float(t)) if start - 1e-9 <= v <= end + 1e-9)
        times = sorted(times)
    return list(times) or [start]  # no sample in range: the value held at the start


def _moves(prim, attr, UsdGeom):
    """Whether a mesh's points or the transform of it or of a prim above it are time-sampled."""
    if attr.GetNumTimeSamples() > 1:
        return True
    p = prim
    while p and not p.IsPseudoRoot():
        if p.IsA(UsdGeom.Xformable) and UsdGeom.Xformable(p).TransformMightBeTimeVarying():
            return True
        p = p.GetParent()
    return False


def _sample_range(attr):
    """``(first, last)`` time sample of ``attr`` (by bracketing), or None."""
    from pxr import Usd

    lo = attr.GetBracketingTimeSamples(Usd.TimeCode.EarliestTime().GetValue())
    hi = attr.GetBracketingTimeSamples(float(np.finfo(np.float64).max))
    if not lo or not hi:
        return None
    return float(lo[0]), float(hi[1])


class _Deforming:
    """A deforming mesh (jelly) or, as a fallback, a point cloud."""

    def __init__(self, path, attr, matrix, tri=None, cull=False, flip=False, radius=0.0):
        self.path = path
        self.attr = attr
        self.matrix = matrix
        self.tri = tri
        self.cull = cull
        self.flip = flip
        self.radius = radius
        self.used = None if tri is None else np.unique(tri)

    def points(self, frame):
        from pxr import Usd

        return _transform(_points_array(_read(self.path, self.attr, Usd.TimeCode(float(frame)))), self.matrix)


def open_stage(path):
    """``Usd.Stage`` of ``path``, or a one-line ``ValueError`` saying why it cannot be opened."""
    from pxr import Tf, Usd

    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise ValueError(f"{path}: USD file not found") from None
    except OSError as e:
        raise ValueError(f"{path}: cannot open as USD ({e.strerror or e})") from None
    if stat.S_ISDIR(st.st_mode):
        raise ValueError(f"{path}: cannot open as USD (it is a folder, not a file)")
    if not stat.S_ISREG(st.st_mode):  # a FIFO or a device: USD would block on it or fail to map it
        raise ValueError(f"{path}: cannot open as USD (not a regular file)")
    if st.st_size == 0:
        raise ValueError(f"{path}: cannot open as USD (the file is empty)")
    try:
        with open(path, "rb"):
            pass
    except OSError as e:
        raise ValueError(f"{path}: cannot open as USD ({e.strerror or e})") from None
    try:
        stage = Usd.Stage.Open(path)
    except (Tf.ErrorException, RuntimeError) as exc:
        raise ValueError(f"{path}: cannot open as USD ({_one_line(exc)})") from None
    if stage is None:
        raise ValueError(f"{path}: cannot open as USD")
    return stage


class _Scene:
    """Everything the renderer needs from the stage, in world space."""

    def __init__(self, usd_path):
        from pxr import Tf

        self.path = os.fspath(usd_path)
        stage = open_stage(self.path)
        self.stage = stage
        try:
            self._read(stage)
        except Tf.ErrorException as exc:  # a damaged file that opened: reading a value failed
            raise ValueError(f"{self.path}: cannot read the stage ({_one_line(exc)})") from None

    def _read(self, stage):
        from pxr import Usd, UsdGeom

        fps = float(stage.GetTimeCodesPerSecond())
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"{self.path}: timeCodesPerSecond must be a finite number > 0 (got {fps:g})")
        self.fps = fps
        self.up = 2 if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z else 1
        authored = {}
        for key, get in (("startTimeCode", stage.GetStartTimeCode), ("endTimeCode", stage.GetEndTimeCode)):
            if stage.HasAuthoredMetadata(key):
                authored[key] = float(get())
                if not math.isfinite(authored[key]):
                    raise ValueError(f"{self.path}: {key} must be a finite number (got {authored[key]:g})")
        if "startTimeCode" in authored and "endTimeCode" in authored:
            if authored["startTimeCode"] > authored["endTimeCode"]:
                raise ValueError(
                    f"{self.path}: startTimeCode is after endTimeCode "
                    f"(got {authored['startTimeCode']:g}..{authored['endTimeCode']:g})"
                )

        jelly, clouds, terrain_tris, terrain_cols = [], [], [], []
        # Moving terrain: (prim, points attr, triangles, colours, face mask) re-read at every frame.
        self.moving_terrain = []
        softsim = any(p.GetName().startswith("Jelly_") for p in stage.Traverse())
        skipped, others = [], {}  # what was not drawn, for the message of a stage with nothing to draw
        sample_lo, sample_hi = math.inf, -math.inf
        t0 = Usd.TimeCode(authored["startTimeCode"]) if "startTimeCode" in authored else Usd.TimeCode.EarliestTime()
        xcache = UsdGeom.XformCache(t0)
        for prim in stage.Traverse():
            is_mesh, is_points = prim.IsA(UsdGeom.Mesh), prim.IsA(UsdGeom.Points)
            if not (is_mesh or is_points):
                if prim.IsA(UsdGeom.Gprim):
                    others[prim.GetTypeName()] = others.get(prim.GetTypeName(), 0) + 1
                continue
            imageable = UsdGeom.Imageable(prim)
            if imageable.ComputeVisibility(t0) == UsdGeom.Tokens.invisible:
                skipped.append(f"{prim.GetPath()} is invisible")
                continue
            if imageable.ComputePurpose() in (UsdGeom.Tokens.guide, UsdGeom.Tokens.proxy):
                skipped.append(f"{prim.GetPath()} is a {imageable.ComputePurpose()}")
                continue
            matrix = np.array(xcache.GetLocalToWorldTransform(prim), dtype=np.float64)
            if not np.all(np.isfinite(matrix)):
                skipped.append(f"{prim.GetPath()} has a non-finite transform")
                continue
            attr = UsdGeom.PointBased(prim).GetPointsAttr()
            if not attr.HasValue():
                skipped.append(f"{prim.GetPath()} has no points")
                continue
            first = _read(self.path, attr, Usd.TimeCode.EarliestTime())
            if type(first).__name__ not in ("Vec3fArray", "Vec3dArray", "Vec3hArray"):
                skipped.append(f"{prim.GetPath()}.points holds {type(first).__name__}, not an array of 3D points")
                continue
            samples = attr.GetNumTimeSamples()
            # Deforming: more than one time sample; also a softsim jelly (``Jelly_*/Surface`` or
            # ``Particles``), whether its run has written one frame so far or the stage is static.
            in_jelly = prim.GetParent().GetName().startswith("Jelly")
            deforming = samples > 1 or in_jelly
            moving_terrain = False
            if is_mesh and not in_jelly and (softsim or samples <= 1) and _moves(prim, attr, UsdGeom):
                deforming, moving_terrain = False, True
            if deforming and samples:
                lo_hi = _sample_range(attr)
                if lo_hi:
                    sample_lo, sample_hi = min(sample_lo, lo_hi[0]), max(sample_hi, lo_hi[1])
            if is_points:
                clouds.append((prim, attr, matrix, deforming))
                continue
            mesh = UsdGeom.Mesh(prim)
            try:
                counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64).ravel()
                indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64).ravel()
            except (TypeError, ValueError, OverflowError):
                skipped.append(f"{prim.GetPath()} has malformed faces")
                continue
            if (
                len(counts) == 0
                or np.any(counts < 0)
                or counts.sum() != len(indices)
                or (len(indices) and indices.min() < 0)
            ):
                skipped.append(f"{prim.GetPath()} has no faces or malformed ones")
                continue
            tri, corner, face = _fan_triangulate(counts, indices)
            if len(tri) == 0:
                skipped.append(f"{prim.GetPath()} has no faces with 3 or more corners")
                continue
            if deforming:
                flip = mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded
                jelly.append(_Deforming(self.path, attr, matrix, tri=tri, flip=flip))
                jelly[-1].topology = (counts, indices)
            else:
                pts = _transform(_points_array(_read(self.path, attr, Usd.TimeCode.EarliestTime())), matrix)
                if len(pts) == 0 or tri.max() >= len(pts):
                    skipped.append(f"{prim.GetPath()} has faces that index missing points")
                    continue
                cols = _face_colors(prim, tri, corner, face, len(counts), len(pts))
                ok = np.all(_sane(pts[tri]), axis=1)
                if not ok.any():
                    skipped.append(f"{prim.GetPath()} has no finite points")
                    continue
                terrain_tris.append(pts[tri][ok])
                terrain_cols.append(cols[ok])
                if moving_terrain:
                    self.moving_terrain.append((prim, attr, tri, cols, ok, len(terrain_tris) - 1))

        # Time range: the authored one; an end not authored comes from the deforming prims' samples.
        has_samples = sample_lo <= sample_hi
        start, end = authored.get("startTimeCode"), authored.get("endTimeCode")
        if start is None:
            start = sample_lo if has_samples else (end if end is not None else 0.0)
            if end is not None:
                start = min(start, end)
        if end is None:
            end = max(sample_hi if has_samples else start, start)
        self.start, self.end = float(start), float(end)

        if not jelly:  # fall back to point clouds: the deforming ones, else (a static stage) all
            moving = [c for c in clouds if c[3]]
            for prim, attr, matrix, _ in moving or clouds:
                try:
                    widths = UsdGeom.Points(prim).GetWidthsAttr().Get(Usd.TimeCode.EarliestTime())
                    widths = np.asarray(widths if widths is not None else [], dtype=np.float64).ravel()
                except (TypeError, ValueError):
                    widths = np.zeros(0)
                widths = widths[np.isfinite(widths) & (widths > 0)]
                radius = 0.5 * float(np.median(widths)) if len(widths) else 0.0
                jelly.append(_Deforming(self.path, attr, matrix, radius=radius))
        self.jelly = jelly
        self._terrain_parts = terrain_tris
        self.terrain = np.concatenate(terrain_tris) if terrain_tris else np.zeros((0, 3, 3))
        self.terrain_rgb = np.concatenate(terrain_cols) if terrain_cols else np.zeros((0, 3))
        if not jelly and len(self.terrain) == 0:
            found = skipped[:3] + [f"{n} {t or 'untyped'}" for t, n in sorted(others.items())][:3]
            raise ValueError(
                f"{self.path}: nothing to draw: no UsdGeom.Mesh or UsdGeom.Points with usable points "
                f"(got {'; '.join(found) if found else 'no geometry'})"
            )

        # Bounding box of the jelly over the frames (at most BBOX_SAMPLES per prim), typical edge length.
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        edges = []
        for body in jelly:
            for t in _bbox_times(body.attr, self.start, self.end):
                p = body.points(t)
                if body.used is not None:
                    if len(p) <= body.used[-1]:
                        continue
                    p = p[body.used]
                p = p[_sane(p)]  # an exploded run may hold NaN or inf
                if len(p):
                    lo, hi = np.minimum(lo, p.min(axis=0)), np.maximum(hi, p.max(axis=0))
            self._setup_body(body, edges)
        if not np.all(np.isfinite(lo)):
            if len(self.terrain) == 0:
                raise ValueError(
                    f"{self.path}: nothing to draw: the points are NaN, inf or beyond 1e30 in every frame read "
                    f"(got {len(jelly)} moving prim(s), no terrain)"
                )
            lo, hi = self.terrain.reshape(-1, 3).min(axis=0), self.terrain.reshape(-1, 3).max(axis=0)
            self.has_jelly_box = False
        else:
            self.has_jelly_box = True
        self.lo, self.hi = lo, hi
        extent = max(float(np.max(hi - lo)), 1e-6)
        self.extent = extent
        edges = np.concatenate(edges) if edges else np.zeros(0)
        edges = edges[np.isfinite(edges) & (edges > 0)]
        self.edge = float(np.median(edges)) if len(edges) else extent / 10.0
        for body in jelly:
            if body.tri is None and body.radius <= 0.0:
                body.radius = 0.25 * self.edge

    def terrain_at(self, frame):
        """The terrain's triangles at ``frame``: the static ones as read, the moving ones where
        their points and transforms are then (a face that is not finite there keeps its place)."""
        if not self.moving_terrain:
            return self.terrain
        from pxr import Usd, UsdGeom

        parts = list(self._terrain_parts)
        cache = UsdGeom.XformCache(Usd.TimeCode(float(frame)))
        for prim, attr, tri, _cols, ok, k in self.moving_terrain:
            matrix = np.array(cache.GetLocalToWorldTransform(prim), dtype=np.float64)
            pts = _transform(_points_array(_read(self.path, attr, Usd.TimeCode(float(frame)))), matrix)
            if len(pts) > tri.max():
                moved = pts[tri][ok]
                parts[k] = np.where(_sane(moved)[..., None], moved, parts[k])
        return np.concatenate(parts)

    def _setup_body(self, body, edges):
        """Orientation and culling of a jelly mesh from its first frame; typical edge lengths."""
        p = body.points(self.start)
        if body.tri is None:  # point cloud: spacing = median nearest-neighbour distance (of <= 1000 points)
            p = p[_sane(p)]
            if len(p) > 1:
                q = p[:: -(-len(p) // 1000)]
                d = np.linalg.norm(q[:, None] - q[None], axis=2)
                np.fill_diagonal(d, np.inf)
                nearest = d.min(axis=1)
                nearest = nearest[np.isfinite(nearest) & (nearest > 0)]
                if len(nearest):  # a subsample's spacing is wider: scale back as for a volume
                    edges.append(np.array([np.median(nearest) * (len(q) / len(p)) ** (1 / 3)]))
            return
        if len(p) <= body.used[-1]:
            body.tri = body.tri[:0]
            return
        counts, indices = body.topology
        face = np.repeat(np.arange(len(counts)), counts)
        offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
        pos = np.arange(len(indices))
        nxt = offsets[face] + (pos - offsets[face] + 1) % counts[face]
        edges.append(np.linalg.norm(p[indices[nxt]] - p[indices[pos]], axis=1))
        v = p[body.tri]
        volume = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0
        size = float(np.max(np.ptp(p[body.used], axis=0))) if len(body.used) else 0.0
        if _is_closed(counts, indices) and abs(volume) > 1e-6 * size**3:
            body.cull = True
            body.flip = volume < 0  # make normals point out whatever the authored winding
        del body.topology


def _one_line(exc):
    """The gist of a (multi-line, pxr.Tf) exception message, on one line."""
    import re

    text = " ".join(str(exc).split())
    quoted = re.findall(r" in file \S+ : '(.*?)'(?= Error in |$)", text)
    if quoted:
        text = quoted[0]
    return text[:300] or type(exc).__name__


def _face_colors(prim, tri, corner, face, n_faces, n_points):
    """Per-triangle RGB from ``primvars:displayColor`` (any interpolation), or grey."""
    from pxr import Usd, UsdGeom

    out = np.tile(TERRAIN_RGB, (len(tri), 1))
    primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayColor")
    if not primvar or not primvar.HasValue():
        return out
    values = primvar.ComputeFlattened(Usd.TimeCode.EarliestTime())
    try:
        values = np.asarray(values if values is not None else [], dtype=np.float64)
    except (TypeError, ValueError):
        return out
    if values.size == 0 or values.size % 3:
        return out
    values = np.clip(np.nan_to_num(values.reshape(-1, 3), nan=0.5), 0.0, 1.0)
    interp = primvar.GetInterpolation()
    if len(values) == 1 or interp == UsdGeom.Tokens.constant:
        return np.tile(values[0], (len(tri), 1))
    if interp == UsdGeom.Tokens.uniform and len(values) == n_faces:
        return values[face]
    if interp in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying) and len(values) == n_points:
        return values[tri].mean(axis=1)
    if interp == UsdGeom.Tokens.faceVarying and len(values) > corner.max():
        return values[corner].mean(axis=1)
    return out


# --------------------------------------------------------------------------------------------------
# Camera, terrain preparation
# --------------------------------------------------------------------------------------------------


class _Camera:
    """Perspective camera at an elevated 3/4 view of a box; projects to 2D (x right, y up)."""

    def __init__(self, lo, hi, up_axis):
        up = np.zeros(3)
        up[up_axis] = 1.0
        if up_axis == 1:  # Y up: front is +Z, side is +X
            front, side = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
        else:  # Z up: front is -Y, side is +X
            front, side = np.array([0.0, -1.0, 0.0]), np.array([1.0, 0.0, 0.0])
        el, az = math.radians(ELEVATION_DEG), math.radians(AZIMUTH_DEG)
        horizontal = math.cos(az) * front + math.sin(az) * side
        to_eye = math.cos(el) * horizontal + math.sin(el) * up
        self.target = 0.5 * (lo + hi)
        radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)
        self.distance = radius / math.sin(math.radians(HALF_FOV_DEG))
        self.eye = self.target + self.distance * to_eye
        self.forward = -to_eye
        self.right = np.cross(self.forward, up)
        self.right /= np.linalg.norm(self.right)
        self.cam_up = np.cross(self.right, self.forward)
        self.near = 0.05 * self.distance
        self.basis = np.stack([self.right, self.cam_up, self.forward], axis=1)  # world -> (x, y, depth)
        self.up = up
        # Direction towards the light: above, slightly to the left of and behind the camera.
        light = 1.7 * up + 0.7 * horizontal - 0.6 * self.right
        self.light = light / np.linalg.norm(light)

    def to_camera(self, points):
        return (points - self.eye) @ self.basis

    @staticmethod
    def project(cam):
        """Camera-space ``(..., 3)`` to screen ``(..., 2)`` (perspective divide)."""
        return cam[..., :2] / cam[..., 2:3]


def _clip_polygon(poly, axis, value, keep_above):
    """Sutherland-Hodgman clip of a 3D polygon ``(n, 3)`` against ``x[axis] >= value`` (or <=)."""
    out = []
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        da = (a[axis] - value) if keep_above else (value - a[axis])
        db = (b[axis] - value) if keep_above else (value - b[axis])
        if da >= 0:
            out.append(a)
        if (da >= 0) != (db >= 0):
            out.append(a + (b - a) * (da / (da - db)))
    return np.array(out) if out else np.zeros((0, 3))


def _crop(tris, colors, axes, lo, hi):
    """Clip triangles ``(T, 3, 3)`` to the box ``lo <= x[axes] <= hi``; returns triangles and colors."""
    tmin, tmax = tris.min(axis=1), tris.max(axis=1)
    inside = np.all((tmin[:, axes] >= lo) & (tmax[:, axes] <= hi), axis=1)
    overlap = np.all((tmax[:, axes] >= lo) & (tmin[:, axes] <= hi), axis=1)
    keep_t, keep_c = [tris[inside]], [colors[inside]]
    straddle = np.nonzero(overlap & ~inside)[0]
    new_t, new_c = [], []
    for i in straddle:
        poly = tris[i]
        for ax, l, h in zip(axes, lo, hi):
            poly = _clip_polygon(poly, ax, l, True)
            if len(poly) >= 3:
                poly = _clip_polygon(poly, ax, h, False)
            if len(poly) < 3:
                break
        if len(poly) >= 3:
            for k in range(1, len(poly) - 1):
                new_t.append((poly[0], poly[k], poly[k + 1]))
                new_c.append(colors[i])
    if new_t:
        keep_t.append(np.array(new_t))
        keep_c.append(np.array(new_c))
    return np.concatenate(keep_t), np.concatenate(keep_c)


def _drop_degenerate(tris, colors):
    """Drop zero-area triangles (clipping leaves them where an edge runs along the box); they
    have no normal and would be drawn as dark hairlines."""
    area2 = np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    longest = np.linalg.norm(tris - np.roll(tris, 1, axis=1), axis=2).max(axis=1)
    keep = area2 > 1e-6 * longest**2
    return tris[keep], colors[keep]


def _subdivide(tris, colors, limit_fn, budget):
    """Split triangles (4-way, midpoints) while their longest edge exceeds ``limit_fn(tris)``."""
    for _ in range(12):
        a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
        longest = np.sqrt(np.maximum.reduce([((b - a) ** 2).sum(-1), ((c - b) ** 2).sum(-1), ((a - c) ** 2).sum(-1)]))
        ratio = longest / limit_fn(tris)
        need = ratio > 1.0
        room = (budget - len(tris)) // 3
        if not need.any() or room <= 0:
            break
        if need.sum() > room:  # split the worst first
            order = np.argsort(-ratio)[:room]
            need = np.zeros(len(tris), dtype=bool)
            need[order] = True
        a, b, c = a[need], b[need], c[need]
        ab, bc, ca = 0.5 * (a + b), 0.5 * (b + c), 0.5 * (c + a)
        children = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
        tris = np.concatenate([tris[~need], children])
        colors = np.concatenate([colors[~need], np.tile(colors[need], (4, 1))])
    return tris, colors


def _topmost(tris, centers, up, tol, cells=64):
    """Mask of triangles on top: centre no lower than ``tol`` below the highest terrain sample in its
    cell of a horizontal grid (a plane under a bowl is not on top; the bowl is). Shadows fall on these."""
    hz = [a for a in range(3) if a != up]
    mids = 0.5 * (tris + np.roll(tris, 1, axis=1))
    samples = np.concatenate([tris.reshape(-1, 3), mids.reshape(-1, 3), centers])
    lo = samples[:, hz].min(axis=0)
    cell = max(float(np.max(samples[:, hz].max(axis=0) - lo)) / cells, 1e-12)
    shape = tuple(int(n) for n in np.floor((samples[:, hz].max(axis=0) - lo) / cell) + 1)

    def cell_of(x):
        ij = np.floor((x[:, hz] - lo) / cell).astype(np.int64)
        return np.clip(ij[:, 0], 0, shape[0] - 1), np.clip(ij[:, 1], 0, shape[1] - 1)

    top = np.full(shape, -np.inf)
    np.maximum.at(top, cell_of(samples), samples[:, up])
    # A sloped triangle's centre may lie below higher samples of its own surface in the same cell.
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    slope = np.linalg.norm(normals[:, hz], axis=1) / np.maximum(np.abs(normals[:, up]), 1e-12)
    return centers[:, up] >= top[cell_of(centers)] - tol - 2.0 * cell * np.minimum(slope, 10.0)


def _shade(normals, base_rgb, light):
    """Lambert shading: ``base * (ambient + diffuse * max(0, n.l))``; normals need not be unit."""
    length = np.linalg.norm(normals, axis=1)
    length[length == 0] = 1.0
    lambert = np.clip((normals @ light) / length, 0.0, 1.0)
    return np.clip(base_rgb * (AMBIENT + DIFFUSE * lambert)[:, None], 0.0, 1.0)


# --------------------------------------------------------------------------------------------------
# Renderer
# --------------------------------------------------------------------------------------------------


class _Renderer:
    """A fixed camera, prepared terrain and one reusable figure; ``draw(frame)`` updates it."""

    def __init__(self, scene, width, height):
        import matplotlib

        if "matplotlib.pyplot" not in sys.modules:
            matplotlib.use("Agg")  # headless; never switch a backend pyplot already uses
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.collections import PolyCollection
        from matplotlib.figure import Figure

        self.scene = scene
        self.dpi = 100
        self.width, self.height = width, height
        cam = _Camera(scene.lo, scene.hi, scene.up)
        self.cam = cam

        # Axis limits: the projected jelly box (slightly enlarged), padded to the image aspect.
        lo, hi = scene.lo - 0.08 * scene.extent, scene.hi + 0.08 * scene.extent
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        xy = cam.project(cam.to_camera(corners))
        (x0, y0), (x1, y1) = xy.min(axis=0), xy.max(axis=0)
        cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
        half_w, half_h = 0.5 * (x1 - x0) * 1.06, 0.5 * (y1 - y0) * 1.06
        aspect = width / height
        if half_w / half_h < aspect:
            half_w = half_h * aspect
        else:
            half_h = half_w / aspect
        self.xlim, self.ylim = (cx - half_w, cx + half_w), (cy - half_h, cy + half_h)

        self._prepare_terrain()

        fig = Figure(figsize=(width / self.dpi, height / self.dpi), dpi=self.dpi, facecolor=BACKGROUND_RGB)
        self.canvas = FigureCanvasAgg(fig)
        ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
        ax.set_axis_off()
        ax.set_facecolor(BACKGROUND_RGB)
        ax.set_xlim(*self.xlim)
        ax.set_ylim(*self.ylim)
        ax.set_aspect("equal", adjustable="datalim")
        self.coll = PolyCollection(np.zeros((0, 3, 2)), closed=True, linewidths=EDGE_WIDTH, antialiased=True)
        ax.add_collection(self.coll, autolim=False)
        fontsize = max(7.0, min(14.0, height / 48.0))
        self.label = ax.text(
            0.015,
            0.02,
            "",
            transform=ax.transAxes,
            fontsize=fontsize,
            color=TEXT_RGB,
            family="monospace",
            ha="left",
            va="bottom",
        )
        self.fig, self.ax = fig, ax
        self.background = None

    def _prepare_terrain(self, frame=None):
        scene, cam = self.scene, self.cam
        tris, rgb = scene.terrain, scene.terrain_rgb
        if frame is not None:
            tris = scene.terrain_at(frame)
        self.terrain_frame = frame
        self.t_xy = np.zeros((0, 3, 2))
        self.t_depth = np.zeros(0)
        self.t_rgb = np.zeros((0, 3))
        self.t_min = self.t_max = np.zeros((0, 2))
        self.t_center = np.zeros((0, 3))
        self.t_points = np.zeros((0, 7, 3))
        self.t_size = np.zeros(0)
        self.t_receiver = np.zeros(0, dtype=bool)
        if len(tris) == 0:
            return
        axes = [a for a in range(3) if a != scene.up]
        if scene.has_jelly_box:
            margin = 0.75 * scene.extent
            tris, rgb = _crop(tris, rgb, axes, scene.lo[axes] - margin, scene.hi[axes] + margin)
        tris, rgb = _drop_degenerate(tris, rgb)
        if len(tris) == 0:
            return
        # Drop what lies wholly behind the near plane or off screen, before subdividing.
        cam_pts = cam.to_camera(tris)
        depth_min = cam_pts[..., 2].min(axis=1)
        keep = cam_pts[..., 2].max(axis=1) > cam.near
        in_front = depth_min > cam.near
        xy = cam.project(np.where(cam_pts[..., 2:3] > cam.near, cam_pts, cam.near))
        off = in_front & (
            (xy[..., 0].max(axis=1) < self.xlim[0])
            | (xy[..., 0].min(axis=1) > self.xlim[1])
            | (xy[..., 1].max(axis=1) < self.ylim[0])
            | (xy[..., 1].min(axis=1) > self.ylim[1])
        )
        tris, rgb = tris[keep & ~off], rgb[keep & ~off]
        if len(tris) == 0:
            return
        # Subdivide near the jelly (painter's algorithm needs triangles of a jelly face's size there).
        lo, hi, h0 = scene.lo, scene.hi, 0.75 * scene.edge

        def limit(t):
            c = t.mean(axis=1)
            dist = np.linalg.norm(np.maximum(np.maximum(lo - c, c - hi), 0.0), axis=1)
            return h0 + 0.5 * dist

        if scene.has_jelly_box:
            tris, rgb = _subdivide(tris, rgb, limit, TERRAIN_TRIANGLE_BUDGET)
        cam_pts = cam.to_camera(tris)
        keep = cam_pts[..., 2].min(axis=1) > cam.near
        tris, rgb, cam_pts = tris[keep], rgb[keep], cam_pts[keep]
        normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        towards = np.einsum("ij,ij->i", normals, tris.mean(axis=1) - cam.eye) > 0
        normals[towards] *= -1.0  # two-sided: shade the side the camera sees
        self.t_rgb = _shade(normals, rgb, cam.light)
        self.t_xy = cam.project(cam_pts)
        # Bias: push terrain back by half a jelly edge (resting contact, slight penetration).
        self.t_depth = cam_pts[..., 2].mean(axis=1) + 0.5 * scene.edge
        self.t_min, self.t_max = self.t_xy.min(axis=1), self.t_xy.max(axis=1)
        self.t_center = tris.mean(axis=1)
        self.t_size = np.linalg.norm(tris - np.roll(tris, 1, axis=1), axis=2).max(axis=1)
        mids = 0.5 * (tris + np.roll(tris, 1, axis=1))
        self.t_points = np.concatenate([tris, mids, self.t_center[:, None]], axis=1)  # 7 samples
        self.t_receiver = _topmost(tris, self.t_center, scene.up, tol=max(0.5 * scene.edge, 0.01 * scene.extent))

    def _bodies(self, frame):
        """Per body: ``(xy (n, 3, 2), depth (n,), rgb (n, 3), shadow_idx, shadow_factor)``."""
        cam = self.cam
        out = []
        self.left_out = 0  # points not drawn (NaN, inf, absurd), for the label
        for body in self.scene.jelly:
            p = body.points(frame)
            if body.tri is None:  # point cloud: a camera-facing square (2 triangles) per point
                sane = _sane(p)
                self.left_out += int(len(p) - sane.sum())
                p = p[sane]
                cp = cam.to_camera(p)
                cp = cp[cp[:, 2] > cam.near]
                r = body.radius
                quad = np.array([[-r, -r], [r, -r], [r, r], [-r, r]])
                xy = (cp[:, None, :2] + quad[None]) / cp[:, None, 2:3]
                xy = np.concatenate([xy[:, [0, 1, 2]], xy[:, [0, 2, 3]]])
                depth = np.concatenate([cp[:, 2], cp[:, 2]])
                rgb = np.tile(POINTS_RGB, (len(depth), 1))
                if len(depth):  # farther points a little darker
                    rgb *= 1.0 - 0.35 * ((depth - depth.min()) / max(float(np.ptp(depth)), 1e-12))[:, None]
                out.append((xy, depth, rgb) + self._shadow(p))
                continue
            if len(body.tri) == 0 or len(p) <= body.used[-1]:
                continue
            sane = _sane(p)
            self.left_out += int(len(body.used) - sane[body.used].sum())
            v = p[body.tri]
            v = v[np.all(sane[body.tri], axis=1)]
            normals = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
            if body.flip:
                normals = -normals
            facing = np.einsum("ij,ij->i", normals, v.mean(axis=1) - cam.eye) < 0
            if body.cull:
                v, normals = v[facing], normals[facing]
            else:
                normals[~facing] *= -1.0
            cv = cam.to_camera(v)
            ok = cv[..., 2].min(axis=1) > cam.near
            cv, normals = cv[ok], normals[ok]
            out.append(
                (cam.project(cv), cv[..., 2].mean(axis=1), _shade(normals, JELLY_RGB, cam.light))
                + self._shadow(p[body.used][sane[body.used]])
            )
        return out

    def _shadow(self, p):
        """A soft contact shadow straight below a body: terrain triangles under its horizontal
        footprint are darkened, less the higher the body floats. Returns ``(indices, factors)``."""
        none = (np.zeros(0, dtype=np.int64), np.zeros(0))
        if len(self.t_center) == 0 or len(p) == 0:
            return none
        up = self.scene.up
        hz = [a for a in range(3) if a != up]
        lo, hi = p[:, hz].min(axis=0), p[:, hz].max(axis=0)
        bottom = p[:, up].min()
        size = max(float(np.max(hi - lo)), 1e-9)
        gap = bottom - self.t_center[:, up]
        below = self.t_receiver & (gap > -0.5 * self.scene.edge)
        gap = np.maximum(gap, 0.0)
        width = (0.4 * size + 0.5 * gap)[:, None]
        pts = self.t_points[..., hz]  # (T, 7, 2): coverage averaged over corners, mid-edges, centre
        dist = np.linalg.norm(np.maximum(np.maximum(lo - pts, pts - hi), 0.0), axis=2)
        x = np.clip(dist / width, 0.0, 1.0)
        cover = (1.0 - x * x * (3.0 - 2.0 * x)).mean(axis=1)  # smoothstep fall-off
        strength = SHADOW * np.exp(-gap / (1.5 * size)) * cover
        fine = self.t_size < width[:, 0]  # a coarse triangle cannot show a soft edge: leave it
        idx = np.nonzero(below & fine & (strength > 0.01))[0]
        return idx, 1.0 - strength[idx]

    def _terrain_rgb(self, bodies):
        """Terrain colours with every body's shadow applied, and the mask of shadowed triangles."""
        rgb = self.t_rgb
        shadowed = np.zeros(len(rgb), dtype=bool)
        if any(len(b[3]) for b in bodies):
            factor = np.ones(len(rgb))
            for b in bodies:
                factor[b[3]] *= b[4]
                shadowed[b[3]] = True
            rgb = rgb * factor[:, None]
        return rgb, shadowed

    def _set_polys(self, xy, rgb, clip_box):
        self.coll.set_verts(xy)
        self.coll.set_facecolor(rgb)
        self.coll.set_edgecolor(rgb)  # outlines in the face colour hide hairline seams
        self.coll.set_clip_box(clip_box)

    def _set_label(self, frame):
        text = f"t = {frame / self.scene.fps:.2f} s"
        if getattr(self, "left_out", 0):
            text += f"  ({self.left_out} non-finite points not drawn)"
        self.label.set_text(text)

    def _move_terrain(self, frame):
        """Put moving terrain where it is at ``frame`` (prepared again: it is shaded and projected
        once per frame instead of once); nothing for a stage whose terrain stands still."""
        if self.scene.moving_terrain and self.terrain_frame != frame:
            self._prepare_terrain(frame)

    def draw(self, frame):
        """Draw a frame the plain way: every triangle, one painter's pass, full canvas draw."""
        self._move_terrain(frame)
        bodies = self._bodies(frame)
        t_rgb, _ = self._terrain_rgb(bodies)
        depth = np.concatenate([self.t_depth] + [b[1] for b in bodies])
        order = np.argsort(-depth, kind="stable")
        xy = np.concatenate([self.t_xy] + [b[0] for b in bodies])[order]
        rgb = np.concatenate([t_rgb] + [b[2] for b in bodies])[order]
        self._set_polys(xy, rgb, self.ax.bbox)
        self._set_label(frame)
        self.canvas.draw()

    def _background(self):
        """The terrain alone, drawn once and kept as an Agg buffer to restore each frame."""
        if self.background is None:
            order = np.argsort(-self.t_depth, kind="stable")
            self._set_polys(self.t_xy[order], self.t_rgb[order], self.ax.bbox)
            self.label.set_text("")
            self.canvas.draw()
            self.background = self.canvas.copy_from_bbox(self.fig.bbox)
        return self.background

    def _clusters(self, bodies):
        """Group bodies whose screen boxes (jelly and shadow, display pixels, padded, inside the
        axes) overlap. Yields ``(box, xy, depth, rgb, shadow_idx)`` per group; outside the boxes
        the frame equals the terrain-only picture."""
        ax_box = self.ax.bbox
        groups = []
        for xy, depth, rgb, sidx, _ in bodies:
            if len(depth) == 0 and len(sidx) == 0:
                continue
            flat = np.concatenate([xy.reshape(-1, 2), self.t_min[sidx], self.t_max[sidx]])
            (x0, y0), (x1, y1) = self.ax.transData.transform(np.stack([flat.min(axis=0), flat.max(axis=0)]))
            box = [max(x0 - 3, ax_box.x0), max(y0 - 3, ax_box.y0), min(x1 + 3, ax_box.x1), min(y1 + 3, ax_box.y1)]
            if box[2] > box[0] and box[3] > box[1]:
                groups.append([box, [xy], [depth], [rgb], [sidx]])
        merged = True
        while merged:
            merged = False
            for i in range(len(groups)):
                for j in range(i + 1, len(groups)):
                    a, b = groups[i][0], groups[j][0]
                    if a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]:
                        groups[i][0] = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])]
                        for k in (1, 2, 3, 4):
                            groups[i][k] += groups[j][k]
                        del groups[j]
                        merged = True
                        break
                if merged:
                    break
        for box, xy, depth, rgb, sidx in groups:
            yield box, np.concatenate(xy), np.concatenate(depth), np.concatenate(rgb), np.concatenate(sidx)

    def render_rgb(self, frame):
        """Draw a frame and return it as an ``(H, W, 3)`` uint8 array.

        Same picture as :meth:`draw`, faster. The terrain-only image is restored; then, per group
        of bodies, the changed triangles (jelly, shadowed terrain) and every terrain triangle nearer
        than the farthest of them inside the group's screen box are painted again in depth order,
        clipped to that box. A pixel whose last painted triangle is not redrawn is covered by
        nothing redrawn, so it keeps its terrain-only colour, which is then also the full result.
        """
        from matplotlib.transforms import Bbox

        if self.scene.moving_terrain:  # no terrain-only picture to restore: every triangle, drawn again
            self.draw(frame)
            return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()
        background = self._background()
        bodies = self._bodies(frame)
        t_rgb, shadowed = self._terrain_rgb(bodies)
        self.canvas.restore_region(background)
        self._set_label(frame)
        for box, jxy, jdepth, jrgb, sidx in self._clusters(bodies):
            x0, y0, x1, y1 = box
            (u0, v0), (u1, v1) = self.ax.transData.inverted().transform([[x0, y0], [x1, y1]])
            far = max(jdepth.max(initial=-np.inf), self.t_depth[sidx].max(initial=-np.inf))
            sel = (
                ((self.t_depth < far) | shadowed)
                & (self.t_max[:, 0] >= u0)
                & (self.t_min[:, 0] <= u1)
                & (self.t_max[:, 1] >= v0)
                & (self.t_min[:, 1] <= v1)
            )
            order = np.argsort(-np.concatenate([self.t_depth[sel], jdepth]), kind="stable")
            xy = np.concatenate([self.t_xy[sel], jxy])[order]
            rgb = np.concatenate([t_rgb[sel], jrgb])[order]
            self._set_polys(xy, rgb, Bbox.from_extents(x0, y0, x1, y1))
            self.ax.draw_artist(self.coll)
        self.ax.draw_artist(self.label)
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()

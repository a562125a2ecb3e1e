"""``softsim preview``: pictures of a softsim USD file without a 3D tool (see ``preview.py``).

``softsim preview OUT.usdc --png frame.png [--frame N | --time T] [--gif anim.gif [--fps N]]``
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

from ..core.errors import CommandLineError, UserError
from ..io import preview
from ..io.outputs import Outputs, save_atomic
from .common import ProgressLog

COMMAND = "preview"


def add_parser(subparsers, add_common):
    p = subparsers.add_parser(
        COMMAND,
        help="render a USD file written by softsim to a PNG (one frame) and/or an animated GIF",
        description="Render a softsim USD file headless with matplotlib: --png for one frame, --gif for the clip.",
    )
    p.add_argument("usd", help="USD file written by `softsim run` or `softsim compare`")
    p.add_argument("--png", help="write one frame to this PNG (default frame: the last)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--frame", type=float, help="frame (time code) for --png")
    g.add_argument("--time", type=float, help="time [s] for --png")
    p.add_argument("--gif", help="write the whole clip to this animated GIF, in real time")
    p.add_argument("--fps", type=float, help="GIF frame rate (default the file's, at most 30)")
    p.add_argument("--size", default=None, metavar="WxH", help="image size in pixels (default 800x600 PNG, 640x480 GIF)")
    p.add_argument("--split", action="store_true",
                   help="for a `softsim compare` stage: render each copy alone and tile the pictures in the "
                   "stage's grid, labelled with the copy's name (--png only)")
    # Not add_common: a picture of a USD file has no scene to override and runs no kernels.
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--debug", action="store_true", help="show tracebacks for errors")
    return p


def _size(text):
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise CommandLineError("--size", "must be WIDTHxHEIGHT in pixels, e.g. 800x600", text) from None
    return (w, h)


def run(args) -> int:
    if not args.png and not args.gif:
        raise CommandLineError("softsim preview", "give --png FILE and/or --gif FILE")
    if (args.frame is not None or args.time is not None) and not args.png:
        raise CommandLineError("--frame/--time", "choose the frame of --png; give --png FILE too")
    if args.fps is not None and not args.gif:
        raise CommandLineError("--fps", "sets the frame rate of --gif; give --gif FILE too")
    if args.split and (args.gif or not args.png):
        raise CommandLineError("--split", "tiles one frame of each copy into --png; it does not make GIFs")
    outputs = Outputs()
    outputs.add_input("usd", args.usd)
    outputs.add("--png", args.png, (".png",))
    outputs.add("--gif", args.gif, (".gif",))
    size = _size(args.size)
    with outputs:
        return _render(args, size)


def _render(args, size) -> int:
    try:
        if args.png and args.split:
            frame = render_split_png(args.usd, args.png, frame=args.frame, time=args.time, size=size)
            print(f"{args.usd}: frame {frame:g} of each copy -> {args.png}", file=sys.stderr)
        elif args.png:
            kw = {"size": size} if size else {}
            frame = preview.render_png(args.usd, args.png, frame=args.frame, time=args.time, **kw)
            print(f"{args.usd}: frame {frame:g} -> {args.png}", file=sys.stderr)
        if args.gif:
            kw = {"size": size} if size else {}
            shown = ProgressLog(f"{Path(args.gif).name}", unit="frame", quiet=args.quiet)
            try:
                count = preview.render_gif(args.usd, args.gif, fps=args.fps, progress=shown.progress, **kw)
            finally:
                if shown.bar is not None:
                    shown.bar.close()
            print(f"{args.usd}: {count} frames -> {args.gif}", file=sys.stderr)
    except ValueError as e:
        # preview.py reports bad input as one line "<file>: <what is wrong> (got <value>)".
        raise _user_error(e) from None
    return 0


class _Shown:
    """A value already written as the message shows it (``format_value`` prints it as it is)."""

    def __init__(self, text):
        self.text = text

    def __str__(self):
        return self.text


# preview.py's names of its parameters, as the command line's flags.
_FLAGS = {"frame": "--frame", "time": "--time", "fps": "--fps", "size": "--size", "max_frames": "max_frames",
          "output": "output"}


def _user_error(e: ValueError) -> UserError:
    """preview.py's bad input as a one-line UserError with its parts: ``"<file>: <parameter>: <what is
    wrong> (got <value>)"`` for a parameter, ``"<file>: <what is wrong>"`` for the USD file itself (the
    key is then ``usd`` and the value the file)."""
    source, _, message = str(e).partition(": ")
    key, _, rest = message.partition(": ")
    if key in _FLAGS and rest:
        m = re.match(r"^(.*) \(got (.*)\)$", rest, re.S)
        if m:
            return UserError(source, _FLAGS[key], m.group(1), _Shown(m.group(2)), has_value=True)
        return UserError(source, _FLAGS[key], rest)
    return UserError(source, "usd", message or "cannot render", source, has_value=True)


def render_gif_or_error(usd_path, gif_path, fps=None):
    """``softsim run --preview``: the GIF of a finished run; bad input becomes a one-line UserError."""

    try:
        count = preview.render_gif(usd_path, gif_path, fps=fps)
    except ValueError as e:
        raise _user_error(e) from None
    print(f"{usd_path}: {count} frames -> {gif_path}", file=sys.stderr)


def _copies(stage):
    """The copies of a comparison stage: ``[(name, (x, z) offset)]`` of /World's translated children."""
    from pxr import Usd, UsdGeom  # noqa: PLC0415

    out = []
    world = stage.GetPrimAtPath("/World")
    for child in world.GetChildren() if world else []:
        if not child.IsA(UsdGeom.Xform):
            continue
        has_jelly = any(p.IsA(UsdGeom.Mesh) and UsdGeom.Mesh(p).GetPointsAttr().GetNumTimeSamples() > 1
                        for p in Usd.PrimRange(child))
        if has_jelly:
            t = UsdGeom.Xformable(child).ComputeLocalToWorldTransform(0).ExtractTranslation()
            out.append((child.GetName(), (float(t[0]), float(t[2]))))
    return out


def render_split_png(usd_path, png_path, frame=None, time=None, size=None):
    """Render each copy of a ``softsim compare`` stage alone and tile the pictures in its grid.

    Each copy is shown through a small layer that sublayers the stage and deactivates the other
    copies, so the renderer (``preview.render_png``) sees one copy; rows and columns follow the
    copies' offsets in the stage (row by row, as ``softsim compare`` lays them out). Each tile
    frames its own copy. Returns the frame rendered.
    """
    import os  # noqa: PLC0415
    import tempfile  # noqa: PLC0415

    import numpy as np  # noqa: PLC0415
    from pxr import Sdf, Usd, UsdGeom  # noqa: PLC0415

    path = os.path.abspath(os.fspath(usd_path))
    stage = preview.open_stage(path)
    copies = _copies(stage)
    if len(copies) < 2:
        raise ValueError(f"{usd_path}: --split needs a stage written by `softsim compare`, with copies side by side")
    xs = sorted({round(x, 6) for _, (x, _) in copies})
    zs = sorted({round(z, 6) for _, (_, z) in copies})
    cols, rows = len(xs), len(zs)
    tile_w, tile_h = size or (480, 360)
    import matplotlib  # noqa: PLC0415

    if "matplotlib.pyplot" not in sys.modules:
        matplotlib.use("Agg")
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: PLC0415
    from matplotlib.figure import Figure  # noqa: PLC0415

    fig = Figure(figsize=(cols * tile_w / 100.0, rows * (tile_h + 30) / 100.0), dpi=100, facecolor="white")
    FigureCanvasAgg(fig)
    rendered = None
    with tempfile.TemporaryDirectory() as tmp:
        for name, (x, z) in copies:
            layer_path = os.path.join(tmp, f"{name}.usda")
            layer = Sdf.Layer.CreateNew(layer_path)
            layer.subLayerPaths.append(path)
            # A sublayer's timing is read through the root layer: copy it, or the samples rescale.
            root = stage.GetRootLayer()
            layer.timeCodesPerSecond = root.timeCodesPerSecond
            layer.framesPerSecond = root.framesPerSecond
            layer.startTimeCode = root.startTimeCode
            layer.endTimeCode = root.endTimeCode
            sub = Usd.Stage.Open(layer)
            UsdGeom.SetStageUpAxis(sub, UsdGeom.GetStageUpAxis(stage))
            for other, _ in copies:
                if other != name:
                    sub.OverridePrim(f"/World/{other}").SetActive(False)
            layer.Save()
            tile = os.path.join(tmp, f"{name}.png")
            rendered = preview.render_png(layer_path, tile, frame=frame, time=time, size=(tile_w, tile_h))
            from PIL import Image  # noqa: PLC0415

            img = np.asarray(Image.open(tile).convert("RGB"))
            r, c = zs.index(round(z, 6)), xs.index(round(x, 6))
            ax = fig.add_axes((c / cols, 1.0 - (r + 1) / rows, 1.0 / cols, (1.0 / rows) * tile_h / (tile_h + 30)))
            ax.imshow(img)
            ax.set_axis_off()
            fig.text((c + 0.5) / cols, 1.0 - r / rows - 0.5 * (30 / (tile_h + 30)) / rows, name,
                     ha="center", va="center", fontsize=13, family="monospace")
    save_atomic(png_path, lambda tmp: fig.savefig(tmp, format="png", facecolor="white"), "--png")
    return rendered

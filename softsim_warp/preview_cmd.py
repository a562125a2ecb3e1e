"""``softsim preview``: pictures of a softsim USD file without a 3D tool (see ``preview.py``).

``softsim preview OUT.usdc --png frame.png [--frame N | --time T] [--gif anim.gif [--fps N]]``
"""

from __future__ import annotations

import sys

from .errors import CommandLineError, UserError

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
    add_common(p)
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
    from .outputs import check_writable  # noqa: PLC0415

    if not args.png and not args.gif:
        raise CommandLineError("softsim preview", "give --png FILE and/or --gif FILE")
    if (args.frame is not None or args.time is not None) and not args.png:
        raise CommandLineError("--frame/--time", "choose the frame of --png; give --png FILE too")
    if args.fps is not None and not args.gif:
        raise CommandLineError("--fps", "sets the frame rate of --gif; give --gif FILE too")
    if args.png:
        check_writable(args.png, "--png", suffixes=(".png",))
    if args.gif:
        check_writable(args.gif, "--gif", suffixes=(".gif",))
    size = _size(args.size)
    from . import preview  # noqa: PLC0415

    try:
        if args.png:
            kw = {"size": size} if size else {}
            frame = preview.render_png(args.usd, args.png, frame=args.frame, time=args.time, **kw)
            print(f"{args.usd}: frame {frame:g} -> {args.png}", file=sys.stderr)
        if args.gif:
            kw = {"size": size} if size else {}
            count = preview.render_gif(args.usd, args.gif, fps=args.fps, **kw)
            print(f"{args.usd}: {count} frames -> {args.gif}", file=sys.stderr)
    except ValueError as e:
        # preview.py reports bad input as one line "<file>: <what is wrong> (got <value>)".
        source, _, message = str(e).partition(": ")
        raise UserError(source, None, message or "cannot render") from None
    return 0


def render_gif_or_error(usd_path, gif_path, fps=None):
    """``softsim run --preview``: the GIF of a finished run; bad input becomes a one-line UserError."""
    from . import preview  # noqa: PLC0415

    try:
        count = preview.render_gif(usd_path, gif_path, fps=fps)
    except ValueError as e:
        source, _, message = str(e).partition(": ")
        raise UserError(source, None, message or "cannot render") from None
    print(f"{usd_path}: {count} frames -> {gif_path}", file=sys.stderr)

"""``softsim scenes``: list the built-in scenes."""

from __future__ import annotations

from ..io.scene import builtin_scenes

COMMAND = "scenes"


def add_parser(subparsers, add_common):
    subparsers.add_parser("scenes", help="list the built-in scenes")


def run(args) -> int:
    scenes = builtin_scenes()
    width = max(len(n) for n in scenes)
    for name, desc in scenes.items():
        print(f"{name:<{width}}  {desc}")
    return 0

"""Input and output: scene files and their checks, USD writing and reading, metrics, the frame loop.

Imports the core, never ``softsim_warp.commands``.
"""

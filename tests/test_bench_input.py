"""``softsim bench`` refuses what it cannot use: one line on stderr, exit 2, nothing written.

Values the benchmark would use wrongly (a negative or non-finite step or stiffness for the implicit
peer comparison), ``--set`` where no scene is built (it is validated against ``--scene`` when there
is one), and flags of the ``--contact`` benchmark given without it (or the reverse).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from softsim_warp.commands import bench
from softsim_warp.commands.cli import build_parser, main

sys.path.insert(0, str(Path(__file__).parent))

# The smallest benchmark: a 3^3 jelly, a few steps, one repeat, one integrator.
TINY = ["bench", "--sizes", "3", "--steps", "2", "--repeats", "1", "--integrators", "euler", "--quiet"]


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: "), err
    return err.strip()


@pytest.mark.parametrize(
    "argv, line",
    [
        (["--implicit-peer-dt=-1"], "command line: --implicit-peer-dt: must be a finite number > 0 (got -1.0)"),
        (["--implicit-peer-dt", "0"], "command line: --implicit-peer-dt: must be a finite number > 0 (got 0.0)"),
        (["--implicit-peer-dt", "nan"], "command line: --implicit-peer-dt: must be a finite number > 0 (got nan)"),
        (["--implicit-peer-ks=-1"], "command line: --implicit-peer-ks: must be a finite number > 0 (got -1.0)"),
        (["--implicit-peer-ks", "inf"], "command line: --implicit-peer-ks: must be a finite number > 0 (got inf)"),
        (["--set", "nonsense"], "command line: --set: changes a scene, so it applies only with --scene"),
        (["--set", "jelly.0.springs.structural.ks=-5"], "(got 'jelly.0.springs.structural.ks=-5')"),
        (["--set", "foo.bar=1"], "command line: --set: changes a scene, so it applies only with --scene"),
        (["--jellies", "0"], "command line: --jellies: applies only with --contact (got '0')"),
        (["--contact-size", "3"], "command line: --contact-size: applies only with --contact (got 3)"),
        (["--contact", "--set", "foo.bar=1"], "command line: --set: changes a scene"),
        (["--contact", "--scene", "jelly_drop"], "command line: --scene: not with --contact"),
        (["--contact", "--variants"], "command line: --variants: not with --contact"),
        (["--contact", "--paths", "lattice"], "command line: --paths: not with --contact"),
        (["--contact", "--copies", "2"], "command line: --copies: not with --contact"),
        (["--implicit-peer-dt", "0.02"], "command line: --implicit-peer-dt: sets the implicit integrator's run"),
        (["--peer", "newton", "--implicit-peer-ks", "1e4"], "--implicit-peer-ks: sets the implicit integrator's run"),
    ],
)
def test_bad_flag_is_one_line(tmp_path, capsys, argv, line):
    out = tmp_path / "b.json"
    out.write_text("{}\n")  # an earlier report: left as it is
    assert main([*TINY, *argv, "--out", str(out)]) == 2
    err = _one_line(capsys)
    assert line in err, err
    assert out.read_text() == "{}\n"


def test_plot_with_contact_is_refused(tmp_path, capsys):
    plot = tmp_path / "b.png"
    assert main([*TINY, "--contact", "--plot", str(plot)]) == 2
    assert "command line: --plot: not with --contact" in _one_line(capsys)
    assert not plot.exists()


@pytest.fixture
def scene(base_scene):
    return base_scene


@pytest.mark.parametrize(
    "override, line",
    [
        ("nonsense", "command line: --set: expected KEY=VALUE"),
        ("jelly.0.springs.structural.ks=-5", "base.toml: jelly.0.springs.structural.ks: must be a finite number >= 0"),
        ("foo.bar=1", "base.toml: foo: unknown key"),
    ],
)
def test_set_is_validated_against_the_scene(tmp_path, capsys, scene, override, line):
    out = tmp_path / "b.json"
    assert main([*TINY, "--scene", str(scene), "--set", override, "--out", str(out)]) == 2
    assert line in _one_line(capsys)
    assert not out.exists()


def test_set_with_scene_is_used(tmp_path, capsys, scene):
    """A valid --set with --scene runs on the scene it changed (frames of the scene are irrelevant)."""
    out = tmp_path / "b.json"
    argv = [*TINY, "--scene", str(scene), "--set", "simulation.dt=0.0005", "--out", str(out)]
    assert main(argv) == 0
    data = json.loads(out.read_text())
    assert data["settings"]["scene"] == str(scene)
    assert data["arguments"]["overrides"] == ["simulation.dt=0.0005"]
    assert [r["particles"] for r in data["results"]] == [27]


def test_contact_flags_get_their_defaults_with_contact_only():
    parser = build_parser()
    args = parser.parse_args(["bench", "--contact"])
    bench._check_flags(args)
    assert args.jellies == bench.DEFAULT_JELLIES and args.contact_size == 10
    args = parser.parse_args(["bench", "--contact", "--jellies", "2,8", "--contact-size", "3"])
    bench._check_flags(args)
    assert args.jellies == "2,8" and args.contact_size == 3
    args = parser.parse_args(["bench"])
    bench._check_flags(args)
    assert args.jellies is None and args.contact_size is None

"""Every examples/example_*.py runs on the CPU with a few frames, exits 0 and prints what it should.

Examples are found by glob, so a new one is run too: each takes ``--device`` and ``--frames`` (and
``--out`` if it writes a file). ``ARGS`` holds the small settings of the known ones and ``CHECKS`` a
physical check of their output that a broken example cannot pass by accident.
"""

import math
import pathlib
import re
import subprocess
import sys

import numpy as np
import pytest

EXAMPLES = pathlib.Path(__file__).resolve().parents[1] / "examples"
PATHS = sorted(EXAMPLES.glob("example_*.py"))

# Per example: extra arguments, with {tmp} standing for the test's temporary directory.
ARGS = {
    "example_drop_jelly_usd": ["--frames", "4", "--resolution", "4", "--out", "{tmp}/drop.usda"],
    "example_batched_worlds": ["--frames", "40", "--resolution", "4", "--ks", "30,300,3000", "--out", "{tmp}/b.usdc"],
    "example_pinned_and_custom_force": ["--frames", "5", "--resolution", "4"],
}
DEFAULT_ARGS = ["--frames", "2"]


def value(pattern, text):
    match = re.search(pattern, text, re.MULTILINE)
    assert match, f"{pattern!r} not in the output:\n{text}"
    return float(match.group(1))


def check_drop_jelly_usd(out, tmp):
    from pxr import Usd, UsdGeom  # noqa: PLC0415

    path = tmp / "drop.usda"
    assert f"to {path.resolve()}" in out
    stage = Usd.Stage.Open(str(path))
    points = UsdGeom.Points(stage.GetPrimAtPath("/World/Jelly_0/Particles")).GetPointsAttr()
    assert points.GetTimeSamples() == [0.0, 1.0, 2.0, 3.0, 4.0]
    last = np.array(points.Get(4), dtype=np.float64)
    assert last.shape == (4**3, 3)
    # The printed height is that of the last frame written, and 4 frames (1/15 s) after release the
    # jelly is still in free fall from rest at 1 m. Symplectic Euler takes a constant acceleration
    # exactly up to its lag: y_n = 1 - g t^2 / 2 - g h t / 2 (h the printed steps per frame at 60 fps),
    # to float32 rounding (4 eps sqrt(steps); 4e-8 is measured).
    com = value(r"final centre-of-mass height: (\S+) m", out)
    assert com == pytest.approx(last[:, 1].mean(), abs=2e-6)
    steps_per_frame = int(value(r"(\d+) steps per frame", out))
    h, t = 1.0 / (60 * steps_per_frame), 4 / 60
    exact = 1.0 - 0.5 * 9.8 * t * t - 0.5 * 9.8 * h * t
    eps = float(np.finfo(np.float32).eps)
    assert last[:, 1].mean() == pytest.approx(exact, abs=4 * eps * math.sqrt(4 * steps_per_frame))


def check_batched_worlds(out, tmp):
    from pxr import Usd, UsdGeom  # noqa: PLC0415

    rows = re.findall(r"^\s*(\d+)\s+(\w+)\s+(\S+)\s+(\S+)\s+(\S+)\s+(\S+)$", out, re.MULTILINE)
    table = {(method, float(ks)): (float(impact), float(rebound)) for _, method, ks, impact, rebound, _ in rows}
    assert len(table) == 6, out
    for method in ("symplectic", "rk4"):
        impacts = [table[method, ks][0] for ks in (30.0, 300.0, 3000.0)]
        assert impacts[0] < impacts[1] < impacts[2], out  # softer springs squash deeper
        assert all(table[method, ks][1] > table[method, ks][0] + 0.05 for ks in (30.0, 300.0, 3000.0)), out
    for ks in (30.0, 300.0, 3000.0):  # the two methods agree on the same jelly
        assert table["symplectic", ks][0] == pytest.approx(table["rk4", ks][0], abs=5e-3)
    stage = Usd.Stage.Open(str(tmp / "b.usdc"))
    points = UsdGeom.Points(stage.GetPrimAtPath("/World/rk4_ks_3000/Jelly/Particles")).GetPointsAttr()
    assert len(points.GetTimeSamples()) == 41


def check_pinned_and_custom_force(out, tmp):
    assert value(r"pinned particles moved: (\S+) m", out) == 0.0
    assert value(r"sagged under gravity by (\S+) m", out) > 1e-3
    assert abs(value(r"drift: calm (\S+) m", out)) < 1e-6  # symmetric: no sideways drift without wind
    assert value(r"changed the drift by (\S+) m", out) > 1e-3


CHECKS = {
    "example_drop_jelly_usd": check_drop_jelly_usd,
    "example_batched_worlds": check_batched_worlds,
    "example_pinned_and_custom_force": check_pinned_and_custom_force,
}


def test_examples_found():
    assert set(ARGS) <= {p.stem for p in PATHS}


@pytest.mark.parametrize("path", PATHS, ids=[p.stem for p in PATHS])
def test_example(path, tmp_path):
    args = [a.replace("{tmp}", str(tmp_path)) for a in ARGS.get(path.stem, DEFAULT_ARGS)]
    proc = subprocess.run(
        [sys.executable, str(path), "--device", "cpu", *args],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, f"stdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    if path.stem in CHECKS:
        CHECKS[path.stem](proc.stdout, tmp_path)
    # Nothing written outside the paths given (default outputs would land in the working directory).
    written = {p.name for p in tmp_path.iterdir()}
    expected = {pathlib.Path(a).name for a in args if a.startswith(str(tmp_path))}
    assert written == expected

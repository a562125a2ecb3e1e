"""Regenerate the measured data of docs/ACCURACY.md: one `softsim accuracy` / `softsim stability` run per case.

Usage (from the repository root, with the package installed)::

    python docs/make_accuracy.py                      # every case, on the CPU
    python docs/make_accuracy.py --device cuda:0 --only jelly_drop_cuda
    python docs/make_accuracy.py --quick              # short runs, to check the pipeline

Each case is a command line (kept as data below). The script runs it, keeps its JSON report and plot
in docs/accuracy/, and rewrites the block between ``<!-- generated:CASE -->`` and
``<!-- /generated:CASE -->`` in docs/ACCURACY.md with the command, the table and the plot, so the
document always shows what the commands print. Timings depend on the machine: the report names it.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

DOCS = Path(__file__).resolve().parent
OUT = DOCS / "accuracy"
DOC = DOCS / "ACCURACY.md"

# name: (device kind, arguments after `softsim`). {out} and {plot} are filled in per case.
CASES = {
    "free_flight_f64": ("cpu", "accuracy free_flight --precision float64 --duration 1 "
                               "--dts 4e-3,2e-3,1e-3,5e-4,2.5e-4,1.25e-4,6.25e-5 --reference-dt 1.5e-5"),
    "free_flight_f32": ("cpu", "accuracy free_flight --precision float32 --duration 1 "
                               "--dts 4e-3,2e-3,1e-3,5e-4,2.5e-4,1.25e-4,6.25e-5 --reference-dt 1.5e-5"),
    "jelly_drop": ("cpu", "accuracy jelly_drop --duration 0.5 --dts 1.6e-3,8e-4,4e-4,2e-4,1e-4 --reference-dt 5e-6"),
    "jelly_drop_1s": ("cpu", "accuracy jelly_drop --duration 1 --dts 8e-4,4e-4,2e-4,1e-4 --reference-dt 1e-5"),
    "jelly_drop_cuda": ("cuda", "accuracy jelly_drop --duration 0.5 --dts 1.6e-3,8e-4,4e-4,2e-4,1e-4 "
                                "--reference-dt 5e-6"),
    "seed_bowl": ("cpu", "accuracy seed_bowl --duration 3 --dts 2e-3,1e-3,5e-4,2.5e-4 --reference-dt 2.5e-5"),
    "stability_free_flight": ("cpu", "stability free_flight"),
    "stability_jelly_drop": ("cpu", "stability jelly_drop --duration 0.5"),
}
# --quick: the same commands, shortened, to check the pipeline in a minute.
QUICK = {"--duration 1 ": "--duration 0.1 ", "--duration 3 ": "--duration 0.1 ", "--duration 0.5": "--duration 0.05"}


def builtin_scenes():
    from softsim_warp.io.scene import builtin_scenes as names  # noqa: PLC0415

    return names()


def run_case(name, kind, args, device, quick):
    scene = args.split()[1]
    if scene not in builtin_scenes():
        return None, f"scene `{scene}` is not built in on this branch; TODO: rerun `python docs/make_accuracy.py --only {name}` once it is"
    if kind == "cuda" and not device.startswith("cuda"):
        return None, "needs --device cuda:N"
    if kind == "cpu" and device.startswith("cuda"):
        return None, "a CPU case; run without --device"
    if quick:
        for a, b in QUICK.items():
            args = args.replace(a, b)
        if args.startswith("stability"):
            args += " --ks 1e2,1e6 --steps 200 --rtol 0.1"
    OUT.mkdir(exist_ok=True)
    out, plot = OUT / f"{name}.json", OUT / f"{name}.png"
    cmd = f"softsim {args} --device {device} --out {out.relative_to(DOCS.parent)} --plot {plot.relative_to(DOCS.parent)}"
    print(f"$ {cmd}", flush=True)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "softsim_warp", *shlex.split(cmd)[1:]], cwd=DOCS.parent,
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{name} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    report = json.loads(out.read_text())
    report["generated"] = {"command": cmd, "seconds": time.perf_counter() - t0, "machine": platform.node(),
                           "processor": platform.processor() or platform.machine(), "python": platform.python_version()}
    out.write_text(json.dumps(report, indent=1) + "\n")
    return report, cmd


def unbounded(value):
    """A stability report as the command holds it: its JSON writes an infinite dt (no limit found,
    or none predicted) as null, which the table prints as inf."""
    if isinstance(value, list):
        return [unbounded(v) for v in value]
    if isinstance(value, dict):
        return {k: math.inf if v is None and k in ("predicted", "dt", "unstable_dt") else unbounded(v)
                for k, v in value.items()}
    return value


def table(report):
    if "limits" in report:
        from softsim_warp.studies.stability import format_table  # noqa: PLC0415

        return format_table(unbounded(report))
    else:
        from softsim_warp.studies.accuracy import format_table  # noqa: PLC0415
    return format_table(report)


def block(name, report, note):
    if report is None:
        return f"*Not generated: {note}.*"
    g = report["generated"]
    return (f"```\n$ {g['command']}\n```\n\n```text\n{table(report)}\n```\n\n"
            f"![{name}](accuracy/{name}.png)\n\n"
            f"*{report['device']} on {g['machine']} ({g['processor']}); the command took {g['seconds']:.0f} s.*")


def update_doc(blocks):
    text = DOC.read_text()
    for name, body in blocks.items():
        pattern = re.compile(rf"(<!-- generated:{name} -->\n)(?:.*?\n)?(<!-- /generated:{name} -->)", re.S)
        if not pattern.search(text):
            print(f"note: docs/ACCURACY.md has no block for {name}", file=sys.stderr)
            continue
        text = pattern.sub(lambda m: m.group(1) + body + "\n" + m.group(2), text)
    DOC.write_text(text)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--only", nargs="*", help="case names (default: every case for this device)")
    p.add_argument("--quick", action="store_true", help="short runs; does not touch docs/ACCURACY.md")
    p.add_argument("--render", action="store_true",
                   help="run nothing: rewrite docs/ACCURACY.md from the JSON reports already in docs/accuracy/")
    a = p.parse_args()
    blocks = {}
    for name, (kind, args) in CASES.items():
        if a.only and name not in a.only:
            continue
        if a.render:
            path = OUT / f"{name}.json"
            if path.exists():
                blocks[name] = block(name, json.loads(path.read_text()), "")
            continue
        report, note = run_case(name, kind, args, a.device, a.quick)
        if report is None:
            print(f"skip {name}: {note}", flush=True)
            if "not built in" in note:  # a device mismatch leaves the block as it was
                blocks[name] = block(name, None, note)
            continue
        print(table(report), flush=True)
        blocks[name] = block(name, report, note)
    if not a.quick:
        update_doc(blocks)


if __name__ == "__main__":
    main()

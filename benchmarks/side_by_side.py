"""Builds of softsim-warp timed side by side: ``softsim bench`` for each build in turn, several rounds.

Run (on the GPU machine, from the checkout)::

    python benchmarks/side_by_side.py --build main=main --build merged=merged-last-pass \\
        --rounds 2 --out side_by_side.json -- --contact --device cuda:0 --jellies 1000

Each ``--build NAME=SOURCE`` is a git revision of this checkout (exported with ``git archive``) or a
source directory. Every build is installed into its own folder (``pip install --no-deps --target``),
and each round runs ``python -m softsim_warp bench ARGS --out ...`` once per build, in turn, with
that folder on ``PYTHONPATH`` and the working directory outside the checkout: run from the
checkout's root, ``python -m softsim_warp`` would import the checkout's own package (its
``__init__`` adds the top-level ``kernels/`` to the package) before anything on ``PYTHONPATH``, and
every build would time the same code. Before timing, each build reports the file it imports
``softsim_warp`` from, and a build that imports any other copy stops the run.

The table gives each bench row (jellies or size, solver, contact) by round and build, in ms per
step, and the ratio of each build to the first; ``--out`` writes every run's JSON together.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def export(source: str, into: str) -> str:
    """A source tree for ``source``: the directory itself, or revision ``source`` of this checkout."""
    if os.path.isdir(source):
        return os.path.abspath(source)
    tar = os.path.join(into, "src.tar")
    with open(tar, "wb") as f:
        done = subprocess.run(["git", "-C", ROOT, "archive", source], stdout=f, stderr=subprocess.PIPE, text=True)
    if done.returncode != 0:
        raise SystemExit(f"--build: {source!r} is neither a directory nor a revision of {ROOT}: {done.stderr.strip()}")
    src = os.path.join(into, "src")
    with tarfile.open(tar) as t:
        t.extractall(src, filter="data")
    return src


def install(name: str, source: str, work: str) -> str:
    """Install build ``name`` from ``source`` into its own folder; returns the folder."""
    folder = os.path.join(work, name)
    os.makedirs(folder)
    src = export(source, folder)
    target = os.path.join(folder, "site")
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--target", target, src],
        check=True,
        stdout=subprocess.DEVNULL,
    )
    return target


def imported_from(target: str, cwd: str) -> str:
    """The file ``softsim_warp`` is imported from with ``target`` on PYTHONPATH, run in ``cwd``."""
    out = subprocess.run(
        [sys.executable, "-c", "import softsim_warp.kernels as k; print(k.__file__)"],
        cwd=cwd,
        env=dict(os.environ, PYTHONPATH=target),
        capture_output=True,
        text=True,
        check=True,
    )
    return out.stdout.strip()


def row_key(r: dict) -> str:
    size = r.get("jellies", r.get("size", r.get("particles")))
    contact = r.get("contact")
    return f"{size} {r.get('solver', '')}" + ("" if contact is None else (" contact" if contact else " no contact"))


def write(path: str, builds: list, bench_args: list, runs: list) -> None:
    """Every run so far as JSON, replacing ``path`` whole (a temporary file renamed over it)."""
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump({"builds": dict(builds), "bench_args": bench_args, "runs": runs}, f, indent=1)
    os.replace(tmp, path)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    bench_args = argv[argv.index("--") + 1 :] if "--" in argv else []
    own = argv[: argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--build", action="append", required=True, help="NAME=REVISION or NAME=DIRECTORY (two or more)")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--out", default=None, help="write every run's results as JSON")
    args = p.parse_args(own)
    builds = [b.split("=", 1) for b in args.build]
    if len(builds) < 2 or any(len(b) != 2 or not b[0] or not b[1] for b in builds):
        raise SystemExit(f"--build: expected two or more NAME=SOURCE, got {args.build!r}")
    if len({name for name, _ in builds}) != len(builds):
        raise SystemExit(f"--build: names must differ, got {[name for name, _ in builds]!r}")
    if args.rounds < 1:
        raise SystemExit(f"--rounds: expected at least 1, got {args.rounds}")
    with tempfile.TemporaryDirectory(prefix="side_by_side_") as work:
        run_dir = os.path.join(work, "run")
        os.makedirs(run_dir)
        targets = {}
        for name, source in builds:
            targets[name] = install(name, source, work)
            path = imported_from(targets[name], run_dir)
            if not path.startswith(targets[name] + os.sep):
                raise SystemExit(f"build {name}: softsim_warp.kernels imports from {path}, not from {targets[name]}")
            print(f"build {name}: {source} -> {path}", flush=True)
        runs = []
        for k in range(args.rounds):
            for name, _ in builds:
                out = os.path.join(work, f"{name}_{k}.json")
                print(f"round {k}, build {name}:", flush=True)
                cmd = [sys.executable, "-m", "softsim_warp", "bench", *bench_args, "--out", out]
                subprocess.run(cmd, cwd=run_dir, env=dict(os.environ, PYTHONPATH=targets[name]), check=True)
                with open(out) as f:
                    runs.append({"build": name, "round": k, "report": json.load(f)})
                if args.out:  # after every run, so a run cut short keeps the rounds it finished
                    write(args.out, builds, bench_args, runs)
    first = builds[0][0]
    table = {}
    for run in runs:
        for r in run["report"]["results"]:
            table.setdefault((row_key(r), run["round"]), {})[run["build"]] = r["ms_per_step"]
    names = [name for name, _ in builds]
    print(f"{'bench row':<40} {'round':>5} " + " ".join(f"{n + ' [ms]':>16}" for n in names) + "  ratio to " + first)
    for (key, k), ms in table.items():
        cells = " ".join(f"{ms.get(n, float('nan')):16.4f}" for n in names)
        ratios = " ".join(f"{ms[n] / ms[first]:.3f}" for n in names[1:] if n in ms and first in ms)
        print(f"{key:<40} {k:>5} {cells}  {ratios}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Registers and SASS instruction mix of the fused stage kernels, compiled here without a GPU.

    pip install nvidia-cuda-cuobjdump nvidia-cuda-nvdisasm   # the two tools, any machine
    python benchmarks/sass_probe.py --arch 90 integrate_lattice_stage_single integrate_lattice_stage_padded_uniform

Warp compiles CUDA through NVRTC, which its wheel carries, so a machine without a driver can still
build a module for a given architecture (``wp.compile_aot_module(..., arch=90, use_ptx=False)``,
sm_90: the H100 and H200). ``cuobjdump -res-usage`` then gives each kernel's registers, stack and
static shared memory, and ``cuobjdump -sass`` its machine code, counted here by opcode for the
forward kernel. Static counts: the gather is straight-line, so its share is what a thread
executes; the stage tail's branches (contact, stage kinds) are counted whole.

Checked against the H200: the one-jelly stage gives 64 registers and 2032 instructions
(430 FFMA, 280 LDG), as ``cuobjdump`` of the cubin Warp cached there did (docs/PERFORMANCE.md).
Kernel names are those in ``model.kernels`` (``kernels/lattice.py``), float32.
"""

import argparse
import collections
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile

import warp as wp

wp.config.quiet = True


def _tool(name):
    """A CUDA binary utility from PATH or from the pip wheels (``nvidia/cu*/bin``)."""
    found = shutil.which(name)
    if found:
        return found
    import nvidia  # the namespace package of the wheels

    for root in nvidia.__path__:
        for sub in sorted(os.listdir(root)):
            path = os.path.join(root, sub, "bin", name)
            if os.path.isfile(path):
                return path
    sys.exit(f"sass_probe: {name} not found (pip install nvidia-cuda-cuobjdump nvidia-cuda-nvdisasm)")


def probe(kernel, arch, cuobjdump):
    """Registers, stack, shared memory and opcode counts of ``kernel``'s forward CUDA function."""
    with tempfile.TemporaryDirectory() as out:
        paths = [str(p) for p in wp.compile_aot_module(kernel.module, arch=arch, use_ptx=False, module_dir=out)]
        cubin = next(p for p in paths if p.endswith(".cubin"))
        env = dict(os.environ, PATH=os.path.dirname(cuobjdump) + os.pathsep + os.environ.get("PATH", ""))
        res = subprocess.run([cuobjdump, "-res-usage", cubin], capture_output=True, text=True, check=True).stdout
        sass = subprocess.run([cuobjdump, "-sass", cubin], capture_output=True, text=True, check=True, env=env).stdout
    for body in re.split(r"\n\s*Function : ", sass)[1:]:
        name = body.split("\n", 1)[0].strip()
        if not name.endswith("forward"):
            continue
        ops = collections.Counter()
        for line in body.splitlines():
            m = re.match(r"\s*/\*[0-9a-f]{4}\*/\s+(?:@!?U?P\w+\s+)?([A-Z][A-Z0-9_]*)", line)
            if m:
                ops[m.group(1)] += 1
        usage = re.search(re.escape(name) + r":\s*REG:(\d+) STACK:(\d+) SHARED:(\d+)", res)
        registers, stack, shared = (int(x) for x in usage.groups())
        return {
            "registers": registers,
            "stack_bytes": stack,
            "shared_bytes": shared,
            "instructions": sum(ops.values()),
            "opcodes": dict(ops.most_common()),
        }
    raise RuntimeError(f"no forward function in the cubin of {kernel.key}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("kernels", nargs="*", default=["integrate_lattice_stage_single"])
    parser.add_argument("--arch", type=int, default=90, help="SM architecture (90: Hopper)")
    parser.add_argument("--out", default=None, help="JSON file for the results")
    args = parser.parse_args()
    from softsim_warp.kernels import get_kernels

    kernels = get_kernels(wp.float32)
    cuobjdump = _tool("cuobjdump")
    _tool("nvdisasm")  # cuobjdump -sass calls it
    results = {}
    for name in args.kernels:
        r = results[name] = probe(getattr(kernels, name), args.arch, cuobjdump)
        top = ", ".join(f"{op} {n}" for op, n in list(r["opcodes"].items())[:8])
        print(
            f"{name}: {r['registers']} registers, {r['stack_bytes']} B stack, {r['shared_bytes']} B shared, "
            f"{r['instructions']} instructions ({top})"
        )
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"arch": args.arch, "warp": wp.__version__, "kernels": results}, f, indent=1)


if __name__ == "__main__":
    main()

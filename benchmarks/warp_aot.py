"""Compile the fused solver's Warp kernels ahead of time for a CUDA architecture, on a
machine without a GPU, into Warp's kernel cache (``WARP_CACHE_PATH``, default
``~/.cache/warp``), so that a lent GPU loads them instead of compiling for minutes:

    python benchmarks/warp_aot.py --arch 90 [--block-dims 32 256] [--cache DIR]

Warp compiles one module per set of registered overloads and per threads-per-block
value (``fused.CUDA_BLOCK_DIM``); a process that solves in float64 and then float32 loads
the module with both sets, so every set a run may meet is compiled: float64, float64 +
float32, float32. Each set runs in its own process (registering overloads cannot be
undone). On the GPU, Warp must be told to load cubins (``warp.config.cuda_output =
"cubin"``): it may otherwise pick PTX for the driver and compile that there.
Prints the module hashes written (the cache's folder names end in them).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

from diffcontact.cli_args import positive_int

SETS = ("64", "64 32", "32")

_CHILD = """
import sys, torch
from diffcontact.contact import fused
wp, kernels = fused._load()
arch, block_dim, names = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3].split()
for name in names:
    fused._overloads(torch.float64 if name == "64" else torch.float32)
module = wp.get_module(kernels.__name__)
module.options["block_dim"] = block_dim
wp.compile_aot_module(module, arch=arch, use_ptx=False)
print(names, block_dim, module.get_module_hash(block_dim).hex()[:7])
"""


def compile_set(arch: int, block_dim: int, names: str, env: dict) -> None:
    """Compile the module with the overloads ``names`` (e.g. ``"64 32"``) for ``arch`` and
    ``block_dim`` threads per block, in a process of its own; prints its hash and time."""
    start = time.perf_counter()
    command = [sys.executable, "-c", _CHILD, str(arch), str(block_dim), names]
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode:
        sys.stderr.write(done.stdout + done.stderr)
        raise SystemExit(f"warp_aot.py: compiling {names!r} with {block_dim} threads failed")
    print(done.stdout.strip(), f"{time.perf_counter() - start:.0f} s", flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--arch", type=positive_int, default=90, help="CUDA architecture (90: Hopper)"
    )
    parser.add_argument(
        "--block-dims",
        type=positive_int,
        nargs="+",
        default=None,
        help="threads per block (default: fused.CUDA_BLOCK_DIM)",
    )
    parser.add_argument(
        "--sets",
        nargs="+",
        choices=SETS,
        default=list(SETS),
        help="sets of overloads, in bits (default: all three)",
    )
    parser.add_argument("--cache", default=None, help="Warp's kernel cache (WARP_CACHE_PATH)")
    args = parser.parse_args(argv)
    if args.block_dims is None:
        from diffcontact.contact import fused

        args.block_dims = [fused.CUDA_BLOCK_DIM]
    env = dict(os.environ)
    if args.cache:
        env["WARP_CACHE_PATH"] = args.cache
    for block_dim in args.block_dims:
        for names in args.sets:
            compile_set(args.arch, block_dim, names, env)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Benchmark: the Warp solver's C++ Cholesky routines against the same loops in Warp code.

    python benchmarks/run.py kernels [--quick] [--sizes 10 20 60] [--batch 1024]

One table of microseconds per problem (one CPU thread per launch, ``--batch`` problems,
float64 and float32): the right-looking Cholesky factorisation of an n x n positive
definite matrix and a solve with it, as :mod:`diffcontact.contact.warp_kernels` runs them
(C++ over raw pointers, ``wp.func_native``), and as the same loops written with Warp's
array indexing (which checks every index for a negative value). Both give bitwise the same
factor (checked). Each launch first copies the matrix in, also timed alone (``copy``) and
subtracted. n = 60 is a problem with 30 contacts in two dimensions, all sticking.
"""

import argparse
import statistics
import time
from typing import Any

import torch

from common import machine_header, settings
from diffcontact.cli_args import positive_int


def _kernels():
    from diffcontact.contact import fused

    wp, wk = fused._load()

    @wp.func
    def warp_cholesky(M: wp.array3d(dtype=Any), t: int, n: int):
        zero = type(M[t, 0, 0])(0.0)
        for j in range(n):
            s = M[t, j, j]
            if not (s > zero):
                return False
            ljj = wp.sqrt(s)
            M[t, j, j] = ljj
            for i in range(j + 1, n):
                lij = M[t, i, j] / ljj
                M[t, i, j] = lij
                M[t, j, i] = lij
            for i in range(j + 1, n):
                lij = M[t, j, i]
                for k in range(j + 1, i + 1):
                    M[t, i, k] = M[t, i, k] - lij * M[t, j, k]
        return True

    @wp.func
    def warp_solve(M: wp.array3d(dtype=Any), t: int, n: int, v: wp.array3d(dtype=Any)):
        for i in range(n):
            s = type(M[t, 0, 0])(0.0)
            for k in range(i):
                s = s + M[t, i, k] * v[t, 0, k]
            v[t, 0, i] = (v[t, 0, i] - s) / M[t, i, i]
        for ii in range(n):
            i = n - 1 - ii
            xi = v[t, 0, i] / M[t, i, i]
            v[t, 0, i] = xi
            for k in range(i):
                v[t, 0, k] = v[t, 0, k] - M[t, i, k] * xi

    @wp.func
    def copy_in(M: wp.array3d(dtype=Any), M0: wp.array3d(dtype=Any), v: wp.array3d(dtype=Any),
                v0: wp.array3d(dtype=Any), t: int, n: int):  # fmt: skip
        for i in range(n):
            v[t, 0, i] = v0[t, 0, i]
            for j in range(n):
                M[t, i, j] = M0[t, i, j]

    @wp.kernel(module="unique")
    def copy_only(M: wp.array3d(dtype=Any), M0: wp.array3d(dtype=Any), v: wp.array3d(dtype=Any),
                  v0: wp.array3d(dtype=Any), n: int):  # fmt: skip
        copy_in(M, M0, v, v0, wp.tid(), n)

    @wp.kernel(module="unique")
    def package(M: wp.array3d(dtype=Any), M0: wp.array3d(dtype=Any), v: wp.array3d(dtype=Any),
                v0: wp.array3d(dtype=Any), n: int):  # fmt: skip
        t = wp.tid()
        copy_in(M, M0, v, v0, t, n)
        if wk._cholesky(M, t, n):
            wk._cholesky_solve(M, t, n, v, 0)

    @wp.kernel(module="unique")
    def warp_code(M: wp.array3d(dtype=Any), M0: wp.array3d(dtype=Any), v: wp.array3d(dtype=Any),
                  v0: wp.array3d(dtype=Any), n: int):  # fmt: skip
        t = wp.tid()
        copy_in(M, M0, v, v0, t, n)
        if warp_cholesky(M, t, n):
            warp_solve(M, t, n, v)

    return wp, {"copy": copy_only, "C++": package, "Warp": warp_code}


def _time(wp, kernel, args: list, batch: int, reps: int) -> float:
    """Median microseconds per problem of ``reps`` launches after a warm-up."""
    wp.launch(kernel, dim=batch, inputs=args, device="cpu")
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        wp.launch(kernel, dim=batch, inputs=args, device="cpu")
        wp.synchronize()
        times.append(time.perf_counter() - t0)
    return 1e6 * statistics.median(times) / batch


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="n = 20 only, 3 launches")
    parser.add_argument(
        "--sizes", type=positive_int, nargs="+", default=None,
        help="matrix sizes n (default 10 20 60, quick 20)",
    )  # fmt: skip
    parser.add_argument("--batch", type=positive_int, default=1024)
    args = parser.parse_args(argv)
    try:
        wp, kernels = _kernels()
    except ImportError:
        print("kernels: needs NVIDIA Warp (pip install warp-lang)")
        return 0
    sizes = settings(args, {"sizes": [10, 20, 60]}, {"sizes": [20]})["sizes"]
    reps = 3 if args.quick else 9
    print("Cholesky factorisation + solve per problem, the solver's C++ vs Warp indexing")
    print("\n".join(machine_header("cpu", torch.float64)))
    print(f"{'n':>4} {'dtype':>8} | {'Warp us':>8} {'C++ us':>8} {'ratio':>6} | {'copy us':>8}")
    print("-" * 52)
    gen = torch.Generator().manual_seed(0)
    for n in sizes:
        X = torch.randn(args.batch, n, n, generator=gen, dtype=torch.float64)
        A = X @ X.mT + n * torch.eye(n, dtype=torch.float64)
        rhs = torch.randn(args.batch, 1, n, generator=gen, dtype=torch.float64)
        for dtype in (torch.float64, torch.float32):
            M0, v0 = A.to(dtype), rhs.to(dtype)
            us, factors = {}, {}
            for name, kernel in kernels.items():
                M, v = torch.empty_like(M0), torch.empty_like(v0)
                arrays = [wp.from_torch(x) for x in (M, M0, v, v0)]
                us[name] = _time(wp, kernel, [*arrays, n], args.batch, reps)
                factors[name] = M.tril()
            if not torch.equal(factors["C++"], factors["Warp"]):
                print(f"kernels: n = {n} {dtype}: the two factors differ")
                return 1
            warp_us, cpp_us = us["Warp"] - us["copy"], us["C++"] - us["copy"]
            print(f"{n:>4} {str(dtype).removeprefix('torch.'):>8} | {warp_us:8.2f} {cpp_us:8.2f} "
                  f"{warp_us / cpp_us:6.1f} | {us['copy']:8.2f}")  # fmt: skip
    print("us: microseconds per problem, the copy-in subtracted; ratio: Warp / C++.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

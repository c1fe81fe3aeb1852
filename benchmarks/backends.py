"""Benchmark: the solver's two backends side by side, torch (reference) vs Warp (fused).

    python benchmarks/run.py backends [--quick] [--device cpu|cuda] [--threads N]

For each problem family and batch size the same problems are solved by
``solve_cone_qp`` with ``SolverSettings(backend="torch")`` and ``backend="warp"``, in one
run, and the table prints milliseconds per call for the forward solve and for the forward
plus the backward pass of ``loss = sum(f * W)`` to ``A``, ``b`` and ``mu``, the ratio
torch / warp of each, the largest relative difference of the two solutions' contact
velocity changes ``A f`` and the number of torch operations (dispatches) of one forward
call and of its backward pass. Families:

  BP5     d = 2: the compression and restitution problems of BP5 (five disks in a box),
          recorded from ``System("BP5").simulate`` of random states (padded to the largest
          contact count of the batch, as the simulator pads them);
  3D-K    d = 3: K contacts on four point masses in space (sphere-sphere and sphere-wall
          frames), A = J M^-1 J^T (singular when a body has two or more contacts),
          b = J v for random velocities; mu ~ U(0.1, 1).

Times are medians over repetitions after a warm-up call (which also compiles the Warp
kernel on a fresh machine: its time is printed once). See benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import contextlib
import tempfile
import time

import torch

from common import check_device, machine_header, median_time
from diffcontact.cli_args import non_negative_int, positive_int

BATCHES = (1, 64, 1024)


# --------------------------------------------------------------------------------------------
# problems


def bp5_problems(n: int, seed: int) -> dict:
    """At least n BP5 contact problems (d = 2), padded to one contact count."""
    import diffcontact as dc
    from diffcontact.contact import impulse

    calls = []
    solve = impulse.solve_cone_qp

    def record(A, b, mu, d, lower=None, active=None, **kwargs):
        f = solve(A, b, mu, d, lower, active, **kwargs)
        lower = torch.zeros_like(mu) if lower is None else lower
        calls.append([x.detach() for x in (A, b, mu, lower, active)])
        return f

    system = dc.load_system("BP5")
    impulse.solve_cone_qp = record
    try:
        z0 = system.sample_initial_conditions(max(64, n // 4), seed=seed)
        total, steps = 0, 0
        while total < n and steps < 400:
            z = system.simulate(z0, 10)
            z0 = z[:, -1]
            total = sum(c[1].shape[0] for c in calls)
            steps += 10
    finally:
        impulse.solve_cone_qp = solve
    K = max(c[2].shape[-1] for c in calls)
    padded = [pad(*c, K=K, d=2) for c in calls]
    out = {
        k: torch.cat([p[i] for p in padded])[:n]
        for i, k in enumerate("A b mu lower active".split())
    }
    return out | {"d": 2}


def pad(A, b, mu, lower, active, K: int, d: int):
    """Pad a batch to K contacts with inactive ones (zero blocks, mu = 1)."""
    n, k = mu.shape
    if k == K:
        return A, b, mu, lower, active
    C = K * d
    A2 = A.new_zeros(n, C, C)
    A2[:, : k * d, : k * d] = A
    b2 = b.new_zeros(n, C)
    b2[:, : k * d] = b
    mu2, lower2 = mu.new_ones(n, K), lower.new_zeros(n, K)
    mu2[:, :k], lower2[:, :k] = mu, lower
    active2 = active.new_zeros(n, K)
    active2[:, :k] = active
    return A2, b2, mu2, lower2, active2


def spatial_problems(n: int, K: int, seed: int, bodies: int = 4) -> dict:
    """n problems with K contacts (d = 3) on ``bodies`` point masses in space."""
    gen = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    normal = torch.randn(n, K, 3, generator=gen, dtype=f64)
    normal = normal / normal.norm(dim=-1, keepdim=True)
    helper = torch.where(
        normal[..., :1].abs() < 0.9, torch.tensor([1.0, 0, 0]), torch.tensor([0, 1.0, 0])
    )
    t1 = torch.linalg.cross(normal, helper.to(f64))
    t1 = t1 / t1.norm(dim=-1, keepdim=True)
    t2 = torch.linalg.cross(normal, t1)
    frame = torch.stack([normal, t1, t2], -2)  # (n, K, 3, 3): rows n, t1, t2
    first = torch.randint(0, bodies, (n, K), generator=gen)
    second = torch.randint(-1, bodies, (n, K), generator=gen)  # -1: a wall
    second = torch.where(second == first, -1, second)
    J = torch.zeros(n, K, 3, bodies + 1, 3, dtype=f64)
    idx = torch.arange(n)[:, None], torch.arange(K)[None]
    J[idx[0], idx[1], :, first] = frame
    J[idx[0], idx[1], :, second] = -frame  # the wall's column (-1) is dropped below
    J = J[..., :bodies, :].reshape(n, 3 * K, 3 * bodies)
    m_inv = (0.5 + torch.rand(n, bodies, generator=gen, dtype=f64)).repeat_interleave(3, -1)
    A = J @ torch.diag_embed(m_inv) @ J.transpose(-1, -2)
    b = (J @ torch.randn(n, 3 * bodies, 1, generator=gen, dtype=f64)).squeeze(-1)
    mu = 0.1 + 0.9 * torch.rand(n, K, generator=gen, dtype=f64)
    lower = torch.zeros(n, K, dtype=f64)
    active = torch.ones(n, K, dtype=torch.bool)
    return {"A": A, "b": b, "mu": mu, "lower": lower, "active": active, "d": 3}


# --------------------------------------------------------------------------------------------
# timing


def count_dispatches(fn) -> int:
    from torch.utils._python_dispatch import TorchDispatchMode

    class Count(TorchDispatchMode):
        n = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            Count.n += 1
            return func(*args, **(kwargs or {}))

    with Count():
        fn()
    return Count.n


def time_backend(P: dict, B: int, backend: str, device, reps: int) -> dict:
    from diffcontact.contact import SolverSettings, solve_cone_qp

    settings = SolverSettings(backend=backend, check_inputs=False)
    d = P["d"]
    args = [P[k][:B].to(device) for k in ("A", "b", "mu", "lower", "active")]
    W = torch.randn(args[1].shape, generator=torch.Generator().manual_seed(1), dtype=args[1].dtype)
    W = W.to(device)

    def forward():
        return solve_cone_qp(args[0], args[1], args[2], d, args[3], args[4], settings=settings)

    def both():
        A, b, mu = (x.clone().requires_grad_() for x in args[:3])
        f = solve_cone_qp(A, b, mu, d, args[3], args[4], settings=settings)
        (f * W).sum().backward()

    def median(fn) -> float:
        return median_time(fn, device, reps)

    def backward_only() -> int:
        A, b, mu = (x.clone().requires_grad_() for x in args[:3])
        f = solve_cone_qp(A, b, mu, d, args[3], args[4], settings=settings)
        loss = (f * W).sum()
        return count_dispatches(loss.backward)

    f = forward()  # warm-up
    both()
    return {
        "f": f.detach().to("cpu", torch.float64),
        "forward": median(forward),
        "both": median(both),
        "dispatches": count_dispatches(forward),
        "backward dispatches": backward_only(),
    }


HEADER = (
    f"{'family':>7} {'K':>3} {'batch':>6} | {'fwd torch':>10} {'fwd warp':>10} {'ratio':>7} | "
    f"{'f+b torch':>10} {'f+b warp':>10} {'ratio':>7} | {'diff A f':>8} | {'ops torch/warp':>14} | "
    f"{'bwd ops t/w':>11}"
)


def fmt(x: float) -> str:
    return f"{x:.3g}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer repetitions, batches 1 and 64")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--batches", type=positive_int, nargs="+", default=None)
    ap.add_argument("--spatial-contacts", type=positive_int, nargs="+", default=[4, 10])
    ap.add_argument("--threads", type=positive_int, default=None, help="torch intra-op threads")
    ap.add_argument("--seed", type=non_negative_int, default=0)
    ap.add_argument(
        "--cold-cache",
        action="store_true",
        help="compile the Warp kernels into an empty, temporary kernel cache (the header's "
        "first solve then times the compilation a new install pays once per dtype and device)",
    )
    args = ap.parse_args(argv)
    check_device(ap, args.device)
    from diffcontact.contact import fused

    if not fused.warp_installed():
        print("NVIDIA Warp is not installed (pip install diffcontact[warp]): nothing to compare")
        return 0
    if args.threads:
        torch.set_num_threads(args.threads)
    batches = args.batches or ((1, 64) if args.quick else BATCHES)
    device = torch.device(args.device)

    print("friction-cone QP backends: torch (reference) vs warp (fused), ms per call")
    for line in machine_header(args.device, torch.float64):
        print(line)
    import warp

    print(f"warp {warp.__version__}; Warp CPU kernels run on one thread")
    with contextlib.ExitStack() as stack:
        if args.cold_cache:  # before Warp initialises, which reads the setting
            warp.config.kernel_cache_dir = stack.enter_context(tempfile.TemporaryDirectory())
        t0 = time.perf_counter()
        time_backend(spatial_problems(1, 2, args.seed), 1, "warp", device, reps=1)
        first = time.perf_counter() - t0
        cache = "empty kernel cache: compile" if args.cold_cache else "compile or load the kernels"
        print(f"first Warp solve and backward (initialise Warp, {cache}): {first:.1f} s")
        return _compare(args, batches, device)


def _compare(args: argparse.Namespace, batches, device: torch.device) -> int:
    families = [("BP5", bp5_problems(max(batches), args.seed))]
    families += [
        (f"3D-{K}", spatial_problems(max(batches), K, args.seed + K)) for K in args.spatial_contacts
    ]
    print()
    print(HEADER)
    print("-" * len(HEADER))
    for name, P in families:
        for B in batches:
            if B > P["b"].shape[0]:
                continue
            reps = 3 if B >= 1024 else (5 if args.quick else 20)
            t = time_backend(P, B, "torch", device, reps)
            w = time_backend(P, B, "warp", device, reps)
            A = P["A"][:B]
            Af_t, Af_w = (torch.einsum("bij,bj->bi", A, x["f"]) for x in (t, w))
            diff = ((Af_w - Af_t).abs().amax(-1) / Af_t.abs().amax(-1).clamp_min(1)).max()
            print(
                f"{name:>7} {P['mu'].shape[-1]:>3} {B:>6} | "
                f"{fmt(1e3 * t['forward']):>10} {fmt(1e3 * w['forward']):>10} "
                f"{fmt(t['forward'] / w['forward']):>7} | "
                f"{fmt(1e3 * t['both']):>10} {fmt(1e3 * w['both']):>10} "
                f"{fmt(t['both'] / w['both']):>7} | {float(diff):>8.1e} | "
                f"{t['dispatches']:>6}/{w['dispatches']:<7} | "
                f"{t['backward dispatches']:>5}/{w['backward dispatches']:<5}",
                flush=True,
            )
    print()
    print(
        "ratio: torch time / warp time, measured in this run. diff A f: largest "
        "max|A (f_warp - f_torch)| / max(1, max|A f_torch|), the change of contact velocity "
        "(where the minimiser is not unique, singular A, the backends may return different "
        "minimisers, with the same A f). ops: torch operations of one forward call (input "
        "checks off, as inside a simulation step); bwd ops: those of the backward pass of "
        "loss = sum(f * W) (the loss's own backward included)."
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Benchmark: the cost of one contact resolution per contact model (CM, CMr, LCP, Coulomb).

    python benchmarks/run.py contact_models [--quick] [--tasks BP5 BD5] [--device cpu|cuda]
                                            [--dtype float64|float32] [--repeats R]

For each task, N trajectories are simulated with CM; every step's pre-impact states
that have a contact are collected (the integrated states that ``System.simulate`` hands
to the contact model) and their contact problems recorded once (``J_C``, ``Mhat^-1``,
``v``, the contact parameters, the mask, the penetration target), exactly as the
simulator passes them. Each model's ``resolve`` is then timed on that same batch, forward
only and forward + backward (a gradient with respect to ``v``, ``mu`` and ``e_P``), the
best of ``R`` repeats, and the ratio to CM is printed: the cost of the exact-Coulomb
impulse relative to CM's per call (issue 15).
"""

from __future__ import annotations

import argparse
import time
import warnings

import torch

import diffcontact as dc
from common import check_device, check_tasks, machine_header, settings, sync
from diffcontact.cli_args import positive_int
from diffcontact.contact import create_contact_model

MODELS = ("CM", "CMr", "LCP", "Coulomb")
DEFAULT = {"tasks": ["BP5", "BD5"], "n": 256, "steps": 100, "repeats": 5}
QUICK = {"tasks": ["BP5"], "n": 16, "steps": 20, "repeats": 1}


class _Recorder:
    """A contact model that records the batches it is asked to resolve (and runs CM)."""

    def __init__(self) -> None:
        self.inner = create_contact_model("CM")
        self.calls: list[tuple] = []

    def resolve(self, J_C, Mhat_inv, v, params, active, d, *, v_C_star=None, settings=None):
        self.calls.append((J_C, Mhat_inv, v, params, active, d, v_C_star, settings))
        return self.inner.resolve(
            J_C, Mhat_inv, v, params, active, d, v_C_star=v_C_star, settings=settings
        )


def contact_batch(task: str, n: int, steps: int, device: str, dtype: torch.dtype):
    """The recorded contact problems of one resolution of all pre-impact states in contact."""
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(n, seed=0).to(device=device, dtype=dtype)
    with torch.no_grad():
        traj = system.simulate(z0, steps=steps, on_tunnelling="ignore")
        pre = system.integrate(traj[:, :-1].reshape(-1, *traj.shape[2:]))
        hit = (system.gaps(pre[:, 0]) < 0).any(-1)
        rec = _Recorder()
        system.resolve_contacts(pre[hit], contact_model=rec)
    return rec.calls[0], int(hit.sum())


# Coulomb problems that do not converge would stop the run: keep the last fixed-point
# iterate instead (the count of such problems is printed with the table)
OPTIONS = {"Coulomb": {"on_failure": "warn"}}


def time_model(name: str, call: tuple, device: str, repeats: int, backward: bool) -> float:
    J_C, Mhat_inv, v, params, active, d, v_star, settings = call
    model = create_contact_model(name, **OPTIONS.get(name, {}))
    best = float("inf")
    for _ in range(repeats + 1):  # the first is a warm-up
        vv = v.detach().clone().requires_grad_(backward)
        mu = params.mu.detach().clone().requires_grad_(backward)
        cor = params.cor.detach().clone().requires_grad_(backward)
        p = params.replace(mu=mu, cor=cor)
        sync(device)
        t0 = time.perf_counter()
        with torch.set_grad_enabled(backward), warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            out = model.resolve(J_C, Mhat_inv, vv, p, active, d, v_C_star=v_star,
                                settings=settings)  # fmt: skip
            if backward:
                out.v_plus.square().sum().backward()
        sync(device)
        best = min(best, time.perf_counter() - t0)
    for w in caught:
        NOTES.add(f"{name}: {str(w.message).split(';')[0]}")
    return best


NOTES: set[str] = set()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="one small batch (seconds)")
    ap.add_argument("--tasks", nargs="+", default=None, help="default BP5 BD5")
    ap.add_argument(
        "--n", type=positive_int, default=None, help="trajectories simulated (default 256)"
    )
    ap.add_argument(
        "--steps", type=positive_int, default=None, help="steps simulated (default 100)"
    )
    ap.add_argument("--repeats", type=positive_int, default=None, help="timed repeats, best kept")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    args = ap.parse_args(argv)
    check_device(ap, args.device)
    if args.tasks is not None:
        check_tasks(ap, "--tasks", args.tasks)
    dtype = getattr(torch, args.dtype)
    opts = settings(args, DEFAULT, QUICK)

    print("contact models: one resolve() of every pre-impact state in contact, per model")
    for line in machine_header(args.device, dtype):
        print(line)
    head = (
        f"{'task':>6} {'states':>7} {'model':>8} | {'fwd ms':>9} {'x CM':>6} | "
        f"{'fwd+bwd ms':>11} {'x CM':>6}"
    )
    print(head)
    print("-" * len(head))
    for task in opts["tasks"]:
        call, n_states = contact_batch(task, opts["n"], opts["steps"], args.device, dtype)
        base = {}
        for name in MODELS:
            fwd = time_model(name, call, args.device, opts["repeats"], False)
            both = time_model(name, call, args.device, opts["repeats"], True)
            base.setdefault("fwd", fwd)
            base.setdefault("both", both)
            print(
                f"{task:>6} {n_states:>7} {name:>8} | {1e3 * fwd:>9.1f} "
                f"{fwd / base['fwd']:>6.2f} | {1e3 * both:>11.1f} {both / base['both']:>6.2f}",
                flush=True,
            )
    for note in sorted(NOTES):
        print(f"note: {note}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

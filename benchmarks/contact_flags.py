"""Contact flags of recorded data and the chunks they give (the numbers of docs/data.md).

    python benchmarks/contact_flags.py            # about a minute on one core

1. The velocity-jump detector (``impact_intervals``) on simulated trajectories of the
   built-in tasks (30 per task, seed 5): the share of contact onsets (a state in
   contact after one that is not) that it flags within one interval, and the share of
   intervals flagged at least one step away from any contact, per tolerance.
2. An exact event-driven bouncing ball (parabolas and instantaneous rebounds between
   the samples): the share of windows of 5 states that span a rebound, and the share
   flagged by penetration alone and by ``contact_flags`` (the default of
   ``generate --from-arrays``).
3. Chunks from 320 recorded trajectories of 100 states: one per trajectory vs every
   window.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from diffcontact import load_system
from diffcontact.learning.data.chunks import (
    contact_flags,
    contact_states,
    impact_intervals,
    window_chunks,
)

TOLS = (0.1, 0.2, 0.3)
L = 5


def detector_table() -> None:
    print("1. velocity-jump detector on simulated data (30 trajectories per task, seed 5)")
    print(
        f"{'task':6s} {'onsets':>6s}  " + "  ".join(f"tol {t:.1f}: found / far flags" for t in TOLS)
    )
    for task in ("BP5", "BD5", "CP3", "Gyro", "Rope"):
        s = load_system(task)
        with torch.no_grad():
            traj = s.simulate(s.sample_initial_conditions(30, seed=5), s.default_steps)
        traj = traj.double().numpy()
        c = contact_states(s, traj)  # (N, T)
        onset = c.copy()
        onset[:, 1:] &= ~c[:, :-1]
        onset = onset[:, :-1]  # interval t starts at an onset state t
        near = np.zeros_like(onset)
        for k in (-1, 0, 1, 2):
            near |= np.roll(c[:, :-1], k, axis=1)
        cells = []
        for tol in TOLS:
            f = impact_intervals(traj, tol)
            fw = f.copy()
            fw[:, :-1] |= f[:, 1:]
            fw[:, 1:] |= f[:, :-1]
            found = (fw & onset).sum() / max(onset.sum(), 1)
            far = (f & ~near).sum() / max((~near).sum(), 1)
            cells.append(f"{found:14.1%} / {far:5.2%}")
        print(f"{task:6s} {int(onset.sum()):6d}  " + "  ".join(cells))


def exact_ball(rng: np.random.Generator, T: int, dt: float, g: float, e: float, r: float):
    """``(T, 2, 1, 2)`` samples of a ball bouncing on the floor y = 0, and its rebound times."""
    y, v, vx = rng.uniform(0.4, 1.5), rng.uniform(-1, 2), rng.uniform(-1, 1)
    t = np.arange(T) * dt
    out = np.zeros((T, 2, 1, 2))
    out[:, 0, 0, 0], out[:, 1, 0, 0] = vx * t, vx
    t0, events = 0.0, []
    while t0 < t[-1]:
        tau = (v + math.sqrt(v * v + 2 * g * (y - r))) / g
        seg = (t >= t0) & (t < t0 + tau)
        s = t[seg] - t0
        out[seg, 0, 0, 1] = y + v * s - 0.5 * g * s * s
        out[seg, 1, 0, 1] = v - g * s
        t0, y, v = t0 + tau, r, -e * (v - g * tau)
        events.append(t0)
    return out, events


def ball_table() -> None:
    dt, g, e, r, T = 0.01, 9.81, 0.8, 0.1, 100
    config = {
        "type": "bouncing_masses", "masses": [1.0], "radii": [r], "walls": [[0, 1, 0]],
        "gravity": g, "cor": e, "dt": dt, "horizon": T * dt,
    }  # fmt: skip
    system = load_system(config)
    rng = np.random.default_rng(0)
    runs = [exact_ball(rng, T, dt, g, e, r) for _ in range(200)]
    traj = np.stack([x for x, _ in runs])
    spans = np.zeros((len(runs), T - L + 1), dtype=bool)
    for n, (_, events) in enumerate(runs):
        for tau in events:
            k = int(tau // dt)
            spans[n, max(0, k - L + 2) : min(k, T - L) + 1] = True
    print("\n2. exact bouncing ball: 200 trajectories of 100 states, windows of 5 states")
    print(f"   windows that span a rebound: {spans.mean():.1%}")
    for label, flags in (
        ("penetration only (gap < 0)", contact_states(system, traj)),
        ("contact_flags (default)", contact_flags(system, traj)[0]),
    ):
        has = np.lib.stride_tricks.sliding_window_view(flags, L, axis=1).any(-1)
        ok = ~flags[:, : T - L + 1]  # the windows that may be chunks
        print(
            f"   {label:28s}: flags {has[ok & spans].mean():6.1%} of the windows that span a "
            f"rebound, {has[ok & ~spans].mean():.1%} of the others"
        )


def chunk_counts() -> None:
    s = load_system("BP5")
    with torch.no_grad():
        traj = s.simulate(s.sample_initial_conditions(320, seed=0), 99).double().numpy()
    flags, _ = contact_flags(s, traj)
    owner, _, has = window_chunks(flags, L, 1)
    print("\n3. BP5, 320 recorded trajectories x 100 states (32,000 states)")
    print(f"   one chunk per trajectory: 320 chunks of {L} states ({320 * L} of the states)")
    print(f"   every window (stride 1): {len(owner)} chunks, {has.mean():.0%} with a contact")


if __name__ == "__main__":
    torch.set_num_threads(1)
    detector_table()
    ball_table()
    chunk_counts()

"""``make demo``: the contact solver on a ball hitting a wall, then a simulated task.

Everything is written under ``demo_out/`` (or the folder given to :func:`run_demo`).
"""

from __future__ import annotations

import time
from pathlib import Path

import torch

from diffcontact.contact import solve_cone_qp, two_phase_impulse


def solver_demo() -> bool:
    """A 0.1 kg ball hits the wall x = 0 at 45 degrees; returns True if all checks pass."""
    dt = torch.float64
    mass = torch.tensor(0.1, dtype=dt, requires_grad=True)
    mu = torch.tensor([0.3], dtype=dt, requires_grad=True)
    cor = torch.tensor([0.8], dtype=dt, requires_grad=True)
    v = torch.tensor([-2.0, -2.0], dtype=dt)  # moving left and down, into the wall
    # contact frame at the wall: normal +x, tangent +y; J_C maps v to (v_n, v_t)
    J_C = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=dt)
    Mhat_inv = torch.eye(2, dtype=dt) / mass
    active = torch.tensor([True])
    res = two_phase_impulse(J_C, Mhat_inv, v, mu, cor, active, 2)
    f_c, f_r, v_plus = res.f_c, res.f_r, res.v_plus
    print("ball (m = 0.1 kg) hits the wall x = 0 with v = (-2, -2) m/s, mu = 0.3, e_P = 0.8")
    print(f"  compression impulse  f_c = (n {f_c[0]:.4f}, t {f_c[1]:+.4f}) N s")
    print(f"  restitution impulse  f_r = (n {f_r[0]:.4f}, t {f_r[1]:+.4f}) N s")
    print(f"  velocity after       v+  = ({v_plus[0]:+.4f}, {v_plus[1]:+.4f}) m/s")
    checks = {
        "impulses inside the friction cone": bool(
            (f_c[1].abs() <= mu * f_c[0] + 1e-12) and (f_r[1].abs() <= mu * f_r[0] + 1e-12)
        ),
        "restitution / compression normal impulse = e_P": bool(
            torch.isclose(f_r[0] / f_c[0], cor[0].detach())
        ),
        "ball leaves the wall": bool(v_plus[0] > 0),
        "kinetic energy does not increase": bool((v_plus**2).sum() <= (v**2).sum() + 1e-12),
    }
    # gradients of the outgoing velocity w.r.t. the physical parameters
    grads = torch.autograd.grad(v_plus[0] + v_plus[1], (mass, mu, cor))
    print("  d(v+_x + v+_y)/d(mass, mu, e_P) = " + ", ".join(f"{g.item():+.4f}" for g in grads))
    # the same solve batched: 1024 random incoming angles in one call
    angle = torch.linspace(0.05, torch.pi - 0.05, 1024, dtype=dt)
    b = torch.stack([-2 * torch.sin(angle), 2 * torch.cos(angle)], -1)
    A = torch.eye(2, dtype=dt).expand(1024, 2, 2) / 0.1
    f = solve_cone_qp(A, b, torch.full((1024, 1), 0.3, dtype=dt), 2)
    checks["batched: every impulse inside its cone"] = bool(
        (f[:, 1].abs() <= 0.3 * f[:, 0] + 1e-12).all()
    )
    for name, ok in checks.items():
        print(f"  [{'ok' if ok else 'FAILED'}] {name}")
    return all(checks.values())


def simulation_demo(out: Path, task: str = "BP5", n: int = 4) -> bool:
    """Simulate ``n`` trajectories of ``task`` and write their animation and energy plot."""
    import diffcontact as dc
    from diffcontact.viz import animate, plot_energy, scene_from_system

    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(n, seed=0)
    t0 = time.perf_counter()
    traj = system.simulate(z0, progress=True)
    wall = time.perf_counter() - t0
    energy = system.energy(traj)
    gif = animate(traj, scene_from_system(system), out / f"{task}.gif", dt=system.dt)
    png = plot_energy(energy, system.dt, out / f"{task}_energy.png")
    print(
        f"\nsimulated {n} {task} trajectories of {traj.shape[1]} states in {wall:.1f} s "
        f"(dt = {system.dt}); animation: {gif}, energy plot: {png}"
    )
    loss = (energy[:, -1] / energy[:, 0]).tolist()
    print("  energy kept (end / start): " + ", ".join(f"{x:.3f}" for x in loss))
    checks = {
        "no energy gained over the trajectory (e_P <= 1, dissipative friction)": bool(
            (energy[:, -1] <= energy[:, 0] * (1 + 1e-9)).all()
        ),
        "no body left the box": bool(
            ((traj[..., 0, :, :] > -0.05) & (traj[..., 0, :, :] < 1.05)).all()
        ),
    }
    for name, ok in checks.items():
        print(f"  [{'ok' if ok else 'FAILED'}] {name}")
    return all(checks.values())


def run_demo(out: str | Path = "demo_out") -> int:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ok = solver_demo()
    ok = simulation_demo(out) and ok
    return 0 if ok else 1

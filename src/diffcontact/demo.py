"""``make demo``: the main job end to end, on a small budget.

1. the contact solver on a ball hitting a wall (impulses, checks, gradients);
2. a simulated task (BP5) with its animation;
3. learning: simulate a small CP3 dataset, train CM-CD-CLNN on it for a few
   minutes on the CPU, print the learned mass ratios, mu and e_P next to the
   truth, and write the evaluation (metrics, plots, GIF).

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
    print(
        f"  (it leaves at {v_plus[0].item():.4f} m/s, not e_P x 2 = {2 * cor[0].item():.1f}: with "
        "friction while sliding, Poisson's restitution lifts a ball off the wall; the "
        "energy still falls; docs/training.md, 'What the learned e_P and mu mean')"
    )
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
    # (rounded, + 0.0: a derivative of rounding size prints as +0.0000, not -0.0000)
    shown = ", ".join(f"{round(g.item(), 4) + 0.0:+.4f}" for g in grads)
    print(f"  d(v+_x + v+_y)/d(mass, mu, e_P) = {shown}")
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
    png = plot_energy(energy, system.dt, out / f"{task}_energy.png", title=task)
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


# the learning demo's budget: 200 training chunks in batches of 50, 40 epochs
# (160 steps, 1-3 minutes on a 2-core CPU)
LEARNING_DEMO = {"task": "CP3", "n_train": 200, "n_val": 40, "n_test": 20, "epochs": 40,
                 "batch_size": 50}  # fmt: skip


def learning_demo(out: Path, epochs: int | None = None) -> bool:
    """Generate a small CP3 dataset, train CM-CD-CLNN, compare with the truth, evaluate.

    Returns True when the learned mass ratios are within 2 % and mu, e_P within
    0.05 of the truth (looser than docs/results.md's full-size runs: 4x less
    data and a few minutes of training).
    """
    import shutil

    from diffcontact.learning.data.generate import generate_dataset
    from diffcontact.learning.evaluation.evaluate import evaluate
    from diffcontact.learning.evaluation.metrics import true_parameters
    from diffcontact.learning.training.run import train

    cfg = LEARNING_DEMO
    task = cfg["task"]
    epochs = cfg["epochs"] if epochs is None else epochs
    print(f"\nlearning {task} from simulated trajectories (CM-CD-CLNN, {epochs} epochs)")
    t0 = time.perf_counter()
    data = generate_dataset(
        task, out / "data" / task, n_train=cfg["n_train"], n_val=cfg["n_val"],
        n_test=cfg["n_test"], seed=0, progress=True,
    )  # fmt: skip
    print(f"  dataset: {data} ({time.perf_counter() - t0:.0f} s)")
    run = out / "runs" / f"{task}-CM-CD-CLNN"
    if run.exists():  # the demo's own previous run: start again
        shutil.rmtree(run)
    t0 = time.perf_counter()
    model = train(
        data, run, model="CM-CD-CLNN", epochs=epochs, batch_size=cfg["batch_size"], seed=0,
        progress=True, keep_checkpoints=2,  # (all 40: 130 MB)
    )  # fmt: skip
    train_s = time.perf_counter() - t0
    learned, truth = model.learned_parameters(), true_parameters(task)
    ratios = learned["mass_ratios"][1:]
    print(f"\ntrained in {train_s:.0f} s; run directory {run}")
    rows = [(f"m{i}/m1", a, b) for i, (a, b) in
            enumerate(zip(ratios, truth["mass_ratios"], strict=True), start=2)]  # fmt: skip
    rows += [("mu", learned["mu"][0], truth["mu"][0]), ("e_P", learned["cor"][0], truth["cor"][0])]
    print(f"  {'parameter':<10} {'learned':>9} {'true':>7}")
    for name, a, b in rows:
        print(f"  {name:<10} {a:9.4f} {b:7.4f}")
    metrics = evaluate(run, n_gif=2)
    print(
        f"  test rollouts ({metrics['n_test']} x {metrics['steps']} steps): relative error "
        f"{metrics['rel_err_mean']:.2e} ± {metrics['rel_err_ci95']:.1e} (95% CI)"
    )
    print(f"  evaluation: {run / 'evaluation'} (" + ", ".join(sorted(metrics["files"])) + ")")
    checks = {
        "mass ratios within 2 % of the truth": all(
            abs(a / b - 1) <= 0.02 for a, b in zip(ratios, truth["mass_ratios"], strict=True)
        ),
        "mu within 0.05 of the truth": abs(learned["mu"][0] - truth["mu"][0]) <= 0.05,
        "e_P within 0.05 of the truth": abs(learned["cor"][0] - truth["cor"][0]) <= 0.05,
    }
    for name, ok in checks.items():
        print(f"  [{'ok' if ok else 'FAILED'}] {name}")
    return all(checks.values())


def run_demo(out: str | Path = "demo_out", learning: bool = True, epochs: int | None = None) -> int:
    """Run the demo; 0 when every check passed, else 1."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ok = solver_demo()
    ok = simulation_demo(out) and ok
    if learning:
        ok = learning_demo(out, epochs=epochs) and ok
    print("\ndemo " + ("finished: all checks passed" if ok else "FAILED: see the checks above"))
    return 0 if ok else 1

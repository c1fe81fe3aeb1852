"""Regenerate ``tests/data/reference_values.pt``: rollouts and training-step gradients.

The file pins the numbers of the simulator and of one training step so that a
refactoring that must not change results (issue 10: contact models and learned
models as pluggable components) is checked against the code before it::

    python tests/make_reference_values.py        # only when a change of results is intended
    python tests/make_reference_values.py --rollouts Rope Rope-D100   # just these entries

History: written before issue 10. The Rope and Rope-D100 rollouts were rewritten when
the restitution phase got its warm start (issue 11): a rope state's restitution
problem has many weakly active limits, and the polish from ``e_P f_c`` stops at a
point whose scaled natural-map residual is within rounding (<= 1e-13) but not the
interior point's; the rollouts moved by 3e-11 (2e-11 relative to their scale), the
solver's accuracy on these ill-conditioned problems, not a change of physics. They
were rewritten again when the solver started equilibrating problems whose contacts
differ in scale by more than 1e3 (``cone_qp._contact_scales``, issue 11's scale
robustness): the rope's limit problems are such problems, and the rollouts moved by
3e-11 (Rope) and 1.7e-11 (Rope-D100), again the solver's accuracy on them. All four
rope rollouts (Rope, Rope-D100, Rope-D200, Rope-D400) were rewritten when the rope tasks
got the position projection by default (``position_projection: 10``, issue 11's "rope
limits hold over long simulations"): the old rollouts left the limits behind (stretch
ratios up to 1.57 and bends 0.39 rad past the limit within the Rope task's 1 s at
dt = 0.01, ``python experiments/rope_limits.py --task Rope --horizon 1 --dt 0.01 --n 8``),
so the rope the config describes is a different trajectory, not a rounding change
(Rope moved by up to 1.1). The other tasks' rollouts are unchanged (their projection is
off). Rope (two states) was rewritten once more when the projection began to stop each
state at its own convergence (it iterated both while either had a limit left): it moved
by 3.8e-10, and now equals each state's rollout alone (the one-state rope entries did not
move). All four were rewritten again when the projection began to project the velocities
too (``velocity_projection``, on by default): the positions' projection alone left
velocities pointing into the limits it closed, and the rope gained energy (a rope with a
heavy tip up to 10.4 J over 4.4 J in 0.5 s; ``tests/systems/test_velocity_projection.py``).
They moved by up to 1.3 (Rope), 0.035, 0.0045 and 0.0073 (Rope-D100, -D200, -D400); with
``velocity_projection: false`` they are those of the code before, bitwise (compared on
one machine, where both stand 9e-16 off the entries before in Rope-D100). All four were
rewritten again when the velocities' projection began to foresee the inelastic limits the
velocities would cross within the next step (``project_state``'s ``dt``): a limit the
projection released to a small positive gap was left approaching, and at coarse steps the
rope still gained energy (Rope at dt = 0.02: 0.887 J within 1 s,
``test_the_rope_gains_no_energy_at_a_coarse_step``). They moved by up to 1.02 (Rope), 0.46,
0.29 and 0.041 (Rope-D100, -D200, -D400); with the projection's ``dt`` left out (the
config key ``foresee_crossings: false`` since) they are those of the code before to 6e-15,
as the code before is to its own entries on this machine. The chain pendulums' and
gyroscopes' rollouts (CP3, CP3-e, Gyro, Gyro-e) and CP3's training steps were rewritten
when the contact step began to take the part of the velocities that breaks the equality
constraints out before the impulse (``system._consistent_velocities``): RK4 leaves ``J_E
v`` of the order of its error, and along a direction inside a wide friction cone (Gyro at
mu = 2) the contact problem was unbounded. They moved by up to 1.2e-4 (CP3-e; CP3
8.2e-5, Gyro 8.5e-5, Gyro-e 1.2e-5, on rollouts of scale 5-10) and the CP3 steps'
gradients by up to 1.7e-6 of their size; BD5's rigid disks moved by 1.6e-12, BP5 by
1.8e-12 (this machine's rounding against the file's), the ropes not at all (the whole
file is written at once).

``tests/test_reference_values.py`` compares against it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

OUT = Path(__file__).parent / "data" / "reference_values.pt"
# (task, number of states, steps): every built-in task, long enough for contacts
ROLLOUTS = {
    "BP5": (3, 60), "BP5-e": (3, 60), "BD5": (3, 60), "CP3": (3, 60), "CP3-e": (3, 60),
    "Gyro": (2, 60), "Gyro-e": (2, 60), "Rope": (2, 40), "Rope-D100": (1, 20),
    "Rope-D200": (1, 10), "Rope-D400": (1, 5),
}  # fmt: skip
MODELS = ("CM-CD-CLNN", "CM-CD-CHNN", "CMr-CD-CLNN", "CMr-CD-CHNN")
STEP_TASKS = ("BP5", "CP3")  # a heterogeneous and a homogeneous task with a potential


def reference_rollouts(tasks: list[str] | None = None) -> dict[str, torch.Tensor]:
    from diffcontact import load_system

    out = {}
    for task in tasks or ROLLOUTS:
        n, steps = ROLLOUTS[task]
        system = load_system(task)
        z0 = system.sample_initial_conditions(n, seed=1)
        out[task] = system.simulate(z0, steps)
    return out


def reference_training_step(task: str, model_name: str) -> dict[str, torch.Tensor]:
    """Loss and gradients of one training step from fixed weights and a fixed chunk."""
    from diffcontact import load_system
    from diffcontact.learning.models.physical import LearnedModel

    system = load_system(task)
    z0 = system.sample_initial_conditions(6, seed=2)
    chunk = system.simulate(z0, 30)[:, 25:30]  # (6, 5, 2, P, dim), contacts included
    torch.manual_seed(0)
    kwargs = {"eps": "learnable"} if model_name.startswith("CMr") else {}
    model = LearnedModel(task, model=model_name, hidden=(32, 32), **kwargs).double()
    with torch.no_grad():
        model.log_mass_rel.add_(torch.linspace(-0.2, 0.2, model.log_mass_rel.numel()).double())
        model.raw_mu.add_(0.1)
    pred = model.simulate(chunk[:, 0], chunk.shape[1] - 1, check_overlap=False)
    loss = (pred[:, 1:] - chunk[:, 1:]).abs().mean()
    names, params = zip(*model.named_parameters(), strict=True)
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    out = {"loss": loss.detach()}
    for name, g in zip(names, grads, strict=True):
        out[f"grad/{name}"] = torch.zeros(()) if g is None else g
    return out


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--rollouts", nargs="+", choices=list(ROLLOUTS), metavar="TASK",
        help="rewrite only these rollouts, keep every other entry of the file",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.rollouts:
        data = torch.load(OUT, weights_only=True)
        data["rollouts"].update(reference_rollouts(args.rollouts))
    else:
        data = {"rollouts": reference_rollouts(), "steps": {}}
        for task in STEP_TASKS:
            for model_name in MODELS:
                data["steps"][f"{task}/{model_name}"] = reference_training_step(task, model_name)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    torch.save(data, OUT)
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""diffcontact.optimize: gradients through impacts, convergence, batching, bounds, errors."""

from __future__ import annotations

import math

import pytest
import torch

import diffcontact as dc
from diffcontact.control import ControlError, Parameter, Position, Spin, Velocity, as_planner

# two balls in a box; ball 0 is shot at ball 1 (friction and restitution < 1: the QP is exercised)
TWO_BALLS = {
    "name": "two-balls",
    "type": "bouncing_masses",
    "masses": [0.1, 0.2],
    "radii": [0.1, 0.1],
    "walls": [[1, 0, 0], [0, 1, 0], [-1, 0, 1], [0, -1, 1]],
    "mu": 0.3,
    "cor": 0.5,
    "dt": 0.01,
    "horizon": 0.3,
}


@pytest.fixture(scope="module")
def two_balls():
    system = dc.load_system(TWO_BALLS)
    z0 = torch.zeros(2, 2, 2, dtype=torch.float64)
    z0[0, 0] = torch.tensor([0.25, 0.45])
    z0[0, 1] = torch.tensor([0.55, 0.5])
    return system, z0


def _final(point: int, target: torch.Tensor):
    def objective(traj: torch.Tensor) -> torch.Tensor:
        return (traj[..., -1, 0, point, :] - target).norm(dim=-1)

    return objective


def test_gradient_through_an_impact_matches_finite_differences(two_balls):
    system, z0 = two_balls
    steps = 25

    def loss(v: torch.Tensor) -> torch.Tensor:
        z = z0.clone().unsqueeze(0)
        z[0, 1, 0] = v
        traj = system.simulate(z, steps)
        assert system.gaps(traj[0, 8:12, 0]).min() < 0.05  # ball 1 is hit mid-rollout
        return traj[0, -1, 0, 1] @ torch.tensor([1.0, 0.7], dtype=torch.float64)

    v = torch.tensor([1.5, 0.2], dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(loss(v), v)
    h = 1e-6
    fd = torch.stack(
        [(loss(v.detach() + h * e) - loss(v.detach() - h * e)) / (2 * h) for e in torch.eye(2)]
    )
    assert grad.abs().max() > 0.05  # the impact transmits momentum to ball 1
    torch.testing.assert_close(grad, fd, rtol=1e-5, atol=1e-7)


def _reachable_target(system, z0, v_star, steps):
    z = z0.clone().unsqueeze(0)
    z[0, 1, 0] = torch.tensor(v_star, dtype=torch.float64)
    return system.simulate(z, steps)[0, -1, 0, 1]


@pytest.mark.parametrize("optimizer,iterations,tol", [("lbfgs", 15, 1e-4), ("adam", 40, 5e-3)])
def test_optimizer_reaches_a_reachable_target(two_balls, optimizer, iterations, tol):
    system, z0 = two_balls
    steps = 25
    target = _reachable_target(system, z0, (1.6, 0.35), steps)
    z_start = z0.clone()
    z_start[1, 0] = torch.tensor([1.4, 0.25], dtype=torch.float64)  # also hits ball 1

    def squared(traj):
        return (traj[..., -1, 0, 1, :] - target).square().sum(-1)

    res = dc.optimize(
        system, z_start, squared, variables=[Velocity(0, bounds=(-3, 3))], steps=steps,
        optimizer=optimizer, iterations=iterations, lr=1.0 if optimizer == "lbfgs" else 0.05,
        progress=False,
    )  # fmt: skip
    assert res.objective.sqrt() < tol
    assert res.history.shape == (res.iterations, 1)  # (iterations, starts)
    assert res.history[0, 0] > 100 * res.objective
    z = res.z0.unsqueeze(0)
    final = system.simulate(z, steps)[0, -1, 0, 1]  # the returned state reproduces the value
    assert (final - target).square().sum() == pytest.approx(float(res.objective), abs=1e-12)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_plan_matches_cpu(two_balls):
    """The same optimisation on a CUDA state gives the CPU's shot (float64)."""
    system, z0 = two_balls
    steps = 25
    target = _reachable_target(system, z0, (1.6, 0.35), steps)
    z_start = z0.clone()
    z_start[1, 0] = torch.tensor([1.4, 0.25], dtype=torch.float64)
    results = []
    for device in ("cpu", "cuda"):
        goal = target.to(device)

        def squared(traj, goal=goal):
            return (traj[..., -1, 0, 1, :] - goal).square().sum(-1)

        res = dc.optimize(
            system, z_start.to(device), squared, variables=[Velocity(0, bounds=(-3, 3))],
            steps=steps, optimizer="lbfgs", iterations=10, lr=1.0, progress=False,
        )  # fmt: skip
        assert res.z0.device.type == device
        results.append(res)
    torch.testing.assert_close(results[1].z0.cpu(), results[0].z0, rtol=0, atol=1e-8)


def test_multistart_is_one_batched_call_per_iteration(two_balls):
    system, z0 = two_balls
    planner = as_planner(system)
    calls = []
    inner = planner._simulate

    def counting(z, steps, params, check):
        calls.append(z.shape[0])
        return inner(z, steps, params, check)

    planner._simulate = counting
    target = torch.tensor([0.8, 0.6], dtype=torch.float64)
    res = dc.optimize(
        planner, z0, _final(1, target), variables=[Velocity(0, bounds=(-2, 2))], steps=10,
        starts=64, iterations=3, progress=False,
    )  # fmt: skip
    assert calls == [64, 64, 64]
    assert res.start_objective.shape == (64,) and res.start_variables["velocity[0]"].shape == (
        64,
        2,
    )
    assert res.objective == res.start_objective.min()
    assert int(res.best_start) == int(res.start_objective.argmin())
    v = res.start_variables["velocity[0]"]
    assert v.min() >= -2 and v.max() <= 2  # random starts and steps stay in the box
    assert len(torch.unique(v[:, 0])) > 60  # the starts differ


def test_problems_batch_matches_single_problems(two_balls):
    system, z0 = two_balls
    targets = torch.tensor([[0.8, 0.6], [0.7, 0.3]], dtype=torch.float64)
    kwargs = dict(variables=[Velocity(0, bounds=(-2, 2))], steps=10, starts=3, iterations=4,
                  progress=False)  # fmt: skip

    def objective(traj):  # traj (N, S, T, 2, P, 2)
        return (traj[:, :, -1, 0, 1] - targets[:, None]).norm(dim=-1)

    both = dc.optimize(system, z0.expand(2, -1, -1, -1), objective, **kwargs)
    for i in range(2):
        one = dc.optimize(system, z0, _final(1, targets[i]), **kwargs)
        torch.testing.assert_close(both.history[:, i], one.history, rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(both.variables["velocity[0]"][i], one.variables["velocity[0]"])


def test_physical_parameter_is_recovered(two_balls):
    system, z0 = two_balls
    steps = 25
    z = z0.clone()
    z[1, 0] = torch.tensor([1.5, 0.2], dtype=torch.float64)
    cor = system.parameters().cor.clone()
    cor[0] = 0.8  # contact 0: ball 0 - ball 1 (0.5 in the config)
    truth = system.simulate(z.unsqueeze(0), steps, params=system.parameters().replace(cor=cor))
    truth = truth[0, -1, 0]

    def objective(traj):
        return (traj[..., -1, 0, :, :] - truth).square().sum((-1, -2))

    res = dc.optimize(
        system, z, objective, variables=[Parameter("cor", index=0, bounds=(0.0, 2.0))], steps=steps,
        optimizer="lbfgs", lr=1.0, iterations=20, progress=False,
    )  # fmt: skip
    assert float(res.variables["cor[0]"]) == pytest.approx(0.8, abs=1e-5)
    assert res.params.cor.shape == (1, 9)  # one set per problem
    torch.testing.assert_close(res.params.cor[0, 1:], cor[1:])


def test_spin_and_velocity_write_and_read_back_on_a_disk():
    system = dc.load_system("BD1-ground")
    planner = as_planner(system)
    z0 = system.sample_initial_conditions(3, seed=0)
    spin, vel, pos = Spin(0), Velocity(0), Position(0)
    for var in (spin, vel, pos):
        var.bind(planner)
    w = torch.tensor([[2.0], [-5.0], [0.5]], dtype=torch.float64)
    v = torch.tensor([[1.0, 0.0], [0.0, -2.0], [0.3, 0.4]], dtype=torch.float64)
    z, _ = spin.write(z0, None, w, planner)
    z, _ = vel.write(z, None, v, planner)
    for i in range(3):
        torch.testing.assert_close(spin.read(z[i], None, planner), w[i])
        torch.testing.assert_close(vel.read(z[i], None, planner), v[i])
    # rigid: point velocities are v + w x r, so the body's constraints hold at the new state
    r = z[:, 0, 1:] - z[:, 0, :1]
    u = z[:, 1, 1:] - z[:, 1, :1]
    torch.testing.assert_close((r * u).sum(-1), torch.zeros(3, 2, dtype=torch.float64))
    moved, _ = pos.write(z, None, torch.zeros(3, 2, dtype=torch.float64), planner)
    torch.testing.assert_close(moved[:, 0, 1:] - moved[:, 0, :1], r)  # orientation kept


def test_learned_model_plans_with_frozen_weights():
    from diffcontact.learning.models.registry import create_model

    model = create_model("CM-CD-CLNN", dc.load_system("BD1-ground").config, hidden=[16])
    planner = as_planner(model)
    assert planner.learned and planner.truth.name == "BD1-ground"
    from diffcontact.control.tasks import throw_scene

    z0 = throw_scene(planner)
    res = dc.optimize(
        model, z0, lambda tr: tr[..., -1, 0, 0, 0], variables=[Velocity(0, bounds=(-1, 1)),
        Parameter("mu", bounds=(0, 1))], steps=5, iterations=2, progress=False,
    )  # fmt: skip
    assert res.iterations == 2 and torch.isfinite(res.objective)
    assert all(p.grad is None and p.requires_grad for p in model.parameters())


def test_non_finite_gradient_names_the_variable(two_balls):
    system, z0 = two_balls

    def objective(traj):  # sqrt at 0: a finite value with an infinite gradient
        return (traj[..., -1, 0, 0, 0] - traj[..., -1, 0, 0, 0].detach()).sqrt()

    with pytest.raises(ControlError, match=r"gradient of velocity\[0\] is not finite"):
        dc.optimize(system, z0, objective, variables=[Velocity(0)], steps=3, iterations=2,
                    progress=False)  # fmt: skip


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(variables=[]), "or a list of them, got an empty list"),
        (dict(variables=5), "or a list of them, got int"),
        (dict(variables=[Velocity(0)], contact_model="XYZ"), "XYZ"),
        (dict(variables=[Velocity(0), Velocity(0)]), "distinct"),
        (dict(variables=[Velocity(5)]), r"velocity\[5\]: body must be one of 0..1"),
        (dict(variables=[Spin(0)]), "point .*has no spin"),
        (dict(variables=[Parameter("charge")]), "unknown parameter 'charge'"),
        (dict(variables=[Parameter("mass", index=7)]), "does not fit mass"),
        (dict(variables=[Velocity(0, bounds=(1, -1))]), "low bound above high bound"),
        (dict(variables=[Velocity(0)], optimizer="sgd"), "optimizer must be one of"),
        (dict(variables=[Velocity(0)], iterations=0), "iterations must be an integer >= 1"),
        (dict(variables=[Velocity(0)], starts={"velocity[0]": [1.0, 2.0]}), "shape"),
        (dict(variables=[Velocity(0)], starts={"spin": [[1.0]]}), "unknown variable"),
        (dict(variables=[Velocity(0)], threads="many"), "threads must be"),
        # (a NaN or negative tolerance never stopped anything, silently)
        (dict(variables=[Velocity(0)], tolerance=float("nan")), "tolerance must be a number >= 0"),
        (dict(variables=[Velocity(0)], tolerance=-1), "tolerance must be a number >= 0"),
        (dict(variables=[Velocity(0)], seed="a"), "seed must be an integer"),
    ],
)
def test_bad_arguments_are_named(two_balls, kwargs, match):
    system, z0 = two_balls
    with pytest.raises(ControlError, match=match):
        dc.optimize(system, z0, _final(1, torch.zeros(2)), steps=2, progress=False, **kwargs)


def test_bad_state_and_objective_shapes(two_balls):
    system, z0 = two_balls
    var = [Velocity(0)]
    with pytest.raises(ControlError, match=r"z0 must have shape \(2, 2, 2\)"):
        dc.optimize(system, z0[:, :1], _final(1, torch.zeros(2)), variables=var, progress=False)
    bad = z0.clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(ControlError, match="NaN"):
        dc.optimize(system, bad, _final(1, torch.zeros(2)), variables=var, progress=False)
    with pytest.raises(ControlError, match=r"objective must return shape \(2,\)"):
        dc.optimize(system, z0, lambda tr: tr.sum(), variables=var, starts=2, steps=2,
                    progress=False)  # fmt: skip


def test_iterations_are_governed_once_not_per_rollout(two_balls, monkeypatch):
    """threads="auto": one governor times the iterations (forward and backward); the rollouts
    inside leave the threads to it, and the count is put back at the end."""
    import diffcontact.threads as threads_mod

    system, z0 = two_balls
    made = []

    class Recording(threads_mod.ThreadGovernor):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            made.append(self)

    monkeypatch.setattr(threads_mod, "available_cores", lambda: 2)
    monkeypatch.setattr(threads_mod, "ThreadGovernor", Recording)
    initial = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        res = dc.optimize(
            system, z0, _final(1, torch.zeros(2)), variables=[Velocity(0)], steps=30,
            iterations=30, progress=False,
        )  # fmt: skip
        assert res.iterations == 30 and len(made) == 1
        assert made[0]._steps == 30 and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(initial)


def test_an_objective_without_a_path_to_the_variable_gets_a_zero_gradient(two_balls):
    """mu acts only in contacts: with both balls at rest none happens, the objective does
    not depend on it, and optimize warns once and leaves it in place (it raised autograd's
    "does not require grad" before); a batch without problems is named."""
    system, z0 = two_balls
    with pytest.warns(UserWarning, match=r"does not depend on mu at iteration 0"):
        res = dc.optimize(
            system, z0, _final(1, torch.zeros(2)), variables=[Parameter("mu")], steps=3,
            starts=2, iterations=2, progress=False,
        )  # fmt: skip
    assert res.iterations == 2
    start = res.start_variables["mu"][int(res.best_start)]  # the best start, unmoved
    assert torch.equal(res.params.mu.flatten(), start.flatten())
    assert torch.equal(res.history[0], res.history[-1])
    with pytest.raises(ControlError, match=r"z0 holds no problem"):
        dc.optimize(system, z0[None][:0], _final(1, torch.zeros(2)), variables=[Velocity(0)],
                    progress=False)  # fmt: skip


def test_a_position_moved_into_an_overlap_is_never_the_plan():
    """Pulling ball 0 onto ball 1: the best plan was a start with the two balls overlapping
    (0.19 deep), which simulate refuses, reached with a tunnelling warning per iteration
    that blamed dt."""
    system = dc.load_system("BP5-e")
    z0 = system.sample_initial_conditions(1, seed=0)[0]
    z0[1] = 0
    target = z0[0, 1].clone()

    def objective(traj):
        return (traj[:, -1, 0, 0] - target).norm(dim=-1)

    with pytest.warns(UserWarning, match=r"position\[0\] moved start\(s\) \[0\] into an overlap"):
        res = dc.optimize(system, z0, objective, variables=[Position(0, bounds=(0.0, 1.0))],
                          steps=5, iterations=40, progress=False)  # fmt: skip
    assert (system.gaps(res.z0[None, 0]) > 0).all()  # a state simulate accepts
    traj = system.simulate(res.z0[None], 5, params=res.params)
    assert float(objective(traj)[0]) == pytest.approx(float(res.objective), rel=1e-12)


def test_random_starts_moved_into_an_overlap_count_as_infinite():
    """Several random starts of a Position: the first iteration checked every start for
    overlaps, so a drawn start inside another ball or a wall stopped the call
    (ControlError), where the docs promise it counts as infinite. The caller's own z0 is
    still checked."""
    system = dc.load_system("BP5-e")
    z0 = system.sample_initial_conditions(1, seed=0)[0]
    z0[1] = 0
    target = torch.tensor([0.3, 0.7], dtype=torch.float64)

    def objective(traj):
        return (traj[:, -1, 0, 0] - target).norm(dim=-1)

    kwargs = {"variables": [Position(0, bounds=(0.05, 0.95))], "steps": 10, "starts": 8,
              "iterations": 1, "progress": False}  # fmt: skip
    with pytest.warns(UserWarning, match=r"moved start\(s\) \[1, 5, 6, 7\] into an overlap"):
        res = dc.optimize(system, z0, objective, **kwargs)
    assert torch.isinf(res.start_objective[[1, 5, 6, 7]]).all()
    assert torch.isfinite(res.start_objective[[0, 2, 3, 4]]).all() and math.isfinite(res.objective)
    inside = z0.clone()
    inside[0, 1] = inside[0, 0] + 0.01  # ball 1 inside ball 0
    with pytest.raises(ControlError, match=r"z0 has overlapping bodies"):
        dc.optimize(system, inside, objective, **kwargs)


def test_a_number_parameter_is_read_exactly():
    """eps, a plain number in PhysicalParams, was read through float32 (start 0 of a
    Parameter("eps") plan was 0.009999999776, not the current 0.01)."""
    system = dc.load_system("BD1-ground")
    value = Parameter("eps").read(None, system.parameters(), system)
    assert value.dtype == torch.float64 and float(value) == system.parameters().eps


def test_a_short_plan_on_a_loaded_cpu_runs_its_backward_pass_on_one_thread(two_balls, monkeypatch):
    """Fewer than 24 iterations are not governed: each rollout's forward steps were (one
    thread on a loaded CPU), but the backward pass ran on every core: the thread cliff,
    for a learned model's short plan beside one busy process. It now follows the
    rollouts' choice."""
    import diffcontact.control.optimize as opt_module
    from diffcontact.threads import available_cores

    if min(available_cores(), torch.get_num_threads()) < 2:
        pytest.skip("needs two cores")
    system, z0 = two_balls
    seen: list[int] = []

    class Record(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x):
            return x.clone()

        @staticmethod
        def backward(ctx, g):
            seen.append(torch.get_num_threads())
            return g

    def objective(traj):
        return Record.apply(traj[:, -1, 0, 0]).norm(dim=-1)

    for loaded, want in ((True, 1), (False, torch.get_num_threads())):
        seen.clear()
        monkeypatch.setattr(opt_module, "settled_on_one", lambda device, loaded=loaded: loaded)
        dc.optimize(system, z0, objective, variables=[Velocity(0)], steps=3, iterations=2,
                    progress=False)  # fmt: skip
        assert seen and set(seen) == {want}, (loaded, seen)


def test_one_variable_need_not_be_in_a_list(two_balls):
    """``variables=Velocity(0)`` was a bare TypeError ('Velocity' object is not iterable)."""
    system, z0 = two_balls
    goal = _final(0, torch.full((2,), 0.5))
    kwargs = dict(steps=3, iterations=2, progress=False, threads=None)
    one = dc.optimize(system, z0, goal, variables=Velocity(0), **kwargs)
    listed = dc.optimize(system, z0, goal, variables=[Velocity(0)], **kwargs)
    assert torch.equal(one.variables["velocity[0]"], listed.variables["velocity[0]"])


def test_starts_outside_the_bounds_are_clipped_with_a_warning(two_balls):
    """Given starts (or a current value) outside a variable's bounds were clipped silently."""
    system, z0 = two_balls
    goal = _final(0, torch.full((2,), 0.5))
    var = Velocity(0, bounds=(-4.0, 4.0))
    starts = {"velocity[0]": [[10.0, 10.0], [1.0, 1.0]]}
    with pytest.warns(UserWarning, match=r"starts\['velocity\[0\]'\] of velocity\[0\] lies "
                      r"outside its bounds in 1 of 2 starts: clipped"):  # fmt: skip
        res = dc.optimize(system, z0, goal, variables=[var], starts=starts,
                          steps=3, iterations=1, progress=False, lr=1e-9)  # fmt: skip
    clipped = res.start_variables["velocity[0]"][0]  # the best of start 0, from (4, 4)
    torch.testing.assert_close(clipped, torch.tensor([4.0, 4.0], dtype=clipped.dtype))
    fast = z0.clone()
    fast[1, 0] = torch.tensor([6.0, 0.0])
    with pytest.warns(UserWarning, match=r"the current value \(start 0\) of velocity\[0\]"):
        dc.optimize(system, fast, goal, variables=[var], starts=2,
                    steps=3, iterations=1, progress=False)  # fmt: skip


def test_overlapping_z0_and_integer_objectives_are_named(two_balls):
    """optimize's overlap error pointed to simulate's check_overlap, which it does not take;
    an integer objective was accepted."""
    system, z0 = two_balls
    goal = _final(0, torch.full((2,), 0.5))
    inside = z0.clone()
    inside[0, 0] = inside[0, 1] - torch.tensor([0.1, 0.0])
    with pytest.raises(ControlError, match="overlapping") as err:
        dc.optimize(system, inside, goal, variables=[Position(0)],
                    steps=2, progress=False)  # fmt: skip
    assert "check_overlap" not in str(err.value) and "optimize starts from z0" in str(err.value)
    with pytest.raises(ControlError, match="objective must return floating-point values"):
        dc.optimize(system, z0, lambda tr: torch.zeros(tr.shape[0], dtype=torch.long),
                    variables=[Velocity(0)], starts=2, steps=2, progress=False)  # fmt: skip


def test_parameter_bounds_outside_the_valid_range_are_refused(two_balls):
    """Bounds (-1, -0.5) on a mass were clipped to (1e-9, -0.5), warned about, and 1e-9
    returned as the optimised mass."""
    system, z0 = two_balls
    goal = _final(0, torch.full((2,), 0.5))
    for field, bounds, valid in (("mass", (-1.0, -0.5), r"\[1e-09, inf\]"),
                                 ("cor", (1.5, 2.0), r"\[0, 1\]")):  # fmt: skip
        var = Parameter(field, index=0, bounds=bounds)
        with pytest.raises(ControlError, match=rf"bounds .* lie outside the valid range of "
                           rf"{field} {valid}"):  # fmt: skip
            dc.optimize(system, z0, goal, variables=[var], steps=2, starts=2, iterations=1,
                        progress=False)  # fmt: skip


def test_non_finite_starts_are_named(two_balls):
    """A NaN in ``starts`` was reported as 'simulation failed: z0 contains NaN'."""
    system, z0 = two_balls
    goal = _final(0, torch.full((2,), 0.5))
    starts = {"velocity[0]": [[float("nan"), 1.0], [1.0, 1.0]]}
    with pytest.raises(ControlError, match=r"starts\['velocity\[0\]'\] contains NaN"):
        dc.optimize(system, z0, goal, variables=[Velocity(0)], starts=starts, steps=2,
                    iterations=1, progress=False)  # fmt: skip


def test_a_system_planner_takes_the_systems_own_contact_model():
    """A learned CMr model's as_system() plans with CMr (it had planned with CM); a System
    with no contact model set plans with CM, and an explicit one wins."""
    from diffcontact.control.planner import as_planner
    from diffcontact.learning.models.physical import LearnedModel

    model = LearnedModel("BP5-e", model="CMr-CD-CLNN", eps=0.05, hidden=(8,))
    assert as_planner(model.as_system()).truth_contact_model == "CMr"
    assert as_planner(dc.load_system("BP5-e")).truth_contact_model == "CM"
    assert as_planner(model.as_system(), contact_model="LCP").truth_contact_model == "LCP"

"""The rollout of ``System.simulate(cuda_graph=...)``: one step with static shapes and no
read of the device, captured in a CUDA graph and replayed.

On the CPU the same static step runs without a capture
(``Rollout.graphed(capture=False)``): it must give the step-by-step trajectories to
rounding, read the device once per rollout (not per step) and hand failures back to the
step-by-step rollout, which names them. The capture itself is tested on CUDA (marker
``cuda``)."""

import warnings

import pytest
import torch

import diffcontact as dc
from diffcontact.contact import SolverSettings, solve_cone_qp
from diffcontact.contact.cone_qp import deferred_checks, deferred_error
from diffcontact.contact.fused import FLAGS
from diffcontact.systems import rollout as rollout_module
from diffcontact.testing import count_host_reads

pytest.importorskip("warp")


def _static_rollout(system, z0, steps, params=None, strict=False):
    """``Rollout.graphed`` without the capture, with simulate's default options."""
    model, dynamics, fraction, params = system._options("CM", None, None, params)
    iterations = system._projection_iterations(None)
    ctx = system._context(z0, params, z0.shape[0])
    options = rollout_module.RolloutOptions(model, dynamics, fraction, iterations, None)
    run = rollout_module.Rollout(system, ctx, z0, steps, options, keep_gaps=True)
    return run.graphed(strict=strict, capture=False)


@pytest.mark.parametrize("task", ["BP5", "BP5-e", "BD5", "CP3", "Gyro"])
def test_the_static_step_gives_the_step_by_step_trajectories(task):
    """Every state through the solve, padded to GRAPH_CONTACTS contacts: the same impulses
    (the padding takes no part), to the rounding of matrix products of another size,
    which the chaotic contacts of BP5 may grow over the steps."""
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(16, seed=2)
    eager = system.simulate(z0, 60, cuda_graph=False)
    traj, gaps, _ = _static_rollout(system, z0, 60)
    assert (system.gaps(traj[:, 1:, 0].flatten(0, 1)) < 0).any()  # contacts were met
    torch.testing.assert_close(traj, eager, rtol=0, atol=1e-8)
    torch.testing.assert_close(gaps, system.gaps(traj[..., 0, :, :]), rtol=0, atol=1e-12)


def test_a_state_with_more_contacts_than_the_padding_reruns_with_more_and_remembers(
    monkeypatch,
):
    """With the padding cut to two contacts, BP5's states with three or more at once
    overflow: the rollout goes on from the state before the step that overflowed, padded
    to half as many more contacts as the most a state had (rounded up to 8; not to every
    candidate, which Rope-D400's 799 would make a 20 GB problem), with the step-by-step
    result, and the system remembers that padding for its next rollouts."""
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(64, seed=2)
    eager = system.simulate(z0, 60, cuda_graph=False)
    K = len(system.contact_names)
    tries = []
    attempt = rollout_module.Rollout._attempt

    def spy(self, contacts, *args):
        out = attempt(self, contacts, *args)
        step = out.step if isinstance(out, rollout_module.Overflow) else None
        tries.append((contacts, self.steps, step))
        return out

    monkeypatch.setattr(rollout_module, "GRAPH_CONTACTS", 2)
    monkeypatch.setattr(rollout_module.Rollout, "_attempt", spy)
    traj, gaps, _ = _static_rollout(system, z0, 60, strict=True)
    # (the most active contacts of a state, counted at the integrated positions before
    # the impulses, halved again and rounded up to 8)
    (two, steps, step), (grown, rest, done) = tries
    assert (two, steps, done) == (2, 60, None) and 1 < step < 60
    assert rest == 60 - (step - 1)  # the steps before the overflow are not run again
    assert grown % 8 == 0 and grown < K
    torch.testing.assert_close(traj, eager, rtol=0, atol=1e-8)
    torch.testing.assert_close(gaps, system.gaps(traj[..., 0, :, :]), rtol=0, atol=1e-12)
    assert system._contact_padding == grown
    tries.clear()
    _static_rollout(system, z0, 60)
    assert tries == [(grown, 60, None)]  # remembered: no rerun


def test_the_rest_of_an_overflowed_rollout_goes_step_by_step_where_too_short(monkeypatch):
    """Not ``strict`` (``cuda_graph="auto"``): the remaining steps after an overflow go
    step by step (deferred) where they are fewer than GRAPH_MIN_STEPS, or the projection's
    rows grew past GRAPH_MAX_ROWS; an overflow at the first step then gives up the graph
    (None: simulate goes step by step)."""
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(64, seed=2)
    eager = system.simulate(z0, 60, cuda_graph=False)
    runs = []
    step_by_step = rollout_module.Rollout.eager

    def spy(self, defer=False):
        runs.append((self.steps, defer))
        return step_by_step(self, defer)

    monkeypatch.setattr(rollout_module, "GRAPH_CONTACTS", 2)
    monkeypatch.setattr(rollout_module, "GRAPH_MIN_STEPS", 61)
    monkeypatch.setattr(rollout_module.Rollout, "eager", spy)
    traj, gaps, failed = _static_rollout(system, z0, 60)
    assert not bool(failed) and len(runs) == 1
    ((rest, defer),) = runs
    assert defer and 1 < rest < 60
    torch.testing.assert_close(traj, eager, rtol=0, atol=1e-8)
    torch.testing.assert_close(gaps, system.gaps(traj[..., 0, :, :]), rtol=0, atol=1e-12)


def test_long_ropes_go_step_by_step_when_auto():
    """``cuda_graph="auto"`` does not graph a rollout whose read-free projection pads to
    more than GRAPH_MAX_ROWS rows (each captured step projects every state at that size),
    or of a rope with more than GRAPH_MAX_LIMIT_ROWS limit rows; ``True`` still does."""
    system = dc.load_system("Rope-D100")
    z0 = system.sample_initial_conditions(4, seed=1)
    options = rollout_module.RolloutOptions(
        *system._options("CM", None, None, None)[:2], 0.0, system._projection_iterations(None), None
    )
    run = rollout_module.Rollout(system, system._context(z0, None, 4), z0, 20, options)
    assert run._graph_pays()
    system._projection_rows = rollout_module.GRAPH_MAX_ROWS + 8
    assert not run._graph_pays()
    no_projection = run.options._replace(iterations=0)
    assert rollout_module.Rollout(system, run.ctx, z0, 20, no_projection)._graph_pays()
    # a rope whose problem can hold more than GRAPH_MAX_LIMIT_ROWS rows goes step by step
    # from its first call (Rope-D100's 198 rows do not; Rope-D200's 398 do)
    assert system._projection_rows_all() <= rollout_module.GRAPH_MAX_LIMIT_ROWS
    longer = dc.load_system("Rope-D200")
    z0 = longer.sample_initial_conditions(4, seed=1)
    run = rollout_module.Rollout(longer, longer._context(z0, None, 4), z0, 20, options)
    assert longer._projection_rows <= rollout_module.GRAPH_MAX_ROWS
    assert not run._graph_pays()
    assert rollout_module.Rollout(longer, run.ctx, z0, 20, no_projection)._graph_pays()


def test_the_static_rollout_reads_the_device_once(monkeypatch):
    """No read inside a step (a graph could not capture one): the overflow flag, the
    deferred solver flags and the finiteness of the trajectory are read after the last
    step."""
    monkeypatch.delenv("DIFFCONTACT_SOLVER", raising=False)  # (a property of the fused solver)
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(32, seed=1)
    _static_rollout(system, z0, 2)
    reads = [count_host_reads(lambda k=k: _static_rollout(system, z0, k)) for k in (5, 25)]
    assert reads[1] == reads[0]  # nothing per step
    assert reads[0] <= 5


def test_a_failed_solve_is_flagged_for_the_step_by_step_rerun(monkeypatch):
    """A solve that fails inside the static rollout raises nothing there; its flag comes
    back for simulate to read, which then reruns step by step and names the states. (The
    failure is injected: the fused solver reports its first problem of every call
    unconverged; BP5, whose step-by-step rollout has problems of several contacts for it.
    CP3 under gravity 1e6 used to fail so, until the contact step took the velocities'
    constraint drift out: it now blows up instead.)"""
    monkeypatch.delenv("DIFFCONTACT_SOLVER", raising=False)  # (a property of the fused solver)
    from diffcontact.contact import ConeQPError, fused

    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(8, seed=0)
    _, _, failed = _static_rollout(system, z0, 30)
    assert not bool(failed)
    solve = fused.FusedConeQP.apply

    def failing(*args):
        f, converged, unbounded, iterations, residual, flags = solve(*args)
        converged, flags = converged.clone(), flags.clone()
        converged[:1], flags[5] = False, 1
        return f, converged, unbounded, iterations, residual, flags

    monkeypatch.setattr(fused.FusedConeQP, "apply", failing)
    _, _, failed = _static_rollout(system, z0, 20)
    assert bool(failed)
    with pytest.raises(ConeQPError, match="the contact solve failed at step"):
        system.simulate(z0, 20, on_tunnelling="ignore")


def test_deferred_checks_gather_the_flags_instead_of_raising():
    A = torch.zeros(1, 2, 2, dtype=torch.float64)
    b = torch.tensor([[0.1786, 0.3511]], dtype=torch.float64)
    mu = torch.tensor([[1.4538]], dtype=torch.float64)
    warp = SolverSettings(backend="warp")
    with pytest.raises(RuntimeError, match="unbounded"):
        solve_cone_qp(A, b.neg(), mu, 2, settings=warp)  # unbounded: raises at once
    flags = torch.zeros(len(FLAGS), dtype=torch.int32)
    with deferred_checks(flags):
        solve_cone_qp(A + torch.eye(2), b, mu, 2, settings=warp)
        assert deferred_error(flags) is None
        solve_cone_qp(A, b.neg(), mu, 2, settings=warp)  # no error here
        bad = torch.full_like(b, float("nan"))
        solve_cone_qp(A + torch.eye(2), bad, mu, 2, settings=warp)
    assert "unbounded or did not converge" not in (deferred_error(flags) or "")
    assert deferred_error(flags) == "solve_cone_qp: b contains NaN or infinite values"
    assert flags[5] == 1  # the unbounded problem's flag was gathered too
    # with return_status the caller handles failures: only input errors are gathered
    flags.zero_()
    with deferred_checks(flags):
        _, status = solve_cone_qp(A, b.neg(), mu, 2, settings=warp, return_status=True)
    assert status.unbounded.all() and deferred_error(flags) is None
    with pytest.raises(ValueError, match="int32"):
        with deferred_checks(torch.zeros(len(FLAGS))):
            pass


def test_cuda_graph_option_is_checked():
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(2, seed=0)
    with pytest.raises(ValueError, match="cuda_graph must be"):
        system.simulate(z0, 2, cuda_graph="yes")
    with pytest.raises(ValueError, match="cuda_graph=True, but the states are on cpu"):
        system.simulate(z0, 2, cuda_graph=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        system.simulate(z0, 20)  # "auto" on the CPU: step by step, quietly


cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@pytest.mark.cuda
@cuda
@pytest.mark.parametrize("task", ["BP5", "BD5", "CP3", "Gyro", "Rope"])
def test_graph_replay_equals_the_step_by_step_rollout_on_cuda(task):
    """(Rope: with the read-free position projection in the captured step.)"""
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(64, seed=3).cuda()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the capture must not fall back
        graphed = system.simulate(z0, 40, cuda_graph=True)
    eager = system.simulate(z0, 40, cuda_graph=False)
    torch.testing.assert_close(graphed, eager, rtol=0, atol=1e-8)


@pytest.mark.cuda
@cuda
def test_graph_replay_hands_failures_and_gradients_back_on_cuda():
    from diffcontact.contact import ConeQPError

    system = dc.load_system("CP3")
    z0 = system.sample_initial_conditions(8, seed=0).cuda()
    params = system.parameters().replace(gravity=1e6)
    with pytest.raises(ConeQPError, match="the contact solve failed at step"):
        system.simulate(z0, 20, params=params, on_tunnelling="ignore", cuda_graph=True)
    bp5 = dc.load_system("BP5")
    z = bp5.sample_initial_conditions(4, seed=5).cuda().requires_grad_(True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # "auto" with gradients: step by step, quietly
        bp5.simulate(z, 30)[:, -1, 0].sum().backward()
    assert torch.isfinite(z.grad).all()
    with pytest.raises(ValueError, match="needs gradients"):
        bp5.simulate(z, 30, cuda_graph=True)


def _replayed(fn):
    """``fn()`` captured in a CUDA graph (after a warm-up on a side stream), replayed once."""
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        fn()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph, capture_error_mode="relaxed"):
        out = fn()
    graph.replay()
    torch.cuda.synchronize()
    return out


@pytest.mark.cuda
@cuda
def test_the_steps_linear_algebra_and_the_fused_solve_can_be_captured():
    """The pieces a captured step needs, each captured alone, replay the eager results
    (torch's batched cholesky_solve, through MAGMA, cannot be captured)."""
    from diffcontact.fastops import cholesky_solve, spd_solve

    g = torch.Generator().manual_seed(0)
    R = torch.randn(256, 6, 6, generator=g, dtype=torch.float64)
    A = (R @ R.mT + 0.1 * torch.eye(6, dtype=torch.float64)).cuda()
    b = torch.randn(256, 6, generator=g, dtype=torch.float64).cuda()
    mu = torch.full((256, 3), 0.5, dtype=torch.float64, device="cuda")
    flags = torch.zeros(len(FLAGS), dtype=torch.int32, device="cuda")
    warp = SolverSettings(backend="warp")

    def qp():
        with deferred_checks(flags):
            return solve_cone_qp(A, b, mu, 2, settings=warp)

    cases = {
        "fused solve": qp,
        "cholesky_solve": lambda: cholesky_solve(b[..., None], torch.linalg.cholesky_ex(A)[0]),
        "spd_solve": lambda: spd_solve(A, b[..., None]),
    }
    for name, fn in cases.items():
        torch.testing.assert_close(_replayed(fn), fn(), rtol=0, atol=0, msg=name)
    assert deferred_error(flags) is None

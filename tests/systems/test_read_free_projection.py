"""The position projection without reading the device (``projection.ReadFree``): what
a captured CUDA step and a step-by-step rollout on CUDA run.

Every state and every iteration take part and each state's problem is padded to a
fixed number of rows, so no shape depends on the data; a state's correction stops
where the early stop of the reading projection would have stopped. On the CPU it must
give the reading projection's positions and gradients, read the device a fixed number
of times per rollout (not per step or iteration), and redo a rollout whose states
needed more rows than the padding, remembering the larger count."""

import itertools

import pytest
import torch

import diffcontact as dc
from diffcontact.systems import rollout as rollout_module
from diffcontact.systems.projection import ReadFree, project_positions
from diffcontact.testing import count_host_reads

pytest.importorskip("warp")


def _read_free(rows: int, system) -> ReadFree:
    needed = torch.zeros((), dtype=torch.long)
    return ReadFree(rows, needed, system._point_masses, system._two_sided)


def _violating_states(task: str, n: int, steps: int):
    """Positions after ``steps`` steps without the projection, most past a limit."""
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(n, seed=3)
    traj = system.simulate(z0, steps, position_projection=0, on_tunnelling="ignore")
    return system, traj


@pytest.mark.parametrize("task", ["Rope", "Rope-D100"])
def test_the_read_free_projection_gives_the_reading_ones_positions(task):
    system, traj = _violating_states(task, 32, 10)
    x = traj[:, -1, 0]
    violated = (system.gaps(x) < 0).any(-1)
    assert 0 < int(violated.sum()) < x.shape[0] or task == "Rope-D100"
    geometry, M_inv = system.geometry, system.inverse_mass_matrix()
    want = project_positions(x, geometry, M_inv, 10)
    read_free = _read_free(64, system)
    got = project_positions(x, geometry, M_inv, 10, read_free=read_free)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    assert torch.equal(got[~violated], x[~violated])  # admissible states untouched
    assert 0 < int(read_free.needed) <= 64 and not bool(read_free.overflowed)
    # padded to fewer rows than a state selects: flagged
    few = _read_free(2, system)
    project_positions(x, geometry, M_inv, 10, read_free=few)
    assert bool(few.overflowed) and int(few.needed) == int(read_free.needed)


def test_the_read_free_projection_damps_as_the_reading_one(monkeypatch):
    """A rope with a heavy tip, whose states' iterations damp (projection.DAMPING)."""
    from diffcontact.systems import projection

    system = dc.load_system("Rope", mass=[0.1] * 9 + [30.0], dt=0.01)
    z0 = system.sample_initial_conditions(16, seed=0)
    traj = system.simulate(z0, 20, position_projection=0, on_tunnelling="ignore")
    x = traj[:, -1, 0]
    geometry, M_inv = system.geometry, system.inverse_mass_matrix()
    # 20 steps without the projection: a few states are too far for 10 iterations
    with pytest.warns(RuntimeWarning, match="did not converge within 10 iterations"):
        want = project_positions(x, geometry, M_inv, 10)
    got = project_positions(x, geometry, M_inv, 10, read_free=_read_free(64, system))
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    monkeypatch.setattr(projection, "DAMPING", 0.0)
    with pytest.warns(RuntimeWarning, match="did not converge within 10 iterations"):
        undamped = project_positions(x, geometry, M_inv, 10)
    assert float((undamped - want).abs().max()) > 1e-4  # the damping took part


def test_the_read_free_projection_keeps_equality_constraints():
    """Disks pushed into a wall (block mass matrix, rigid-body constraints)."""
    system, traj = _violating_states("BD5", 6, 40)
    flat = traj.flatten(0, 1)
    hit = (system.gaps(flat[:, 0]) < -1e-4).any(-1)
    z = torch.cat([flat[hit][:4], flat[~hit][:2]])
    ctx = system._context(z, None, z.shape[0])
    args = (z[:, 0], ctx.geometry, ctx.M_inv, 10)
    want = project_positions(*args, constraints=ctx.constraints)
    got = project_positions(*args, constraints=ctx.constraints, read_free=_read_free(16, system))
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    assert float((got - z[:, 0]).abs().max()) > 1e-4


@pytest.mark.parametrize("task", list(dc.list_tasks()))
def test_the_structure_known_without_a_read_is_the_matrices(task):
    """``System._point_masses`` and ``_two_sided`` (what the read-free projection takes
    from the structure) agree with the inverse mass matrix and the geometry."""
    system = dc.load_system(task)
    M_inv = system.inverse_mass_matrix()
    assert system._point_masses == bool((M_inv == torch.diag_embed(M_inv.diagonal())).all())
    widths = getattr(system.geometry, "gap_widths", lambda: None)()
    assert system._two_sided == (widths is not None and bool(torch.isfinite(widths).any()))


def _static_rollout(system, z0, steps, strict=False):
    """``Rollout.graphed`` without the capture, with simulate's default options
    (``strict``: as ``cuda_graph=True``, the rest of a rollout after an overflow is graphed
    too)."""
    model, dynamics, _, params = system._options("CM", None, None, None)
    iterations = system._projection_iterations(None)  # (the penetration target is then off)
    ctx = system._context(z0, params, z0.shape[0])
    options = rollout_module.RolloutOptions(model, dynamics, 0.0, iterations, None)
    run = rollout_module.Rollout(system, ctx, z0, steps, options)
    return run.graphed(strict=strict, capture=False)


def test_the_static_rope_step_gives_the_step_by_step_trajectories(monkeypatch):
    monkeypatch.delenv("DIFFCONTACT_SOLVER", raising=False)  # (torch's solver reads)
    system = dc.load_system("Rope")
    z0 = system.sample_initial_conditions(32, seed=4)
    eager = system.simulate(z0, 20, cuda_graph=False)
    loose = system.simulate(z0, 20, position_projection=0)
    assert float((loose - eager).abs().max()) > 1e-3  # the projection acted
    traj, _, failed = _static_rollout(system, z0, 20)
    assert not bool(failed)
    torch.testing.assert_close(traj, eager, rtol=0, atol=1e-12)
    assert system._projection_rows == rollout_module.PROJECTION_ROWS  # enough: no rerun
    reads = [count_host_reads(lambda k=k: _static_rollout(system, z0, k)) for k in (4, 16)]
    assert reads[0] == reads[1] <= 3  # nothing per step or iteration


def test_too_few_rows_rerun_the_static_rollout_and_are_remembered(monkeypatch):
    system = dc.load_system("Rope")
    z0 = system.sample_initial_conditions(32, seed=4)
    eager = system.simulate(z0, 20, cuda_graph=False)
    system._projection_rows = 2
    tries = []
    attempt = rollout_module.Rollout._attempt

    def spy(self, contacts, capture, read_free):
        out = attempt(self, contacts, capture, read_free)
        overflow = isinstance(out, rollout_module.Overflow)
        tries.append((read_free.rows, "rows" if overflow else "done"))
        return out

    monkeypatch.setattr(rollout_module.Rollout, "_attempt", spy)
    traj, _, _ = _static_rollout(system, z0, 20, strict=True)
    torch.testing.assert_close(traj, eager, rtol=0, atol=1e-12)
    assert tries[0] == (2, "rows") and tries[-1][1] == "done"
    assert all(a[0] < b[0] for a, b in itertools.pairwise(tries))
    assert 2 < system._projection_rows <= 2 * system.n_contacts
    tries.clear()
    _static_rollout(system, z0, 20)
    assert tries == [(system._projection_rows, "done")]  # remembered: no rerun


def test_rows_counted_after_dropped_contacts_do_not_inflate_the_padding(monkeypatch):
    """An attempt whose contacts were too few also reports the rows its projection needed,
    but only up to the step where a state first dropped contacts: after it the trajectory
    is not the rollout's, and its rows would inflate the remembered padding. Every attempt
    reports at most the rows that the successful one needed, and both paddings grow from the
    reports."""
    system = dc.load_system("Rope-D100")
    z0 = system.sample_initial_conditions(32, seed=4)
    eager = system.simulate(z0, cuda_graph=False)
    system._projection_rows = 2
    monkeypatch.setattr(rollout_module, "GRAPH_CONTACTS", 1)
    tries = []
    attempt = rollout_module.Rollout._attempt

    def spy(self, contacts, capture, read_free):
        out = attempt(self, contacts, capture, read_free)
        overflow = out if isinstance(out, rollout_module.Overflow) else None
        tries.append((contacts, read_free.rows, overflow, int(read_free.needed)))
        return out

    monkeypatch.setattr(rollout_module.Rollout, "_attempt", spy)
    traj, _, _ = _static_rollout(system, z0, system.default_steps, strict=True)
    torch.testing.assert_close(traj, eager, rtol=0, atol=1e-12)
    *failed, (contacts, rows, last, rows_needed) = tries
    assert last is None and failed and failed[0][2].contacts > 1  # the contacts overflowed
    assert all(report.rows <= rows_needed for _, _, report, _ in failed)
    assert any(needed > rows_needed for *_, needed in failed)  # (what a report would be)
    assert contacts >= max(report.contacts for _, _, report, _ in failed)
    assert rows >= rows_needed


def _simulate_with_grad(system, z0, steps, pads: bool, monkeypatch):
    """``simulate`` with a gradient to the masses; ``pads``: as on CUDA with the
    read-free projection chosen (every state padded through the contact solve)."""
    monkeypatch.setattr(rollout_module, "_pads_contacts", lambda device: pads)
    monkeypatch.setattr(rollout_module, "_projects_read_free", lambda device: pads)
    base = system.parameters()
    mass = base.mass.clone().requires_grad_(True)
    traj = system.simulate(z0, steps, params=base.replace(mass=mass))
    (grad,) = torch.autograd.grad(traj[:, -1, 0].square().sum(), mass)
    return traj, grad


def test_the_cuda_step_by_step_path_projects_without_reads(monkeypatch):
    """The rollout with gradients as on CUDA with the read-free projection chosen
    (``rollout._projects_read_free``): the reading rollout's trajectory and
    gradient, and a fixed number of reads per call (the reading one reads in every
    iteration of every step)."""
    monkeypatch.delenv("DIFFCONTACT_SOLVER", raising=False)  # (torch's solver reads)
    system = dc.load_system("Rope")
    z0 = system.sample_initial_conditions(16, seed=5)
    want, grad_want = _simulate_with_grad(system, z0, 20, False, monkeypatch)
    got, grad_got = _simulate_with_grad(system, z0, 20, True, monkeypatch)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    torch.testing.assert_close(grad_got, grad_want, rtol=1e-10, atol=1e-12)

    def reads(steps: int, pads: bool) -> int:
        return count_host_reads(lambda: _simulate_with_grad(system, z0, steps, pads, monkeypatch))

    assert reads(5, True) == reads(15, True) <= 5
    assert reads(15, False) > reads(5, False) + 20


def test_the_cuda_step_by_step_path_reruns_with_too_few_rows(monkeypatch):
    system = dc.load_system("Rope")
    z0 = system.sample_initial_conditions(16, seed=5)
    want, grad_want = _simulate_with_grad(system, z0, 20, False, monkeypatch)
    system._projection_rows = 2
    got, grad_got = _simulate_with_grad(system, z0, 20, True, monkeypatch)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    torch.testing.assert_close(grad_got, grad_want, rtol=1e-10, atol=1e-12)
    assert system._projection_rows > 2


def test_the_rope_limits_widths_are_made_on_the_ropes_device(monkeypatch):
    """A captured CUDA step cannot copy from the host: the projection's widths must be
    made where the rope lives (the H200 run of 2026-11-27 failed to capture the Rope
    step on exactly this copy). The "meta" device stands in for CUDA here."""
    from diffcontact.geometry.base import ContactGeometry, GeometryBase
    from diffcontact.geometry.rope import rope_limits

    class OneSided(GeometryBase):  # a part with the default (all inf) widths
        d = 1
        n_candidates = 3

    rope = rope_limits(5).to("meta")
    assert [p.gap_widths().device.type for p in rope.parts] == ["meta", "meta"]

    def made_on_the_host(self):
        raise AssertionError("the default widths were made on the host and copied")

    monkeypatch.setattr(GeometryBase, "gap_widths", made_on_the_host)
    mixed = ContactGeometry((*rope.parts, OneSided()))
    widths = mixed.gap_widths()
    assert widths.device.type == "meta" and widths.shape == (rope.n_candidates + 3,)


@pytest.mark.parametrize("task", ["Rope", "Rope-D100"])
def test_point_masses_scale_the_rows_once_with_the_general_products_result(task):
    """With point masses the projection scales the sparse rows by sqrt(M^-1) and forms one
    dense matrix (A = J_s J_s^T, step M^-1/2 J_s^T lambda); the general path (J M^-1 J^T,
    M^-1 J^T lambda with the dense mass matrix) gives the same positions and gradients (a
    read-free projection takes ``diagonal`` from its caller, which picks the path)."""
    system, traj = _violating_states(task, 16, 10)
    x0 = traj[:, -1, 0]
    M_inv0 = system.inverse_mass_matrix() * torch.linspace(0.5, 2.0, x0.shape[-2])
    results = []
    for diagonal in (True, False):
        x = x0.clone().requires_grad_(True)
        M_inv = M_inv0.clone().requires_grad_(True)
        needed = torch.zeros((), dtype=torch.long)
        read_free = ReadFree(64, needed, diagonal, system._two_sided)
        got = project_positions(x, system.geometry, M_inv, 10, read_free=read_free)
        loss = (got.sin() * torch.linspace(-1, 1, got.numel()).view(got.shape)).sum()
        grad_x, grad_M = torch.autograd.grad(loss, [x, M_inv])
        # (the diagonal path reads only M^-1's diagonal: compare the gradient there)
        results.append((got.detach(), grad_x, grad_M.diagonal()))
    assert float((results[0][0] - x0).abs().max()) > 1e-4  # it moved
    for fast, general in zip(*results, strict=True):
        torch.testing.assert_close(fast, general, rtol=1e-9, atol=1e-12)


def test_an_overflowed_attempt_reports_no_more_rows_than_the_rollout_needs(monkeypatch):
    """Each attempt that overflowed its rows reports the rows its states needed up to and
    including the step that overflowed (after it, its states are not the rollout's), never
    more than a rollout padded to every row needs; the rollout goes on from the step before
    each overflow and gives the step-by-step trajectory."""
    monkeypatch.delenv("DIFFCONTACT_SOLVER", raising=False)  # (torch's solver reads)
    system = dc.load_system("Rope-D100")
    z0 = system.sample_initial_conditions(32, seed=4)
    eager = system.simulate(z0, cuda_graph=False)
    reports = []
    attempt = rollout_module.Rollout._attempt

    def spy(self, contacts, capture, read_free):
        out = attempt(self, contacts, capture, read_free)
        reports.append(out if isinstance(out, rollout_module.Overflow) else int(read_free.needed))
        return out

    monkeypatch.setattr(rollout_module.Rollout, "_attempt", spy)
    system._contact_padding = len(system.contact_names)  # (only the rows overflow)
    system._projection_rows = system._projection_rows_all()
    _static_rollout(system, z0, system.default_steps, strict=True)
    (needed,) = reports
    reports.clear()
    system._projection_rows = 2
    traj, _, _ = _static_rollout(system, z0, system.default_steps, strict=True)
    torch.testing.assert_close(traj, eager, rtol=0, atol=1e-12)
    *overflows, _ = reports
    assert len(overflows) >= 2 and all(1 <= o.rows <= needed for o in overflows)
    assert sorted(o.step for o in overflows) != [1] * len(overflows)  # it went on


@pytest.mark.parametrize("task", ["Rope", "Rope-D100"])
def test_the_sparse_gram_gives_the_dense_rows_positions_and_gradients(task, monkeypatch):
    """With point masses on the CPU the projection forms A = J_s J_s^T and the step J_s^T
    lambda from the rows' entries (``geometry.sparse_gram``, a Warp kernel; here at every
    size); the dense rows (small problems, no Warp, or the torch backend) give the same
    positions and gradients, with per-point masses and reading or read-free."""
    from diffcontact.systems import projection

    monkeypatch.setattr(projection, "MIN_DENSE_SIZE", 0)
    monkeypatch.delenv("DIFFCONTACT_SOLVER", raising=False)  # (torch: the dense rows)
    system, traj = _violating_states(task, 16, 10)
    x0 = traj[:, -1, 0]
    M_inv0 = system.inverse_mass_matrix() * torch.linspace(0.5, 2.0, x0.shape[-2])
    calls = []
    sparse_gram = projection.sparse_gram
    monkeypatch.setattr(projection, "sparse_gram", lambda *a: calls.append(1) or sparse_gram(*a))
    available = projection.sparse_gram_available
    for read_free in (None, 64):
        results = []
        for sparse in (True, False):
            monkeypatch.setattr(
                projection, "sparse_gram_available", available if sparse else lambda *a: False
            )
            x = x0.clone().requires_grad_(True)
            M_inv = M_inv0.clone().requires_grad_(True)
            rf = None if read_free is None else _read_free(read_free, system)
            got = project_positions(x, system.geometry, M_inv, 10, read_free=rf)
            loss = (got.sin() * torch.linspace(-1, 1, got.numel()).view(got.shape)).sum()
            grad_x, grad_M = torch.autograd.grad(loss, [x, M_inv])
            results.append((got.detach(), grad_x, grad_M.diagonal()))
            assert bool(calls) == sparse
            calls.clear()
        assert float((results[0][0] - x0).abs().max()) > 1e-4  # it moved
        for fast, dense in zip(*results, strict=True):
            torch.testing.assert_close(fast, dense, rtol=1e-9, atol=1e-12)


def test_the_sparse_gram_is_taken_only_where_the_dense_rows_are_large(monkeypatch):
    """``MIN_DENSE_SIZE`` decides by the size of the dense rows, ``n R P dim``: with it at
    20,000, 64 ten-point ropes (Rope: 53 states x 5 rows x 20) keep the dense rows and 64
    fifty-point ropes (Rope-D100: 64 x 13 x 100) take the kernel."""
    from diffcontact.systems import projection

    monkeypatch.setattr(projection, "MIN_DENSE_SIZE", 20_000)
    monkeypatch.delenv("DIFFCONTACT_SOLVER", raising=False)  # (torch: the dense rows)
    calls = []
    sparse_gram = projection.sparse_gram
    monkeypatch.setattr(projection, "sparse_gram", lambda *a: calls.append(a) or sparse_gram(*a))
    for task, used in (("Rope", False), ("Rope-D100", True)):
        system, traj = _violating_states(task, 64, 10)
        project_positions(traj[:, -1, 0], system.geometry, system.inverse_mass_matrix(), 10)
        assert bool(calls) == used, task
        for points, _ in calls:
            n, R, _ = points.shape
            assert n * R * traj.shape[-2] * traj.shape[-1] >= projection.MIN_DENSE_SIZE
        calls.clear()

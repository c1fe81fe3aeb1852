"""The position projection after each step (``position_projection``): limits hold.

The rope's limits are inelastic contacts resolved at velocity level; without a
position-level correction a whipping rope drifts far past them (docs/config.md,
``rope``). ``System.project_positions`` (systems/projection.py) moves the
positions onto the admissible set, keeping the equality constraints' values;
the rope tasks switch it on by default.
"""

import warnings

import pytest
import torch

import diffcontact as dc
from diffcontact.testing import assert_gradients_close

F64 = torch.float64


def segment_ratios(system, x: torch.Tensor) -> torch.Tensor:
    """``(..., P)`` segment lengths over the rest length (segment 0 from the anchor)."""
    anchor = torch.as_tensor(system.config.anchor, dtype=x.dtype)
    seg = torch.cat([x[..., :1, :] - anchor, x[..., 1:, :] - x[..., :-1, :]], dim=-2)
    return seg.norm(dim=-1) / float(system.config.rest_length)


def bending_angles(x: torch.Tensor) -> torch.Tensor:
    """``(..., P - 1)`` signed angles between consecutive segments (anchor at the origin)."""
    seg = torch.cat([x[..., :1, :], x[..., 1:, :] - x[..., :-1, :]], dim=-2)
    a, b = seg[..., :-1, :], seg[..., 1:, :]
    cross = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return torch.atan2(cross, (a * b).sum(-1))


def assert_limits_hold(system, x: torch.Tensor, tol: float = 1e-8) -> None:
    """Every gap of positions ``x: (..., P, 2)`` above ``-tol``, segment ratios and bends
    within the config's limits."""
    cfg = system.config
    assert float(system.gaps(x).min()) > -tol
    r = segment_ratios(system, x)
    assert float(r.max()) <= cfg.max_ratio + tol and float(r.min()) >= cfg.min_ratio - tol
    assert float(bending_angles(x).abs().max()) <= cfg.max_angle + tol


def test_defaults_and_validation():
    assert dc.load_system("Rope").position_projection == 10
    assert dc.load_system("Rope-D200").position_projection == 10
    for task in ("BP5", "BD5", "CP3", "Gyro"):
        assert dc.load_system(task).position_projection == 0
    assert dc.load_system("BP5", position_projection=3).position_projection == 3
    for bad in (-1, 1.5, True, "3"):
        with pytest.raises(ValueError, match="position_projection"):
            dc.load_system("Rope", position_projection=bad)
    system = dc.load_system("Rope")
    z0 = system.sample_initial_conditions(1, seed=0)
    with pytest.raises(ValueError, match="position_projection"):
        system.simulate(z0, 2, position_projection=-2)
    # the call's override has the config's bound (101 was accepted)
    with pytest.raises(ValueError, match=r"position_projection must be an integer in \[0, 100\]"):
        system.simulate(z0, 2, position_projection=101)


def test_rope_limits_hold_over_a_long_simulation():
    """1 s of a whipping rope at dt = 0.01: the limits hold with the projection only."""
    system = dc.load_system("Rope", dt=0.01, horizon=1.0)
    cfg = system.config
    z0 = system.sample_initial_conditions(4, seed=0)
    traj = system.simulate(z0, 100, on_tunnelling="ignore")
    assert_limits_hold(system, traj[:, :, 0])
    # the same rollout without it leaves the limits far behind: the test can fail
    loose = system.simulate(z0, 100, on_tunnelling="ignore", position_projection=0)
    r0 = segment_ratios(system, loose[:, :, 0])
    assert float(r0.max()) > 1.3 and float(r0.min()) < 0.7
    assert float(bending_angles(loose[:, :, 0]).abs().max()) > cfg.max_angle + 0.1


def test_projection_keeps_equality_constraints_and_velocities():
    """Disks (rigid-body constraints) and a chain (link constraints) pushed into walls."""
    for task, n, steps in (("BD5", 6, 40), ("CP3", 8, 60)):
        system = dc.load_system(task)
        z0 = system.sample_initial_conditions(n, seed=1)
        traj = system.simulate(z0, steps, on_tunnelling="ignore")  # projection off (default)
        flat = traj.flatten(0, 1)
        gaps = system.gaps(flat[:, 0])
        hit = (gaps < -1e-4).any(-1)
        assert bool(hit.any()), f"{task}: the rollout must contain a penetration"
        z = torch.cat([flat[hit][:4], flat[~hit][:2]])  # violated states and clean ones
        zp = system.project_positions(z, iterations=10)
        assert float(system.gaps(zp[:, 0]).min()) > -1e-10
        phi = system.constraints.phi
        assert float((phi(zp[:, 0]) - phi(z[:, 0])).abs().max()) < 1e-12
        # the velocities keep the constraints' rates (tangent at the new positions; they
        # were left as they were before, off the constraints, test_projection_constraints.py)
        J = system.constraints.jacobian
        rates, rates_p = (J(s[:, 0]) @ s[:, 1].flatten(1).unsqueeze(-1) for s in (z, zp))
        assert float((rates_p - rates).abs().max()) < 1e-10
        k = int(hit.sum().clamp(max=4))
        assert torch.equal(zp[k:], z[k:])  # admissible states untouched
        assert float((zp[:k, 0] - z[:k, 0]).abs().max()) > 1e-4


def test_projection_is_the_nearest_admissible_point_of_a_small_rope():
    """A 2-point rope with one stretch limit violated: the exact projection is known."""
    system = dc.load_system(
        {"type": "rope", "n_points": 2, "mass": [0.1, 0.3], "rest_length": 1.0,
         "stiffness": 0.0, "dt": 0.01, "horizon": 1.0}
    )  # fmt: skip
    # segment 0 along -y at length 1, segment 1 along -y stretched to 1.5 (limit 1.2)
    z = torch.tensor([[[[0.0, -1.0], [0.0, -2.5]], [[0.0, 0.0], [0.0, 0.0]]]], dtype=F64)
    zp = system.project_positions(z, iterations=5)
    # min 0.1 d0^2 + 0.3 d1^2 s.t. d0 + d1 >= 0.3 (segment 1 back to 1.2) gives d0 = 0.225,
    # past segment 0's own limit (d0 <= 0.2): so d0 = 0.2 (point 0 down) and d1 = 0.1 (up)
    expected = torch.tensor([[0.0, -1.2], [0.0, -2.4]], dtype=F64)
    torch.testing.assert_close(zp[0, 0], expected, rtol=0, atol=1e-12)


def test_a_geometry_with_the_protocol_only_projects_the_same():
    """The projection's gaps and rows come from ``gaps_and_rows_all`` where a geometry has
    it (the rope's); a geometry with only ``gaps`` and ``jacobian_sparse`` (and
    ``gap_widths``) gets the same positions."""
    from diffcontact.systems.projection import project_positions

    class ProtocolOnly:  # the methods a user's geometry must have, and gap_widths
        def __init__(self, inner):
            self.inner, self.d, self.n_candidates = inner, inner.d, inner.n_candidates

        def gaps(self, x):
            return self.inner.gaps(x)

        def jacobian_sparse(self, x, idx):
            return self.inner.jacobian_sparse(x, idx)

        def gap_widths(self):
            return self.inner.gap_widths()

    system = dc.load_system("Rope", initial_conditions={"angular_velocity_std": 6.0})
    z = system.simulate(system.sample_initial_conditions(8, seed=1), 5, position_projection=0)
    x = z[:, -1, 0]
    geometry, M_inv = system.geometry, system.inverse_mass_matrix()
    assert (geometry.gaps(x) < 0).any(-1).sum() >= 4, "most states violate a limit"
    want = project_positions(x, geometry, M_inv, 10)
    got = project_positions(x, ProtocolOnly(geometry), M_inv, 10)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    assert (geometry.gaps(got) > -1e-9).all()


def test_gradient_through_one_projected_step():
    system = dc.load_system(
        "Rope", n_points=5, dt=0.01, initial_conditions={"angular_velocity_std": 6.0}
    )
    z0 = system.sample_initial_conditions(3, seed=3)
    with torch.no_grad():
        loose = system.step(z0, position_projection=0)
        gaps = system.gaps(loose[:, 0])
    assert bool((gaps < -1e-3).any()), "the step must violate a limit"
    assert float(gaps.abs().min()) > 1e-5  # the active set stays put under perturbation
    base = system.parameters()
    names = ("mass", "stiffness", "gravity")

    def step(mass, stiffness, gravity, z):
        p = base.replace(mass=mass, stiffness=stiffness, gravity=gravity)
        return system.step(z, params=p)

    inputs = [getattr(base, n).detach().clone() for n in names] + [z0]
    results = assert_gradients_close(step, inputs, n_directions=2, rtol=1e-4)
    assert all(float(r.finite_difference.abs().max()) > 0 for r in results)
    with torch.no_grad():
        assert float(system.gaps(step(*inputs)[:, 0]).min()) > -1e-10


def test_float32_projection():
    system = dc.load_system("Rope", dt=0.01, horizon=1.0)
    z0 = system.sample_initial_conditions(4, seed=0)
    traj64 = system.simulate(z0, 30, on_tunnelling="ignore")
    traj32 = system.simulate(z0.float(), 30, on_tunnelling="ignore")
    assert traj32.dtype == torch.float32
    assert float(system.gaps(traj32[:, :, 0]).min()) > -1e-4
    # a step of each from the same float64 state agrees to float32 accuracy
    z = traj64[:, 20]
    one64 = system.step(z)
    one32 = system.step(z.float())
    assert float(system.gaps(one64[:, 0]).min()) > -1e-8
    torch.testing.assert_close(one32.double(), one64, rtol=0, atol=1e-4)


def test_gradient_through_the_projection_with_equality_constraints():
    """Disks pushed into a wall: the projection (with Mhat^-1 and the Phi restoration)."""
    system = dc.load_system("BD5")
    z0 = system.sample_initial_conditions(6, seed=1)
    traj = system.simulate(z0, 40, on_tunnelling="ignore")
    flat = traj.flatten(0, 1)
    gaps = system.gaps(flat[:, 0])
    hit = (gaps < -1e-3).any(-1) & ((gaps.abs() > 1e-5).all(-1))
    z = flat[hit][:2]
    assert z.shape[0] == 2
    base = system.parameters()

    def project(mass, z):
        return system.project_positions(z, params=base.replace(mass=mass), iterations=10)

    results = assert_gradients_close(project, [base.mass.clone(), z], n_directions=2, rtol=1e-4)
    assert all(float(r.finite_difference.abs().max()) > 0 for r in results)


@pytest.mark.parametrize("task", ["Rope", "BD5", "CP3"])
def test_metric_norms_of_the_sparse_rows_equal_the_dense_ones(task):
    """The projection's distance scale ||J_k||_{M^-1}, computed from the sparse rows, equals
    the dense product for diagonal (rope), block (disks) and per-state mass matrices; for
    point masses also by the diagonal's shortcut (``diagonal=True``)."""
    from diffcontact.systems.projection import _metric_norms

    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(5, seed=2)
    ctx = system._context(z0, system.parameters(), z0.shape[0])
    x = z0[:, 0]
    n, P, dim = x.shape
    K = ctx.geometry.n_candidates
    J = ctx.geometry.jacobian(x, torch.arange(K).expand(n, K))[:, :, 0].reshape(n, K, P * dim)
    for M_inv in (ctx.M_inv, ctx.M_inv * torch.linspace(1.0, 2.0, n, dtype=F64).view(n, 1, 1)):
        Mi = M_inv.expand(n, P, P) if M_inv.dim() == 2 else M_inv
        big = torch.kron(Mi, torch.eye(dim, dtype=F64))  # (n, P dim, P dim)
        dense = torch.einsum("nkd,nde,nke->nk", J, big, J).sqrt()
        torch.testing.assert_close(_metric_norms(ctx.geometry, x, M_inv), dense, rtol=1e-12, atol=0)
        if task == "Rope":
            got = _metric_norms(ctx.geometry, x, M_inv, diagonal=True)
            torch.testing.assert_close(got, dense, rtol=1e-12, atol=0)


def test_the_projection_takes_any_minimiser_with_the_canonical_ones_positions(monkeypatch):
    """The projection's step M^-1 J^T lambda is the same for every minimiser lambda, so it
    asks the solver for any (SolverSettings.canonical=False), which spares the fused
    solver's interior point at the kinks its problems are full of: the same trajectories
    as with the canonical minimiser, to 1e-10, and fewer interior-point iterations."""
    pytest.importorskip("warp")
    monkeypatch.delenv("DIFFCONTACT_SOLVER", raising=False)  # (a property of the fused solver)
    from diffcontact.systems import projection

    system = dc.load_system("Rope-D100")
    z0 = system.sample_initial_conditions(16, seed=3)
    solve = projection.solve_cone_qp
    calls = []

    def spy(*args, settings=None, **kwargs):
        out = solve(*args, settings=settings, **kwargs)
        calls.append((settings.canonical, int(out[1].iterations.sum())))
        return out

    monkeypatch.setattr(projection, "solve_cone_qp", spy)
    traj = system.simulate(z0, cuda_graph=False)
    assert calls and not any(canonical for canonical, _ in calls)
    iterations_any = sum(it for _, it in calls)
    calls.clear()

    def canonical_replace(settings, **changes):
        return settings  # (the projection's replace(settings, canonical=False) undone)

    monkeypatch.setattr(projection, "replace", canonical_replace)
    canonical = system.simulate(z0, cuda_graph=False)
    assert all(canonical for canonical, _ in calls)
    torch.testing.assert_close(traj, canonical, rtol=0, atol=1e-10)
    assert iterations_any < sum(it for _, it in calls)


def _heavy_tip(tip: float, **keys):
    """The 10-point Rope with its last point ``tip`` kg (the others 0.1 kg)."""
    return dc.load_system("Rope", mass=[0.1] * 9 + [tip], **keys)


def test_a_heavy_tip_keeps_the_limits(monkeypatch):
    """A tip 300x the other points: the damped iterations keep the limits, and the energy
    does not rise; plain Gauss-Newton steps stalled and the rope stretched to 3x."""
    from diffcontact.systems import projection

    system = _heavy_tip(30.0, dt=0.01, horizon=1.0)
    z0 = system.sample_initial_conditions(4, seed=0)
    traj = system.simulate(z0, 100, on_tunnelling="ignore")
    assert_limits_hold(system, traj[:, :, 0])
    E = system.energy(traj)
    assert float((E - E[:, :1]).max()) < 1e-6
    # without the damping (a zero DAMPING never damps) the projection stalls
    monkeypatch.setattr(projection, "DAMPING", 0.0)
    stalled = system.simulate(z0, 100, on_tunnelling="ignore")
    assert float(segment_ratios(system, stalled[:, :, 0]).max()) > 2.0


def test_equal_point_masses_are_not_damped(monkeypatch):
    """Their damped metric is the masses' times a number: the same steps, so they take
    the undamped iterations' exact positions."""
    from diffcontact.systems import projection

    system = dc.load_system("Rope", dt=0.01)
    z0 = system.sample_initial_conditions(4, seed=0)
    traj = system.simulate(z0, 40, on_tunnelling="ignore")
    monkeypatch.setattr(projection, "DAMPING", 0.0)
    assert torch.equal(system.simulate(z0, 40, on_tunnelling="ignore"), traj)
    # ... but the damped metric is used: the masses' times a number
    w = torch.full((3, 5), 10.0, dtype=F64)
    damped = projection._damped(w, torch.tensor([0.0, 1.0, 100.0], dtype=F64), True)
    torch.testing.assert_close(damped, w / torch.tensor([[1.0], [2.0], [101.0]], dtype=F64))


def test_the_damped_metric_of_a_matrix_is_that_of_its_diagonal():
    """``(M + rho mbar I)^-1`` from a full ``M_inv`` and from the diagonal of point masses."""
    from diffcontact.systems.projection import _damped

    w = torch.tensor([[10.0, 10.0, 0.01], [1.0, 2.0, 4.0]], dtype=F64)
    rho = torch.tensor([3.0, 0.0], dtype=F64)
    want = _damped(w, rho, True)  # (2, 3)
    mbar = (1 / w[0]).mean()
    torch.testing.assert_close(want[0], 1 / (1 / w[0] + 3.0 * mbar))
    torch.testing.assert_close(want[1], w[1])  # rho = 0: the masses' metric
    got = _damped(torch.diag_embed(w), rho, False)
    torch.testing.assert_close(got, torch.diag_embed(want))


def test_gradient_through_a_damped_projection(monkeypatch):
    """A heavy-tip step whose projection damps: autograd against finite differences.

    The line search's step lengths and the damping are discrete choices; the state is one
    whose choices stay put under the finite differences' perturbation (many heavy-tip
    states are near a switch, as the undamped projection's are near one of the line
    search's)."""
    from diffcontact.systems import projection

    system = _heavy_tip(30.0, dt=0.01)
    z0 = system.sample_initial_conditions(4, seed=0)
    z = system.simulate(z0, 22, on_tunnelling="ignore")[1:2, -1]
    with torch.no_grad():
        gaps = system.gaps(system.step(z, position_projection=0)[:, 0])
        damped = system.step(z)
        monkeypatch.setattr(projection, "DAMPING", 0.0)
        undamped = system.step(z)
        monkeypatch.undo()
    assert float((damped - undamped).abs().max()) > 1e-5, "the step's projection must damp"
    assert float(gaps.abs().min()) > 1e-5  # the active set stays put under perturbation
    base = system.parameters()

    def step(mass, stiffness, z):
        return system.step(z, params=base.replace(mass=mass, stiffness=stiffness))

    inputs = [base.mass.detach().clone(), base.stiffness.detach().clone(), z]
    results = assert_gradients_close(step, inputs, n_directions=2, rtol=1e-4)
    assert all(float(r.finite_difference.abs().max()) > 0 for r in results)


def test_a_projection_that_does_not_converge_warns():
    """A rope stretched to twice its length is far from its limits: 100 iterations leave
    it stretched (ratios up to 2.1), which the public call said nothing about."""
    system = dc.load_system("Rope")
    z = system.sample_initial_conditions(2, seed=0)
    far = z.clone()
    far[:, 0] *= 2
    with pytest.warns(RuntimeWarning, match=r"did not converge within 100 iterations for 2 of 2"):
        out = system.project_positions(far, iterations=100)
    assert float(system.gaps(out[:, 0]).min()) < -0.01
    # a state one step from its limits converges, and nothing is said
    traj = system.simulate(z, 20)
    near = traj[:, -1].clone()
    near[:, 0] *= 1.01
    assert float(system.gaps(near[:, 0]).min()) < 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = system.project_positions(near)
    assert float(system.gaps(out[:, 0]).min()) > -1e-10


def test_a_rope_with_restitution_and_the_projection_warns():
    """Restitution on a rope's limits with the position projection can raise its energy
    without bound (docs/config.md, rope, "Restitution"): loading such a rope says so; the
    defaults (cor 0) and a rope without the projection do not."""
    from diffcontact.systems.system import ROPE_RESTITUTION_WARNING

    with pytest.warns(UserWarning, match="rope limits with cor > 0") as record:
        dc.load_system("Rope", cor=0.5)
    assert str(record[0].message) == ROPE_RESTITUTION_WARNING
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dc.load_system("Rope")
        dc.load_system("Rope", cor=0.5, position_projection=0)
        dc.load_system("BP5", cor=0.5, position_projection=10)

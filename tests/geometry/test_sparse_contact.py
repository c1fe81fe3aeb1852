"""The contact impulse from a long rope's sparse rows (``SparseContact``) against the dense
``J_C`` and ``Mhat^-1`` (``DenseContact``): each map, the two-phase impulse and the
penetration target, the simulator's choice of route, trajectories and gradients."""

import pytest
import torch

import diffcontact as dc
from diffcontact.contact import DenseContact, penetration_target, two_phase_impulse
from diffcontact.contact.operator import as_operator
from diffcontact.geometry.base import SparseJacobian
from diffcontact.geometry.sparse_contact import SparseContact
from diffcontact.systems import system as system_module

pytest.importorskip("warp")

F64 = torch.float64
TOL = dict(rtol=1e-12, atol=1e-12)


def _dense_inverse_inertia(op: SparseContact) -> torch.Tensor:
    """The operator's ``Mhat^-1 = kron(diag(w), I_dim)`` as ``(n, D, D)``."""
    n, dim = op.rows.values.shape[0], op.rows.values.shape[-1]
    w = op.inverse_mass.expand(n, op.n_points)
    return torch.diag_embed(w.repeat_interleave(dim, -1))


def _rope_contacts(task="Rope-D100", n=6, seed=0, per_state_masses=False):
    """The rows of ``n`` states' most violated limits after a short rollout without the
    projection (real rope rows, several per state, the last contact padded with zeros),
    the point masses, and both operators of them."""
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(n, seed=seed)
    z = system.simulate(z0, 8, position_projection=0, on_tunnelling="ignore")[:, -1]
    x = z[:, 0]
    gaps = system.gaps(x)
    K = 5
    idx = gaps.argsort(-1)[:, :K]  # (n, K)
    active = torch.ones(n, K, dtype=torch.bool)
    active[:, -1] = False
    rows = system.geometry.jacobian_sparse(x, idx)
    values = torch.where(active[:, :, None, None, None], rows.values, 0.0)
    points = rows.points.expand(n, K, rows.points.shape[-1])
    w = system.inverse_mass_matrix().diagonal()  # (P,)
    if per_state_masses:
        gen = torch.Generator().manual_seed(seed + 1)
        w = w * (0.5 + torch.rand(n, w.shape[-1], generator=gen, dtype=F64))
    sparse = SparseContact(SparseJacobian(points, values), w)
    J = sparse.dense()
    dense = DenseContact(J, _dense_inverse_inertia(sparse))
    return system, z, active, sparse, dense, gaps.gather(-1, idx)


@pytest.mark.parametrize("per_state_masses", [False, True])
def test_every_map_equals_the_dense_products(per_state_masses):
    _, z, active, sparse, dense, _ = _rope_contacts(per_state_masses=per_state_masses)
    n, D = z.shape[0], z[0, 1].numel()
    gen = torch.Generator().manual_seed(3)
    v = torch.randn(n, D, generator=gen, dtype=F64)
    f = torch.randn(n, active.shape[1] * sparse.rows.values.shape[2], generator=gen, dtype=F64)
    for name, args in [
        ("contact_velocity", (v,)),
        ("generalized_impulse", (f,)),
        ("velocity_change", (f,)),
        ("delassus", ()),
        ("gram", ()),
    ]:
        got, want = getattr(sparse, name)(*args), getattr(dense, name)(*args)
        assert got.shape == want.shape, name
        torch.testing.assert_close(got, want, **TOL, msg=name)
    A = dense.delassus()
    assert float(A.abs().max()) > 0  # real rows
    assert float(A[:, -1].abs().max()) == 0  # the padded contact: exact zeros
    assert torch.equal(sparse.delassus(), sparse.delassus().mT)  # exactly symmetric


def test_impulse_and_penetration_target_equal_the_dense_ones():
    """Two-phase impulses (CM and CMr) and the penetration target from the sparse rows
    equal those from the dense ``J_C`` (d = 1 rope limits, restitution set)."""
    system, z, active, sparse, dense, gaps = _rope_contacts(n=8, seed=1)
    n, K = active.shape
    v = z[:, 1].reshape(n, -1)
    mu = torch.zeros(n, K, dtype=F64)
    cor = torch.full((n, K), 0.4, dtype=F64)
    depth = (-gaps).clamp_min(0)
    got_t = penetration_target(sparse, depth, active, system.dt, 1, 0.2)
    want_t = penetration_target(dense.J_C, depth, active, system.dt, 1, 0.2)
    torch.testing.assert_close(got_t, want_t, **TOL)
    assert float(want_t.abs().max()) > 0
    for eps in (None, 0.01):
        got = two_phase_impulse(sparse, None, v, mu, cor, active, 1, v_C_star=got_t, eps=eps)
        want = two_phase_impulse(
            dense.J_C, dense.Mhat_inv, v, mu, cor, active, 1, v_C_star=want_t, eps=eps
        )
        pairs = zip((got.v_plus, got.f_c, got.f_r), (want.v_plus, want.f_c, want.f_r), strict=True)
        for a, b in pairs:
            torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11)
        assert float(want.f_c.abs().max()) > 0  # the limits push


@pytest.mark.parametrize("model", ["LCP", "Coulomb"])
def test_the_other_built_in_models_take_the_operator_too(model):
    """LCP (one phase, Lemke) and exact Coulomb (two phases) from the sparse rows equal
    their impulses from the dense ``J_C``."""
    from diffcontact.contact import ContactParams, create_contact_model

    _, z, active, sparse, dense, _ = _rope_contacts(n=8, seed=1)
    n, K = active.shape
    v = z[:, 1].reshape(n, -1) - sparse.generalized_impulse(active.to(F64))
    params = ContactParams(torch.zeros(n, K, dtype=F64), torch.full((n, K), 0.4, dtype=F64))
    contact_model = create_contact_model(model)
    assert contact_model.accepts_contact_operator
    got = contact_model.resolve(sparse, None, v, params, active, 1)
    want = contact_model.resolve(dense.J_C, dense.Mhat_inv, v, params, active, 1)
    for a, b in zip((got.v_plus, got.f_c, got.f_r), (want.v_plus, want.f_c, want.f_r), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11)
    assert float(want.f_c.abs().max()) > 0


def test_gradients_match_finite_differences_and_the_dense_ones():
    """Gradients of the impulse in the rows' values and the inverse masses (learned masses):
    against finite differences, and against the dense route's."""
    _, z, active, sparse, _, _ = _rope_contacts(n=2, seed=2, per_state_masses=True)
    n, K = active.shape
    # velocities into the limits (J_C v = -J_C J_C^T 1 on the real contacts): impulses
    v = z[:, 1].reshape(n, -1) - sparse.generalized_impulse(active.to(F64))
    mu = torch.zeros(n, K, dtype=F64)
    cor = torch.full((n, K), 0.3, dtype=F64)
    points = sparse.rows.points

    def through(values, w, dense):
        op = SparseContact(SparseJacobian(points, values), w)
        if dense:
            return two_phase_impulse(op.dense(), _dense_inverse_inertia(op), v, mu, cor, active, 1)
        return two_phase_impulse(op, None, v, mu, cor, active, 1)

    values = sparse.rows.values.clone().requires_grad_(True)
    w = sparse.inverse_mass.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: through(a, b, False).v_plus, (values, w))
    W = torch.randn(n, v.shape[-1], dtype=F64, generator=torch.Generator().manual_seed(4))
    grads = [
        torch.autograd.grad((through(values, w, dense).v_plus * W).sum(), (values, w))
        for dense in (False, True)
    ]
    for a, b in zip(*grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11)
        assert float(b.abs().max()) > 0


def test_as_operator_checks_its_arguments():
    J, Mh = torch.zeros(1, 2, 4, dtype=F64), torch.eye(4, dtype=F64).expand(1, 4, 4)
    op = as_operator(J, Mh)
    assert isinstance(op, DenseContact) and as_operator(op, None) is op
    with pytest.raises(ValueError, match="pass Mhat_inv=None"):
        as_operator(op, Mh)
    with pytest.raises(TypeError, match="tensor or a ContactOperator"):
        as_operator([[0.0]], None)
    with pytest.raises(ValueError, match="no Mhat_inv"):
        DenseContact(J, None).delassus()


class _Spy:
    """A CM that records the type of ``J_C`` it was given."""

    accepts_contact_operator = True

    def __init__(self, accepts: bool = True):
        from diffcontact.contact import PoissonTwoPhase

        self.inner, self.seen = PoissonTwoPhase(), []
        self.accepts_contact_operator = accepts

    def resolve(self, J_C, Mhat_inv, *args, **kwargs):
        self.seen.append(type(J_C).__name__)
        return self.inner.resolve(J_C, Mhat_inv, *args, **kwargs)


@pytest.mark.parametrize(
    ("task", "steps", "projection"), [("Rope", 30, None), ("Rope", 30, 0), ("Rope-D100", 12, None)]
)
def test_rollouts_with_the_sparse_rows_equal_the_dense_ones(task, steps, projection, monkeypatch):
    """A rope simulated with the impulse from the sparse rows (forced at this small size)
    follows the dense route's trajectory, with the same gradient in the initial state
    (with the position projection, and without it: then with the penetration target)."""
    monkeypatch.delenv("DIFFCONTACT_SOLVER", raising=False)
    monkeypatch.setattr(system_module, "MIN_DENSE_SIZE", 0)
    monkeypatch.setattr(system_module, "SPARSE_CONTACT_COLUMNS", 0)
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(6, seed=5).requires_grad_(True)
    out = []
    for accepts in (True, False):
        spy = _Spy(accepts)
        traj = system.simulate(
            z0, steps, contact_model=spy, position_projection=projection, on_tunnelling="ignore"
        )
        (grad,) = torch.autograd.grad(traj[:, -1, 0].square().sum(), z0)
        out.append((traj.detach(), grad))
        want = "SparseContact" if accepts else "Tensor"
        assert spy.seen and set(spy.seen) == {want}, spy.seen
    torch.testing.assert_close(out[0][0], out[1][0], rtol=0, atol=1e-11)
    torch.testing.assert_close(out[0][1], out[1][1], rtol=1e-8, atol=1e-9)


def test_the_route_follows_the_size_and_the_structure(monkeypatch):
    """The dense ``J_C`` below ``MIN_DENSE_SIZE`` or ``SPARSE_CONTACT_COLUMNS``, with the
    torch solver, for bodies other than point masses or with equality constraints, and in
    ``resolve_contacts`` (which returns ``J_C``)."""
    monkeypatch.delenv("DIFFCONTACT_SOLVER", raising=False)
    rope = dc.load_system("Rope")
    z0 = rope.sample_initial_conditions(6, seed=5)
    torch_solver = dc.contact.SolverSettings(backend="torch")
    for size, columns, settings, want in [
        (0, 0, None, "SparseContact"),
        (10**9, 0, None, "Tensor"),
        (0, 21, None, "Tensor"),  # the rope's rows have 20 columns
        (0, 0, torch_solver, "Tensor"),
    ]:
        monkeypatch.setattr(system_module, "MIN_DENSE_SIZE", size)
        monkeypatch.setattr(system_module, "SPARSE_CONTACT_COLUMNS", columns)
        spy = _Spy()
        rope.simulate(z0, 30, contact_model=spy, solver_settings=settings)
        assert set(spy.seen) == {want}, (size, columns, settings, spy.seen)
    z = rope.simulate(z0, 30, position_projection=0)[:, -1]
    res = rope.resolve_contacts(z, contact_model=_Spy())
    assert isinstance(res.J_C, torch.Tensor) and res.J_C.shape[0] == res.batch_index.shape[0] > 0
    # BP5: point masses (sparse where forced); BD5: extended bodies; CP3: point masses with
    # equality constraints (a Mhat^-1 that is not diagonal)
    monkeypatch.setattr(system_module, "MIN_DENSE_SIZE", 0)
    monkeypatch.setattr(system_module, "SPARSE_CONTACT_COLUMNS", 0)
    for task, want in (("BP5", "SparseContact"), ("BD5", "Tensor"), ("CP3", "Tensor")):
        system, spy = dc.load_system(task), _Spy()
        system.simulate(system.sample_initial_conditions(8, seed=0), 40, contact_model=spy)
        assert spy.seen and set(spy.seen) == {want}, (task, spy.seen)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_the_sparse_maps_on_cuda_equal_the_cpu():
    """What ``--sparse-gram-cuda`` switches on for the impulse: every map on CUDA."""
    _, z, active, sparse, _, _ = _rope_contacts()
    n = z.shape[0]
    v = z[:, 1].reshape(n, -1)
    f = torch.randn(n, active.shape[1], dtype=F64, generator=torch.Generator().manual_seed(6))
    rows = SparseJacobian(sparse.rows.points.cuda(), sparse.rows.values.cuda())
    on_cuda = SparseContact(rows, sparse.inverse_mass.cuda())
    for name, args in [
        ("contact_velocity", (v,)),
        ("velocity_change", (f,)),
        ("delassus", ()),
        ("gram", ()),
    ]:
        got = getattr(on_cuda, name)(*(a.cuda() for a in args))
        torch.testing.assert_close(got.cpu(), getattr(sparse, name)(*args), **TOL, msg=name)

"""Bad inputs to ``System``'s public methods: one-line ``ValueError``s naming the argument
(not torch's TypeError/RuntimeError/AssertionError from inside, nor silent garbage)."""

import pytest
import torch

import diffcontact as dc

F64 = torch.float64


@pytest.fixture(scope="module")
def bp5():
    return dc.load_system("BP5")


@pytest.fixture(scope="module")
def z0(bp5):
    return bp5.sample_initial_conditions(3, seed=0)


@pytest.fixture
def no_cuda(monkeypatch):
    """CUDA reported unavailable (the message is the same with or without a GPU)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


# ------------------------------------------------------------------ mass matrices
@pytest.mark.parametrize("method", ["mass_matrix", "inverse_mass_matrix"])
@pytest.mark.parametrize("dtype", [torch.long, torch.int32, torch.float16, "float32", None])
def test_mass_matrix_refuses_other_dtypes(bp5, method, dtype):
    """``mass_matrix(torch.long)`` had truncated the masses to 0 (a zero matrix)."""
    with pytest.raises(ValueError, match=r"dtype must be torch.float32 or torch.float64"):
        getattr(bp5, method)(dtype)


@pytest.mark.parametrize("method", ["mass_matrix", "inverse_mass_matrix"])
def test_mass_matrix_names_bad_devices(bp5, method, no_cuda):
    with pytest.raises(ValueError, match=r"device must be 'cpu' or 'cuda', got 'bogus'"):
        getattr(bp5, method)(device="bogus")
    with pytest.raises(ValueError, match=r"device 'cuda' requested but CUDA is not available"):
        getattr(bp5, method)(device="cuda")


@pytest.mark.parametrize("task", ["BP5", "BD5", "Gyro"])
def test_mass_matrix_of_batched_params(task):
    """The documented ``(N, P, P)`` for batched masses (or second moments): each row the
    matrix of that trajectory's parameters (they had been refused)."""
    system = dc.load_system(task)
    p = system.parameters()
    scale = torch.tensor([1.0, 2.0, 0.5], dtype=F64)[:, None]
    batched = p.replace(mass=p.mass * scale)
    M = system.mass_matrix(params=batched)
    M_inv = system.inverse_mass_matrix(params=batched)
    P = system.n_points
    assert M.shape == M_inv.shape == (3, P, P)
    for i in range(3):
        row = p.replace(mass=p.mass * scale[i])
        torch.testing.assert_close(M[i], system.mass_matrix(params=row), rtol=1e-14, atol=0)
        want = system.inverse_mass_matrix(params=row)
        torch.testing.assert_close(M_inv[i], want, rtol=1e-14, atol=0)
    if p.second_moments is not None:
        both = batched.replace(second_moments=p.second_moments.expand(3, *p.second_moments.shape))
        torch.testing.assert_close(system.mass_matrix(params=both), M, rtol=0, atol=0)
    unbatched_mu = p.replace(mu=p.mu.expand(3, *p.mu.shape) if p.mu.dim() else p.mu.expand(3, 1))
    assert system.mass_matrix(params=unbatched_mu).shape == (P, P)  # masses not batched
    mixed = batched.replace(cor=torch.full((2, 1), 0.5, dtype=F64))
    with pytest.raises(ValueError, match="disagree on the batch size"):
        system.mass_matrix(params=mixed)


# ------------------------------------------------------------- contact velocities
def test_contact_velocities_checks_its_state(bp5, z0):
    assert bp5.contact_velocities(z0).shape == (3, bp5.n_contacts, bp5.d)
    traj = z0[:, None].expand(3, 2, *z0.shape[1:])
    assert bp5.contact_velocities(traj).shape == (3, 2, bp5.n_contacts, bp5.d)
    with pytest.raises(ValueError, match=r"z must have shape \(\.\.\., \(2, 5, 2\)\)"):
        bp5.contact_velocities(z0[:, :, :2])  # 2 points, not 5 (an IndexError)
    with pytest.raises(ValueError, match=r"z must be a float32 or float64 tensor"):
        bp5.contact_velocities(z0.long())  # (torch.finfo's TypeError)
    with pytest.raises(ValueError, match=r"z must be a torch.Tensor, got list"):
        bp5.contact_velocities(z0.tolist())  # (an AttributeError)


# ---------------------------------------------------------------------- potential
def _bad_potential(x):
    return (x**2).sum(-1)  # (..., P): one value per point, not per state


def test_a_potential_of_the_wrong_output_shape_is_named(bp5, z0):
    """Accepted by ``simulate`` (its forces sum it) and a broadcast RuntimeError in
    ``energy``; now refused at each public entry, naming the expected and actual shape."""
    params = bp5.parameters().replace(potential=_bad_potential)
    pattern = r"potential .* expected shape \(3,\) for positions of shape \(3, 5, 2\), got \(3, 5\)"
    with pytest.raises(ValueError, match=pattern):
        bp5.simulate(z0, 2, params=params)
    with pytest.raises(ValueError, match=pattern):
        bp5.energy(z0, params=params)
    with pytest.raises(ValueError, match=pattern):
        bp5.potential(z0[:, 0], params=params)
    with pytest.raises(ValueError, match=pattern):
        bp5.grad_potential(z0[:, 0], params=params)
    with pytest.raises(ValueError, match=pattern):
        bp5.step(z0, params=params)
    with pytest.raises(ValueError, match=pattern):
        bp5.integrate(z0, params=params)
    not_a_tensor = bp5.parameters().replace(potential=lambda x: 0.0)
    with pytest.raises(ValueError, match=r"potential .* got float"):
        bp5.energy(z0, params=not_a_tensor)


def test_a_good_potential_is_evaluated_once_at_simulate_s_boundary(bp5, z0):
    """One extra evaluation per call (the check), not one per step or RK4 stage."""
    calls = []

    def quadratic(x):
        if not torch.is_grad_enabled():
            calls.append(tuple(x.shape))
        return 0.1 * (x**2).sum((-2, -1))

    params = bp5.parameters().replace(potential=quadratic)
    traj = bp5.simulate(z0, 5, params=params, threads=None)
    assert calls == [(3, 5, 2)]
    assert bp5.energy(traj, params=params).shape == (3, 6)


# ------------------------------------------------------------- small option checks
def test_project_positions_names_iterations(bp5, z0):
    with pytest.raises(ValueError, match=r"^iterations must be an integer in \[0, 100\]"):
        bp5.project_positions(z0, iterations=-1)


@pytest.mark.parametrize("bad", ["a", [0.5], True, float("nan"), 1.5])
def test_simulate_names_penetration_fraction(bp5, z0, bad):
    with pytest.raises(ValueError, match=r"penetration_fraction must be a number in \[0, 1\]"):
        bp5.simulate(z0, 5, penetration_fraction=bad)


def test_sample_initial_conditions_names_the_device(bp5, no_cuda):
    with pytest.raises(ValueError, match=r"device 'cuda' requested but CUDA is not available"):
        bp5.sample_initial_conditions(2, device="cuda")
    with pytest.raises(ValueError, match=r"device must be 'cpu' or 'cuda', got 'gpu'"):
        bp5.sample_initial_conditions(2, device="gpu")
    assert bp5.sample_initial_conditions(2, device="cpu").device.type == "cpu"


@pytest.mark.parametrize("option", ["check_overlap", "progress"])
@pytest.mark.parametrize("bad", ["no", "x", 1, None])
def test_simulate_type_checks_its_boolean_options(bp5, z0, option, bad):
    """``check_overlap="no"`` had been read as True, like any non-empty string."""
    with pytest.raises(ValueError, match=rf"^{option} must be True or False, got {bad!r}"):
        bp5.simulate(z0, 2, **{option: bad})

"""System.potential_model: an extra potential (e.g. a learned network) in the dynamics."""

import torch

import diffcontact as dc


def test_potential_model_reproduces_builtin_gravity():
    truth = dc.load_system("CP3")
    z0 = truth.sample_initial_conditions(3, seed=1)
    ref = truth.simulate(z0, steps=30)

    model = dc.load_system("CP3")
    g = model.gravity.clone()
    model.gravity = torch.tensor(0.0, dtype=torch.float64)
    masses = model.mass.clone()

    def gravity(x):  # point masses at the joints: V = g sum_i m_i y_i
        return g * (masses * x[..., 1]).sum(-1)

    model.potential_model = gravity
    out = model.simulate(z0, steps=30)
    torch.testing.assert_close(out, ref, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(model.energy(out), truth.energy(ref), rtol=1e-10, atol=1e-10)


def test_gradient_reaches_the_potential_models_parameters():
    system = dc.load_system("CP3")
    z0 = system.sample_initial_conditions(2, seed=0)
    system.gravity = torch.tensor(0.0, dtype=torch.float64)
    scale = torch.tensor(9.81, dtype=torch.float64, requires_grad=True)
    system.potential_model = lambda x: scale * (system.mass * x[..., 1]).sum(-1)
    traj = system.simulate(z0, steps=5)
    (grad,) = torch.autograd.grad(traj[:, -1, 0, :, 1].sum(), scale)
    assert torch.isfinite(grad) and grad < 0  # stronger gravity pulls the joints down

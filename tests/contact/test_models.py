"""Contact models as registered objects: protocol, registry, CM and CMr."""

from __future__ import annotations

import re

import pytest
import torch

import diffcontact as dc
from diffcontact.contact import (
    ContactModel,
    PoissonTwoPhase,
    contact_models,
    create_contact_model,
    register_contact_model,
    unregister_contact_model,
)


class Frictionless:
    """CM with friction switched off: a contact model from outside the package."""

    def __init__(self, scale: float = 0.0) -> None:
        self.inner = PoissonTwoPhase()
        self.scale = scale

    def resolve(self, J_C, Mhat_inv, v, params, active, d, **kwargs):
        params = params.replace(mu=params.mu * self.scale)
        return self.inner.resolve(J_C, Mhat_inv, v, params, active, d, **kwargs)


@pytest.fixture
def frictionless():
    register_contact_model("Frictionless", Frictionless)
    yield "Frictionless"
    unregister_contact_model("Frictionless")


def test_builtin_names_and_unknown_name():
    assert contact_models()[:4] == ["CM", "CMr", "LCP", "Coulomb"]
    with pytest.raises(
        ValueError, match=r"unknown contact model 'Stribeck'; registered .*: CM, CMr, LCP, Coulomb"
    ):
        create_contact_model("Stribeck")
    assert isinstance(create_contact_model("CM"), ContactModel)
    with pytest.raises(ValueError, match=r"has no resolve method|registered name"):
        create_contact_model(42)


def test_registered_model_runs_by_name(frictionless):
    assert frictionless in contact_models()
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(3, seed=0)
    by_name = system.simulate(z0, 40, contact_model=frictionless)
    zero_mu = system.simulate(z0, 40, params=system.parameters().replace(mu=0.0))
    assert torch.equal(by_name, zero_mu)
    assert (by_name - system.simulate(z0, 40)).abs().max() > 1e-6  # friction mattered
    # options reach the factory; an object is used as it is
    half = system.simulate(z0, 40, contact_model=create_contact_model(frictionless, scale=0.5))
    half_mu = system.simulate(z0, 40, params=system.parameters().replace(mu=system.mu * 0.5))
    assert torch.equal(half, half_mu)


def test_registry_guards(frictionless):
    with pytest.raises(ValueError, match="already registered"):
        register_contact_model(frictionless, Frictionless)
    register_contact_model(frictionless, Frictionless, overwrite=True)
    with pytest.raises(ValueError, match="built-in"):
        register_contact_model("CM", Frictionless, overwrite=True)
    with pytest.raises(ValueError, match="callable"):
        register_contact_model("Broken", 3)
    for bad in ("--out", "my model", "a/b", ".hidden"):  # --contact-model values, folder names
        with pytest.raises(ValueError, match=rf"contact model name '{re.escape(bad)}' is not al"):
            register_contact_model(bad, Frictionless)
    with pytest.raises(ValueError, match="contact model 'CM' has no option 'eps'; it takes: none"):
        create_contact_model("CM", eps=0.1)
    with pytest.raises(ValueError, match="options are for contact-model names"):
        create_contact_model(PoissonTwoPhase(), eps=0.1)


def test_cmr_eps_on_the_object_or_in_params():
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(2, seed=1)
    p = system.parameters()
    fixed = system.simulate(z0, 20, contact_model=create_contact_model("CMr", eps=0.1))
    from_params = system.simulate(z0, 20, contact_model="CMr", params=p.replace(eps=0.1))
    default = system.simulate(z0, 20, contact_model="CMr")
    assert torch.equal(fixed, from_params)
    assert (fixed - default).abs().max() > 0
    with pytest.raises(ValueError, match=r"CM .* takes none"):
        PoissonTwoPhase(regularized=False, eps=0.1)


def test_poisson_two_phase_is_the_two_phase_impulse():
    from diffcontact.contact import ContactParams, two_phase_impulse

    gen = torch.Generator().manual_seed(0)
    n, K, d, D = 4, 3, 2, 6
    J = torch.randn(n, K * d, D, generator=gen, dtype=torch.float64)
    Mh = torch.eye(D, dtype=torch.float64).expand(n, D, D)
    v = torch.randn(n, D, generator=gen, dtype=torch.float64)
    mu = torch.rand(n, K, generator=gen, dtype=torch.float64)
    cor = torch.rand(n, K, generator=gen, dtype=torch.float64)
    active = torch.ones(n, K, dtype=torch.bool)
    for model, eps in ((PoissonTwoPhase(), None), (PoissonTwoPhase(True, 0.05), 0.05)):
        res = model.resolve(J, Mh, v, ContactParams(mu, cor), active, d)
        ref = two_phase_impulse(J, Mh, v, mu, cor, active, d, eps=eps)
        assert torch.equal(res.v_plus, ref.v_plus) and torch.equal(res.f_r, ref.f_r)


def _impulse_args(**change):
    """Two states, two contacts in 2D on three coordinates (K = 2, d = 2, D = 3)."""
    f64 = torch.float64
    args = {
        "J_C": torch.randn(2, 4, 3, dtype=f64, generator=torch.Generator().manual_seed(0)),
        "Mhat_inv": torch.eye(3, dtype=f64).expand(2, 3, 3),
        "v": torch.ones(2, 3, dtype=f64),
        "mu": torch.full((2, 2), 0.3, dtype=f64),
        "cor": torch.full((2, 2), 0.5, dtype=f64),
        "active": torch.ones(2, 2, dtype=torch.bool),
        "d": 2,
    }
    args.update(change)
    return args


F64 = torch.float64
SHAPE = r"must have shape \(\.\.\., "


@pytest.mark.parametrize("name", ["two_phase_impulse", "lcp_impulse", "coulomb_two_phase_impulse"])
@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"Mhat_inv": torch.eye(4, dtype=F64)}, "Mhat_inv " + SHAPE + "3, 3"),
        ({"v": torch.ones(2, 4, dtype=F64)}, "v " + SHAPE + "3"),
        ({"cor": torch.full((2, 3), 0.5, dtype=F64)}, "cor " + SHAPE + "2"),
        ({"mu": torch.full((2, 1), 0.3, dtype=F64)}, "mu " + SHAPE + "2"),
        ({"v_C_star": torch.zeros(2, 2, dtype=F64)}, "v_C_star " + SHAPE + "4"),
        ({"active": torch.ones(2, 3, dtype=torch.bool)}, "active " + SHAPE + "2"),
        ({"Mhat_inv": torch.eye(3).expand(2, 3, 3)}, "Mhat_inv has dtype torch.float32, J_C"),
        ({"J_C": torch.ones(2, 5, 3, dtype=F64)}, "J_C must be a floating tensor of shape"),
        ({"mu": torch.full((2, 2), -0.1, dtype=F64)}, "mu must be >= 0"),
        ({"v": torch.ones(2, 3, dtype=torch.int64)}, "v must be a floating-point .*torch.int64"),
        ({"J_C": torch.ones(2, 4, 3, dtype=F64).to_sparse()}, "J_C must be a dense tensor"),
        ({"Mhat_inv": torch.eye(3, dtype=F64).expand(2, 3, 3).to("meta")}, "Mhat_inv is on the"),
    ],
)
def test_impulse_functions_name_bad_inputs(name, change, message):
    import diffcontact.contact as contact

    with pytest.raises(ValueError, match=f"{name}: {message}"):
        getattr(contact, name)(**_impulse_args(**change))


def test_two_phase_impulse_refuses_a_negative_eps():
    # its QPs' matrix checks are off (A is semi-definite by construction): A + eps I with
    # eps < 0 is not, and must be named here
    from diffcontact.contact import two_phase_impulse

    with pytest.raises(ValueError, match=r"eps \(CMr's regulariser\) must be >= 0"):
        two_phase_impulse(**_impulse_args(), eps=-0.5)

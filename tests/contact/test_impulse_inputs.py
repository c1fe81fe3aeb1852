"""Bad inputs to ``penetration_target`` and ``two_phase_impulse``: one-line ``ValueError``s
naming the argument, not torch's errors from inside (or silent inf/NaN targets)."""

import pytest
import torch

import diffcontact as dc
from diffcontact.contact import DenseContact, penetration_target, two_phase_impulse

F64 = torch.float64


def _target_problem(n=2, K=2, d=2, D=6, seed=0):
    gen = torch.Generator().manual_seed(seed)
    J = torch.randn(n, K * d, D, generator=gen, dtype=F64)
    depth = torch.rand(n, K, generator=gen, dtype=F64)
    active = torch.ones(n, K, dtype=torch.bool)
    return J, depth, active


@pytest.mark.parametrize(
    ("change", "pattern"),
    [
        ({"dt": 0.0}, r"penetration_target: dt must be a finite number > 0"),
        ({"dt": -0.1}, r"penetration_target: dt must be a finite number > 0"),
        ({"dt": float("inf")}, r"penetration_target: dt must be"),
        ({"dt": "0.01"}, r"penetration_target: dt must be"),
        ({"fraction": 1.5}, r"penetration_target: fraction must be a number in \[0, 1\]"),
        ({"fraction": -0.1}, r"penetration_target: fraction must be a number in \[0, 1\]"),
        ({"fraction": float("nan")}, r"penetration_target: fraction must be"),
        ({"fraction": True}, r"penetration_target: fraction must be"),
        ({"depth": "nan"}, r"penetration_target: depth contains NaN or infinite values"),
        ({"depth": "K+1"}, r"penetration_target: J_C must .* K = 3 contacts"),
        ({"depth": "float32"}, r"penetration_target: depth has dtype torch.float32"),
        ({"depth": [0.1, 0.2]}, r"penetration_target: depth must be a torch.Tensor, got list"),
        ({"active": "float"}, r"penetration_target: active must be a bool tensor"),
        ({"active": "K+1"}, r"penetration_target: active must be a bool tensor of shape"),
        ({"J_C": "long"}, r"penetration_target: J_C must be a floating tensor"),
        ({"J_C": [[1.0]]}, r"penetration_target: J_C must be a torch.Tensor .* got list"),
        ({"batch": 3}, r"penetration_target: batch dimensions do not broadcast \(depth \(3,\)"),
        ({"J_E": "columns"}, r"penetration_target: J_E must be a floating tensor"),
        ({"Mhat_inv": "shape"}, r"penetration_target: Mhat_inv must be a floating tensor"),
    ],
)
def test_penetration_target_names_bad_inputs(change, pattern):
    J, depth, active = _target_problem()
    args = {"J_C": J, "depth": depth, "active": active, "dt": 0.01, "d": 2, "fraction": 0.125}
    value = next(iter(change.values()))
    key = next(iter(change))
    if key == "depth" and value == "nan":
        args["depth"] = depth.clone().fill_(float("nan"))
    elif key == "depth" and value == "K+1":
        args["depth"] = torch.rand(2, 3, dtype=F64)
        args["active"] = torch.ones(2, 3, dtype=torch.bool)
    elif key == "depth" and value == "float32":
        args["depth"] = depth.float()
    elif key == "active" and value == "float":
        args["active"] = active.double()
    elif key == "active" and value == "K+1":
        args["active"] = torch.ones(2, 3, dtype=torch.bool)
    elif key == "J_C" and value == "long":
        args["J_C"] = J.long()
    elif key == "batch":
        args["depth"] = torch.rand(3, 2, dtype=F64)
        args["active"] = torch.ones(3, 2, dtype=torch.bool)
    elif key == "J_E":
        args["J_E"] = torch.randn(2, 1, 5, dtype=F64)  # D = 5, J_C has 6 columns
    elif key == "Mhat_inv":
        args["J_E"] = torch.randn(2, 1, 6, dtype=F64)
        args["Mhat_inv"] = torch.eye(5, dtype=F64)
    else:
        args[key] = value
    with pytest.raises(ValueError, match=pattern):
        penetration_target(**args)


def test_penetration_target_accepts_what_it_documents():
    """A NaN depth at an inactive (padded) contact is ignored, as the target ignores it;
    numbers of any real type, the operator form and a tensor ``dt`` still work."""
    J, depth, active = _target_problem()
    want = penetration_target(J, depth, active, 0.01, 2)
    masked = depth.clone()
    masked[0, 1] = float("nan")
    off = active.clone()
    off[0, 1] = False
    out = penetration_target(J, masked, off, 0.01, 2)
    assert torch.isfinite(out).all()
    assert torch.equal(penetration_target(DenseContact(J, None), depth, active, 0.01, 2), want)
    assert torch.equal(
        penetration_target(J, depth, active, torch.tensor(0.01, dtype=F64), 2, 0.125), want
    )
    assert torch.equal(penetration_target(J, depth, active, 1 / 100, 2, fraction=1 / 8), want)


def test_the_simulator_step_does_not_pay_for_the_target_checks(monkeypatch):
    """The step calls the unchecked target: the public entry's checks (a host read for the
    depth's finiteness) stay at the public boundary."""
    import diffcontact.contact.impulse as impulse

    def refuse(*args, **kwargs):
        raise AssertionError("the step ran the public penetration_target's checks")

    monkeypatch.setattr(impulse, "_check_target_inputs", refuse)
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(4, seed=0)
    traj = system.simulate(z0, 60, threads=None)  # bounces: the target is used
    assert system.penetration_fraction > 0 and torch.isfinite(traj).all()
    with pytest.raises(AssertionError, match="public penetration_target"):
        J, depth, active = _target_problem()
        penetration_target(J, depth, active, 0.01, 2)


def _impulse_problem(n=3, K=2, d=2, D=6, seed=0):
    gen = torch.Generator().manual_seed(seed)
    J = torch.randn(n, K * d, D, generator=gen, dtype=F64)
    M_inv = torch.eye(D, dtype=F64).expand(n, D, D)
    v = torch.randn(n, D, generator=gen, dtype=F64)
    mu = torch.full((n, K), 0.3, dtype=F64)
    cor = torch.full((n, K), 0.5, dtype=F64)
    active = torch.ones(n, K, dtype=torch.bool)
    return J, M_inv, v, mu, cor, active


@pytest.mark.parametrize("name", ["v", "eps", "active", "v_C_star"])
def test_two_phase_impulse_names_batch_mismatches(name):
    """A ``v`` or ``eps`` of 4 states against ``J_C``'s 3 failed in torch's broadcast
    ("size of tensor a (4) must match b (3)"); now named as ``active``'s mismatch is."""
    J, M_inv, v, mu, cor, active = _impulse_problem()
    kwargs = {}
    if name == "v":
        v = torch.randn(4, 6, dtype=F64)
    elif name == "eps":
        kwargs["eps"] = torch.full((4,), 0.01, dtype=F64)
    elif name == "active":
        active = torch.ones(4, 2, dtype=torch.bool)
    else:
        kwargs["v_C_star"] = torch.zeros(4, 4, dtype=F64)
    pattern = rf"two_phase_impulse: batch dimensions do not broadcast \(.*{name} \(4,\)"
    with pytest.raises(ValueError, match=pattern):
        two_phase_impulse(J, M_inv, v, mu, cor, active, 2, **kwargs)


def test_two_phase_impulse_still_broadcasts_shared_inputs():
    """Shared (unbatched) ``Mhat_inv``, ``mu``, ``cor`` and a per-state ``eps`` broadcast."""
    J, M_inv, v, mu, cor, active = _impulse_problem()
    full = two_phase_impulse(J, M_inv, v, mu, cor, active, 2, eps=torch.full((3,), 0.01, dtype=F64))
    shared = two_phase_impulse(J, M_inv[0], v, mu[0], cor[0], active, 2, eps=0.01)
    torch.testing.assert_close(shared.v_plus, full.v_plus, rtol=1e-10, atol=1e-12)

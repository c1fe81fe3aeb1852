"""What CM's learned e_P means: the lift-off of the maximum-dissipation cone QP in sliding
impacts (the numbers of docs/training.md, "What the learned e_P and mu mean")."""

import pytest
import torch

from diffcontact.contact import coulomb_two_phase_impulse, two_phase_impulse

F64 = torch.float64


def wall_impact(solver, v_n: float, v_t, e: float, mu: float) -> torch.Tensor:
    """Post-impact velocities ``(n, 2)`` of a unit point mass hitting a wall (J_C = I)."""
    v_t = torch.as_tensor(v_t, dtype=F64).reshape(-1)
    n = v_t.numel()
    v = torch.stack([torch.full((n,), v_n, dtype=F64), v_t], -1)
    eye = torch.eye(2, dtype=F64).expand(n, 2, 2)
    full = torch.ones(n, 1, dtype=F64)
    return solver(eye, eye, v, mu * full, e * full, torch.ones(n, 1, dtype=torch.bool), 2).v_plus


def test_cm_lifts_a_sliding_point_mass_off_the_wall():
    # the example: v_n = -1, v_t = 2, e_P = 0.745, mu = 0.2
    cm = wall_impact(two_phase_impulse, -1.0, 2.0, 0.745, 0.2)[0]
    exact = wall_impact(coulomb_two_phase_impulse, -1.0, 2.0, 0.745, 0.2)[0]
    assert float(cm[0]) == pytest.approx(1.349038, abs=1e-6)  # leaves at about +1.35
    assert float(exact[0]) == pytest.approx(0.745, abs=1e-9)  # textbook -e v_n
    assert exact.tolist() == pytest.approx([0.745, 2.0 - 0.2 * 1.745 * 1.0], abs=1e-9)
    assert float(cm[1]) == pytest.approx(1.530192, abs=1e-6)


def test_the_lift_follows_the_closed_form_while_the_mass_slides():
    """CM's excess normal velocity over Coulomb's: (1 + e) mu (|v_t| - mu |v_n|) / (1 + mu^2)."""
    e, mu, v_n = 0.745, 0.2, -1.0
    v_t = torch.tensor([0.5, 1.0, 2.0, 4.0], dtype=F64)  # all slide through both phases
    cm = wall_impact(two_phase_impulse, v_n, v_t, e, mu)
    exact = wall_impact(coulomb_two_phase_impulse, v_n, v_t, e, mu)
    lift = (1 + e) * mu * (v_t - mu * abs(v_n)) / (1 + mu * mu)
    torch.testing.assert_close(cm[:, 0] - exact[:, 0], lift, atol=1e-9, rtol=0)
    # at least mu |v_t+|: CM's post-compression velocity lies in the dual cone
    assert bool((cm[:, 0] >= mu * cm[:, 1].abs() - 1e-9).all())
    # head-on (v_t = 0) the two agree: the learned e_P is Newton's there
    head_on = wall_impact(two_phase_impulse, v_n, 0.0, e, mu)[0]
    assert head_on.tolist() == pytest.approx([e, 0.0], abs=1e-9)


def test_cm_needs_a_smaller_e_p_that_depends_on_the_slip():
    """The e_P with which CM reproduces a textbook (Coulomb, e = 0.745) impact."""
    e, mu, v_n = 0.745, 0.2, -1.0

    def equivalent(v_t: float) -> float:  # (1 + e') = (1 + e) |v_n| (1 + mu^2) / (|v_n| + mu |v_t|)
        return (1 + e) * abs(v_n) * (1 + mu * mu) / (abs(v_n) + mu * v_t) - 1

    assert equivalent(2.0) == pytest.approx(0.2962857, abs=1e-7)
    for v_t in (0.5, 2.0, 4.0):
        cm = wall_impact(two_phase_impulse, v_n, v_t, equivalent(v_t), mu)[0]
        exact = wall_impact(coulomb_two_phase_impulse, v_n, v_t, e, mu)[0]
        torch.testing.assert_close(cm, exact, atol=1e-9, rtol=0)  # normal and tangential
    assert equivalent(0.5) == pytest.approx(0.6498, abs=1e-4)
    assert equivalent(4.0) == pytest.approx(0.0082, abs=1e-4)

"""The exact event-driven point-mass simulator, and the Coulomb learning demonstration."""

import importlib.util
from pathlib import Path

import pytest
import torch

import diffcontact as dc
from diffcontact.systems.event_driven import simulate_event_driven

F64 = torch.float64
BOX = {
    "type": "bouncing_masses", "masses": [0.3], "radii": [0.1],
    "walls": [[1, 0, 0], [0, 1, 0], [-1, 0, 1], [0, -1, 1]], "gravity": 0.0, "mu": 0.3,
    "cor": 0.7, "dt": 0.01, "horizon": 1.0, "penetration_fraction": 0.0,
}  # fmt: skip


def test_one_impact_exactly():
    system = dc.load_system(BOX)
    # 0.05 from the floor at speed (2, -1): impact after 0.05 s, sliding (2 > 0.3 * 1.7)
    z0 = torch.tensor([[[[0.3, 0.15]], [[2.0, -1.0]]]], dtype=F64)
    traj = simulate_event_driven(system, z0, 10)
    v_after = [2.0 - 0.3 * 1.7, 0.7]
    assert traj[0, 4, 1, 0].tolist() == [2.0, -1.0]
    assert traj[0, 5, 1, 0].tolist() == pytest.approx(v_after, abs=1e-12)
    # position at t = 0.1: 0.05 s to the floor, then 0.05 s with the new velocity
    x = [0.3 + 2.0 * 0.05 + v_after[0] * 0.05, 0.1 + 0.7 * 0.05]
    assert traj[0, 10, 0, 0].tolist() == pytest.approx(x, abs=1e-12)


def test_energy_and_box_with_elastic_frictionless_walls_and_gravity():
    system = dc.load_system({**BOX, "cor": 1.0, "mu": 0.0, "gravity": 9.8})
    z0 = system.sample_initial_conditions(16, seed=0)
    traj = simulate_event_driven(system, z0)
    x, v = traj[:, :, 0, 0], traj[:, :, 1, 0]
    energy = 0.5 * (v * v).sum(-1) + 9.8 * x[..., 1]
    assert float((energy - energy[:, :1]).abs().max()) < 1e-9
    assert bool((x > 0.1 - 1e-12).all() and (x < 0.9 + 1e-12).all())


def test_scaled_walls_are_the_same_walls():
    """Walls are normalised on load (docs/config.md): a wall's line scaled by any positive
    factor is the same wall. The event-driven simulator read them unnormalised, and a
    ball under gravity over ``[0, 2, 0]`` gained 447 J and ended inside the ground."""
    scaled = [[3, 0, 0], [0, 2, 0], [-0.5, 0, 0.5], [0, -4, 4]]
    for settings in ({"cor": 1.0, "mu": 0.0, "gravity": 9.8}, {}):  # BOX: mu 0.3, e 0.7
        unit = dc.load_system({**BOX, **settings})
        other = dc.load_system({**BOX, **settings, "walls": scaled})
        z0 = unit.sample_initial_conditions(8, seed=0)
        a, b = simulate_event_driven(unit, z0), simulate_event_driven(other, z0)
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


def test_velocities_match_coulomb_time_stepping_and_not_cm():
    """Between impacts the velocities are constant; after each impact the time-stepping
    Coulomb model gives the exact post-impact velocity (states that differ: impacts
    that the time-stepping positions, lagging by the penetration, meet one step
    later or earlier); CM's lift-off changes them at many states."""
    system = dc.load_system(BOX)
    z0 = system.sample_initial_conditions(16, seed=0)
    exact = simulate_event_driven(system, z0)
    ours = system.simulate(z0, contact_model="Coulomb")
    cm = system.simulate(z0)

    def differ(traj):
        return float(
            ((traj[:, :, 1] - exact[:, :, 1]).abs().flatten(2).amax(-1) > 1e-9).double().mean()
        )

    assert differ(ours) < 0.02
    assert differ(cm) > 0.2


def test_bad_input():
    with pytest.raises(ValueError, match="one body"):
        simulate_event_driven(dc.load_system("BP5"), torch.zeros(1, 2, 5, 2, dtype=F64))
    with pytest.raises(ValueError, match="z0 must have shape"):
        simulate_event_driven(dc.load_system(BOX), torch.zeros(1, 2, 2, dtype=F64))
    # a ball coming to rest on the floor under gravity: not modelled, reported
    system = dc.load_system({**BOX, "gravity": 9.8, "cor": 0.5})
    z0 = torch.tensor([[[[0.5, 0.3]], [[0.0, 0.0]]]], dtype=F64)
    with pytest.raises(ValueError, match="resting contact"):
        simulate_event_driven(system, z0, 200)


@pytest.mark.slow
def test_coulomb_learns_e_and_mu_where_cm_does_not(tmp_path):
    """experiments/coulomb.py at its defaults (about a minute on two cores)."""
    path = Path(__file__).resolve().parents[2] / "experiments" / "coulomb.py"
    spec = importlib.util.spec_from_file_location("coulomb_experiment", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    res = module.run(tmp_path)
    ours, cm = res["Coulomb-CD-CLNN"], res["CM-CD-CLNN"]
    assert abs(ours["cor"] - 0.7) <= 0.02 and abs(ours["mu"] - 0.3) <= 0.02
    assert abs(cm["cor"] - 0.7) > 0.02 or abs(cm["mu"] - 0.3) > 0.02

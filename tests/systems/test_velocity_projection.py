"""The velocities' projection after the positions' (``velocity_projection``, on by default).

The position projection closes limits that the step's impulse did not treat (those
violated only at the projected positions) and, alone, left the velocities pointing into
them: the next step turned potential energy into that speed, and the projection put the
potential energy back, so an inelastic rope gained energy (docs/config.md, ``rope``).
``projection.project_state`` also projects the velocities, inelastically in the mass
metric, onto the limits closed at the projected positions, and a step's impulse treats
closed limits as active (``System._contact_margin``).
"""

import pytest
import torch

import diffcontact as dc
from diffcontact.systems.projection import CLOSED, ReadFree, project_positions, project_state
from diffcontact.testing import assert_gradients_close


def _energy_rise(system, n: int = 4) -> tuple[float, float]:
    """The largest ``E(t) - E(0)`` of ``n`` rollouts over the system's horizon, and ``E(0)``'s
    mean."""
    traj = system.simulate(system.sample_initial_conditions(n, seed=0))
    energy = system.energy(traj)
    return float((energy - energy[:, :1]).max()), float(energy[:, 0].mean())


@pytest.mark.parametrize("mass", [None, [0.1] * 9 + [1.0]], ids=["uniform", "heavy tip"])
def test_the_inelastic_rope_gains_no_energy(mass):
    """The limits are inelastic and there is no other source: the energy must not rise.
    With the positions' projection alone it rose by 1.17 J over 1.64 J (uniform) and by
    10.4 J over 4.4 J (a heavy tip) within 0.5 s."""
    kwargs = {"horizon": 0.5} | ({} if mass is None else {"mass": mass})
    rise, e0 = _energy_rise(dc.load_system("Rope", **kwargs))
    assert rise < 1e-6 * e0
    before, _ = _energy_rise(dc.load_system("Rope", velocity_projection=False, **kwargs))
    assert before > 0.1 * e0  # the defect this key removes (kept reachable by the key)


def _pre_projection_states(task: str = "Rope", n: int = 8, steps: int = 30):
    """States as a step hands them to the projection (after the impulse), many past a
    limit: ``(system, z)``."""
    system = dc.load_system(task)
    traj = system.simulate(system.sample_initial_conditions(n, seed=2), steps)
    z = traj[:, 5:].flatten(0, 1)
    res = system.resolve_contacts(system.integrate(z), penetration_fraction=0.0)
    keep = (system.gaps(res.z[:, 0]) < 0).any(-1)
    return system, res.z[keep]


def test_no_velocity_points_into_a_limit_closed_by_the_projection():
    system, z = _pre_projection_states()
    for velocities, approaching in ((False, True), (True, False)):
        out = system.project_positions(z, velocities=velocities)
        closed = system.gaps(out[:, 0]) < CLOSED
        assert bool(closed.any())
        rate = system.contact_velocities(out)[..., 0]  # (N, K) the gaps' rates
        worst = float(rate[closed].min())
        # without the velocities' projection they approach at up to tens of rad/s
        assert (worst < -1.0) if approaching else (worst > -1e-9), (velocities, worst)
    # inelastic in the mass metric: no state's kinetic energy rises
    kinetic = system.kinetic_energy(out)
    assert bool((kinetic <= system.kinetic_energy(z) + 1e-12).all())
    # positions: those of the positions' projection alone
    torch.testing.assert_close(out[:, 0], system.project_positions(z, velocities=False)[:, 0])


def test_no_open_limit_is_crossed_within_the_next_step():
    """A limit that the projection released (a neighbour's correction moved it to a small
    positive gap) was left approaching: the next step crossed it, at up to 33 rad/s. The
    velocities now close such a limit within ``dt`` at most: ``gap + dt J v >= 0``."""
    system, z = _pre_projection_states()
    closed_only = dc.load_system("Rope", foresee_crossings=False)

    def worst_crossing(system) -> float:
        out = system.project_positions(z)
        gaps = system.gaps(out[:, 0])
        rate = system.contact_velocities(out)[..., 0]
        open_ = gaps >= CLOSED
        assert bool(open_.any())
        return float((gaps + system.dt * rate)[open_].min())

    assert worst_crossing(system) > -1e-9
    assert worst_crossing(closed_only) < -1e-3  # the defect, with the closed limits alone


@pytest.mark.filterwarnings("ignore:rope limits with cor > 0")  # on purpose
def test_only_the_inelastic_limits_are_foreseen():
    """A limit with restitution keeps its approach: closing it within ``dt`` would take
    the speed its bounce needs. ``foresee`` all false is the closed limits alone."""
    system, z = _pre_projection_states(n=4)
    x, v = z[:, 0], z[:, 1]
    geometry, M_inv, K = system.geometry, system.inverse_mass_matrix(), system.n_contacts
    closed_only = project_state(x, v, geometry, M_inv, 10)
    none = torch.zeros(K, dtype=torch.bool)
    got = project_state(x, v, geometry, M_inv, 10, dt=system.dt, foresee=none)
    for a, b in zip(got, closed_only, strict=True):
        assert torch.equal(a, b)
    every = project_state(x, v, geometry, M_inv, 10, dt=system.dt)
    assert not torch.equal(every[1], closed_only[1])
    # per state: the first two states foresee, the others do not
    rows = torch.zeros(z.shape[0], K, dtype=torch.bool)
    rows[:2] = True
    mixed = project_state(x, v, geometry, M_inv, 10, dt=system.dt, foresee=rows)
    torch.testing.assert_close(mixed[1][:2], every[1][:2], rtol=0, atol=1e-12)
    torch.testing.assert_close(mixed[1][2:], closed_only[1][2:], rtol=0, atol=1e-12)
    # a system foresees its inelastic limits only (and gives the others' restitution)
    bouncing = dc.load_system("Rope", cor=0.5)
    iterations = bouncing.position_projection
    cor = torch.full((K,), 0.5, dtype=z.dtype)
    M_inv = bouncing.inverse_mass_matrix()
    want = project_state(x, v, bouncing.geometry, M_inv, iterations, restitution=cor)
    # (with restitution, System's motion along a lift pays for it: _lift_within_energy)
    from diffcontact.systems.system import _lift_within_energy

    ctx = bouncing._context(z, None, bouncing._batch(z, None, 3))
    paid = _lift_within_energy(bouncing, ctx, x, want[0], want[1])
    assert torch.equal(bouncing.project_positions(z)[:, 1], paid)
    assert torch.equal(system.project_positions(z)[:, 1], every[1])
    for bad in (0.0, -0.01, float("nan")):
        with pytest.raises(ValueError, match="dt must be"):
            project_state(x, v, geometry, M_inv, 10, dt=bad)


def test_the_rope_gains_no_energy_at_a_coarse_step():
    """Rope at dt = 0.02 (four times its config's): with the closed limits alone, 7 of 64
    trajectories gained energy, one 0.887 J within 1 s."""
    system = dc.load_system("Rope", horizon=1.0, dt=0.02)
    z0 = system.sample_initial_conditions(64, seed=0)

    def rise(system) -> tuple[float, float]:
        """The largest rise of ``E(t)`` over ``E(0)``, and the mean loss over 1 s."""
        energy = system.energy(system.simulate(z0))
        change = energy - energy[:, :1]
        return float(change.max()), -float(change[:, -1].mean())

    rise_now, loss = rise(system)
    assert loss > 1.0  # the limits dissipate (about 1.7 J); the integrator's error is 2e-7 J
    assert rise_now < 1e-5 * loss
    closed_only = dc.load_system("Rope", horizon=1.0, dt=0.02, foresee_crossings=False)
    assert rise(closed_only)[0] > 0.1


def test_a_state_without_a_violated_limit_is_untouched():
    system, z = _pre_projection_states(n=4)
    traj = system.simulate(system.sample_initial_conditions(4, seed=5), 3)
    free = traj[:, 0][(system.gaps(traj[:, 0, 0]) > 0).all(-1)]
    assert free.shape[0] > 0
    both = torch.cat([free, z[:3]])
    out = system.project_positions(both)
    assert torch.equal(out[: free.shape[0]], free)


def test_gradients_of_the_velocity_projection():
    """Masses and the state, through the positions' and the velocities' projection, against
    finite differences (states whose closed limits are not at a kink: every closed limit
    either clearly pushed or clearly released)."""
    system, z = _pre_projection_states(n=6)
    out = system.project_positions(z)
    moved = (out[:, 1] - z[:, 1]).flatten(1).norm(dim=-1) > 1e-2
    gaps = system.gaps(out[:, 0])
    near = (gaps.abs() < 1e-3) & (gaps.abs() > CLOSED)  # limits near the closed threshold
    pick = z[moved & ~near.any(-1)][:2]
    assert pick.shape[0] == 2
    base = system.parameters()

    def project(mass, z):
        return system.project_positions(z, params=base.replace(mass=mass))

    assert_gradients_close(project, [base.mass.clone(), pick], n_directions=2, rtol=1e-4)


@pytest.mark.parametrize("dt", [None, 0.02])
@pytest.mark.parametrize("task", ["Rope", "Rope-D100"])
def test_read_free_gives_the_reading_velocities(task, dt):
    pytest.importorskip("warp")
    system, z = _pre_projection_states(task, n=6, steps=12)
    z = torch.cat([z, system.sample_initial_conditions(2, seed=9)])  # and states at rest
    geometry, M_inv = system.geometry, system.inverse_mass_matrix()
    x, v = z[:, 0], z[:, 1]
    want = project_state(x, v, geometry, M_inv, 10, dt=dt)

    def read_free(rows: int) -> ReadFree:
        needed = torch.zeros((), dtype=torch.long)
        return ReadFree(rows, needed, system._point_masses, system._two_sided)

    wide = read_free(system._projection_rows_all())
    got = project_state(x, v, geometry, M_inv, 10, read_free=wide, dt=dt)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    assert not bool(wide.overflowed)
    few = read_free(1)
    project_state(x, v, geometry, M_inv, 10, read_free=few, dt=dt)
    assert bool(few.overflowed)


def test_the_step_treats_closed_limits_as_active():
    """A limit resting at gap 0 (a rope locked at a bending limit) entered a step's impulse
    or not by rounding; with the velocity projection, closed limits are active (the
    batch-invariance test of the rope failed at step 40 without this)."""
    rope = dc.load_system("Rope")
    assert rope._contact_margin(10, torch.float64) == CLOSED
    assert rope._contact_margin(10, torch.float32) == CLOSED
    assert rope._contact_margin(0, torch.float64) == 0.0
    assert dc.load_system("Rope", velocity_projection=False)._contact_margin(10, torch.float64) == 0
    # a state with a limit just short of closing: its approach is stopped this step
    system, z = _pre_projection_states(n=4)
    out = system.step(z)
    gaps = system.gaps(out[:, 0])
    rate = system.contact_velocities(out)[..., 0]
    assert float(rate[gaps < CLOSED].min()) > -1e-9


@pytest.mark.parametrize(
    ("changes", "named"),
    [({"rest_length": 1e-6}, "stretch band"), ({"max_angle": 1e-5}, "bending band")],
)
def test_a_rope_whose_bands_the_closed_gap_would_fill_is_refused(changes, named):
    """ "Closed" is an absolute gap (CLOSED): a rope of rest length 1e-6 had every stretch
    limit closed on both sides and froze its segments. Such a rope is refused, naming the
    band and the remedy; without the velocities' projection it loads."""
    with pytest.raises(ValueError, match=named) as info:
        dc.load_system("Rope", **changes)
    assert "velocity_projection: false" in str(info.value)
    dc.load_system("Rope", velocity_projection=False, **changes)
    dc.load_system("Rope", position_projection=0, **changes)
    dc.load_system("Rope", rest_length=1e-3)  # millimetre segments in metres: fine


def test_the_key_and_files_of_earlier_versions():
    from diffcontact.learning.data.write import _differences
    from diffcontact.systems.config import stored_config

    assert dc.load_system("Rope").velocity_projection is True
    assert dc.load_system("BP5").velocity_projection is True  # (no effect without projection)
    for bad in (1, "yes", None):
        with pytest.raises(ValueError, match="velocity_projection"):
            dc.load_system("Rope", velocity_projection=bad)
    with pytest.raises(ValueError, match="velocities must be True, False or None"):
        dc.load_system("Rope").project_positions(torch.zeros(1, 2, 10, 2), velocities=1)
    # a stored config without the key was written before it: the velocities were not projected
    dump = dc.load_system("Rope").config.model_dump(mode="json")
    old = {k: v for k, v in dump.items() if k != "velocity_projection"}
    assert stored_config(old)["velocity_projection"] is False
    assert stored_config(dump) == dump
    # one written before position_projection existed: no projection then (it loaded as the
    # rope's 10 with the velocities' off, the energy-gaining combination)
    older = {k: v for k, v in old.items() if k != "position_projection"}
    rope = dc.load_system(stored_config(older))
    assert (rope.position_projection, rope.velocity_projection) == (0, False)
    # an earlier dataset: reused where the key cannot matter (no position projection) only
    bp5 = dc.load_system("BP5").config.model_dump(mode="json")
    before = {k: v for k, v in bp5.items() if k != "velocity_projection"}
    assert _differences({"config": before}, {"config": bp5}) == []
    assert _differences({"config": old}, {"config": dump}) == [
        "config.velocity_projection (not recorded there, requested true)"
    ]
    positions_only = dump | {"velocity_projection": False}
    assert _differences({"config": old}, {"config": positions_only}) == []
    # foresee_crossings: stored before it, off; an earlier dataset is reused only where it
    # cannot matter (the velocities not projected)
    assert dc.load_system("Rope").foresee_crossings is True
    with pytest.raises(ValueError, match="foresee_crossings"):
        dc.load_system("Rope", foresee_crossings=1)
    unforeseen = {k: v for k, v in dump.items() if k != "foresee_crossings"}
    assert stored_config(unforeseen)["foresee_crossings"] is False
    assert dc.load_system(stored_config(unforeseen)).foresee_crossings is False
    assert _differences({"config": unforeseen}, {"config": dump}) == [
        "config.foresee_crossings (not recorded there, requested true)"
    ]
    positions_before = {k: v for k, v in positions_only.items() if k != "foresee_crossings"}
    assert _differences({"config": positions_before}, {"config": positions_only}) == []
    closed_only = dump | {"foresee_crossings": False}
    assert _differences({"config": unforeseen}, {"config": closed_only}) == []


def _experiment(name: str):
    """``experiments/NAME.py`` as a module."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "experiments" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _rope_limits_script():
    return _experiment("rope_limits")


def test_rope_limits_script_compares_with_the_positions_only(capsys):
    """experiments/rope_limits.py --positions-only: the row without the velocities'
    projection gains energy, the default's does not (docs/config.md's rope tables)."""
    script = _rope_limits_script()
    argv = ["--task", "Rope", "--horizon", "0.5", "--dt", "0.01", "--n", "4", "--positions-only"]
    assert script.main(argv) == 0
    lines = capsys.readouterr().out.splitlines()
    columns = ["steps", "max ratio", "min ratio", "max bend-lim", "min gap", "mean dE"]
    assert all(c in lines[1] for c in columns)
    rows = {}
    for line in lines[2:]:
        label = " ".join(line.split()[1:-8])
        rows[label] = [float(v) for v in line.split()[-8:]]
    assert set(rows) == {"projection 10", "positions only 10", "fraction 0.125"}
    rise = {label: values[-2] for label, values in rows.items()}
    assert rise["projection 10"] < 1e-6 < 0.1 < rise["positions only 10"]
    # limits: ratio within [0.8, 1.2], no bend past the limit and no gap below the
    # projection's tolerance with the projection; without it, violated
    steps, max_ratio, min_ratio, bend, gap = rows["projection 10"][:5]
    assert steps == 50 and max_ratio < 1.2 + 1e-8 and min_ratio > 0.8 - 1e-8 and bend < 1e-8
    assert gap > -1e-9 and rows["fraction 0.125"][4] < -1e-3
    for bad in (["--dt", "0"], ["--n", "0"], ["--fraction", "2"], ["--projection", "0"]):
        with pytest.raises(SystemExit) as exit_info:
            script.main(["--task", "Rope", *bad])
        assert exit_info.value.code == 2


def test_rope_limits_script_compares_a_heavy_tip_with_the_undamped_projection(capsys):
    """experiments/rope_limits.py --tip-mass 100 --undamped (docs/config.md, "Heavy tips"):
    the damped projection keeps the limits, the undamped one lets the rope stretch."""
    from diffcontact.systems import projection

    script = _rope_limits_script()
    argv = ["--task", "Rope", "--horizon", "0.5", "--dt", "0.01", "--n", "2"]
    assert script.main([*argv, "--tip-mass", "100", "--undamped"]) == 0
    out = capsys.readouterr().out
    assert "tip mass 100 (the others' 0.1)" in out.splitlines()[0]
    rows = {" ".join(line.split()[1:-8]): line.split()[-7] for line in out.splitlines()[2:]}
    assert set(rows) == {"projection 10", "undamped 10", "fraction 0.125"}
    assert float(rows["projection 10"]) < 1.2 + 1e-8 < 1.5 < float(rows["undamped 10"])
    assert projection.DAMPING == 1.0  # put back after the undamped rows


def test_long_ropes_keep_their_limits_at_a_coarse_step():
    """Rope-D200 (100 points) at dt = 0.01 for 1 s: with the positions' projection alone
    the whipping rope's violations outgrew the iterations (stretch ratios up to 2.8 within
    1 s, docs/config.md); the velocities' projection stops the energy that drove them."""
    system = dc.load_system("Rope-D200", dt=0.01, horizon=1.0)
    cfg = system.config
    z0 = system.sample_initial_conditions(2, seed=0)
    script = _rope_limits_script()
    traj = system.simulate(z0, 100, on_tunnelling="ignore")
    ratios = script.segment_ratios(system, traj)
    assert cfg.min_ratio - 1e-8 < float(ratios.min()) and float(ratios.max()) < cfg.max_ratio + 1e-8
    assert float(script.bending_excess(system, traj).max()) < 1e-8
    before = dc.load_system("Rope-D200", dt=0.01, horizon=1.0, velocity_projection=False)
    loose = before.simulate(z0, 50, on_tunnelling="ignore")
    assert float(script.segment_ratios(before, loose).max()) > cfg.max_ratio + 0.01


def test_elastic_billiards_keep_their_energy_with_the_projection():
    """BP5 with cor 1 and the projection on: a contact that only the position projection
    closed bounces (Poisson's restitution in the velocities' projection). Inelastic, it
    lost up to 68 % of a trajectory's energy in one event."""
    system = dc.load_system("BP5", cor=1.0, mu=0.0, position_projection=10)
    z0 = system.sample_initial_conditions(16, seed=0)
    traj = system.simulate(z0, on_tunnelling="ignore")
    assert float(system.gaps(traj[:, :, 0]).min()) > -1e-12  # the projection took part
    energy = system.energy(traj)
    change = (energy - energy[:, :1]) / energy[:, :1]
    assert float(change.abs().max()) < 1e-9, float(change.min())


@pytest.mark.filterwarnings("ignore:rope limits with cor > 0")  # on purpose
@pytest.mark.parametrize("cor", [0.0, 0.5, 1.0])
def test_a_limit_closed_by_the_projection_bounces_with_its_restitution(cor):
    """A 2-point rope whose first segment is stretched past its limit and still
    stretching: the projection puts it on the limit, and its velocity becomes ``-cor``
    times the approach (Newton's and Poisson's restitution agree on one contact)."""
    system = dc.load_system("Rope", n_points=2, cor=cor)
    l0 = float(system.config.rest_length)
    x = torch.tensor([[[0.0, -1.25 * l0], [0.0, -2.2 * l0]]], dtype=torch.float64)
    v = torch.tensor([[[0.0, -1.0], [0.0, -1.0]]], dtype=torch.float64)
    z = torch.stack([x, v], dim=1)
    out = system.project_positions(z)
    assert float(out[0, 0, 0, 1]) == pytest.approx(-1.2 * l0, abs=1e-9)
    assert float(out[0, 1, 0, 1]) == pytest.approx(cor * 1.0, abs=1e-9)
    torch.testing.assert_close(out[0, 1, 1], v[0, 1])  # the other point keeps its velocity
    if cor:  # the restitution phase; without it, the inelastic correction
        M_inv = system.inverse_mass_matrix()
        plain = project_state(x, v, system.geometry, M_inv, 10)[1]
        assert float(plain[0, 0, 1]) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("task", ["BP5", "BD5"])
def test_read_free_gives_the_reading_restitution(task):
    pytest.importorskip("warp")
    system, z = _pre_projection_states(task, n=8, steps=40)
    geometry, M_inv = system.geometry, system.inverse_mass_matrix()
    x, v = z[:, 0], z[:, 1]
    cor = torch.linspace(0.2, 1.0, system.n_contacts, dtype=z.dtype)
    want = project_state(x, v, geometry, M_inv, 10, restitution=cor)
    inelastic = project_state(x, v, geometry, M_inv, 10)
    assert float((want[1] - inelastic[1]).abs().max()) > 1e-3  # the restitution took part
    needed = torch.zeros((), dtype=torch.long)
    wide = ReadFree(system._projection_rows_all(), needed, system._point_masses, system._two_sided)
    got = project_state(x, v, geometry, M_inv, 10, read_free=wide, restitution=cor)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


def test_bad_restitution_and_foresee_are_clear_errors():
    system = dc.load_system("Rope", n_points=2)
    l0 = float(system.config.rest_length)
    x = torch.tensor([[[0.0, -1.25 * l0], [0.0, -2.2 * l0]]], dtype=torch.float64)
    v = torch.zeros_like(x)
    args = (x, v, system.geometry, system.inverse_mass_matrix(), 10)
    K = system.n_contacts
    for bad in (torch.ones(K + 2), torch.ones(2, K)):
        with pytest.raises(ValueError, match=rf"restitution must have shape \({K},\)"):
            project_state(*args, restitution=bad)
        with pytest.raises(ValueError, match=rf"foresee must have shape \({K},\)"):
            project_state(*args, dt=0.01, foresee=bad.bool())
    for bad in (1.5, -0.1, float("nan")):
        with pytest.raises(ValueError, match=r"restitution must lie in \[0, 1\]"):
            project_state(*args, restitution=torch.full((K,), bad, dtype=torch.float64))


@pytest.mark.filterwarnings("ignore:rope limits with cor > 0")  # on purpose
def test_gradient_through_the_restitution():
    """The bounce of a limit closed by the projection, against finite differences in its
    ``cor`` and the state."""
    system = dc.load_system("Rope", n_points=2, cor=0.5)
    l0 = float(system.config.rest_length)
    x = torch.tensor([[[0.1 * l0, -1.25 * l0], [0.3 * l0, -2.2 * l0]]], dtype=torch.float64)
    v = torch.tensor([[[0.2, -1.0], [0.1, -0.7]]], dtype=torch.float64)
    z = torch.stack([x, v], dim=1)
    base = system.parameters()

    def project(cor, z):
        return system.project_positions(z, params=base.replace(cor=cor))

    cor = base.cor.detach().clone()
    results = assert_gradients_close(project, [cor, z], n_directions=2, rtol=1e-5)
    assert all(float(r.finite_difference.abs().max()) > 0 for r in results)


def test_projection_energy_script_compares_the_settings(capsys):
    """experiments/projection_energy.py (docs/config.md, ``velocity_projection`` and
    ``position_projection``): elastic billiards keep their energy with and without the
    projection, and the projection removes the penetration; a gyroscope's constraints
    drift no more with the projection than without."""
    script = _experiment("projection_energy")
    assert script.main(["--tasks", "BP5", "Gyro", "--n", "4"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "cor 1, mu 0; 4 trajectories per task"
    assert lines[1].split()[-2:] == ["deepest", "drift"]
    rows = {}
    for line in lines[2:]:
        words = line.split()
        rows[(words[0], " ".join(words[1:-5]))] = words[-5:]
    settings = {"no projection", "projection 10", "positions only 10"}
    assert set(rows) == {(task, s) for task in ("BP5", "Gyro") for s in settings}
    for setting in settings:
        low, high, _, _ = (float(v) for v in rows["BP5", setting][:4])
        assert -1e-9 < low <= high < 1e-9
        assert rows["BP5", setting][-1] == "-"  # no equality constraints
    deepest = {s: float(rows["BP5", s][3]) for s in settings}
    assert deepest["no projection"] < -1e-3 < -1e-9 < deepest["projection 10"]
    free = float(rows["Gyro", "no projection"][-1])
    assert 0 < free < 0.01
    for setting in ("projection 10", "positions only 10"):
        assert float(rows["Gyro", setting][-1]) < 1.5 * free


def test_bad_arguments_of_the_public_projections_are_clear_errors():
    """``project_state`` and ``project_positions`` called directly (a stress test found
    IndexErrors from deep inside, a misleading solver error for a negative ``M_inv``, NaN
    returned for NaN input, and a ``gaps`` of too few states leaving a state unprojected)."""
    system, z = _pre_projection_states(n=3)
    x, v = z[:3, 0], z[:3, 1]
    M_inv = system.inverse_mass_matrix()
    geometry = system.geometry
    N, P = x.shape[:2]
    K = system.n_contacts
    nan = x.clone()
    nan[0, 0, 0] = float("nan")
    good = (x, v, geometry, M_inv, 10)
    cases = [
        ((x, v[:, :5], geometry, M_inv, 10), {}, r"v must have the shape of x"),
        ((x, v[:2], geometry, M_inv, 10), {}, r"v must have the shape of x"),
        ((x, v, geometry, M_inv[:5, :5], 10), {}, rf"M_inv must have shape \({P}, {P}\)"),
        ((x, v, geometry, -M_inv, 10), {}, r"diagonal must be positive"),
        ((x.float(), v.float(), geometry, M_inv, 10), {}, r"M_inv has dtype torch.float64"),
        ((x, v.float(), geometry, M_inv, 10), {}, r"v has dtype torch.float32"),
        ((nan, v, geometry, M_inv, 10), {}, r"x contains NaN"),
        ((x, nan, geometry, M_inv, 10), {}, r"v contains NaN"),
        ((x, v, geometry, M_inv, -1), {}, r"iterations must be an integer >= 0"),
        (good, {"tol": float("nan")}, r"tol must be a number >= 0"),
        (good, {"tol": -1.0}, r"tol must be a number >= 0"),
        (good, {"gaps": system.gaps(x)[:2]}, rf"gaps must have shape \({N}, {K}\)"),
        (good, {"restitution": "0.5"}, r"restitution must be a number or a tensor"),
        (good, {"dt": 0.01, "foresee": torch.ones(K)}, r"foresee must be a bool tensor"),
        ((x[0], v[0], geometry, M_inv, 10), {}, r"x must be a floating-point tensor of shape"),
    ]
    for args, kwargs, message in cases:
        with pytest.raises(ValueError, match=message):
            project_state(*args, **kwargs)
        if "dt" not in kwargs and "restitution" not in kwargs and args[1] is v:
            with pytest.raises(ValueError, match=message):
                project_positions(args[0], *args[2:], **kwargs)
    # a number for restitution is every candidate's
    number = project_state(x, v, geometry, M_inv, 10, restitution=0.5)
    tensor = project_state(x, v, geometry, M_inv, 10, restitution=torch.full((K,), 0.5))
    for a, b in zip(number, tensor, strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("velocities", [True, False], ids=["with velocities", "positions only"])
def test_an_elastic_ball_dropped_with_the_projection_keeps_its_energy(velocities):
    """The projection lifts a bouncing ball out of the ground by its penetration (``m g``
    times it in energy) while the bounce kept the speed: it gained 0.7 % of its energy in 5 s
    (9.3 % with the positions alone). The motion along the lift now pays for it."""
    system = dc.load_system({"type": "bouncing_masses", "masses": [1.0], "radii": [0.1],
                             "walls": [[0, 1, 0]], "gravity": 9.81, "mu": 0.0, "cor": 1.0,
                             "dt": 0.01, "horizon": 5.0, "position_projection": 10,
                             "velocity_projection": velocities})  # fmt: skip
    z0 = torch.tensor([[[[0.0, 1.0]], [[0.0, 0.0]]]], dtype=torch.float64)
    traj = system.simulate(z0)
    energy = system.energy(traj)[0]
    assert float((energy - energy[0]).abs().max()) < 1e-9 * float(energy[0])
    assert float(traj[0, 50:, 0, 0, 1].max()) == pytest.approx(1.0, abs=1e-3)  # its height
    assert int((system.gaps(traj[0, :, 0]) >= -1e-10).all())  # the projection held


def test_the_lift_s_energy_is_taken_from_the_motion_along_it():
    """``_lift_within_energy`` on one state: a ball lifted by ``delta`` keeps ``v^2 - 2 g
    delta`` along the lift and its sideways speed; a ball whose potential did not rise, or
    without enough speed along the lift (it stops there), as stated."""
    from diffcontact.systems.system import _lift_within_energy

    system = dc.load_system({"type": "bouncing_masses", "masses": [2.0], "radii": [0.1],
                             "walls": [[0, 1, 0]], "gravity": 9.81, "mu": 0.0, "cor": 1.0,
                             "dt": 0.01, "horizon": 1.0})  # fmt: skip
    x = torch.tensor([[[0.0, 0.09]], [[0.0, 0.09]], [[0.0, 0.09]]], dtype=torch.float64)
    x_p = x + torch.tensor([[[0.0, 0.01]], [[0.0, 0.0]], [[0.0, 0.01]]], dtype=torch.float64)
    v = torch.tensor([[[0.3, 2.0]], [[0.3, 2.0]], [[0.3, 0.1]]], dtype=torch.float64)
    z = torch.stack([x, v], 1)
    ctx = system._context(z, None, system._batch(z, None, 3))
    out = _lift_within_energy(system, ctx, x, x_p, v)
    assert float(out[0, 0, 1]) == pytest.approx((4.0 - 2 * 9.81 * 0.01) ** 0.5, rel=1e-12)
    assert float(out[0, 0, 0]) == pytest.approx(0.3, rel=1e-12)  # sideways: kept
    torch.testing.assert_close(out[1], v[1])  # not lifted: untouched
    assert abs(float(out[2, 0, 1])) < 1e-15 and float(out[2, 0, 0]) == pytest.approx(0.3)
    before = system.energy(torch.stack([x, v], 1))[0]
    after = system.energy(torch.stack([x_p, out], 1))[0]
    assert float(after) == pytest.approx(float(before), rel=1e-12)

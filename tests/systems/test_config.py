"""Config loading and validation: built-in tasks hold the paper-facts.md numbers,
bad input raises ValueError naming the problem, custom systems from dicts and files."""

import json
import math

import pytest
import torch

import diffcontact as dc
from diffcontact.systems import list_tasks, load_config

TASKS = [
    "BP5-e", "BP5", "BD5", "CP3-e", "CP3", "Gyro-e", "Gyro",
    "Rope", "Rope-D100", "Rope-D200", "Rope-D400",
    "BD1-ground",  # not a paper task: the throwing task of docs/control.md
]  # fmt: skip

BOX = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 1.0], [0.0, -1.0, 1.0]]


def test_builtin_task_list():
    assert sorted(list_tasks()) == sorted(TASKS)


@pytest.mark.parametrize("task", TASKS)
def test_every_task_loads(task):
    system = dc.load_system(task)
    assert system.name == task
    assert system.n_contacts == len(system.contact_names) == system.mu.shape[0]
    assert system.mu.dtype == system.cor.dtype == system.mass.dtype == torch.float64
    T = round(system.horizon / system.dt)
    assert system.default_steps == T - 1
    assert T == (20 if task.startswith("Rope") else 100)


def _vals(t):
    return [round(v, 12) for v in t.tolist()]


def test_throwing_task_is_one_disk_on_a_ground_under_gravity():
    system = dc.load_system("BD1-ground")
    assert system.type == "bouncing_disks" and system.n_bodies == 1 and system.n_contacts == 1
    assert system.config.walls == [(0.0, 1.0, 0.0)] and system.config.gravity == 9.8
    assert _vals(system.mu) == [0.3] and _vals(system.cor) == [0.6]


def test_bouncing_tasks_hold_paper_numbers():
    e = dc.load_system("BP5-e")
    assert _vals(e.mass) == [0.1] * 5 and e.config.radii == [0.1] * 5
    assert [list(w) for w in e.config.walls] == BOX
    assert _vals(e.mu) == [0.0] * 30 and _vals(e.cor) == [1.0] * 30
    assert float(e.gravity) == 0.0 and e.dt == 0.01 and e.horizon == 1.0

    bp = dc.load_system("BP5")
    assert _vals(bp.mass) == [0.05, 0.1, 0.3, 0.4, 0.5]
    assert bp.config.radii == [0.05, 0.1, 0.13, 0.15, 0.18]
    assert _vals(bp.mu) == [0.5, 0.4, 0.6, 0.8, 0.9, 1.1, 0.7, 0.1, 0.0, 0.3] + [0.1] * 20
    assert _vals(bp.cor) == [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0] + [0.8] * 20
    # contact numbering: pairs lexicographic, then body-major walls
    assert bp.contact_names[1] == "body 0 and body 2 overlap"
    assert bp.contact_names[10 + 4 * 2 + 3] == "body 2 penetrates wall 3"

    bd = dc.load_system("BD5")
    assert _vals(bd.mass) == [0.05, 0.1, 0.3, 0.4, 0.5]
    r = torch.tensor([0.05, 0.1, 0.13, 0.15, 0.18], dtype=torch.float64)
    torch.testing.assert_close(bd.second_moments, (r**2 / 4)[:, None].expand(5, 2))
    assert _vals(bd.mu) == [0.3, 0.5, 0.1, 0.4, 1.4, 0.9, 0.8, 0.0, 0.2, 0.6] + [0.1] * 20
    assert _vals(bd.cor) == [0.2, 0.4, 0.1, 0.9, 0.8, 0.3, 1.0, 0.9, 0.7, 0.0] + [0.8] * 20
    assert bd.n_points == 15 and bd.dim == 2


def test_pendulum_gyro_rope_hold_paper_numbers():
    cpe, cp = dc.load_system("CP3-e"), dc.load_system("CP3")
    assert _vals(cpe.mass) == [0.2, 0.13, 0.15] and cpe.config.radii == [0.15, 0.08, 0.1]
    assert _vals(cp.mass) == [0.1, 0.2, 0.15] and cp.config.radii == [0.05, 0.15, 0.1]
    for s in (cpe, cp):
        assert s.config.link_lengths == [0.35, 0.4, 0.35]
        assert [list(w) for w in s.config.walls] == [[0.0, 1.0, 1.0]]
        assert float(s.gravity) == 9.81 and s.dt == 0.01 and s.horizon == 1.0
    assert _vals(cpe.mu) == [0.0] * 3 and _vals(cpe.cor) == [1.0] * 3
    assert _vals(cp.mu) == [0.5] * 3 and _vals(cp.cor) == [0.0] * 3

    for name, mu, cor in (("Gyro-e", 0.0, 1.0), ("Gyro", 0.1, 0.8)):
        g = dc.load_system(name)
        c = g.config
        assert _vals(g.mass) == [0.1] and list(c.second_moments) == [0.24, 0.24, 0.04]
        assert c.com_distance == 0.5 and c.rim_radius == 0.3
        assert list(c.wall) == [0.0, 1.0, 0.0, 0.33]
        assert _vals(g.mu) == [mu] and _vals(g.cor) == [cor]
        assert float(g.gravity) == 9.81 and g.dt == 0.02 and g.horizon == 2.0
        assert g.dim == 3 and g.n_points == 4 and g.d == 3

    for name, n in (("Rope", 10), ("Rope-D100", 50), ("Rope-D200", 100), ("Rope-D400", 200)):
        rope = dc.load_system(name)
        c = rope.config
        assert c.n_points == n and rope.n_points * rope.dim == (20 if n == 10 else 2 * n)
        assert _vals(rope.mass) == [0.1] * n
        assert c.rest_length == 0.05 and c.stiffness == 50.0 and c.max_angle == 0.2
        assert (c.min_ratio, c.max_ratio) == (0.8, 1.2)
        assert rope.n_contacts == 2 * n - 1 and rope.d == 1
        assert _vals(rope.mu) == [0.0] * (2 * n - 1) and _vals(rope.cor) == [0.0] * (2 * n - 1)
        assert float(rope.gravity) == 9.81 and rope.dt == 0.005 and rope.horizon == 0.1


def test_unknown_task_lists_known_ones():
    with pytest.raises(ValueError, match=r"unknown task 'BP6'.*BP5-e.*Rope-D400"):
        dc.load_system("BP6")
    with pytest.raises(ValueError, match="does not exist"):
        dc.load_system("/nonexistent/system.yaml")


def test_system_takes_a_task_name_or_a_path_like_load_system(tmp_path):
    # System("BP5") said "expected a mapping of keys, got str"
    assert dc.System("BP5").config == dc.load_system("BP5").config
    path = tmp_path / "mine.json"
    path.write_text(json.dumps(dc.load_system("CP3").config.model_dump(mode="json")))
    for spec in (path, str(path)):
        assert dc.System(spec).config == dc.load_system("CP3").config
    with pytest.raises(ValueError, match=r"unknown task 'BP6'"):
        dc.System("BP6")


def test_a_file_that_is_not_a_config_is_named(tmp_path):
    path = tmp_path / "sim.npz"  # e.g. what diffcontact simulate writes
    path.write_bytes(b"")
    with pytest.raises(ValueError, match=r"sim\.npz' is not a config file: .*\.yaml, \.yml or"):
        dc.load_system(str(path))


@pytest.mark.parametrize("name", ["dir.yaml", "files"])
def test_a_directory_is_named_as_one(tmp_path, name):
    """A directory named dir.yaml was said not to exist, one named files to be an unknown
    task."""
    (tmp_path / name).mkdir()
    with pytest.raises(ValueError, match=rf"{name}' is a directory, not a config file"):
        dc.load_system(tmp_path / name)


@pytest.mark.parametrize(
    ("override", "pattern"),
    [
        ({"masses": [0.1, -0.1, 0.3, 0.4, 0.5]}, r"masses\.1: .*greater than 0"),
        ({"masses": [0.1, 0.0, 0.3, 0.4, 0.5]}, r"masses\.1: .*greater than 0"),
        ({"radii": [0.1]}, r"radii: expected 5 values"),
        ({"mu": -0.1}, r"mu: value -0\.1 .* must be finite and >= 0"),
        ({"mu": float("inf")}, r"mu: value inf of contact 0 must be finite and >= 0"),
        ({"cor": float("nan")}, r"cor: value nan of contact 0 must lie in \[0, 1\]"),
        ({"cor": 1.5}, r"cor: value 1\.5 .* must lie in \[0, 1\]"),
        ({"cor": [0.5] * 7}, r"cor: expected one number or 30 values .* got a list of 7"),
        ({"mu": {"pairs": [0.1] * 3, "walls": 0.1}}, r"mu\.pairs: expected one number or 10"),
        ({"mu": {"pairs": 0.1}}, r"mu: missing group 'walls'"),
        ({"mu": {"pairs": 0.1, "walls": 0.1, "stretch": 0}}, r"mu: .*no contact group.*stretch"),
        ({"foo": 1}, r"foo: unknown key"),
        ({"initial_conditions": {"velocity_sdt": 1}}, r"initial_conditions\.velocity_sdt: unknown"),
        ({"type": "bouncing_ballz"}, r"unknown system type 'bouncing_ballz'"),
        ({"dt": 0.03}, r"horizon / dt must be a whole number"),
        ({"dt": -0.01}, r"dt: .*greater than 0"),
        ({"walls": [[0, 0, 1]]}, r"walls\[0\]: the normal part"),
        ({"walls": [[0, 1]]}, r"walls\.0: too few numbers: got 2$"),  # was walls.0.2: missing key
        ({"walls": [[0, 1, 0, 1]]}, r"walls\.0: too many values: at most 3, got 4"),
        ({"gravity": -9.81}, r"gravity: .*greater than or equal to 0"),
        ({"penetration_fraction": 2}, r"penetration_fraction"),
        ({"dynamics": "newtonian"}, r"dynamics"),
        ({"integrator": "euler"}, r"integrator: .*'rk4' or 'rk4_38'"),
    ],
)
def test_validation_errors_name_the_key(override, pattern):
    with pytest.raises(ValueError, match=pattern):
        dc.load_system("BP5", **override)


NOT_FROM_STRINGS = "numbers are not read from strings or booleans"


@pytest.mark.parametrize(
    ("task", "override", "lines"),
    [
        ("Rope", {"mass": -0.1}, ["mass: Input should be greater than 0 (got -0.1)"]),
        ("Rope", {"mass": [0.1] * 9 + [-1]}, ["mass.9: Input should be greater than 0 (got -1)"]),
        ("Rope", {"mass": float("nan")}, ["mass: Input should be a finite number (got nan)"]),
        (
            "Rope",
            {"mass": "5"},
            [f"mass: Input should be a valid number (got '5'; {NOT_FROM_STRINGS})"],
        ),
        (
            "Rope",
            {"mass": (0.1, "x")},
            [f"mass.1: Input should be a valid number (got 'x'; {NOT_FROM_STRINGS})"],
        ),
        (
            "Rope",
            {"mass": -0.1, "rest_length": 0},
            [
                "mass: Input should be greater than 0 (got -0.1)",
                "rest_length: Input should be greater than 0 (got 0)",
            ],
        ),
        (
            "Rope",
            {"mu": "a"},
            [f"mu: Input should be a valid number (got 'a'; {NOT_FROM_STRINGS})"],
        ),
        (
            "Rope",
            {"mu": [0.1, True]},
            [f"mu.1: Input should be a valid number (got True; {NOT_FROM_STRINGS})"],
        ),
        (
            "Rope",
            {"cor": {"bending": [0.1, "a"], "stretch": 0.0}},
            [f"cor.bending.1: Input should be a valid number (got 'a'; {NOT_FROM_STRINGS})"],
        ),
        (
            "Rope",
            {"cor": {"bending": 0.0, "stretch": 0.0, "walls2": 1}},
            ["cor.walls2: unknown key (not part of the schema; see docs/config.md)"],
        ),
        (
            "BP5",
            {"mu": {"pairs": "0.1", "walls": 0.1}},
            [f"mu.pairs: Input should be a valid number (got '0.1'; {NOT_FROM_STRINGS})"],
        ),
        ("Gyro", {"mass": -1}, ["mass: Input should be greater than 0 (got -1)"]),
        # the hint only where a number belongs and a string or boolean was given: "name:
        # Input should be a valid string (got 5; numbers are not read from strings ...)"
        ("BP5", {"name": 5}, ["name: Input should be a valid string (got 5)"]),
        ("BP5", {"masses": 1.0}, ["masses: Input should be a valid list (got 1.0)"]),
        (
            "BP5",
            {"masses": [0.1, "0.2", 0.3, 0.4, 0.5]},
            [f"masses.1: Input should be a valid number (got '0.2'; {NOT_FROM_STRINGS})"],
        ),
        (
            "Rope",
            {"n_points": True},
            [f"n_points: Input should be a valid integer (got True; {NOT_FROM_STRINGS})"],
        ),
        ("Rope", {"n_points": 5.0}, ["n_points: Input should be a valid integer (got 5.0)"]),
    ],
)
def test_number_or_list_errors_name_only_the_form_given(task, override, lines):
    """A key taking one number or a list (or, per contact, a mapping of groups) reports
    what is wrong with the value given, not also that it is not of the other forms
    ("mass: Input should be greater than 0; mass: Input should be a valid list (got
    -0.1 ...)"), each error on one line with the value that broke the range."""
    with pytest.raises(ValueError) as info:
        load_config(task, **override)
    header, *got = str(info.value).splitlines()
    assert header == f"invalid system config of built-in task {task!r}:"
    assert got == [f"  {line}" for line in lines]


def test_number_or_list_keys_accept_every_form():
    as_list = load_config("Rope", mass=[0.1] * 10, cor={"bending": 0.5, "stretch": [0.2] * 10})
    assert as_list.point_masses() == [0.1] * 10
    assert as_list.per_contact("cor") == [0.5] * 9 + [0.2] * 10
    assert load_config("Rope", mass=(0.1,) * 10).mass == [0.1] * 10  # a tuple is a list
    assert load_config("Rope", mass=2).point_masses() == [2.0] * 10  # an integer is a number
    assert load_config("Rope", mu=[0.0] * 19).per_contact("mu") == [0.0] * 19
    groups = load_config("Rope", cor=as_list.cor)  # a ContactGroups instance
    assert groups.cor == as_list.cor
    again = load_config("Rope", **as_list.model_dump())
    assert again == as_list


def test_validation_errors_other_types():
    with pytest.raises(ValueError, match=r"link_lengths: expected 3 values"):
        dc.load_system("CP3", link_lengths=[0.3, 0.4])
    with pytest.raises(ValueError, match=r"second_moments\.1: .*greater than 0"):
        dc.load_system("Gyro", second_moments=[0.2, -0.1, 0.04])
    with pytest.raises(ValueError, match=r"wall: the normal part"):
        dc.load_system("Gyro", wall=[0, 0, 0, 1])
    with pytest.raises(ValueError, match=r"mu: .*no contact group.*pairs"):
        dc.load_system("Rope", mu={"pairs": 0.1, "bending": 0, "stretch": 0})
    with pytest.raises(ValueError, match=r"mass: expected one number or 10 values"):
        dc.load_system("Rope", mass=[0.1, 0.2])
    with pytest.raises(ValueError, match=r"min_ratio < 1 < max_ratio"):
        dc.load_system("Rope", max_ratio=0.9)
    with pytest.raises(ValueError, match=r"missing key 'type'"):
        dc.load_system({"masses": [1.0]})
    with pytest.raises(ValueError, match=r"second_moments: expected 5 pairs"):
        dc.load_system("BD5", second_moments=[[0.1, 0.1]])
    with pytest.raises(ValueError, match="task name, a path or a dict"):
        dc.load_system(42)


def _two_balls():
    return {
        "name": "two-balls",
        "type": "bouncing_masses",
        "masses": [0.1, 0.3],
        "radii": [0.1, 0.15],
        "walls": [[0, 1, 0]],
        "gravity": 9.81,
        "mu": {"pairs": 0.2, "walls": [0.5, 0.1]},
        "cor": 0.9,
        "dt": 0.01,
        "horizon": 0.5,
        "initial_conditions": {"position_low": [0.0, 0.2], "position_high": [1.0, 1.0]},
    }


def test_custom_system_from_dict_yaml_and_json(tmp_path):
    import yaml

    cfg = _two_balls()
    a = dc.load_system(cfg)
    assert a.name == "two-balls" and a.n_contacts == 3
    assert _vals(a.mu) == [0.2, 0.5, 0.1] and _vals(a.cor) == [0.9] * 3
    assert a.default_steps == 49

    (tmp_path / "two.yaml").write_text(yaml.safe_dump(cfg))
    (tmp_path / "two.json").write_text(json.dumps(cfg))
    for path in (tmp_path / "two.yaml", str(tmp_path / "two.json")):
        b = dc.load_system(path)
        assert b.config == a.config
    z0 = a.sample_initial_conditions(3, seed=1)
    assert z0.shape == (3, 2, 2, 2)
    assert bool((z0[:, 0, :, 1] >= 0.2).all())
    traj = a.simulate(z0, steps=4)
    assert traj.shape == (3, 5, 2, 2, 2)

    (tmp_path / "bad.yaml").write_text("type: bouncing_masses\nmasses: [1]\nradii: [1]\nwals: []\n")
    with pytest.raises(ValueError, match=r"(?s)bad\.yaml.*dt: missing key.*wals: unknown key"):
        dc.load_system(tmp_path / "bad.yaml")


def test_overrides_and_config_roundtrip():
    cfg = load_config("CP3", mu=0.3)
    assert cfg.mu == 0.3
    again = dc.load_system(cfg.model_dump())
    assert again.config == cfg
    assert math.isclose(float(again.mu[0]), 0.3)


def test_bad_parameter_tensors_are_rejected_at_simulate():
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(2, seed=0)
    cases = [
        ("mass", torch.tensor([0.1, -0.1, 0.3, 0.4, 0.5], dtype=torch.float64), "mass must be"),
        ("mass", torch.ones(3, dtype=torch.float64), r"mass must have shape \(5,\)"),
        ("mu", torch.full((30,), -0.5, dtype=torch.float64), r"mu must be >= 0"),
        ("cor", torch.full((30,), 1.2, dtype=torch.float64), r"cor must be in \[0, 1\]"),
        ("cor", torch.full((7,), 0.5, dtype=torch.float64), r"cor must be one number or .*\(30,\)"),
    ]
    for name, value, pattern in cases:
        fresh = dc.load_system("BP5")
        setattr(fresh, name, value)
        with pytest.raises(ValueError, match=pattern):
            fresh.simulate(z0, steps=1)
    # a 0-d coefficient broadcasts to every contact
    system.mu = torch.tensor(0.2, dtype=torch.float64)
    assert system.simulate(z0, steps=1).shape == (2, 2, 2, 5, 2)


def test_energies_and_gaps_check_their_states():
    """Integer positions gave zero kinetic energy and a wrong potential (the masses were
    cast to the states' dtype: 0.05 -> 0); a wrong point count a deep matmul error."""
    system = dc.load_system("BP5")
    z = (system.sample_initial_conditions(2, seed=1) * 10).round()
    assert float(system.kinetic_energy(z).min()) > 0
    for call, arg, name in (
        (system.kinetic_energy, z.long(), "z"),
        (system.potential, z[:, 0].long(), "x"),
        (system.grad_potential, z[:, 0].int(), "x"),
        (system.gaps, z[:, 0].long(), "x"),
    ):
        with pytest.raises(ValueError, match=rf"{name} must be a float32 or float64 tensor"):
            call(arg)
    with pytest.raises(ValueError, match=r"z must have shape \(\.\.\., \(2, 5, 2\)\)"):
        system.kinetic_energy(z[:, :, :4])
    with pytest.raises(ValueError, match=r"x must have shape \(\.\.\., 5, 2\) for BP5"):
        system.potential(z[:, 0, :4])
    with pytest.raises(ValueError, match=r"x must be a torch\.Tensor"):
        system.gaps(z[:, 0].numpy())


def test_counts_and_seeds_take_integers_of_any_kind_and_nothing_else():
    """numpy integers were refused ("got np.int64(2)"); seed=None was a TypeError, 1.5
    silently 1, 2**70 an overflow."""
    import numpy as np

    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(np.int64(2), seed=np.int64(3))
    assert torch.equal(z0, system.sample_initial_conditions(2, seed=3))
    assert system.simulate(z0, np.int64(3), progress=False).shape[1] == 4
    for seed in (None, 1.5, 2**70, -1, True):
        with pytest.raises(ValueError, match=r"seed must be an integer in \[0, 2\*\*63\)"):
            system.sample_initial_conditions(2, seed=seed)
    for steps in (1.5, True, "3"):
        with pytest.raises(ValueError, match="steps must be a non-negative integer"):
            system.simulate(z0, steps)


def test_bad_initial_states_are_rejected():
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(4, seed=0)
    with pytest.raises(ValueError, match=r"z0 must have shape \(N, 2, 5, 2\)"):
        system.simulate(z0[:, :, :4])
    with pytest.raises(ValueError, match=r"z0 must have shape"):
        system.simulate(z0[0])
    # half precision failed at the first contact (no Cholesky for it), meta tensors at a
    # read of their values
    for dtype in (torch.float16, torch.bfloat16, torch.int64):
        with pytest.raises(ValueError, match=rf"z0 must be a float32 or float64 .*got {dtype}"):
            system.simulate(z0.to(dtype), steps=2)
    with pytest.raises(ValueError, match=r"z0 is on the meta device"):
        system.simulate(z0.to("meta"), steps=2)
    with pytest.raises(ValueError, match=r"z0 must be a dense tensor, got layout torch\.sparse"):
        system.simulate(z0.to_sparse(), steps=2)  # (a SparseCPU error from deep inside)
    # steps=10**12 ran, filling the memory at 100 MB/s before any error
    with pytest.raises(ValueError, match=r"simulate BP5: steps=1000000000000: at most 1000000"):
        system.simulate(z0, steps=10**12)
    bad = z0.clone()
    bad[2, 1, 0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"NaN or infinite values \(states \[2\]\)"):
        system.simulate(bad)
    overlap = z0.clone()
    overlap[1, 0, 2] = overlap[1, 0, 0] + 0.05  # body 2 onto body 0
    with pytest.raises(ValueError, match=r"(?s)z0\[1\]: body 0 and body 2 overlap.*check_overlap"):
        system.simulate(overlap)  # the message says how to go on from a simulated state
    outside = z0.clone()
    outside[3, 0, 4, 0] = 1.1  # body 4 through wall 2 (x = 1)
    with pytest.raises(ValueError, match=r"z0\[3\]: body 4 penetrates wall 2"):
        system.simulate(outside)
    # float32: a clear overlap still raises; a gap within rounding of a limit does not
    with pytest.raises(ValueError, match=r"(?s)\(gap < -3\.5e-04\).*body 0 and body 2 overlap"):
        system.simulate(overlap.float())
    grazing = z0.clone()
    k = int(grazing[0, 0, :, 0].argmax())  # the body nearest wall 2 (x = 1), moved 1e-5 into it
    grazing[0, 0, k, 0] = 1.0 - float(system.config.radii[k]) + 1e-5
    with pytest.raises(ValueError, match=rf"z0\[0\]: body {k} penetrates wall 2 \(gap -1e-05\)"):
        system.simulate(grazing, steps=1)
    assert system.simulate(grazing.float(), steps=1, on_tunnelling="ignore").isfinite().all()
    with pytest.raises(ValueError, match=r"steps must be a non-negative integer"):
        system.simulate(z0, steps=-1)
    with pytest.raises(ValueError, match=r"unknown contact model 'Stribeck'.*CM, CMr"):
        system.simulate(z0, steps=1, contact_model="Stribeck")
    with pytest.raises(ValueError, match=r"dynamics must be one of"):
        system.simulate(z0, steps=1, dynamics="newton")
    rope = dc.load_system("Rope")
    zr = rope.sample_initial_conditions(1, seed=0)
    zr[0, 0, 5] = zr[0, 0, 4] + 0.3 * (zr[0, 0, 5] - zr[0, 0, 4])  # squash segment 5
    with pytest.raises(ValueError, match=r"stretch limit of segment 5 exceeded"):
        rope.simulate(zr)


# a config of the stress tests: two point masses in the unit box
B = {
    "type": "bouncing_masses",
    "masses": [1.0, 1.0],
    "radii": [0.1, 0.1],
    "walls": [[1, 0, 0], [0, 1, 0], [-1, 0, 1], [0, -1, 1]],
    "dt": 0.01,
    "horizon": 0.1,
}


def _message(spec, **overrides):
    with pytest.raises(ValueError) as info:
        load_config(spec, **overrides)
    return str(info.value)


def test_yaml_aliases_expanding_past_the_limit_are_refused(tmp_path):
    """Nested anchors made a 600-byte file stand for 10^8 values: load_system ran for
    minutes (the depth check and pydantic walked every expanded value). The file is
    sized before it is built (benchmarks, not tests, say how fast)."""
    import yaml

    from diffcontact.systems.config import MAX_NODES

    valid = yaml.safe_dump(B)
    bomb = ['a0: &a0 ["x", "x", "x", "x", "x", "x", "x", "x", "x", "x"]']
    bomb += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, 7)]
    path = tmp_path / "bomb.yaml"  # 10^7 values once expanded
    path.write_text(valid + "\n".join(bomb) + "\n")
    with pytest.raises(
        ValueError, match=rf"bomb\.yaml: with its aliases .* more than {MAX_NODES:,}"
    ):
        dc.load_system(path)
    # the same shared structure from Python is counted where it appears, and refused
    shared: list = ["x"] * 10
    for _ in range(6):
        shared = [shared] * 10
    with pytest.raises(ValueError, match=rf"more than {MAX_NODES:,} values"):
        load_config({**B, "extra": shared})
    # an alias inside the value it names
    (tmp_path / "loop.yaml").write_text(valid + "masses: &m [1.0, *m]\n".replace("masses", "x"))
    with pytest.raises(ValueError, match=r"loop\.yaml: an alias lies inside the value it names"):
        dc.load_system(tmp_path / "loop.yaml")
    # a config with a few aliases loads
    (tmp_path / "few.yaml").write_text(
        "type: bouncing_masses\nmasses: &m [1.0, 1.0]\nradii: [0.1, 0.1]\n"
        "walls: [&ground [0, 1, 0], [1, 0, 0]]\ndt: &dt 0.01\nhorizon: 0.1\n"
        "mu: {pairs: *dt, walls: [*dt, *dt, 0, 0]}\n"
    )
    cfg = load_config(tmp_path / "few.yaml")
    assert cfg.masses == [1.0, 1.0] and cfg.per_contact("mu") == [0.01, 0.01, 0.01, 0, 0]


def test_rope_min_ratio_must_be_positive():
    # min_ratio 0 let a segment collapse to a point, where its bending is undefined
    assert "min_ratio: Input should be greater than 0 (got 0)" in _message("Rope", min_ratio=0)
    assert load_config("Rope", min_ratio=1e-3).min_ratio == 1e-3


def test_walls_of_any_finite_scale_are_normalised():
    """[1e160, 0, 0] had a norm of inf and became a zero normal (every gap -r);
    [1e-170, 0, 0] one of 0 ("wall normals (a, b) must be non-zero")."""
    unit = dc.load_system({**B, "walls": [[1, 0, 0], [0, 1, 0]]})
    x = unit.sample_initial_conditions(4, seed=0)[:, 0]
    for scale in (1e160, 1e-170, 1e300, 5e-324):
        scaled = dc.load_system({**B, "walls": [[scale, 0, 0], [0, 1, 0]]})
        torch.testing.assert_close(scaled.gaps(x), unit.gaps(x), rtol=0, atol=1e-15)
    gyro = dc.load_system("Gyro")
    xg = gyro.sample_initial_conditions(4, seed=0)[:, 0]
    plane_x = dc.load_system("Gyro", wall=[1, 0, 0, 0]).gaps(xg)
    torch.testing.assert_close(dc.load_system("Gyro", wall=[1e300, 0, 0, 1]).gaps(xg), plane_x)
    far = dc.load_system("Gyro", wall=[1e-200, 0, 0, 1]).gaps(xg)  # the plane x = -1e200
    torch.testing.assert_close(far, torch.full_like(far, 1e200))
    # the same normalisation where walls are read again: planning, event-driven data, drawing
    from diffcontact.control.tasks import _walls
    from diffcontact.geometry.base import unit_normal_planes
    from diffcontact.viz.animation import _normalized_walls

    lines = [[1e160, 0, 0], [0, -1e-170, 1e-170], [3, 4, 5]]
    want = torch.tensor([[1.0, 0, 0], [0, -1, 1], [0.6, 0.8, 1]], dtype=torch.float64)
    cfg = load_config({**B, "walls": lines})
    torch.testing.assert_close(_walls(cfg), want)
    torch.testing.assert_close(torch.from_numpy(_normalized_walls(lines)), want)
    got = unit_normal_planes(torch.tensor(lines, dtype=torch.float64), 2)
    torch.testing.assert_close(got, want)
    # a line whose distance from the origin is no float64 is named
    assert "walls[0]: [1e-300, 0.0, 1e+300] lies too far from the origin" in _message(
        {**B, "walls": [[1e-300, 0, 1e300]]}
    )
    assert "wall: [0.0, 1e-300, 0.0, 1e+300] lies too far" in _message(
        "Gyro", wall=[0, 1e-300, 0, 1e300]
    )


def test_yaml_keys_that_are_lists_or_mappings_are_named(tmp_path):
    # "TypeError: unhashable type: 'list'" from the duplicate-key check
    for name, text, line, what in (
        ("list.yaml", "type: bouncing_masses\n? [1, 2]\n: 3\n", 2, "list"),
        ("map.yaml", "type: bouncing_masses\n{a: 1}: 2\n", 2, "mapping"),
        ("deep.yaml", "type: bouncing_masses\nmu:\n  ? [1]\n  : 2\n", 3, "list"),
    ):
        (tmp_path / name).write_text(text)
        pattern = rf"config file .*{name}: line {line}: a key is a {what}; keys must be strings"
        with pytest.raises(ValueError, match=pattern):
            dc.load_system(tmp_path / name)


@pytest.mark.parametrize(
    ("task", "override", "key"),
    [
        ("CP3", {"link_lengths": [1e300, 0.4, 0.35]}, "link_lengths.0"),
        ("CP3", {"radii": [0.1, 1e200, 0.1]}, "radii.1"),
        ("Rope", {"rest_length": 1e300}, "rest_length"),
        ("Gyro", {"rim_radius": 1e160}, "rim_radius"),
        ("Gyro", {"com_distance": 1e300}, "com_distance"),
        ("BD5", {"radii": [1e300, 0.1, 0.13, 0.15, 0.18]}, "radii.0"),
    ],
)
def test_lengths_whose_square_overflows_are_refused_at_the_schema(task, override, key):
    """link_lengths [1e300, 1] passed the schema, then load_system failed inside with
    "target must be finite" (the squared length overflowed)."""
    (value,) = (v[int(key[-1])] if isinstance(v, list) else v for v in override.values())
    message = _message(task, **override)
    assert f"{key}: Input should be less than or equal to 1e+150 (got {value!r})" in message
    at_limit = {k: [1e150 if x == value else x for x in v] if isinstance(v, list) else 1e150
                for k, v in override.items()}  # fmt: skip
    dc.load_system(task, **at_limit)


def test_many_errors_are_counted_not_listed():
    """20,000 bad radii made a 1 MB message (and took 4.6 s: a quadratic dedupe)."""
    n = 20_000
    message = _message({**B, "masses": [1.0] * n, "radii": [-0.001] * n})
    lines = message.splitlines()
    assert lines[1] == "  radii.0: Input should be greater than 0 (got -0.001)"
    assert len(lines) == 12 and lines[-1] == f"  and {n - 10:,} more errors"
    # below the cap every problem is listed, each once
    few = _message({**B, "radii": [-1, -1], "dt": -1})
    assert few.count("\n") == 3 and "more error" not in few


def test_sets_are_refused_where_lists_belong(tmp_path):
    """A set was read as a list in its own order: masses {2.0, 1.0} became [1.0, 2.0]."""
    for override, key in (
        ({"masses": {2.0, 1.0}, "radii": [0.2, 0.1]}, "masses"),
        ({"walls": [{0.5, 1, 0}]}, "walls.0"),
        ({"walls": frozenset({(1, 0, 0)})}, "walls"),
        ({"mu": {0.1, 0.2}}, "mu"),
        ({"mu": {"pairs": {0.1}, "walls": 0.1}}, "mu.pairs"),
        ({"initial_conditions": {"position_low": {0.1, 0.2}}}, "initial_conditions.position_low"),
    ):
        assert f"{key}: a set has no order; give a list (got " in _message({**B, **override})
    assert "mass: a set has no order" in _message("Rope", mass={0.1, 0.2})
    assert "second_moments: a set has no order" in _message("Gyro", second_moments={1, 2, 3})
    path = tmp_path / "set.yaml"
    path.write_text(
        "type: bouncing_masses\nmasses: !!set {2.0, 1.0}\nradii: [0.2, 0.1]\n"
        "walls: [[0, 1, 0]]\ndt: 0.01\nhorizon: 0.1\n"
    )
    with pytest.raises(ValueError, match=r"set\.yaml:\n  masses: a set has no order"):
        dc.load_system(path)
    assert load_config({**B, "masses": (2.0, 1.0)}).masses == [2.0, 1.0]  # a tuple is ordered


def test_error_wording():
    # nan is not finite (was "less than or equal to 1 (got nan)")
    assert "penetration_fraction: Input should be a finite number (got nan)" in _message(
        "BP5", penetration_fraction=float("nan")
    )
    assert "max_angle: Input should be a finite number (got nan)" in _message(
        "Rope", max_angle=float("nan")
    )
    # the key once (was "initial_conditions: initial_conditions.position_low must be ...")
    low_high = {"position_low": [1, 1], "position_high": [0, 0]}
    assert "\n  initial_conditions: position_low must be below position_high" in _message(
        {**B, "initial_conditions": low_high}
    )
    assert "\n  initial_conditions: angle_low must be below angle_high" in _message(
        "CP3", initial_conditions={"angle_low": 1, "angle_high": 0}
    )
    # one pair, one value, one wall (was "1 pairs", "1 values", "1 walls")
    one = {**B, "masses": [1.0], "radii": [0.1], "walls": [[0, 1, 0]]}
    assert "second_moments: expected 1 pair (one per body), got 2" in _message(
        {**one, "type": "bouncing_disks", "second_moments": [[1, 1], [1, 1]]}
    )
    assert "mu: expected one number or 1 value (one per contact: 1 wall), got a list of 2" in (
        _message({**one, "mu": [0.1, 0.2]})
    )
    assert "radii: expected 1 value (one per mass), got 2" in _message({**one, "radii": [1, 1]})
    two = {**B, "walls": [[0, 1, 0]]}
    assert "(one per contact: 1 pair, 2 walls)" in _message({**two, "cor": [0.1]})

"""``diffcontact billiards`` and ``diffcontact throw`` on good and bad input."""

from __future__ import annotations

import json

import pytest
from PIL import Image

from diffcontact.testing import assert_usage_error, run_cli

QUICK = ["--time", "0.2", "--starts", "2", "--iterations", "2", "--quiet"]


run = run_cli


def test_billiards_plans_reports_and_writes_json_and_gif(capsys, tmp_path):
    out, gif = tmp_path / "shot.json", tmp_path / "shot.gif"
    code, stdout, err = run(
        capsys, "billiards", "BP5-e", "--target", "0.5", "0.5", "--cue", "0", "--ball", "2",
        *QUICK, "--json", str(out), "--gif", str(gif),
    )  # fmt: skip
    assert code == 0, err
    assert "under the planning model" in stdout and "under the ground truth" in stdout
    info = json.loads(out.read_text())
    # 2 iterations rarely reach the target: a missed one is said (it was only "stopped:
    # iterations"), a reached one is not
    missed = info["distance_model"] > 0.005
    assert ("warning: target not reached: the best plan ends" in err) == missed, err
    assert set(info) >= {"variables", "distance_model", "distance_true"}
    assert len(info["variables"]["velocity"]) == 2
    assert all(abs(v) <= 4.0 for v in info["variables"]["velocity"])
    # the true system plans: its own model is the truth
    assert info["distance_model"] == pytest.approx(info["distance_true"], abs=1e-12)
    with Image.open(gif) as im:
        assert im.n_frames > 2


def test_throw_with_a_saved_model(capsys, tmp_path):
    import diffcontact as dc
    from diffcontact.learning.models.registry import create_model
    from diffcontact.learning.models.storage import save_model

    model = create_model("CM-CD-CLNN", dc.load_system("BD1-ground").config, hidden=[8])
    save_model(model, tmp_path / "model.pt")
    out = tmp_path / "throw.json"
    code, stdout, err = run(
        capsys, "throw", str(tmp_path), "--target", "0.4", *QUICK, "--json", str(out), "--no-gif"
    )
    assert code == 0, err
    info = json.loads(out.read_text())
    assert set(info["variables"]) == {"velocity", "spin"}
    assert "CM-CD-CLNN model of BD1-ground" in stdout
    assert not (tmp_path / "throw.gif").exists()


@pytest.mark.parametrize(
    ("argv", "needles"),
    [
        (["billiards", "BP5-e", "--target", "1.5", "0.5"], ["outside the table"]),
        (["billiards", "BP5-e", "--target", "0.5", "0.5", "--cue", "2"], ["different bodies"]),
        (["billiards", "BP5-e", "--target", "0.5", "0.5", "--ball", "9"], ["ball must be"]),
        (["billiards", "BP5-e", "--target", "0.5", "0.5", "--time", "0.015"], ["multiple"]),
        # (it ran until the memory was full)
        (["billiards", "BP5-e", "--target", "0.5", "0.5", "--time", "1e7"], ["at most 1000000"]),
        (["throw", "BD1-ground", "--target", "1", "--time", "1e5"], ["10000000 steps"]),
        (["billiards", "no-such-task", "--target", "0.5", "0.5"], ["unknown task"]),
        (["billiards", "CP3", "--target", "0.5", "0.5"], ["system of circles"]),
        (["throw", "BP5", "--target", "1"], ["throw needs rigid disks"]),
        (["throw", "BD1-ground", "--target", "1", "--start", "0", "0.05"], ["overlaps"]),
        (["throw", "BD1-ground", "--target", "nan"], ["finite"]),
    ],
)
def test_bad_input_is_one_line(capsys, argv, needles):
    code, _, err = run(capsys, *argv, "--quiet", "--no-gif")
    assert_usage_error(code, err, *needles)


def _run_of(tmp_path, name, data):
    """A training-run folder: an (untrained) CM-CD-CLNN model of BD1-ground, its data."""
    import diffcontact as dc
    from diffcontact.learning.models.registry import create_model
    from diffcontact.learning.models.storage import save_model

    run_dir = tmp_path / name
    run_dir.mkdir()
    model = create_model("CM-CD-CLNN", dc.load_system("BD1-ground").config, hidden=[8])
    save_model(model, run_dir / "model.pt")
    (run_dir / "run.json").write_text(json.dumps({"data_dir": str(data)}))
    return run_dir


def test_a_run_s_plans_are_judged_by_its_data_s_truth(capsys, tmp_path):
    """The truth simulates with the contact model of the run's data (it was always CM),
    and recorded data without declared parameters has no truth to judge by (the config's
    placeholders judged it)."""
    import math

    import torch

    import diffcontact as dc
    from diffcontact.control import as_planner
    from diffcontact.control.tasks import plan_throw
    from diffcontact.learning.data.arrays import dataset_from_arrays
    from diffcontact.learning.data.generate import generate_dataset
    from diffcontact.mechanics import disk_points_2d

    truth = dc.load_system("BD1-ground")
    lcp = generate_dataset("BD1-ground", tmp_path / "lcp", n_train=2, n_val=1, n_test=1,
                           contact_model="LCP", progress=False)  # fmt: skip
    planner = as_planner(str(_run_of(tmp_path, "on_lcp", lcp)))
    assert (planner.truth_contact_model, planner.truth_known) == ("LCP", True)
    # a spinning disk that slides when it hits the ground: CM and LCP bounce it differently
    one = torch.ones(1, dtype=torch.float64)
    z0 = disk_points_2d(torch.tensor([[0.0, 0.2]], dtype=torch.float64), 0 * one,
                        torch.tensor([[3.0, -1.0]], dtype=torch.float64), 40 * one)  # fmt: skip
    z0 = z0.transpose(0, 1).reshape(1, 2, 3, 2)
    lcp_traj = truth.simulate(z0, 30, contact_model="LCP")
    assert not torch.allclose(lcp_traj, truth.simulate(z0, 30))  # CM's differs
    torch.testing.assert_close(planner.simulate_truth(z0, 30), lcp_traj, rtol=0, atol=0)
    plan = plan_throw(planner, 0.8, starts=2, iterations=2, progress=False)
    steps = plan.traj_true.shape[1] - 1
    torch.testing.assert_close(plan.traj_true, planner.simulate_truth(plan.result.z0, steps))

    recorded = dataset_from_arrays(
        truth.simulate(truth.sample_initial_conditions(5, seed=1)), "BD1-ground",
        tmp_path / "recorded", val_fraction=0.2, test_fraction=0.2, progress=False,
    )  # fmt: skip
    run_dir = _run_of(tmp_path, "on_recorded", recorded)
    assert as_planner(str(run_dir / "model.pt")).truth_known is False
    out = tmp_path / "t.json"
    code, stdout, err = run(
        capsys, "throw", str(run_dir), "--target", "0.4", *QUICK, "--json", str(out), "--no-gif"
    )
    assert code == 0, err
    assert "unknown under the ground truth (recorded data" in stdout
    assert json.loads(out.read_text())["distance_true"] is None
    plan = plan_throw(as_planner(str(run_dir)), 0.8, starts=2, iterations=2, progress=False)
    assert math.isnan(float(plan.distance_true[0]))
    # a run whose data is gone: the config's CM truth, and a warning that says so
    with pytest.warns(UserWarning, match=r"data of run .* cannot be read .*config's system"):
        planner = as_planner(str(_run_of(tmp_path, "data_gone", tmp_path / "missing")))
    assert (planner.truth_contact_model, planner.truth_known) == ("CM", True)


def test_a_target_beyond_reach_is_warned_and_the_miss_said(capsys, tmp_path):
    """throw --target 100 planned silently towards a point no throw within the bounds
    reaches; warnings came as Python's, with a source line."""
    out = str(tmp_path / "t.json")
    code, _, err = run(
        capsys, "throw", "BD1-ground", "--target", "100", *QUICK, "--json", out, "--no-gif"
    )
    assert code == 0, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines[0] == (
        "diffcontact throw: warning: throw: target(s) [100.0] are beyond reach from x = 0 in "
        "0.2 s (at most 0.8 m at max_speed 4 m/s and max_spin 30 rad/s): the plan gets as "
        "close as it can"
    ), err
    assert len(lines) == 2 and lines[1].startswith(
        "diffcontact throw: warning: target not reached: the best plan ends 100 from it"
    ), err


def test_a_gif_of_another_name_is_refused(capsys, tmp_path):
    """``--gif shot.png`` wrote GIF bytes under the .png name, after the planning."""
    code, _, err = run(
        capsys, "billiards", "BP5-e", "--target", "0.5", "0.5", "--gif", str(tmp_path / "s.png")
    )
    assert_usage_error(code, err, "--gif", "must end in .gif")
    assert not (tmp_path / "s.png").exists()


def test_json_replaces_only_a_plan_unless_forced(capsys, tmp_path):
    """``--json rec.npz`` replaced a recording with the plan's JSON; ``--json x.gif --gif
    x.gif`` wrote both to one file (the GIF won)."""
    recording = tmp_path / "rec.json"
    recording.write_text('{"traj": [1, 2, 3]}')
    base = ["throw", "BD1-ground", "--target", "0.4", *QUICK, "--no-gif"]
    code, _, err = run(capsys, *base, "--json", str(recording))
    assert_usage_error(code, err, "--json", "is not a plan written by billiards or throw")
    assert recording.read_text() == '{"traj": [1, 2, 3]}'
    code, _, err = run(capsys, *base, "--json", str(tmp_path / "rec.npz"))
    assert_usage_error(code, err, "--json", "must end in .json")
    same = str(tmp_path / "x.json")
    code, _, err = run(capsys, "throw", "BD1-ground", "--target", "0.4", *QUICK, "--json", same,
                       "--gif", same)  # fmt: skip
    assert_usage_error(code, err, "--gif", "must end in .gif")
    # a plan is replaced by the next one; anything with --force
    plan = tmp_path / "plan.json"
    assert run(capsys, *base, "--json", str(plan))[0] == 0
    assert run(capsys, *base, "--json", str(plan))[0] == 0
    assert json.loads(plan.read_text())["task"]
    code, _, err = run(capsys, *base, "--json", str(recording), "--force")
    assert code == 0, err
    assert "variables" in json.loads(recording.read_text())


TABLE = "allowed: x in [0.13, 0.87], y in [0.13, 0.87], where ball 2, of radius 0.13, fits"
REACH = "allowed: x in [-4000, 4000], within 1000 times the 4 m a throw from x = 0 covers in 1 s"


@pytest.mark.parametrize(
    ("argv", "needles"),
    [
        (["billiards", "BP5", "--target", "1e300", "0.5"], ["[1e+300, 0.5] is outside", TABLE]),
        # (argparse took -1e300 for an option: "expected 2 arguments")
        (["billiards", "BP5", "--target", "-1e300", "0.5"], ["[-1e+300, 0.5] is outside", TABLE]),
        (["billiards", "BP5", "--target", "1e30", "0.5"], ["[1e+30, 0.5] is outside", TABLE]),
        # ("target must be finite (x, y) points, got shape (1, 2)")
        (["billiards", "BP5", "--target", "nan", "0.5"], ["[nan, 0.5] is not finite", TABLE]),
        (["billiards", "BP5", "--target", "0.5", "-inf"], ["[0.5, -inf] is not finite", TABLE]),
        # (planned, exit 0: "velocity = (0, 0)", a distance of 1e+300)
        (["throw", "BD1-ground", "--target", "1e300"], ["x = 1e+300 is far out of reach", REACH]),
        (["throw", "BD1-ground", "--target", "-1e300"], ["x = -1e+300 is far out of", REACH]),
        (["throw", "BD1-ground", "--target", "1e30"], ["x = 1e+30 is far out of reach", REACH]),
        (["throw", "BD1-ground", "--target", "nan"], ["x = nan is not finite", REACH]),
        (["throw", "BD1-ground", "--target", "-inf"], ["x = -inf is not finite", REACH]),
    ],
)  # fmt: skip
def test_absurd_targets_are_refused_with_the_allowed_range(capsys, argv, needles):
    """Targets that are not finite or far outside where a shot can go: one line naming the
    target and the allowed range, exit status 2."""
    code, _, err = run(capsys, *argv, "--quiet", "--no-gif")
    assert_usage_error(code, err, "error: target ", *needles)


@pytest.mark.parametrize(
    "start",
    [
        ["1e300", "0.5"],  # (planned as a throw at rest, exit 0)
        ["0", "1e300"],  # ("simulation failed: z0 contains NaN or infinite values")
        ["-4000001", "0.5"],
    ],
)
def test_a_start_too_far_from_the_origin_is_refused(capsys, start):
    """A throw's start where float64 cannot resolve its motion: one line naming the start
    and the allowed distance, exit status 2."""
    code, _, err = run(capsys, "throw", "BD1-ground", "--target", "1", "--start", *start,
                       "--quiet", "--no-gif")  # fmt: skip
    assert_usage_error(code, err, "error: start (", "is too far from the origin",
                       "within 1e+06 times the 4 m a throw covers in 1 s")  # fmt: skip


def test_absurd_targets_are_refused_by_the_python_api_too():
    """plan_billiards and plan_throw raise ControlError (the module's error for bad input)
    naming the target and the allowed range; a table no wall bounds refuses targets
    FAR times beyond the cue's reach."""
    import math

    import diffcontact as dc
    from diffcontact.control import ControlError
    from diffcontact.control.tasks import FAR, plan_billiards, plan_throw

    quick = {"starts": 1, "iterations": 1, "progress": False}
    for target in ((1e300, 0.5), (-1e300, 0.5), (math.inf, 0.5), (0.5, math.nan)):
        with pytest.raises(ControlError, match=r"allowed: x in \[0\.13, 0\.87\]"):
            plan_billiards("BP5", target, **quick)
    with pytest.raises(ControlError, match=r"\[1e\+300, 0\.5\] is outside the table"):
        plan_billiards("BP5", [[0.5, 0.5], [1e300, 0.5]], **quick)  # (one of two)
    for target in (1e300, -1e300, 1e30, math.nan, [0.5, math.inf]):
        with pytest.raises(ControlError, match=r"allowed: x in \[-4000, 4000\]"):
            plan_throw("BD1-ground", target, **quick)
    # no walls: the table is open; the cue covers at most 0.1 * 4 * sqrt(2) m in 0.1 s
    cfg = {"name": "open", "type": "bouncing_masses", "masses": [0.1, 0.2, 0.3],
           "radii": [0.05] * 3, "mu": 0.2, "cor": 0.9, "dt": 0.01, "horizon": 0.1}  # fmt: skip
    open_table = dc.load_system(cfg)
    with pytest.raises(ControlError, match=r"\[1e\+300, 0\.5\] is far out of reach \(allowed: x"):
        plan_billiards(open_table, (1e300, 0.5), time=0.1, **quick)
    with pytest.raises(ControlError, match="is not finite"):
        plan_billiards(open_table, (math.nan, 0.5), time=0.1, **quick)
    near = FAR * 0.1 * 4 * math.sqrt(2) / 2  # well within the range: planned
    plan = plan_billiards(open_table, (near, 0.5), time=0.1, **quick)
    assert plan.target.tolist() == [[near, 0.5]]

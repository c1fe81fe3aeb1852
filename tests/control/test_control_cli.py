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

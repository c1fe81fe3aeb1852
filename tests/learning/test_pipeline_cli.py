"""The whole job through the command line: generate -> train -> evaluate, and the demo."""

import json
import math
import subprocess
import sys

import pytest

from diffcontact import demo as demo_mod
from diffcontact.cli import main

pytestmark = pytest.mark.filterwarnings("ignore:.*LeafSpec")


def test_generate_train_evaluate_through_the_cli(tmp_path, capsys):
    data, run, ev = tmp_path / "data", tmp_path / "run", tmp_path / "eval"
    code = main(
        ["generate", "CP3", "--out", str(data), "--n-train", "8", "--n-val", "2", "--n-test", "2",
         "--seed", "1", "--quiet"]
    )  # fmt: skip
    assert code == 0
    assert {p.name for p in data.iterdir()} == {"metadata.json", "train.npz", "val.npz", "test.npz"}
    code = main(
        ["train", str(data), "--out", str(run), "--epochs", "2", "--batch-size", "4",
         "--hidden", "8,8", "--quiet"]
    )  # fmt: skip
    assert code == 0
    learned = json.loads((run / "learned.json").read_text())
    assert learned["finished"] and learned["global_step"] == 4  # 2 epochs x 2 batches
    assert (run / "model.pt").is_file() and (run / "logs" / "metrics.csv").is_file()
    capsys.readouterr()
    code = main(["evaluate", str(run), "--out", str(ev), "--steps", "20", "--n-gif", "1"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "m2/m1" in printed and "e_P" in printed and "relative error" in printed
    metrics = json.loads((ev / "metrics.json").read_text())
    assert metrics["task"] == "CP3" and metrics["model"] == "CM-CD-CLNN"
    assert metrics["n_test"] == 2 and metrics["steps"] == 20
    assert math.isfinite(metrics["rel_err_mean"]) and metrics["rel_err_mean"] > 0
    assert metrics["mass_ratios"]["true"] == pytest.approx([2.0, 1.5])
    assert metrics["mu"]["true"] == [0.5] * 3 and metrics["cor"]["true"] == [0.0] * 3
    assert metrics["mu"]["learned"] == pytest.approx(learned["learned"]["mu"])
    for name in ("rel_error.png", "energy.png", "training.png", "rollout.gif", "rollout.npz"):
        assert (ev / name).is_file(), name
    # the same run again without --resume is refused, with one line and exit 2
    code = main(["train", str(data), "--out", str(run), "--epochs", "2", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "already holds a run" in err and err.count("\n") == 1
    # resuming the finished run to more epochs continues it
    code = main(
        ["train", str(data), "--out", str(run), "--epochs", "3", "--batch-size", "4",
         "--hidden", "8,8", "--resume", "--quiet"]
    )  # fmt: skip
    assert code == 0
    assert json.loads((run / "learned.json").read_text())["global_step"] == 6


def test_bad_arguments_through_the_console_script(tmp_path):
    """Through a real process: one line on stderr, exit status 2, no traceback."""
    cases = [
        (["train", str(tmp_path), "--out", str(tmp_path / "r"), "--physics-lr", "-1"],
         "--physics-lr"),
        (["train", str(tmp_path), "--out", str(tmp_path / "r"), "--schedule", "step"],
         "--schedule"),
        (["demo", "--epochs", "0"], "--epochs"),
        (["evaluate", str(tmp_path / "nothing")], "nothing"),
    ]  # fmt: skip
    for argv, text in cases:
        proc = subprocess.run(
            [sys.executable, "-m", "diffcontact", *argv], capture_output=True, text=True
        )
        assert proc.returncode == 2, (argv, proc.stderr)
        assert text in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
        assert proc.stderr.strip().count("\n") == 0, proc.stderr


def test_learning_demo_runs_end_to_end_on_a_tiny_budget(tmp_path, monkeypatch, capsys):
    """The demo's learning part with 6 training chunks and 1 epoch: files and the table.

    (The real budget, 40 epochs on 200 chunks, is what ``make demo`` runs; its
    checks are asserted there, not here.)
    """
    small = dict(demo_mod.LEARNING_DEMO, n_train=6, n_val=2, n_test=2, batch_size=3)
    monkeypatch.setattr(demo_mod, "LEARNING_DEMO", small)
    ok = demo_mod.learning_demo(tmp_path, epochs=1)
    out = capsys.readouterr().out
    assert ok is False  # one epoch does not learn CP3: the checks say so
    assert "[FAILED] mass ratios within 2 % of the truth" in out
    rows = [line for line in out.splitlines() if line.split()[:1] in (["m2/m1"], ["mu"], ["e_P"])]
    assert len(rows) == 3 and len({line.index(".") for line in rows}) == 1  # one column
    assert "(95% CI)" in out
    run = tmp_path / "runs" / "CP3-CM-CD-CLNN"
    assert (run / "evaluation" / "metrics.json").is_file()
    assert (run / "evaluation" / "rel_error.png").is_file()
    # a second demo starts its run again instead of refusing the existing folder
    assert demo_mod.learning_demo(tmp_path, epochs=1) is False

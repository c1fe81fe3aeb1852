"""``diffcontact generate``: one-line errors, summaries, reuse."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from diffcontact.learning.data.cli import register_cli
from diffcontact.learning.data.format import load_dataset

from .support import BP5, read_only_storage, short_config


def cli(capsys, *argv: str) -> tuple[int, str, str]:
    parser = argparse.ArgumentParser(prog="diffcontact")
    register_cli(parser.add_subparsers(dest="command"))
    args = parser.parse_args(list(argv))
    code = args.func(args)
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code: int, err: str, *needles: str) -> None:
    assert code == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("diffcontact generate: error: "), err
    for needle in needles:
        assert needle in lines[0], lines[0]


def test_cli_bad_input_exits_2(recorded, tmp_path, capsys):
    out = str(tmp_path / "out")
    code, _, err = cli(capsys, "generate", "NoSuchTask", "--out", out)
    assert_one_line_error(code, err, "unknown task 'NoSuchTask'")
    code, _, err = cli(capsys, "generate", "--out", out)
    assert_one_line_error(code, err, "give TASK_OR_CONFIG")
    code, _, err = cli(capsys, "generate", "--from-arrays", str(tmp_path / "no.npz"), "--out", out)
    assert_one_line_error(code, err, "does not exist")
    np.savez(tmp_path / "wrong.npz", x=recorded)
    code, _, err = cli(
        capsys, "generate", "--from-arrays", str(tmp_path / "wrong.npz"), "--config", "BP5",
        "--out", out,
    )  # fmt: skip
    assert_one_line_error(code, err, "no array named 'traj'", "found: x")
    np.savez(tmp_path / "rec.npz", traj=recorded)
    code, _, err = cli(
        capsys, "generate", "--from-arrays", str(tmp_path / "rec.npz"), "--config", "CP3",
        "--out", out,
    )  # fmt: skip
    assert_one_line_error(code, err, "(N, T, 2, 3, 2)", "got (12, 20, 2, 5, 2)")
    code, _, err = cli(
        capsys, "generate", "--from-arrays", str(tmp_path / "rec.npz"), "--config", "BP5",
        "--n-train", "5", "--out", out,
    )  # fmt: skip
    assert_one_line_error(code, err, "--n-train does not apply with --from-arrays")
    code, _, err = cli(capsys, "generate", "BP5", "--dt", "0.01", "--out", out)
    assert_one_line_error(code, err, "--dt applies only with --from-arrays")
    # --dt against the file's own dt (--dt won silently, and the metadata said 0.02)
    np.savez(tmp_path / "rec_dt.npz", traj=recorded, dt=0.01)
    code, _, err = cli(
        capsys, "generate", "--from-arrays", str(tmp_path / "rec_dt.npz"), "--config", "BP5",
        "--dt", "0.02", "--out", out,
    )  # fmt: skip
    assert_one_line_error(code, err, "--dt 0.02 contradicts the dt 0.01 stored in")
    # --dt -0.01 said "in [0, inf)", and then --dt 0 was refused with another message
    from diffcontact.testing import assert_usage_error, run_cli

    for dt in ("0", "-0.01"):
        code, _, err = run_cli(capsys, "generate", "--from-arrays", str(tmp_path / "rec_dt.npz"),
                               "--config", "BP5", "--dt", dt, "--out", out)  # fmt: skip
        assert_usage_error(code, err, "--dt", "must be a finite number > 0")
    assert not Path(out).exists()


def test_cli_from_arrays_summary_and_reuse(recorded, tmp_path, capsys):
    config = tmp_path / "bp5.yaml"
    config.write_text(json.dumps(BP5))  # JSON is YAML
    np.savez(tmp_path / "rec.npz", traj=recorded, dt=0.01)
    out = tmp_path / "ds"
    argv = ["generate", "--from-arrays", str(tmp_path / "rec.npz"), "--config", str(config)]
    code, stdout, err = cli(capsys, *argv, "--out", str(out))
    assert code == 0, err
    assert "BP5 dataset (arrays) written" in stdout
    assert "train: 10 trajectories x 20 states" in stdout and "% of chunks" in stdout
    assert str(out / "train.npz") in stdout
    code, stdout, _ = cli(capsys, *argv, "--out", str(out))
    assert code == 0 and "reused" in stdout
    code, _, err = cli(capsys, *argv, "--seed", "3", "--out", str(out))
    assert_one_line_error(code, err, "different arguments", "seed (0 there, 3 requested)")


def test_cli_reuses_a_finished_dataset_on_read_only_storage(
    recorded, bp5_dir, tmp_path, monkeypatch, capsys
):
    """``OSError: [Errno 30] Read-only file system: '.../.generating.json'``, exit 1."""
    np.savez(tmp_path / "rec.npz", traj=recorded, dt=0.01)
    argv = ["generate", "--from-arrays", str(tmp_path / "rec.npz"), "--config", "BP5"]
    out = tmp_path / "ds"
    code, _, err = cli(capsys, *argv, "--out", str(out), "--quiet")
    assert code == 0, err
    attempts = read_only_storage(monkeypatch, tmp_path)
    code, stdout, err = cli(capsys, *argv, "--out", str(out))
    assert code == 0 and "reused" in stdout and err == "", err
    assert attempts == []
    # a simulated one: the same arguments as bp5_dir's
    folder = tmp_path / "sim"
    monkeypatch.undo()
    folder.mkdir()
    for p in bp5_dir.iterdir():
        (folder / p.name).write_bytes(p.read_bytes())
    config = tmp_path / "bp5.json"
    config.write_text(json.dumps(BP5))
    attempts = read_only_storage(monkeypatch, tmp_path)
    code, stdout, err = cli(
        capsys, "generate", str(config), "--out", str(folder), "--n-train", "6", "--n-val", "3",
        "--n-test", "3",
    )  # fmt: skip
    assert code == 0 and "reused" in stdout and err == "", err
    assert attempts == []


def test_cli_simulates_a_tiny_dataset(tmp_path, capsys):
    config = tmp_path / "tiny.json"
    config.write_text(json.dumps(short_config("BP5", 0.1)))  # 10 states
    out = tmp_path / "ds"
    code, stdout, err = cli(
        capsys, "generate", str(config), "--out", str(out), "--n-train", "2", "--n-val", "1",
        "--n-test", "1", "--seed", "2", "--quiet",
    )  # fmt: skip
    assert code == 0, err
    assert stdout == ""
    ds = load_dataset(out)
    assert ds.counts == {"train": 2, "val": 1, "test": 1}
    assert ds.metadata["seeds"] == {"train": 2000, "val": 2001, "test": 2002}


def test_cli_refuses_an_infinite_noise_std(tmp_path, capsys):
    """``--noise-std inf`` wrote a dataset of infinite chunks, found only by ``train``."""
    from diffcontact.learning.data.generate import generate_dataset

    for value in ("inf", "nan", "-1"):
        with pytest.raises(SystemExit) as exc:
            cli(capsys, "generate", "BP5-e", "--noise-std", value, "--out", str(tmp_path / "x"))
        assert exc.value.code == 2
        assert "--noise-std: must be a finite number in [0, inf)" in capsys.readouterr().err
    # where inf means "off" it stays accepted (--impact-tol)
    parser = argparse.ArgumentParser(prog="diffcontact")
    register_cli(parser.add_subparsers(dest="command"))
    args = parser.parse_args(
        ["generate", "--out", "o", "--from-arrays", "a.npz", "--impact-tol", "inf"]
    )
    assert args.impact_tol == float("inf")
    with pytest.raises(ValueError, match=r"noise_std must be a finite number in \[0, inf\)"):
        generate_dataset(BP5, tmp_path / "y", n_train=2, n_val=0, n_test=0, noise_std=np.inf)
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()

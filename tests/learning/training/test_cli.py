"""``diffcontact train``: bad input gives one line on stderr and exit status 2."""

from __future__ import annotations

import argparse
import json

import pytest
import torch

from diffcontact.learning.training.cli import register_cli
from diffcontact.learning.training.options import TrainingInputError
from diffcontact.learning.training.run import train


def _run_cli(argv, capsys):
    parser = argparse.ArgumentParser(prog="diffcontact")
    register_cli(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    code = args.func(args)
    return code, capsys.readouterr().err


def test_cli_bad_input_gives_one_line_and_exit_2(bp5_data, tmp_path, capsys):
    out = str(tmp_path / "run")
    recording = tmp_path / "two_balls.npz"  # a file: "dataset folder ... does not exist"
    recording.write_bytes(b"")
    cases = [
        (["train", str(tmp_path / "missing"), "--out", out], "does not exist"),
        (
            ["train", str(recording), "--out", out],
            f"{recording} is a file, not a dataset folder: a recording",
        ),
        (["train", str(recording), "--out", out], f"generate --from-arrays {recording} --out"),
        (
            ["train", str(bp5_data / "metadata.json"), "--out", out],
            f"pass the folder that holds it, {bp5_data}",
        ),
        (["train", str(bp5_data), "--model", "XX-CD-CLNN", "--out", out], "unknown model"),
        (["train", str(bp5_data), "--dtype", "float16", "--out", out], "dtype"),
        (["train", str(bp5_data), "--threads", "0", "--out", out], "threads must be"),
        (["train", str(bp5_data), "--threads", "many", "--out", out], "threads must be"),
        # (it was ignored: CM has no regulariser)
        (["train", str(bp5_data), "--eps", "0.1", "--out", out], "eps is the regulariser of"),
    ]
    if not torch.cuda.is_available():
        cases.append((["train", str(bp5_data), "--device", "cuda", "--out", out], "CUDA"))
    for argv, text in cases:
        code, err = _run_cli(argv, capsys)
        assert code == 2, argv
        assert text in err and err.count("\n") == 1, err
    # an out dir holding a different run
    run = tmp_path / "other"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.ckpt").write_bytes(b"")
    other = {"format_version": 1, "model": "CM-CD-CLNN", "lr": 0.5, "versions": {"diffcontact": ""}}
    (run / "run.json").write_text(json.dumps(other))
    code, err = _run_cli(["train", str(bp5_data), "--resume", "--out", str(run)], capsys)
    assert code == 2 and "different run" in err and err.count("\n") == 1
    code, err = _run_cli(["train", str(bp5_data), "--out", str(run)], capsys)
    assert code == 2 and "already holds a run" in err
    with pytest.raises(TrainingInputError, match="epochs"):
        train(bp5_data, tmp_path / "x", epochs=0)
    with pytest.raises(TrainingInputError, match="strategy"):
        train(bp5_data, tmp_path / "x", epochs=1, strategy="nonsense", progress=False)
    assert not (tmp_path / "x").exists()  # nothing written before the checks pass


@pytest.mark.parametrize(
    ("argv", "text"),
    [
        # model_options won silently over the flag
        (["--hidden", "16", "--model-option", "hidden=[8]"], "hidden given twice"),
        (["--model", "CMr-CD-CLNN", "--eps", "0.2", "--model-option", "eps=0.1"],
         "eps given twice"),
        # CM has no regulariser: dropped silently through model_options
        (["--model-option", "eps=0.5"], "eps is the regulariser of the CMr models"),
        # hidden applies to the baselines: only eps is out of place
        (["--model", "MLP-CD-CLNN", "--hidden", "16", "--eps", "learnable"],
         "eps: option(s) of the physical models only; MLP-CD-CLNN takes hidden"),
    ],
)  # fmt: skip
def test_options_given_twice_or_out_of_place_are_refused(bp5_data, tmp_path, capsys, argv, text):
    out = tmp_path / "run"
    code, err = _run_cli(["train", str(bp5_data), "--out", str(out), *argv], capsys)
    assert code == 2 and text in err and err.count("\n") == 1, err
    assert not out.exists()

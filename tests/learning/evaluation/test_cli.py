"""``diffcontact evaluate``: bad input gives one line on stderr and exit status 2."""

from __future__ import annotations

import json

import pytest

from .support import cli


def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, dataset, capsys):
    run = tmp_path / "run"
    assert cli(["evaluate", str(run)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("diffcontact evaluate: error:") and "does not exist" in err
    assert err.count("\n") == 1
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"data_dir": str(dataset)}))
    assert cli(["evaluate", str(run)]) == 2
    assert "no trained model" in capsys.readouterr().err
    (run / "model.pt").write_bytes(b"")
    assert cli(["evaluate", str(run), "--data", str(tmp_path / "nodata")]) == 2
    err = capsys.readouterr().err
    assert "test data not found" in err and err.count("\n") == 1
    with pytest.raises(SystemExit) as exc:
        cli(["evaluate", str(run), "--n-gif", "-1"])
    assert exc.value.code == 2

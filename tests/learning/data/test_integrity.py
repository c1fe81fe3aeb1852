"""Files that cannot lie or half-exist: metadata checksum, truncated and garbage data files."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from diffcontact.learning.data.format import DatasetError, load_dataset, metadata_checksum
from diffcontact.testing import assert_usage_error, run_cli

from .support import copy_dataset, sha256

FORMAT_LOG = "diffcontact.learning.data.format"


def _edit_metadata(folder, change, sign=False):
    meta = json.loads((folder / "metadata.json").read_text())
    change(meta)
    if sign:
        meta["metadata_sha256"] = metadata_checksum(meta)
    (folder / "metadata.json").write_text(json.dumps(meta, indent=2))


def test_metadata_carries_its_own_checksum(bp5_dir, tmp_path, capsys):
    meta = json.loads((bp5_dir / "metadata.json").read_text())
    assert meta["metadata_sha256"] == metadata_checksum(meta)
    folder = copy_dataset(bp5_dir, tmp_path)

    def halve_dt(meta):
        meta["config"]["dt"] = meta["dt"] = meta["dt"] / 2

    _edit_metadata(folder, halve_dt)
    with pytest.raises(DatasetError, match=r"metadata\.json does not match its checksum"):
        load_dataset(folder)
    out = tmp_path / "run"
    code, _, err = run_cli(capsys, "train", str(folder), "--out", str(out), "--quiet")
    assert_usage_error(code, err, "metadata.json", "checksum")
    assert not out.exists()
    # a data file changed and its checksum in metadata.json updated: the metadata's fails
    folder = copy_dataset(bp5_dir, tmp_path / "b")
    with np.load(folder / "test.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays["traj"] = arrays["traj"] * 1.01
    np.savez(folder / "test.npz", **arrays)
    _edit_metadata(folder, lambda m: m["files"].update({"test.npz": sha256(folder / "test.npz")}))
    with pytest.raises(DatasetError, match=r"metadata\.json does not match its checksum"):
        load_dataset(folder)


@pytest.mark.parametrize("dt", [0.005, "0.01", None, True])
def test_metadata_whose_dt_is_not_its_configs_is_refused(bp5_dir, tmp_path, dt):
    """A hand-edited, re-signed metadata.json whose dt is not the config's had loaded:
    Dataset.dt said one step, the data's system another."""
    folder = copy_dataset(bp5_dir, tmp_path)
    _edit_metadata(folder, lambda m: m.update(dt=dt), sign=True)
    with pytest.raises(DatasetError, match=r"'dt' is .*, but its config steps at dt = 0\.01 s"):
        load_dataset(folder)


def test_metadata_of_earlier_versions_loads_with_one_warning(bp5_dir, tmp_path, caplog):
    folder = copy_dataset(bp5_dir, tmp_path)
    _edit_metadata(folder, lambda m: m.pop("metadata_sha256"))
    with caplog.at_level(logging.WARNING, logger=FORMAT_LOG):
        load_dataset(folder)
        ds = load_dataset(folder)
    warned = [r.getMessage() for r in caplog.records if "has no checksum" in r.getMessage()]
    assert len(warned) == 1 and "metadata.json" in warned[0]
    assert len(ds.split("train")) == 6


def test_truncated_and_garbage_files_name_the_file(bp5_dir, tmp_path, capsys):
    folder = copy_dataset(bp5_dir, tmp_path)
    raw = (folder / "train.npz").read_bytes()
    (folder / "train.npz").write_bytes(raw[: len(raw) // 2])
    code, _, err = run_cli(capsys, "train", str(folder), "--out", str(tmp_path / "r"), "--quiet")
    assert_usage_error(code, err, "train.npz")
    (folder / "metadata.json").write_text('{"format_version": 1, "task": ')
    with pytest.raises(DatasetError, match=r"metadata\.json is not valid JSON"):
        load_dataset(folder)
    # a garbage .npz whose checksums were made to match: the reader still names it
    folder = copy_dataset(bp5_dir, tmp_path / "b")
    (folder / "val.npz").write_bytes(b"PK\x03\x04 this is not a zip archive")
    _edit_metadata(
        folder, lambda m: m["files"].update({"val.npz": sha256(folder / "val.npz")}), sign=True
    )
    with pytest.raises(DatasetError, match=r"val\.npz is not a readable \.npz file"):
        load_dataset(folder).split("val")


def test_from_arrays_reports_bad_files_in_one_line(recorded, tmp_path, capsys):
    good = tmp_path / "traj.npz"
    np.savez(good, traj=recorded, dt=np.array([0.01, 0.01]))
    out = str(tmp_path / "out")
    argv = ["generate", "--from-arrays", str(good), "--config", "BP5", "--out", out]
    code, _, err = run_cli(capsys, *argv)
    assert_usage_error(code, err, "traj.npz", "'dt' must be one number")
    np.savez(good, traj=recorded)
    raw = good.read_bytes()
    for name, data in (("cut.npz", raw[: len(raw) // 2]), ("junk.npz", b"\x00" * 64)):
        (tmp_path / name).write_bytes(data)
        argv[2] = str(tmp_path / name)
        code, _, err = run_cli(capsys, *argv)
        assert_usage_error(code, err, name, "cannot read")

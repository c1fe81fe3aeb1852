"""Every bad file or config a user can hand the command line gives exit status 2 and one line.

A ``dt`` array in a ``--from-arrays`` file, an ``.npy`` header that claims a
huge shape, YAML/JSON nested thousands deep, configs whose sizes would run for
days or exhaust memory, and strings or booleans where numbers belong.
"""

from __future__ import annotations

import io
import json
import zipfile

import numpy as np
import pytest

import diffcontact as dc
from diffcontact.io import read_npz
from diffcontact.systems.config import ALLOW_LARGE_ENV, MAX_STATES, state_bytes
from diffcontact.testing import assert_usage_error, run_cli

BALL = {
    "type": "bouncing_masses",
    "masses": [1.0],
    "radii": [0.1],
    "walls": [[0.0, 1.0, 0.0]],
    "dt": 0.01,
    "horizon": 0.2,
}


def _forged_npy(shape: tuple[int, ...]) -> bytes:
    """An .npy header claiming ``shape`` of float64, followed by 64 bytes only."""
    buf = io.BytesIO()
    header = {"descr": "<f8", "fortran_order": False, "shape": shape}
    np.lib.format.write_array_header_1_0(buf, header)
    return buf.getvalue() + bytes(64)


def _forged_npz(path, name: str, shape: tuple[int, ...], deflate: bool = False) -> None:
    method = zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED
    with zipfile.ZipFile(path, "w", compression=method) as zf:
        zf.writestr(f"{name}.npy", _forged_npy(shape))


@pytest.fixture
def recorded(tmp_path):
    """A small recorded-data file: (traj, config path)."""
    system = dc.load_system(BALL)
    z0 = system.sample_initial_conditions(3, seed=0)
    traj = system.simulate(z0, 19, progress=False).numpy()
    config = tmp_path / "ball.json"
    config.write_text(json.dumps(BALL))
    return traj, config


# ------------------------------------------------------------------ arrays files


def test_dt_array_in_from_arrays_file(tmp_path, capsys, recorded):
    traj, config = recorded
    path = tmp_path / "rec.npz"
    np.savez(path, traj=traj, dt=np.array([0.01, 0.01]))
    code, _, err = run_cli(
        capsys, "generate", "--from-arrays", str(path), "--config", str(config),
        "--out", str(tmp_path / "d"), "--quiet",
    )  # fmt: skip
    assert_usage_error(code, err, "entry 'dt' must be one number", "(2,)")


def test_forged_npy_header_is_refused_before_allocating(tmp_path, capsys, recorded):
    _, config = recorded
    path = tmp_path / "forged.npz"
    _forged_npz(path, "traj", (2_000_000, 1_000_000))  # 14.6 TiB claimed, 64 bytes stored
    code, _, err = run_cli(
        capsys, "generate", "--from-arrays", str(path), "--config", str(config),
        "--out", str(tmp_path / "d"), "--quiet",
    )  # fmt: skip
    assert_usage_error(code, err, "array 'traj'", "14.6 TiB", "64 bytes")
    assert not (tmp_path / "d").exists()
    # the converter's input file too, and a forged .npy file
    _forged_npz(path, "x", (2_000_000, 1_000_000), deflate=True)
    code, _, err = run_cli(
        capsys, "convert", "positions", str(path), "--config", str(config),
        "--out", str(tmp_path / "c.npz"),
    )  # fmt: skip
    assert_usage_error(code, err, "array 'x'", "14.6 TiB")
    npy = tmp_path / "forged.npy"
    npy.write_bytes(_forged_npy((1 << 20, 1 << 20, 8)))
    code, _, err = run_cli(
        capsys, "generate", "--from-arrays", str(npy), "--config", str(config),
        "--out", str(tmp_path / "d"), "--quiet",
    )  # fmt: skip
    assert_usage_error(code, err, "the .npy array", "64 TiB")


def test_read_npz_checks_headers_and_reads_good_files(tmp_path):
    good = tmp_path / "good.npz"
    a, b = np.arange(12.0).reshape(3, 4), np.array(3, dtype=np.int64)
    np.savez_compressed(good, a=a, b=b)
    arrays, members = read_npz(good)
    assert members == ["a", "b"] and np.array_equal(arrays["a"], a) and arrays["b"] == 3
    arrays, _ = read_npz(io.BytesIO(good.read_bytes()), ["b", "absent"])
    assert list(arrays) == ["b"]
    np.save(tmp_path / "one.npy", a)
    assert np.array_equal(read_npz(tmp_path / "one.npy")[0][""], a)
    # a header claiming a few bytes more than stored is refused too (truncated)
    raw = (tmp_path / "one.npy").read_bytes()
    (tmp_path / "cut.npy").write_bytes(raw[:-8])
    with pytest.raises(ValueError, match=r"3x4 array of float64 \(96 bytes\), but 88 bytes"):
        read_npz(tmp_path / "cut.npy")
    with pytest.raises(ValueError, match="BadZipFile"):
        read_npz(io.BytesIO(good.read_bytes()[:200]))
    np.save(tmp_path / "obj.npy", np.array([{}, 1], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match="Python objects"):
        read_npz(tmp_path / "obj.npy")
    # a text file said "the magic string is not correct; expected b'\\x93NUMPY'"
    (tmp_path / "x.csv").write_text("6.9559,1.0\n2.0,3.0\n")
    with pytest.raises(ValueError, match=r"not an \.npz or \.npy file \(it starts with b'6\.9559'"):
        read_npz(tmp_path / "x.csv")


# ---------------------------------------------------------------------- configs


def test_deeply_nested_yaml_and_json(tmp_path, capsys):
    deep_yaml = tmp_path / "deep.yaml"
    deep_yaml.write_text("[" * 20_000 + "]" * 20_000 + "\n")
    code, _, err = run_cli(capsys, "simulate", str(deep_yaml), "--out", str(tmp_path / "x.npz"))
    assert_usage_error(code, err, "deep.yaml", "nested too deeply")
    deep_map = tmp_path / "deep2.yaml"
    deep_map.write_text("a:\n" + "".join(" " * (i + 1) + "b:\n" for i in range(3000)))
    code, _, err = run_cli(capsys, "simulate", str(deep_map), "--out", str(tmp_path / "x.npz"))
    assert_usage_error(code, err, "deep2.yaml", "nested too deeply")
    deep_json = tmp_path / "deep.json"
    deep_json.write_text('{"type": ' + "[" * 20_000 + "]" * 20_000 + "}")
    code, _, err = run_cli(capsys, "simulate", str(deep_json), "--out", str(tmp_path / "x.npz"))
    assert_usage_error(code, err, "deep.json", "nested too deeply")
    # nesting below Python's recursion limit but beyond any config: refused by depth
    nested: list = []
    for _ in range(50):
        nested = [nested]
    with pytest.raises(ValueError, match="nested more than 16 levels"):
        dc.load_config({**BALL, "walls": nested})


def test_duplicate_keys_are_refused_and_exponent_numbers_read(tmp_path, capsys):
    """A key given twice took its last value silently (yaml.safe_load, json.loads); YAML
    1.1 read ``1e-3`` as a string, which validation then refused as not a number."""
    dup = tmp_path / "dup.yaml"
    dup.write_text("type: bouncing_masses\nmasses: [1.0]\nradii: [0.1]\nradii: [0.5]\n")
    code, _, err = run_cli(capsys, "simulate", str(dup), "--out", str(tmp_path / "x.npz"))
    assert_usage_error(code, err, "dup.yaml", "'radii' is given twice", "line 3 and line 4")
    nested = tmp_path / "nested.yaml"
    nested.write_text("mu: {pairs: 0.1, walls: 0.2, pairs: 0.3}\n")
    with pytest.raises(ValueError, match="'pairs' is given twice"):
        dc.load_config(nested)
    dup_json = tmp_path / "dup.json"
    dup_json.write_text('{"type": "bouncing_masses", "dt": 0.01, "dt": 0.02}')
    with pytest.raises(ValueError, match=r"dup\.json.*'dt' is given twice"):
        dc.load_config(dup_json)
    sci = tmp_path / "sci.yaml"
    sci.write_text(
        "type: bouncing_masses\nmasses: [1.0]\nradii: [1e-1]\nwalls: [[0, 1, 0]]\n"
        "dt: 1e-2\nhorizon: 5e-1\ngravity: 9.81\nmu: 2E-1\n"
    )
    config = dc.load_config(sci)
    assert (config.dt, config.horizon, config.radii, config.mu) == (0.01, 0.5, [0.1], 0.2)


def test_yaml_integers_and_booleans_are_read_by_yaml_1_2(tmp_path):
    """PyYAML's YAML 1.1 read ``010`` as eight (octal) and ``yes`` / ``off`` as booleans,
    so a typo passed as a setting; YAML 1.2 (and JSON) read ten and strings."""
    from diffcontact.systems.config_file import read_config_file

    path = tmp_path / "scalars.yaml"
    path.write_text("a: 010\nb: 0o10\nc: 0x1F\nd: -5\ne: yes\nf: off\ng: true\nh: False\n")
    assert read_config_file(path) == {
        "a": 10, "b": 8, "c": 31, "d": -5, "e": "yes", "f": "off", "g": True, "h": False,
    }  # fmt: skip
    rope = tmp_path / "rope.yaml"
    base = ("type: rope\nmass: 0.1\nrest_length: 0.05\nstiffness: 50.0\nmax_angle: 0.2\n"
            "min_ratio: 0.8\nmax_ratio: 1.2\ndt: 0.005\nhorizon: 0.1\nn_points: 010\n")  # fmt: skip
    rope.write_text(base + "velocity_projection: yes\n")
    with pytest.raises(ValueError, match="velocity_projection"):
        dc.load_config(rope)
    rope.write_text(base)
    assert dc.load_config(rope).n_points == 10


def test_a_step_or_horizon_that_overflows_their_ratio_is_a_clear_error():
    for overrides in ({"dt": 1e-320}, {"horizon": 1e300, "dt": 1e-10}):
        with pytest.raises(ValueError, match=r"horizon / dt .*ratio inf"):
            dc.load_config("BP5", **overrides)


def test_config_entry_of_arrays_file_nested_too_deeply(tmp_path, capsys, recorded):
    traj, _ = recorded
    path = tmp_path / "rec.npz"
    np.savez(path, traj=traj, dt=0.01, config=np.str_("[" * 100_000 + "]" * 100_000))
    code, _, err = run_cli(
        capsys, "generate", "--from-arrays", str(path), "--out", str(tmp_path / "d"), "--quiet"
    )
    assert_usage_error(code, err, "entry 'config' is nested too deeply")


def _write_yaml(path, lines: dict[str, str]) -> str:
    path.write_text("".join(f"{k}: {v}\n" for k, v in lines.items()))
    return str(path)


ROPE = {
    "type": "rope", "n_points": "5", "mass": "0.1", "rest_length": "0.1",
    "stiffness": "1.0", "dt": "0.01", "horizon": "0.1",
}  # fmt: skip


def test_sizes_that_would_run_for_days_are_refused(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv(ALLOW_LARGE_ENV, raising=False)
    ball = {k: json.dumps(v) for k, v in BALL.items()}
    cfg = _write_yaml(tmp_path / "fine.yaml", {**ball, "dt": "1.0e-9", "horizon": "1.0"})
    code, _, err = run_cli(capsys, "simulate", cfg, "--out", str(tmp_path / "x.npz"))
    assert_usage_error(
        code, err, "fine.yaml", "1,000,000,000 states per trajectory", "999,999,999 steps",
        "29.8 GiB", f"limit is {MAX_STATES:,} states", ALLOW_LARGE_ENV,
    )  # fmt: skip
    cfg = _write_yaml(tmp_path / "long.yaml", {**ROPE, "n_points": "1000000"})
    code, _, err = run_cli(capsys, "simulate", cfg, "--out", str(tmp_path / "x.npz"))
    assert_usage_error(
        code, err, "1,000,000 points in 2D", "1,999,999 candidate contacts", "204 TiB",
        "limit of 1 GiB per state",
    )  # fmt: skip
    # the same sizes pass validation when the user lifts the limits (nothing is simulated)
    monkeypatch.setenv(ALLOW_LARGE_ENV, "1")
    assert dc.load_config({**BALL, "dt": 1e-9, "horizon": 1.0}).n_states == 1_000_000_000
    # the built-in tasks stay far below both limits
    monkeypatch.delenv(ALLOW_LARGE_ENV)
    for task in dc.list_tasks():
        config = dc.load_config(task)
        assert config.n_states <= MAX_STATES // 1000
        assert state_bytes(*config.points_and_dim(), config.n_contacts) < 2**30 / 100


def test_state_bytes_counts_the_dense_contact_matrices():
    # D = 4, K d = 6: 8 (36 + 24 + 16)
    assert state_bytes(2, 2, 3) == 8 * (36 + 24 + 16)


def test_strings_and_booleans_are_not_numbers(tmp_path, capsys):
    cfg = _write_yaml(
        tmp_path / "rope.yaml",
        {k: v.strip('"') for k, v in ROPE.items()} | {"n_points": '"5"', "mass": "true"},
    )
    code, _, err = run_cli(capsys, "simulate", cfg, "--out", str(tmp_path / "x.npz"))
    assert_usage_error(code, err, "rope.yaml", "n_points:", "got '5'", "mass:", "got True")
    bad = {**BALL, "masses": [1.0, True], "radii": [0.1, "0.2"], "mu": "0.5", "cor": False}
    cfg = tmp_path / "balls.json"
    cfg.write_text(json.dumps(bad))
    code, _, err = run_cli(capsys, "simulate", str(cfg), "--out", str(tmp_path / "x.npz"))
    assert_usage_error(
        code, err, "masses.1:", "got True", "radii.1:", "got '0.2'", "mu:", "got '0.5'",
        "cor:", "got False",
    )  # fmt: skip
    assert err.count("mu:") == 1  # one message per key, not one per union branch
    with pytest.raises(ValueError, match=r"n_points: Input should be a valid integer \(got 5.0"):
        dc.load_config("Rope", n_points=5.0)
    # integers where floats belong are fine, and so are the built-in tasks
    assert dc.load_config({**BALL, "masses": [1], "dt": 0.01, "horizon": 1}).masses == [1.0]

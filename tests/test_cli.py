"""The ``diffcontact`` command line and the atomic file helpers it uses."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from PIL import Image

from diffcontact import __version__
from diffcontact.io import atomic_path, atomic_save_npz, atomic_write_bytes, check_writable
from diffcontact.testing import assert_usage_error, run_cli

run = run_cli


# ----------------------------------------------------------------------- help


def test_help_and_version(capsys):
    code, out, _ = run(capsys, "--help")
    assert code == 0 and "simulate" in out and "demo" in out
    code, out, _ = run(capsys, "simulate", "--help")
    assert code == 0
    for flag in ("--n", "--steps", "--seed", "--out", "--gif", "--contact-model", "--device"):
        assert flag in out
    import diffcontact as dc

    listed = "".join(out.split())  # (argparse wraps the help text, also at hyphens)
    assert all(f"{task}," in listed or f"{task})" in listed for task in dc.list_tasks())
    code, out, _ = run(capsys, "--version")
    assert code == 0 and out.strip() == f"diffcontact {__version__}"
    code, out, _ = run(capsys)  # no command: help
    assert code == 0 and "COMMAND" in out


# ------------------------------------------------------------------- simulate

try:
    import diffcontact.systems  # noqa: F401

    HAVE_SYSTEMS = True
except ImportError:  # the simulator is not installed in this tree
    HAVE_SYSTEMS = False
needs_systems = pytest.mark.skipif(not HAVE_SYSTEMS, reason="diffcontact.systems not available")


@needs_systems
def test_simulate_bp5_writes_npz_and_gif(tmp_path, capsys):
    out, gif, png = tmp_path / "sim.npz", tmp_path / "sim.gif", tmp_path / "energy.png"
    code, stdout, _ = run(
        capsys,
        "simulate",
        "BP5",
        "--n",
        "2",
        "--steps",
        "4",
        "--seed",
        "3",
        "--out",
        str(out),
        "--gif",
        str(gif),
        "--energy-plot",
        str(png),
    )
    assert code == 0
    assert "(2, 5, 2, 5, 2)" in stdout and "energy" in stdout
    with np.load(out) as d:  # no pickle needed
        assert d["traj"].shape == (2, 5, 2, 5, 2) and d["traj"].dtype == np.float64
        assert d["energy"].shape == (2, 5)
        np.testing.assert_allclose(d["t"], np.arange(5) * 0.01)
        assert str(d["task"]) == "BP5" and int(d["seed"]) == 3 and float(d["dt"]) == 0.01
        assert str(d["contact_model"]) == "CM"
        assert str(d["diffcontact_version"]) == __version__
        config = json.loads(str(d["config"]))
        assert config["type"] == "bouncing_masses" and config["radii"][0] == 0.05
        traj = d["traj"]
    # the same seed gives the same initial states as the library call
    import diffcontact as dc

    z0 = dc.load_system("BP5").sample_initial_conditions(2, seed=3)
    np.testing.assert_array_equal(traj[:, 0], z0.numpy())
    with Image.open(gif) as im:
        assert im.format == "GIF" and im.n_frames == 5
    with Image.open(png) as im:
        assert im.format == "PNG"
    assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]


@needs_systems
def test_simulate_from_config_file_is_reproducible(tmp_path, capsys):
    import yaml

    from diffcontact.systems import load_config

    cfg = load_config("CP3").model_dump(mode="json")
    path = tmp_path / "my_pendulum.yaml"
    path.write_text(yaml.safe_dump(cfg))
    outs = []
    for k in range(2):
        out = tmp_path / f"run{k}.npz"
        argv = ["simulate", str(path), "--n", "1", "--steps", "2", "--out", str(out), "--quiet"]
        code, stdout, _ = run(capsys, *argv)
        assert code == 0 and stdout == ""
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]  # same command, same bytes


@needs_systems
def test_ctrl_c_between_the_outputs_says_what_was_written(tmp_path, capsys, monkeypatch):
    """Ctrl-C while the GIF was written left the new .npz beside an earlier run's GIF, and
    the message said only "interrupted"."""
    import diffcontact.viz

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(diffcontact.viz, "animate", interrupted)
    out, gif = tmp_path / "r.npz", tmp_path / "r.gif"
    argv = ["simulate", "BP5", "--n", "1", "--steps", "2", "--quiet", "--out", str(out)]
    code, _, err = run(capsys, *argv, "--gif", str(gif))
    assert code == 130 and out.is_file() and not gif.exists()
    assert f"interrupted after writing {out}; not written: {gif} (a file of that name is " in err


def test_simulate_warnings_are_one_line_each(tmp_path, capsys, monkeypatch):
    """The tunnelling warning came as Python's two lines ('.../cli.py:278: RuntimeWarning:
    ...' and the source line 'traj = system.simulate(')."""
    import warnings

    from diffcontact.systems import System

    simulate = System.simulate

    def warns(self, *args, **kwargs):
        for _ in range(2):
            warnings.warn("bodies tunnelled\n  in 1 of 1 states", RuntimeWarning, stacklevel=2)
        return simulate(self, *args, **kwargs)

    monkeypatch.setattr(System, "simulate", warns)
    argv = ["simulate", "BP5", "--n", "1", "--steps", "2", "--quiet"]
    code, _, err = run(capsys, *argv, "--out", str(tmp_path / "w.npz"))
    assert code == 0, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines == ["diffcontact simulate: warning: bodies tunnelled: in 1 of 1 states"]


def test_simulate_keeps_a_file_it_did_not_write(tmp_path, capsys):
    """``--out`` silently replaced any file, a user's recording too (convert refused)."""
    recording = tmp_path / "recording.npz"
    np.savez(recording, traj=np.zeros((1, 3, 2, 5, 2)), dt=0.01)
    before = recording.read_bytes()
    argv = ["simulate", "BP5", "--n", "1", "--steps", "2", "--quiet", "--out"]
    code, _, err = run(capsys, *argv, str(recording))
    assert_usage_error(code, err, "was not written by diffcontact simulate", "--force")
    assert recording.read_bytes() == before
    (tmp_path / "notes.npz").write_text("not an archive")
    code, _, err = run(capsys, *argv, str(tmp_path / "notes.npz"))
    assert_usage_error(code, err, "--force")
    sim = tmp_path / "sim.npz"
    assert run(capsys, *argv, str(sim))[0] == 0
    assert run(capsys, *argv, str(sim), "--seed", "1")[0] == 0  # its own output: replaced
    assert run(capsys, *argv, str(recording), "--force")[0] == 0
    assert "energy" in np.load(recording).files


@needs_systems
def test_unknown_task(capsys, tmp_path):
    code, _, err = run(capsys, "simulate", "BP7", "--out", str(tmp_path / "x.npz"))
    assert_usage_error(code, err, "unknown task", "'BP7'", "BP5", "Rope-D400")
    assert not (tmp_path / "x.npz").exists()


@pytest.mark.parametrize(
    ("flag", "value"), [("--n", "0"), ("--n", "-2"), ("--n", "two"), ("--steps", "0")]
)
def test_bad_numbers(capsys, flag, value):
    code, _, err = run(capsys, "simulate", "BP5", flag, value)
    assert_usage_error(code, err, f"argument {flag}")


@needs_systems
@pytest.mark.parametrize("value", ["0", "many"])
def test_bad_threads(capsys, tmp_path, value):
    out = tmp_path / "x.npz"
    code, _, err = run(capsys, "simulate", "BP5", "--threads", value, "--out", str(out))
    assert_usage_error(code, err, "argument --threads")
    assert not out.exists()


@needs_systems
def test_missing_config_file(capsys, tmp_path):
    missing = tmp_path / "nope.yaml"
    code, _, err = run(capsys, "simulate", str(missing), "--out", str(tmp_path / "x.npz"))
    assert_usage_error(code, err, "does not exist", "nope.yaml")


@needs_systems
def test_invalid_config_file(capsys, tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"type": "rope", "dt": 0.01, "horizon": 1.0, "colour": "red"}))
    code, _, err = run(capsys, "simulate", str(bad), "--out", str(tmp_path / "x.npz"))
    assert_usage_error(code, err, "colour")


def test_unwritable_output(capsys, tmp_path):
    code, _, err = run(capsys, "simulate", "BP5", "--out", str(tmp_path / "no" / "x.npz"))
    assert_usage_error(code, err, "--out", "does not exist")
    (tmp_path / "d.npz").mkdir()
    code, _, err = run(capsys, "simulate", "BP5", "--out", str(tmp_path / "d.npz"))  # a directory
    assert_usage_error(code, err, "--out", "directory")
    code, _, err = run(
        capsys, "simulate", "BP5", "--out", str(tmp_path / "a.npz"), "--gif", "/no/such/dir/a.gif"
    )
    assert_usage_error(code, err, "--gif")


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
def test_cuda_not_available(capsys, tmp_path):
    out = str(tmp_path / "x.npz")
    code, _, err = run(capsys, "simulate", "BP5", "--device", "cuda", "--out", out)
    assert_usage_error(code, err, "CUDA is not available")


@needs_systems
@pytest.mark.parametrize(
    ("flag", "name", "want"),
    [("--out", "s.txt", ".npz"), ("--gif", "s.txt", ".gif"), ("--energy-plot", "e.txt", ".png")],
)
def test_output_names_must_say_what_they_hold(capsys, tmp_path, flag, name, want):
    """--out s.txt wrote an .npz archive named .txt (and --gif a GIF), without a word."""
    args = ["simulate", "BP5", "--n", "1", "--steps", "2"]
    if flag != "--out":
        args += ["--out", str(tmp_path / "x.npz")]
    code, _, err = run(capsys, *args, flag, str(tmp_path / name))
    assert_usage_error(code, err, f"the file name must end in {want}")
    assert not any(tmp_path.iterdir())


@needs_systems
@pytest.mark.parametrize(
    ("flag", "name"),
    [("--gif", ".gif"), ("--energy-plot", ".png"), ("--gif", "sub/.gif"), ("--out", ".npz")],
)
def test_an_output_name_that_is_only_a_suffix_is_refused_up_front(capsys, tmp_path, flag, name):
    """--gif .gif passed the CLI's check (the name ends in .gif) but not animate's (pathlib
    reads no suffix in '.gif'): a traceback after the .npz had been written."""
    (tmp_path / "sub").mkdir()
    out = tmp_path / "x.npz"
    args = ["simulate", "BP5", "--n", "1", "--steps", "3", "--quiet", "--out", str(out)]
    code, _, err = run(capsys, *args, flag, str(tmp_path / name))
    assert_usage_error(code, err, f"{flag} '{tmp_path / name}' has no file name before its suffix")
    assert [p.name for p in tmp_path.rglob("*")] == ["sub"]  # nothing written


@needs_systems
def test_a_failed_write_says_which_outputs_were_written(capsys, tmp_path, monkeypatch):
    """A full disk while the GIF was written: "writing output failed: [Errno 28] ..."
    did not say that the .npz had been written (the Ctrl-C message did)."""
    import diffcontact.io
    import diffcontact.viz

    def disk_full(path):
        raise OSError(28, "No space left on device", str(path))

    out, gif, png = tmp_path / "r.npz", tmp_path / "r.gif", tmp_path / "r.png"
    argv = ["simulate", "BP5", "--n", "1", "--steps", "2", "--quiet", "--out", str(out)]
    argv += ["--gif", str(gif), "--energy-plot", str(png)]
    monkeypatch.setattr(diffcontact.viz, "plot_energy", lambda E, dt, path, **kw: disk_full(path))
    code, _, err = run(capsys, *argv)
    assert code == 1 and out.is_file() and gif.is_file() and not png.exists()
    assert err.splitlines() == [
        f"diffcontact simulate: error: writing {png} failed: [Errno 28] No space left on "
        f"device: '{png}'; wrote {out}, {gif}; not written: {png} (a file of that name is "
        "from an earlier run)"
    ]
    monkeypatch.setattr(diffcontact.viz, "animate", lambda traj, scene, path, **kw: disk_full(path))
    code, _, err = run(capsys, *argv)
    assert code == 1
    assert f"writing {gif} failed: [Errno 28] " in err
    assert f"; wrote {out}; not written: {gif}, {png} (a file of that name is " in err
    monkeypatch.setattr(diffcontact.io, "atomic_save_npz", lambda path, **kw: disk_full(path))
    code, _, err = run(capsys, *argv)
    assert code == 1 and f"writing {out} failed: [Errno 28] " in err
    assert err.rstrip().endswith("; nothing written")


@needs_systems
def test_a_simulation_too_large_is_refused_up_front(capsys, tmp_path, monkeypatch):
    """--steps 2e8 ran (a 25-hour estimate, 32 GB for 23 GB of memory), --n 1e8 sampled
    silently for minutes; billiards --time and config horizons had the limit already."""
    monkeypatch.delenv("DIFFCONTACT_ALLOW_LARGE", raising=False)
    out = str(tmp_path / "x.npz")
    code, _, err = run(
        capsys, "simulate", "BP5-e", "--n", "1", "--steps", "200000000", "--out", out
    )
    assert_usage_error(code, err, "--steps 200000000: at most 1000000")
    code, _, err = run(
        capsys, "simulate", "BP5-e", "--n", "100000000", "--steps", "20", "--out", out
    )
    assert_usage_error(code, err, "GiB, more than half of this machine's")
    assert not (tmp_path / "x.npz").exists()


@needs_systems
def test_cuda_graph_on_the_cpu_is_a_usage_error(capsys, tmp_path):
    out = str(tmp_path / "x.npz")
    args = ("simulate", "BP5", "--n", "2", "--steps", "3", "--out", out, "--quiet")
    code, _, err = run(capsys, *args, "--cuda-graph", "on")
    # the flag, not the Python argument (cuda_graph=True) of System.simulate
    assert_usage_error(code, err, "--cuda-graph on needs --device cuda, not --device cpu")
    assert "cuda_graph" not in err and not os.path.exists(out)
    code, _, _ = run(capsys, *args, "--cuda-graph", "off")
    assert code == 0


@needs_systems
def test_console_error_has_no_traceback(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "diffcontact.cli", "simulate", "NoSuchTask"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and "unknown task" in proc.stderr


# ------------------------------------------------------------------------ io


def test_atomic_save_npz_roundtrip_and_determinism(tmp_path):
    arrays = {
        "a": np.arange(6.0).reshape(2, 3),
        "t": torch.ones(3, dtype=torch.float64),
        "name": np.str_("BP5"),
        "seed": np.int64(7),
    }
    p1 = atomic_save_npz(tmp_path / "one.npz", **arrays)
    p2 = atomic_save_npz(tmp_path / "two.npz", **arrays)
    assert p1.read_bytes() == p2.read_bytes()
    with np.load(p1, allow_pickle=False) as d:
        assert d.files == ["a", "t", "name", "seed"]
        np.testing.assert_array_equal(d["a"], arrays["a"])
        assert d["t"].tolist() == [1.0, 1.0, 1.0] and str(d["name"]) == "BP5"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one.npz", "two.npz"]
    umask = os.umask(0)
    os.umask(umask)
    assert os.stat(p1).st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's private 0o600


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    path = tmp_path / "data.npz"
    atomic_write_bytes(path, b"old")
    with pytest.raises(TypeError, match="object"):
        atomic_save_npz(path, bad=np.array([{"a": 1}], dtype=object))
    assert path.read_bytes() == b"old"
    with pytest.raises(RuntimeError, match="boom"), atomic_path(path) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("boom")
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["data.npz"]


def test_a_failed_atomic_write_names_its_file(tmp_path):
    """A full disk's error (errno 28, no file name) reached the user without the file."""
    import errno

    path = tmp_path / "run" / "model.pt"
    path.parent.mkdir()
    with pytest.raises(OSError, match=r"No space left on device: '.*model\.pt'") as caught:
        with atomic_path(path) as tmp:
            tmp.write_bytes(b"half")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(path)
    assert list(path.parent.iterdir()) == []


def test_check_writable(tmp_path):
    assert check_writable(tmp_path / "x.npz") == tmp_path / "x.npz"
    with pytest.raises(IsADirectoryError):
        check_writable(tmp_path)
    with pytest.raises(FileNotFoundError):
        check_writable(tmp_path / "missing" / "x.npz")
    assert list(tmp_path.iterdir()) == []  # the write probe leaves nothing behind
    (tmp_path / "afile").write_text("")  # a file where a folder should be: not "missing"
    with pytest.raises(NotADirectoryError, match="afile is not a folder"):
        check_writable(tmp_path / "afile" / "x.npz")


def test_check_writable_tries_a_file(monkeypatch):
    """Permission bits pass everything for root: a folder where no file can be
    created (here /proc) is refused up front, not after the expensive work."""
    monkeypatch.setattr(os, "access", lambda *a, **k: True)  # as root
    with pytest.raises(PermissionError, match="folder /proc is not writable"):
        check_writable("/proc/result.json")

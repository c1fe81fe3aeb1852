"""Importing recordings (``dataset_from_arrays``, ``generate --from-arrays``): the checks a
stress test found missing. A stride beyond the last start, a split left without a chunk
at the starts a stride uses, velocities that are not the positions' motion, recordings of
no state, event times and flags that are not numbers, and files that are not
``--from-arrays`` files: each named on one line, before anything is written."""

from __future__ import annotations

import argparse
import json
import warnings

import numpy as np
import pytest

import diffcontact as dc
from diffcontact.learning.data.arrays import dataset_from_arrays
from diffcontact.learning.data.chunks import event_states
from diffcontact.learning.data.cli import register_cli
from diffcontact.learning.data.format import STREAM_SPLIT, load_dataset
from diffcontact.learning.data.generate import generate_dataset

from .support import BP5, L, short_config

MISMATCH = "the velocities do not match the motion of the positions"


def cli(capsys, *argv: str) -> tuple[int, str, str]:
    parser = argparse.ArgumentParser(prog="diffcontact")
    register_cli(parser.add_subparsers(dest="command"))
    try:
        args = parser.parse_args(["generate", *argv])
    except SystemExit as exc:  # argparse's usage errors
        out, err = capsys.readouterr()
        return int(exc.code), out, err
    code = args.func(args)
    out, err = capsys.readouterr()
    return code, out, err


def _split_index(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """The trajectories of each split for ``n`` trajectories, val and test 0.1 (one each)."""
    perm = np.random.default_rng([seed, STREAM_SPLIT]).permutation(n)
    return {"test": perm[:1], "val": perm[1:2], "train": np.sort(perm[2:])}


def _mismatch_warnings(caught) -> list[str]:
    return [str(w.message) for w in caught if MISMATCH in str(w.message)]


# ------------------------------------------------------------------------------ stride
def test_a_stride_beyond_the_last_start_takes_the_first_window(recorded, tmp_path, capsys):
    """``stride=2**63`` (``--stride 99999999999999999999``) crashed in ``window_chunks`` with
    numpy's IndexError and left the folder holding only ``.generating.json``, which then
    blocked every later run ("holds an unfinished dataset ... stride (9999... there)").
    Any stride beyond the last start takes the window at state 0, as the largest does."""
    for k, stride in enumerate((16, 17, 2**63, 10**20)):  # 20 states, chunks of 5: starts 0..15
        out = dataset_from_arrays(recorded, BP5, tmp_path / f"rec{k}", stride=stride,
                                  progress=False)  # fmt: skip
        split = load_dataset(out).split("train")
        assert (split.chunk_start == 0).all() and len(split.chunk_start) == len(split.traj)
    # the command line: written, and run again with the same arguments it is reused
    np.savez(tmp_path / "rec.npz", traj=recorded, dt=0.01)
    argv = ["--from-arrays", str(tmp_path / "rec.npz"), "--config", "BP5", "--quiet",
            "--stride", "99999999999999999999", "--out", str(tmp_path / "cli")]  # fmt: skip
    for _ in range(2):
        code, _, err = cli(capsys, *argv)
        assert code == 0, err
    assert not (tmp_path / "cli" / ".generating.json").exists()
    # simulated data too
    out = generate_dataset(BP5, tmp_path / "sim", n_train=1, n_val=0, n_test=0, stride=2**63,
                           progress=False)  # fmt: skip
    assert (load_dataset(out).split("train").chunk_start == 0).all()


def test_a_split_without_a_chunk_at_the_starts_of_the_stride_is_refused(recorded, tmp_path):
    """Only the starts 0, K, 2K ... are used, but the "flagged at every possible start"
    check looked at all: event times at 0 with the stride of one window per trajectory
    wrote splits of no chunk (exit 0), and ``train`` then said "its train split is empty"
    of a split of 10 trajectories."""
    out = tmp_path / "rec"
    N, T = recorded.shape[:2]
    with pytest.raises(ValueError) as info:
        dataset_from_arrays(recorded, BP5, out, event_times=np.zeros((N, 1)), stride=T - L + 1)
    msg = str(info.value)
    assert msg.startswith("stride=16 leaves the train split without a chunk: its 10 "), msg
    assert "flagged in contact at every state the stride lets a chunk start at (state 0;" in msg
    assert "flagged by an event time before it at 1 of them" in msg and "\n" not in msg
    assert "Use a smaller stride" in msg and "check the event times" in msg
    assert not out.exists()
    # only val's trajectory flagged at the starts 0, 5, 10, 15: val gets no chunk
    index = _split_index(N)
    flags = np.zeros((N, T), dtype=bool)
    (v,) = index["val"]
    flags[v, 0::5] = True
    with pytest.raises(ValueError, match=rf"stride=5 leaves the val split without a chunk: its "
                       rf"1 trajectory \({v}\) is flagged .* \(states 0, 5, 10, 15; .* by the "
                       r"contact flags given at 4 of them"):  # fmt: skip
        dataset_from_arrays(recorded, BP5, out, contact=flags, stride=5, progress=False)
    assert not out.exists()
    # the same flags with stride 1 (other starts are out of contact), or on one training
    # trajectory of ten: written, the latter with a warning naming it
    dataset_from_arrays(recorded, BP5, out, contact=flags, stride=1, progress=False)
    t = int(index["train"][3])
    flags = np.zeros((N, T), dtype=bool)
    flags[t, 0::5] = True
    with pytest.warns(RuntimeWarning, match=rf"stride=5: 1 of 12 trajectories \({t}\) give no "
                      r"chunk: .* \(states 0, 5, 10, 15\); a smaller stride"):  # fmt: skip
        folder = dataset_from_arrays(recorded, BP5, tmp_path / "w", contact=flags, stride=5,
                                     progress=False)  # fmt: skip
    split = load_dataset(folder).split("train")
    assert 3 not in split.chunk_traj.tolist() and len(split.chunks) > 0


# -------------------------------------------------------------------------- velocities
def test_velocities_that_are_not_the_positions_motion_are_warned(recorded, tmp_path, capsys):
    """``convert`` measures ``velocity_mismatch`` and warns above 0.25; the import checked
    nothing: velocities x1000, all zero, swapped between bodies, or a recording at dt 0.02
    with a config of dt 0.01 were accepted silently."""
    at_02 = dc.load_system(short_config("BP5", 0.4) | {"dt": 0.02})
    z0 = at_02.sample_initial_conditions(12, seed=0)
    slow = at_02.simulate(z0, 19, progress=False, on_tunnelling="ignore")
    scaled, zero, swapped = recorded.copy(), recorded.copy(), recorded.copy()
    scaled[:, :, 1] *= 1000
    zero[:, :, 1] = 0
    swapped[:, :, 1] = recorded[:, :, 1, [1, 0, 3, 2, 4]]
    for k, (traj, size) in enumerate(
        ((scaled, r"by 1\.00 of the median speed"),
         (zero, "by more than the median speed, which is 0"),
         (swapped, r"by \d+\.\d\d of the median"), (slow.numpy(), r"by 1\.\d\d of the median"))
    ):  # fmt: skip
        with pytest.warns(RuntimeWarning, match=rf"{MISMATCH}: .*\(at the config's dt=0\.01\) "
                          rf"{size}.*check their units, frame and order of points, and that "
                          r"the data are sampled at the config's dt"):  # fmt: skip
            dataset_from_arrays(traj, BP5, tmp_path / f"bad{k}", progress=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        dataset_from_arrays(recorded, BP5, tmp_path / "good", progress=False)
    assert _mismatch_warnings(caught) == []
    # the command line: one line on stderr, the dataset written
    np.savez(tmp_path / "mm.npz", traj=scaled, dt=0.01)
    code, out, err = cli(capsys, "--from-arrays", str(tmp_path / "mm.npz"), "--config", "BP5",
                         "--out", str(tmp_path / "cli"))  # fmt: skip
    assert code == 0 and "dataset (arrays) written" in out, err
    assert err.startswith(f"diffcontact generate: warning: {MISMATCH}") and err.count("\n") == 1


# ----------------------------------------------------------------- no state, bad flags
def test_a_recording_of_no_state_is_named(recorded, tmp_path):
    """``T = 0`` gave numpy's "cannot reshape array of size 0 into shape (12,0,newaxis)"."""
    with pytest.raises(ValueError, match=r"hold 0 states, fewer than chunk_length=5: each "
                       r"trajectory needs at least 5 states"):  # fmt: skip
        dataset_from_arrays(recorded[:, :0], BP5, tmp_path / "rec")
    assert not (tmp_path / "rec").exists()


def test_event_times_and_flags_that_are_not_numbers_are_named(recorded, tmp_path):
    """Event times of strings or a ragged list gave numpy's messages ("could not convert
    string to float", "inhomogeneous shape") without naming ``event_times``."""
    out = tmp_path / "rec"
    N, T = recorded.shape[:2]
    for bad, said in (
        ([["a"]] * N, "event_times must be numbers .*, got strings"),
        ([[0.1]] * (N - 1) + [[0.1, 0.2]], r"event_times must be an \(N, E\) array .*rows of "
         "one length .*pad trajectories with fewer events with NaN"),
        (np.ones((N, 1), dtype=bool), "event_times must be numbers .*, got bool"),
    ):  # fmt: skip
        with pytest.raises(ValueError, match=said):
            dataset_from_arrays(recorded, BP5, out, event_times=bad)
    ragged = [[False] * T] * (N - 1) + [[False] * (T - 1)]
    with pytest.raises(ValueError, match=r"contact flags must be .* \(12, 20\), got rows of "):
        dataset_from_arrays(recorded, BP5, out, contact=ragged)
    assert not out.exists()
    # None pads as NaN did
    padded = [[0.05, None]] + [[0.1, 0.12]] * (N - 1)
    assert event_states(padded, N, T, 0.01).sum() == 1 + 2 * (N - 1)


def test_event_times_get_the_same_tolerance_at_both_ends():
    """-1e-15 was refused as outside [0, T_end] while T_end + 1e-15 was accepted."""
    dt, T = 0.01, 10
    end = (T - 1) * dt
    flags = event_states([[-1e-15, end + 1e-15]], 1, T, dt)
    np.testing.assert_array_equal(flags[0], np.isin(np.arange(T), (0, T - 1)))
    for tau in (-1e-3, end + 1e-3):
        with pytest.raises(ValueError, match="outside its recording"):
            event_states([[tau]], 1, T, dt)


def test_positions_in_other_units_are_named_as_a_cause(recorded, tmp_path):
    """Positions x1000 (mm for m) are in contact everywhere: the message pointed at the
    geometry only, where ``convert`` names the units."""
    mm = recorded.copy()
    mm[:, :, 0] *= 1000
    with pytest.raises(ValueError, match=r"flagged in contact at every state .* check the "
                       r"config's geometry \(radii, walls, limits\) and the units of the "
                       r"positions \(mm where the config has m\?\)"):  # fmt: skip
        dataset_from_arrays(mm, BP5, tmp_path / "rec")


# --------------------------------------------------------------------------- the CLI
def test_from_arrays_files_that_are_not_such_files_say_what_to_do(recorded, tmp_path, capsys):
    """A file of positions only said "has no array named 'traj' (found: x)"; a JSON list as
    its config "load_system expects a task name, a path or a dict; got list"."""
    out = str(tmp_path / "ds")
    np.savez(tmp_path / "x.npz", x=recorded[:, :, 0], dt=0.01)
    code, _, err = cli(capsys, "--from-arrays", str(tmp_path / "x.npz"), "--config", "BP5",
                       "--out", out)  # fmt: skip
    assert code == 2 and "no array named 'traj' (found: x, dt)" in err, err
    assert f"`diffcontact convert positions {tmp_path / 'x.npz'} --config CONFIG" in err
    for config, said in (
        ([1, 2], "entry 'config' must be a JSON object (a config, as `diffcontact simulate` "
         "and `diffcontact convert` write it) or a task name, got an array"),
        ({"type": "bouncing_masses"}, "entry 'config' is not a usable config: invalid system "
         "config: dt: missing key"),
    ):  # fmt: skip
        np.savez(tmp_path / "c.npz", traj=recorded, config=np.str_(json.dumps(config)))
        code, _, err = cli(capsys, "--from-arrays", str(tmp_path / "c.npz"), "--out", out)
        assert code == 2 and err.count("\n") == 1, err
        assert f"error: {tmp_path / 'c.npz'}: {said}" in err
    assert not (tmp_path / "ds").exists()


def test_the_fraction_options_state_the_range_they_accept(recorded, tmp_path, capsys):
    """``--val-fraction 1.5`` said "in [0, 1]", and ``--val-fraction 1`` then "[0, 1)"."""
    np.savez(tmp_path / "rec.npz", traj=recorded, dt=0.01)
    for option in ("--val-fraction", "--test-fraction"):
        for value in ("1", "1.5", "nan", "-0.1"):
            code, _, err = cli(capsys, "--from-arrays", str(tmp_path / "rec.npz"), "--config",
                               "BP5", "--out", str(tmp_path / "ds"), option, value)  # fmt: skip
            assert code == 2 and f"{option}: must be a finite number in [0, 1), got" in err, err
    code, _, err = cli(capsys, "--from-arrays", str(tmp_path / "rec.npz"), "--config", "BP5",
                       "--out", str(tmp_path / "ds"), "--val-fraction", "0", "--quiet")  # fmt: skip
    assert code == 0, err

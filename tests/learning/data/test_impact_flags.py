"""Contact flags that see impacts between samples, on an exact event-driven bouncing ball.

The ball's motion is closed-form: parabolas joined by instantaneous rebounds
(``v_y -> -e v_y`` at the floor), sampled every ``dt``. It never penetrates
the floor at a sample, so a penetration test flags nothing; the velocity jump
across each rebound is what shows the impact.
"""

from __future__ import annotations

import argparse
import json
import logging
import math

import numpy as np
import pytest
import torch

from diffcontact.learning.data.arrays import dataset_from_arrays
from diffcontact.learning.data.chunks import (
    contact_flags,
    contact_states,
    event_states,
    impact_intervals,
)
from diffcontact.learning.data.cli import register_cli
from diffcontact.learning.data.format import load_dataset
from diffcontact.systems import load_system

DT, G, E, R = 0.01, 9.81, 0.8, 0.1
T = 120
BALL = {
    "type": "bouncing_masses",
    "name": "ball",
    "masses": [1.0],
    "radii": [R],
    "walls": [[0, 1, 0]],  # the floor y = 0
    "gravity": G,
    "cor": E,
    "mu": 0.0,
    "dt": DT,
    "horizon": T * DT,
}


def exact_ball(y0: float, vx: float, vy0: float = 0.0) -> tuple[np.ndarray, list[float]]:
    """``(T, 2, 1, 2)`` samples of the exact bouncing ball and its rebound times."""
    t = np.arange(T) * DT
    out = np.zeros((T, 2, 1, 2))
    out[:, 0, 0, 0] = vx * t
    out[:, 1, 0, 0] = vx
    t0, y, v, events = 0.0, y0, vy0, []
    while t0 < t[-1]:
        tau = (v + math.sqrt(v * v + 2 * G * (y - R))) / G  # time to the floor (centre at R)
        seg = (t >= t0) & (t < t0 + tau)
        s = t[seg] - t0
        out[seg, 0, 0, 1] = y + v * s - 0.5 * G * s * s
        out[seg, 1, 0, 1] = v - G * s
        t0, y, v = t0 + tau, R, -E * (v - G * tau)
        if t0 < t[-1]:
            events.append(t0)
    return out, events


@pytest.fixture(scope="module")
def balls() -> tuple[np.ndarray, list[list[float]]]:
    runs = [exact_ball(0.5 + 0.13 * k, 0.3 * (k - 3), 0.5 * (k % 3)) for k in range(10)]
    traj = np.stack([r[0] for r in runs])
    events = [r[1] for r in runs]
    # the rebounds fall between samples (never on one), and there are several
    assert sum(map(len, events)) >= 15
    assert all(abs(e / DT - round(e / DT)) > 1e-3 for ev in events for e in ev)
    return traj, events


def _impact_intervals_expected(events: list[list[float]]) -> np.ndarray:
    want = np.zeros((len(events), T - 1), dtype=bool)
    for n, ev in enumerate(events):
        for tau in ev:
            want[n, int(tau // DT)] = True
    return want


def test_penetration_alone_misses_impacts_between_samples(balls):
    traj, _ = balls
    system = load_system(BALL)
    assert not contact_states(system, traj).any()  # never below the floor at a sample


def test_velocity_jumps_flag_exactly_the_intervals_with_a_rebound(balls):
    traj, events = balls
    want = _impact_intervals_expected(events)
    np.testing.assert_array_equal(impact_intervals(traj), want)
    np.testing.assert_array_equal(impact_intervals(torch.from_numpy(traj), 0.5), want)
    assert not impact_intervals(traj, math.inf).any()
    assert not impact_intervals(traj[:, :2]).any()  # no neighbouring interval to compare with


@pytest.mark.parametrize("scale", [2.0**-1000, 1e-300, 1e200, 1e300])
def test_impact_flags_do_not_depend_on_the_units(balls, scale):
    """The test is homogeneous in the velocities: recorded in other units, the same
    intervals are flagged (at 1e300 the squared speeds overflowed and none was)."""
    traj, events = balls
    np.testing.assert_array_equal(
        impact_intervals(traj * scale), _impact_intervals_expected(events)
    )


def test_event_times_flag_the_state_after_each_event(balls):
    _, events = balls
    E_max = max(map(len, events))
    times = np.full((len(events), E_max), np.nan)
    for n, ev in enumerate(events):
        times[n, : len(ev)] = ev
    flags = event_states(times, len(events), T, DT)
    want = np.zeros_like(flags)
    want[:, 1:] = _impact_intervals_expected(events)
    np.testing.assert_array_equal(flags, want)
    # a time on a sample flags that sample
    np.testing.assert_array_equal(event_states([[0.05]], 1, 10, DT)[0], np.arange(10) == 5)
    with pytest.raises(ValueError, match=r"event_times must have shape \(N, E\) = \(10, E\)"):
        event_states(times[:3], 10, T, DT)
    with pytest.raises(ValueError, match=r"trajectory 0 has an event at t = 5 s, outside"):
        event_states([[5.0]], 1, T, DT)


def test_recorded_dataset_flags_every_window_that_spans_a_rebound(balls, tmp_path, caplog):
    traj, events = balls
    out = dataset_from_arrays(traj, BALL, tmp_path / "ds", seed=1, progress=False)
    ds = load_dataset(out)
    meta = ds.metadata
    assert meta["stride"] == 1 and meta["contact_flags"]["gap"] == 0
    assert meta["contact_flags"]["impact"] == sum(map(len, events))
    L, total, with_contact = ds.chunk_length, 0, 0
    for name in ("train", "val", "test"):
        split = ds.split(name)
        for n, s, has in zip(
            split.chunk_traj.tolist(), split.chunk_start.tolist(),
            split.chunk_has_contact.tolist(), strict=True,
        ):  # fmt: skip
            ev = events[meta["source_indices"][name][n]]
            assert has == any(s * DT < tau < (s + L - 1) * DT for tau in ev)
            # no chunk starts right after a rebound (its first state is flagged)
            assert not any((s - 1) * DT < tau < s * DT for tau in ev)
            total, with_contact = total + 1, with_contact + has
    # every window is used: T - L + 1 starts per trajectory, less one per rebound
    assert total == len(traj) * (T - L + 1) - sum(
        sum(1 for tau in ev if math.ceil(tau / DT) <= T - L) for ev in events
    )
    # each rebound in (k dt, (k + 1) dt) lies in the L - 1 windows starting at k - L + 2 .. k
    spans = sum(
        len(range(max(0, int(tau // DT) - L + 2), min(int(tau // DT), T - L) + 1))
        for ev in events
        for tau in ev
    )
    assert with_contact == spans > 0
    # only penetration (the old flags): nothing flagged, and a warning says the fraction fails
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        plain = dataset_from_arrays(
            traj, BALL, tmp_path / "plain", seed=1, impact_tol=math.inf, progress=False
        )
    assert not load_dataset(plain).split("train").chunk_has_contact.any()
    assert "--contact-fraction 0.5 cannot be met: none of the" in caplog.text


def test_user_flags_and_event_times_replace_detection(balls):
    traj, events = balls
    system = load_system(BALL)
    E_max = max(map(len, events))
    times = np.full((len(events), E_max), np.nan)
    for n, ev in enumerate(events):
        times[n, : len(ev)] = ev
    detected, _ = contact_flags(system, traj)
    from_events, counts = contact_flags(system, traj, impact_tol=math.inf, event_times=times)
    np.testing.assert_array_equal(from_events, detected)
    assert counts["impact"] == 0 and counts["events"] == counts["total"] == detected.sum()
    given = np.zeros(traj.shape[:2], dtype=bool)
    given[0, 7] = True
    flags, counts = contact_flags(system, traj, impact_tol=math.inf, contact=given)
    assert flags.sum() == 1 and flags[0, 7] and counts["given"] == 1
    with pytest.raises(ValueError, match=r"contact flags must be a boolean array of shape"):
        contact_flags(system, traj, contact=given[:, :5])
    # integer flags: 0 and 1 are booleans, other values a mistake (7 and -3 were taken as True)
    flags01, _ = contact_flags(system, traj, impact_tol=math.inf, contact=given.astype(np.int64))
    np.testing.assert_array_equal(flags01, flags)
    with pytest.raises(ValueError, match=r"booleans \(or 0 and 1\), got values \[-3, 7\]"):
        contact_flags(
            system, traj, contact=np.where(given, 7, 0) - 3 * np.eye(*given.shape, dtype=int)
        )
    # an infinite event time is no time in the recording (it was dropped silently)
    with pytest.raises(ValueError, match=r"trajectory 1 has an infinite event time"):
        contact_flags(
            system, traj, event_times=np.where(np.arange(len(times))[:, None] == 1, np.inf, times)
        )
    # a gap tolerance flags the states near the floor
    near, counts = contact_flags(system, traj, impact_tol=math.inf, gap_tol=0.05)
    assert counts["gap"] == near.sum() > 0
    gaps = traj[:, :, 0, 0, 1] - R
    np.testing.assert_array_equal(near, gaps < 0.05)


def _cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="diffcontact")
    register_cli(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_reads_flags_and_event_times(balls, tmp_path, capsys):
    traj, events = balls
    times = np.full((len(events), max(map(len, events))), np.nan)
    for n, ev in enumerate(events):
        times[n, : len(ev)] = ev
    path = tmp_path / "ball.npz"
    np.savez(path, traj=traj, config=json.dumps(BALL), event_times=times)
    out = tmp_path / "ds"
    argv = ["generate", "--from-arrays", str(path), "--impact-tol", "inf", "--stride", "2"]
    assert _cli([*argv, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "every window, stride 2" in printed and "event times " in printed
    meta = load_dataset(out).metadata
    assert meta["contact_flags"]["events"] == sum(map(len, events))
    assert meta["arguments"]["impact_tol"] is None  # off
    assert "flags_sha256" in meta["arguments"]
    assert _cli([*argv, "--out", str(out)]) == 0  # the same command reuses the dataset
    assert "reusing the dataset" in capsys.readouterr().out
    # bad entries: one line, exit 2
    for bad, match in (
        ({"event_times": times[:2]}, "event_times must have shape"),
        ({"event_times": times + 100.0}, "outside its recording"),
        ({"contact": np.zeros((10, 3), dtype=bool)}, "contact flags must be a boolean array"),
        ({"contact": np.full((10, T), "x")}, "entry 'contact' must be booleans"),
    ):
        np.savez(path, traj=traj, config=json.dumps(BALL), **bad)
        assert _cli(["generate", "--from-arrays", str(path), "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and match in err[0], err
    for argv, match in (
        (["generate", "BP5", "--out", str(tmp_path / "y"), "--impact-tol", "0.1"], "--impact-tol"),
        (["generate", "BP5", "--out", str(tmp_path / "y"), "--true-params"], "--true-params"),
    ):
        assert _cli(argv) == 2
        assert f"{match} applies only with --from-arrays" in capsys.readouterr().err

"""benchmarks/chain.py: the recorded calls replay the rollout's solves, the table runs on
the CPU, and on CUDA the profiled kernels are matched to the launches in order."""

from __future__ import annotations

import sys
import types
from pathlib import Path

import pytest
import torch
from torch.autograd import DeviceType

pytest.importorskip("warp", reason="the chain benchmark times the fused (Warp) solver")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import chain


def test_recorded_calls_replay_to_the_same_impulses():
    calls = chain.record_calls("BP5", 16, 3, "cpu")
    assert calls, "a static step solves its contacts"
    A, active, d = calls[0][0], calls[0][4], calls[0][6]
    assert A.shape[0] == 16 and d == 2 and active.dtype == torch.bool
    row = chain.time_calls(calls, "cpu", reps=1)
    assert row["calls"] == len(calls) and row["note"] == ""
    again = chain.time_calls(calls, "cpu", reps=1)["impulses"]
    for f, g in zip(row["impulses"], again, strict=True):
        assert torch.equal(f, g)  # each replay solves the recorded problems alike


def test_quick_table_runs_on_the_cpu(capsys):
    assert chain.main(["--scenes", "16", "--steps", "2", "--reps", "1"]) == 0
    out = capsys.readouterr().out
    assert "(cpu)" in out and "same f" in out


def _kernel(name: str, start: float, us: float):
    time_range = types.SimpleNamespace(start=start, elapsed_us=lambda: us)
    return types.SimpleNamespace(device_type=DeviceType.CUDA, name=name, time_range=time_range)


def test_kernel_times_follow_the_launches_in_order():
    launches = chain._Launches("cpu")
    launches.labels = [None, (0, "all"), (0, "all"), None, (0, "ipm")]
    launches.ms = {(0, "all"): [9.0, 9.0], (0, "ipm"): [9.0]}
    cpu_op = types.SimpleNamespace(device_type=DeviceType.CPU, name="fused_forward")
    events = [_kernel("fused_forward_abc", t, 100.0 * (t + 1)) for t in (4, 0, 2, 1, 3)]
    events += [cpu_op, _kernel("elementwise", 0.5, 1.0)]
    launches.use_kernel_times(types.SimpleNamespace(events=lambda: events))
    assert launches.ms == {(0, "all"): [0.2, 0.3], (0, "ipm"): [0.5]}  # by start time
    assert "torch.profiler" in launches.note
    # a profile that missed a kernel keeps the wall times, and says so
    launches.ms = {(0, "all"): [9.0, 9.0], (0, "ipm"): [9.0]}
    launches.use_kernel_times(types.SimpleNamespace(events=lambda: events[:3]))
    assert launches.ms[(0, "all")] == [9.0, 9.0] and "wall times" in launches.note

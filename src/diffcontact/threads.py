"""How many CPU threads torch uses: the cores this process may use, and a governor.

A training step of diffcontact is thousands of small tensor operations plus a
few large ones (the potential network's matrix products). With an idle CPU,
several intra-op threads speed the large ones up (measured by
``python benchmarks/run.py threads``). With another process competing for the
cores, every parallel region waits for a thread the operating system has
descheduled, and two threads become *slower* than one (the "thread cliff"
of issue 11). No fixed number is right on a shared machine, so the default of
``train()`` measures:

- :func:`available_cores` is the number of cores this process may use: its CPU
  affinity and, in a container, the cgroup CPU quota (torch itself counts all
  the machine's cores, which oversubscribes a 2-core slot of a 64-core node).
- :class:`ThreadGovernor` times the steps it is told about and chooses between
  one thread and ``max_threads``: it measures a window of steps with each,
  keeps the faster, probes the other again after a while (less often each
  time the probe loses) and at once when the steps become markedly slower
  than they were, which is what a competing process starting up looks like.
- :func:`thread_scope` is the ``threads`` option of every loop of steps
  (``System.simulate``, hence data generation, evaluation and ``diffcontact
  simulate``; ``diffcontact.optimize``): ``"auto"``, their default, governs the
  loop's steps; a loop inside a governed one (a rollout inside a training step
  or a planning iteration) leaves the threads to the outer one.

Nothing here changes results: the thread count changes the order of
floating-point reductions only inside torch's parallel kernels (last-bit
differences), never the algorithm.
"""

from __future__ import annotations

import contextlib
import math
import os
import statistics
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import torch

__all__ = [
    "ThreadGovernor", "available_cores", "claim_threads", "governed", "parse_threads",
    "settled_on_one", "thread_scope",
]  # fmt: skip

MIN_AUTO_STEPS = 24
"""Loops of fewer steps are not governed by ``threads="auto"`` (the threads are left as
they are): the governor needs two windows of 8 steps to compare the candidates, so a
shorter loop would only pay for the probe."""

MEMORY_S = 60.0
"""For this many seconds after a governed loop ended on one thread (a loaded CPU), the next
``threads="auto"`` loop on as many cores starts settled on one thread: it goes on with the
last loop's probe schedule (the windows since its last probe of several threads, and its
interval) instead of probing after its first window. A run of short rollouts on a busy
machine then pays for a probe every few calls, not in every call."""

_GOVERNED = 0  # open thread scopes (the thread count is process-wide, so is this)
_GOVERNED_LOCK = threading.Lock()
# max_threads -> (time.monotonic() at the end, interval, windows since the last probe) of
# the last governed loop that ended on one thread
_SETTLED: dict[int, tuple[float, int, int]] = {}


def _cgroup_quota(root: Path = Path("/sys/fs/cgroup")) -> float | None:
    """CPU quota of this process's cgroup in cores (``None``: no quota or not Linux)."""
    try:
        quota, period = (root / "cpu.max").read_text().split()[:2]  # cgroup v2
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        pass
    try:  # cgroup v1
        quota = int((root / "cpu" / "cpu.cfs_quota_us").read_text())
        period = int((root / "cpu" / "cpu.cfs_period_us").read_text())
        return None if quota <= 0 or period <= 0 else quota / period
    except (OSError, ValueError):
        return None


def available_cores() -> int:
    """Cores this process may run on: CPU affinity, capped by a cgroup CPU quota (>= 1)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    quota = _cgroup_quota()
    if quota is not None:
        cores = min(cores, max(1, math.floor(quota)))
    return max(1, cores)


def parse_threads(value: int | str | None) -> int | str | None:
    """Check a ``threads`` option: ``"auto"``, ``None`` (leave torch alone) or an int >= 1.

    Raises:
        ValueError: anything else, with a one-line message.
    """
    if value is None or value == "auto":
        return value
    if isinstance(value, str):
        try:
            value = int(value)
        except ValueError:
            raise ValueError(
                f"threads must be 'auto' or a positive integer, got {value!r}"
            ) from None
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"threads must be 'auto' or a positive integer, got {value!r}")
    return value


class ThreadGovernor:
    """Chooses torch's intra-op thread count from the measured time of the steps.

    Use :meth:`step` as a context manager around each step (or call
    :meth:`start` and :meth:`stop`). The governor holds one of two candidates,
    ``1`` and ``max_threads``, and works in windows of ``window`` steps, the
    first step of each window discarded (it pays for the switch):

    1. measure a window with ``max_threads`` (or ``first``), then one with the
       other; keep the one whose median step time is lower (ties within
       ``margin`` go to the current one);
    2. run ``interval`` windows with the choice, then probe the other for one
       window; a probe that loses doubles ``interval`` (up to
       ``max_interval``), one that wins switches and resets it;
    3. probe at once when the load changed: a window of several threads more
       than ``1 + slowdown`` times slower than their last one (a competing
       process started), or a window of one thread ``1 - slowdown`` times
       faster than its last one (it ended). One thread getting slower is no
       reason to try more: under load, more threads are the slower choice;
    4. two steps of several threads in a row ``spike`` times slower than one
       thread's last window end the window (or the probe) early: a competing
       process can make several threads ten times slower.

    With ``max_threads == 1`` it sets one thread and never probes.

    Args:
        max_threads: the larger candidate (default :func:`available_cores`,
            capped by torch's current setting).
        window: steps per measurement window (>= 3).
        interval, max_interval: windows between probes, initial and largest.
        margin: relative advantage a probe needs to win.
        slowdown: relative slowdown of the choice that triggers a probe.
        spike: slowdown of single steps that ends a window early.
        first: the candidate measured first (default ``max_threads``; ``1`` suits a
            short loop, where a first window of several threads on a loaded CPU
            would cost most: a probe of several threads after a window of one ends
            after two steps when they are ``spike`` times slower).
        settled: ``first`` is known to be the faster (an earlier loop's result): the
            first probe of the other candidate comes after ``interval`` windows, counting
            ``windows_since_probe`` already run, instead of after the first window.
        windows_since_probe: with ``settled``, the windows run since the last probe.
        clock: the time function (for tests).

    Attributes:
        threads: the thread count in use now (during a probe, the probed one).
        choice: the thread count chosen (the faster one at the last comparison).
        history: ``(step, threads, median seconds)`` of every finished window.
    """

    def __init__(
        self,
        max_threads: int | None = None,
        *,
        window: int = 8,
        interval: int = 4,
        max_interval: int = 64,
        margin: float = 0.1,
        slowdown: float = 0.3,
        spike: float = 3.0,
        first: int | None = None,
        settled: bool = False,
        windows_since_probe: int = 0,
        clock=time.perf_counter,
    ) -> None:
        if max_threads is None:
            max_threads = min(available_cores(), torch.get_num_threads())
        if int(max_threads) < 1:
            raise ValueError(f"max_threads must be >= 1, got {max_threads}")
        if int(window) < 3:
            raise ValueError(f"window must be >= 3 steps, got {window}")
        self.max_threads = int(max_threads)
        self.window = int(window)
        self.interval = self._interval0 = max(1, int(interval))
        self.max_interval = max(self.interval, int(max_interval))
        self.margin = float(margin)
        self.slowdown = float(slowdown)
        self.spike = float(spike)
        self._spikes = 0
        self.clock = clock
        self.history: list[tuple[int, int, float]] = []
        self._steps = 0
        self._times: list[float] = []
        self._t0: float | None = None
        self._best: dict[int, float] = {}  # last median of each candidate
        if first is not None and int(first) not in (1, self.max_threads):
            raise ValueError(f"first must be 1 or max_threads ({self.max_threads}), got {first}")
        start = self.max_threads if first is None else int(first)
        self._choice = start
        self._probing = False
        self._settled = bool(settled)
        self._windows_since_probe = int(windows_since_probe) if settled else 0
        self._initial = torch.get_num_threads()
        self.threads = start
        self._apply(start)

    # ------------------------------------------------------------------ timing
    def start(self) -> None:
        """Mark the start of a step."""
        self._t0 = self.clock()

    def stop(self) -> None:
        """Mark the end of the step started by :meth:`start` and maybe change the threads."""
        if self._t0 is None:
            return
        t = self.clock() - self._t0
        self._times.append(t)
        self._t0 = None
        self._steps += 1
        if self.max_threads == 1:
            return
        # a step of several threads far slower than one thread was: the cliff
        ref = self._best.get(1, self._best.get(self.max_threads))
        spiking = self.threads > 1 and ref is not None and t > self.spike * ref
        self._spikes = self._spikes + 1 if spiking else 0
        if self._spikes >= 2:
            self._spikes = 0
            self._end_window(statistics.median(self._times[-2:]))
            self._times = []
        elif len(self._times) >= self.window:
            self._end_window(statistics.median(self._times[1:]))
            self._times = []

    @property
    def choice(self) -> int:
        return self._choice

    @property
    def windows_since_probe(self) -> int:
        """Windows of the chosen count run since the other was last probed."""
        return self._windows_since_probe

    def step(self) -> _Step:
        """Context manager timing one step: ``with governor.step(): ...``."""
        return _Step(self)

    def restore(self) -> None:
        """Put back the thread count torch had before the governor was made."""
        torch.set_num_threads(self._initial)

    # ------------------------------------------------------------------ policy
    def _apply(self, n: int) -> None:
        if torch.get_num_threads() != n:
            torch.set_num_threads(n)
        self.threads = n

    def _other(self, n: int) -> int:
        return 1 if n == self.max_threads else self.max_threads

    def _end_window(self, median: float) -> None:
        n = self.threads
        self.history.append((self._steps, n, median))
        previous = self._best.get(n)
        self._best[n] = median
        other = self._other(self._choice)
        if self._probing:  # a window of the other candidate has just been measured
            self._probing = False
            self._windows_since_probe = 0
            if median < self._best[self._choice] * (1.0 - self.margin):
                self._choice = n  # the probe won
                self.interval = self._interval0
            else:
                self.interval = min(2 * self.interval, self.max_interval)
            self._apply(self._choice)
            return
        self._windows_since_probe += 1
        # the load changed: several threads got slower (a competitor came), or one
        # thread got faster (it left); one thread getting slower says nothing for more
        changed = previous is not None and (
            median > previous * (1.0 + self.slowdown)
            if n > 1
            else median < previous * (1.0 - self.slowdown)
        )
        unknown = other not in self._best and not self._settled
        if unknown or changed or self._windows_since_probe >= self.interval:
            if changed:
                self.interval = self._interval0
            self._probing = True
            self._apply(other)


class _Step:
    def __init__(self, governor: ThreadGovernor) -> None:
        self.governor = governor

    def __enter__(self) -> ThreadGovernor:
        self.governor.start()
        return self.governor

    def __exit__(self, *exc: object) -> None:
        self.governor.stop()


def governed() -> bool:
    """Whether a :func:`thread_scope` (or ``train()``'s thread option) is open: the
    threads are someone else's to set."""
    return _GOVERNED > 0


@contextlib.contextmanager
def claim_threads() -> Iterator[None]:
    """Mark the threads as set by the caller for the ``with`` block: a
    ``thread_scope("auto")`` opened inside leaves them alone (``train()`` holds
    this while its own governor runs)."""
    global _GOVERNED
    with _GOVERNED_LOCK:
        _GOVERNED += 1
    try:
        yield
    finally:
        with _GOVERNED_LOCK:
            _GOVERNED -= 1


class _Ungoverned:
    """What :func:`thread_scope` yields when nothing is timed: ``step()`` does nothing."""

    choice: int | None = None

    def step(self) -> contextlib.AbstractContextManager[None]:
        return contextlib.nullcontext()


@contextlib.contextmanager
def thread_scope(
    threads: int | str | None,
    device: torch.device | str = "cpu",
    steps: int | None = None,
) -> Iterator[ThreadGovernor | _Ungoverned]:
    """torch's CPU threads for a loop of steps; put back when the loop ends.

    Use as ``with thread_scope(threads, device, steps) as scope:`` and wrap each
    step in ``with scope.step():``.

    Args:
        threads: ``"auto"``: a :class:`ThreadGovernor` times the steps and chooses
            between one thread and ``min(available_cores(), torch.get_num_threads())``,
            measuring one thread first;
            nothing is done on a non-CPU device, for fewer than
            :data:`MIN_AUTO_STEPS` steps, or inside another open scope (the outer
            loop governs). An integer fixes the count for the loop (inside
            another scope too). ``None`` leaves torch alone.
        device: where the loop computes.
        steps: the loop's length, if known.

    Yields:
        The governor, or an object whose ``step()`` does nothing.

    Raises:
        ValueError: a bad ``threads`` value (:func:`parse_threads`).
    """
    threads = parse_threads(threads)
    cpu = torch.device(device).type == "cpu"
    short = steps is not None and steps < MIN_AUTO_STEPS
    if threads is None or not cpu or (threads == "auto" and (governed() or short)):
        yield _Ungoverned()
        return
    initial = torch.get_num_threads()
    try:
        with claim_threads():
            if threads == "auto":
                top = min(available_cores(), initial)
                if top > 1:  # one thread first: cheap to leave where it loses
                    governor = _remembered_governor(top)
                    yield governor
                    _remember(governor)
                    return
                threads = 1
            torch.set_num_threads(int(threads))
            yield _Ungoverned()
    finally:
        torch.set_num_threads(initial)


def _remembered_governor(top: int) -> ThreadGovernor:
    """A governor measuring one thread first, settled on it if a loop on ``top`` cores
    ended on one thread less than :data:`MEMORY_S` seconds ago."""
    last = _SETTLED.get(top)
    if last is None or time.monotonic() - last[0] > MEMORY_S:
        return ThreadGovernor(top, first=1)
    _, interval, windows = last
    governor = ThreadGovernor(top, first=1, settled=True, windows_since_probe=windows)
    governor.interval = interval  # the schedule goes on; a won probe still resets it to 4
    return governor


def settled_on_one(device: torch.device | str = "cpu") -> bool:
    """Whether a governed loop on this process's cores ended on one thread less than
    :data:`MEMORY_S` seconds ago (a CPU that another process uses): work outside any loop,
    such as the backward pass after a governed rollout, then runs best on one thread too."""
    if torch.device(device).type != "cpu":
        return False
    last = _SETTLED.get(min(available_cores(), torch.get_num_threads()))
    return last is not None and time.monotonic() - last[0] <= MEMORY_S


def _remember(governor: ThreadGovernor) -> None:
    """Keep the probe schedule of a loop that ended on one thread, forget it for one that
    ended on several; a loop too short to finish a window changes nothing."""
    if not governor.history:
        return
    if governor.choice == 1:
        schedule = (governor.interval, governor.windows_since_probe)
        _SETTLED[governor.max_threads] = (time.monotonic(), *schedule)
    else:
        _SETTLED.pop(governor.max_threads, None)

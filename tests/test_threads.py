"""The thread governor: it picks the faster thread count and follows a change of load; the
``threads`` option of the loops of steps (simulate, optimize) uses it."""

from __future__ import annotations

import pytest
import torch

import diffcontact.threads as threads_mod
from diffcontact.threads import (
    ThreadGovernor,
    _cgroup_quota,
    available_cores,
    claim_threads,
    governed,
    parse_threads,
    thread_scope,
)  # fmt: skip


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture(autouse=True)
def keep_threads(monkeypatch):
    """Each test starts with torch's threads and no remembered loop (and puts both back)."""
    monkeypatch.setattr(threads_mod, "_SETTLED", {})
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


def run(governor: ThreadGovernor, clock: FakeClock, steps: int, cost) -> list[int]:
    """Run ``steps`` fake steps whose duration is ``cost(step, threads)``; the threads used."""
    used = []
    for i in range(steps):
        with governor.step():
            used.append(torch.get_num_threads())
            clock.now += cost(i, torch.get_num_threads())
    return used


def test_keeps_several_threads_when_they_are_faster():
    clock = FakeClock()
    g = ThreadGovernor(2, clock=clock)
    used = run(g, clock, 400, lambda i, n: 1.0 if n == 2 else 1.6)
    assert g.threads == 2 and g.choice == 2
    # probes back off: after the first two windows, few steps are spent on the slow count
    assert used[16:].count(1) / len(used[16:]) < 0.1


def test_falls_back_to_one_thread_under_load():
    clock = FakeClock()
    g = ThreadGovernor(2, clock=clock)
    used = run(g, clock, 400, lambda i, n: 2.0 if n == 2 else 1.0)
    assert g.threads == 1 and g.choice == 1
    assert used[16:].count(2) / len(used[16:]) < 0.1


def test_follows_a_change_of_load():
    """Idle at first (2 threads faster), then a competing process starts (1 faster)."""
    clock = FakeClock()
    g = ThreadGovernor(2, clock=clock)

    def cost(i: int, n: int) -> float:
        busy = i >= 300
        return (2.0 if n == 2 else 1.0) if busy else (1.0 if n == 2 else 1.5)

    used = run(g, clock, 600, cost)
    assert used[299] == 2
    # the slowdown of the 2-thread windows triggers a probe at once: within 3 windows
    assert used[300 + 3 * g.window :].count(2) / len(used[300 + 3 * g.window :]) < 0.1
    assert g.threads == 1 and g.choice == 1
    assert any(n == 1 for _, n, _ in g.history) and any(n == 2 for _, n, _ in g.history)


def test_ties_keep_the_current_choice():
    clock = FakeClock()
    g = ThreadGovernor(2, clock=clock)
    run(g, clock, 200, lambda i, n: 1.0 if n == 2 else 0.95)  # 5 % is within the margin
    assert g.threads == 2 and g.choice == 2


def test_one_core_never_probes():
    clock = FakeClock()
    g = ThreadGovernor(1, clock=clock)
    used = run(g, clock, 50, lambda i, n: 1.0)
    assert set(used) == {1} and g.history == []


def test_restore_puts_back_the_initial_count():
    torch.set_num_threads(2)
    clock = FakeClock()
    g = ThreadGovernor(2, clock=clock)
    run(g, clock, 40, lambda i, n: 2.0 if n == 2 else 1.0)
    assert torch.get_num_threads() == 1
    g.restore()
    assert torch.get_num_threads() == 2


def test_one_thread_first_leaves_a_loaded_cpu_after_two_steps():
    """first=1 (short loops): the probe of two threads stops after two spiking steps."""
    clock = FakeClock()
    g = ThreadGovernor(2, first=1, clock=clock)
    used = run(g, clock, 40, lambda i, n: 3.5 if n == 2 else 1.0)
    assert used[: g.window] == [1] * g.window and used[g.window : g.window + 2] == [2, 2]
    assert set(used[g.window + 2 :]) == {1} and g.choice == 1
    idle = ThreadGovernor(2, first=1, clock=clock)
    used = run(idle, clock, 40, lambda i, n: 1.0 if n == 2 else 1.6)
    assert idle.choice == 2 and used[-1] == 2


def test_bad_arguments():
    with pytest.raises(ValueError, match="first must be"):
        ThreadGovernor(4, first=2)
    with pytest.raises(ValueError, match="max_threads"):
        ThreadGovernor(0)
    with pytest.raises(ValueError, match="window"):
        ThreadGovernor(2, window=2)
    for bad in ("many", 0, -1, 1.5, True):
        with pytest.raises(ValueError, match="threads must be"):
            parse_threads(bad)
    assert (
        parse_threads("3") == 3 and parse_threads("auto") == "auto" and parse_threads(None) is None
    )


def test_available_cores_respects_a_cgroup_quota(tmp_path, monkeypatch):
    (tmp_path / "cpu.max").write_text("150000 100000\n")
    assert _cgroup_quota(tmp_path) == 1.5
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert _cgroup_quota(tmp_path) is None
    monkeypatch.setattr("diffcontact.threads._cgroup_quota", lambda: 1.5)
    assert available_cores() == 1
    monkeypatch.setattr("diffcontact.threads._cgroup_quota", lambda: None)
    assert 1 <= available_cores() <= (torch.multiprocessing.cpu_count() or 1)


def test_a_sudden_tenfold_slowdown_ends_the_window_early():
    clock = FakeClock()
    g = ThreadGovernor(2, clock=clock)

    def cost(i: int, n: int) -> float:
        if i < 100:
            return 1.0 if n == 2 else 1.5
        return 10.0 if n == 2 else 1.5  # a competing process: two threads 10x slower

    used = run(g, clock, 140, cost)
    first_busy = [n for n in used[100:]]
    # two slow steps, then the probe with one thread wins
    assert first_busy[:2] == [2, 2] and set(first_busy[2 : 2 + g.window]) == {1}
    assert g.threads == 1 and g.choice == 1


def test_more_load_does_not_send_it_back_to_several_threads():
    """Under growing load one thread gets slower, several threads far slower: no probes then;
    when the load leaves, several threads are tried again soon."""
    clock = FakeClock()
    g = ThreadGovernor(2, clock=clock)

    def cost(i: int, n: int) -> float:
        if i < 200:  # one competitor
            return 2.0 if n == 2 else 1.0
        if i < 400:  # more competitors: one thread slower too, two threads much slower
            return 8.0 if n == 2 else 2.4
        return 1.0 if n == 2 else 1.5  # idle

    used = run(g, clock, 600, cost)
    busier = used[200 + g.window : 400]
    assert busier.count(2) / len(busier) < 0.1
    assert used[400 + 3 * g.window :].count(2) / len(used[400 + 3 * g.window :]) > 0.85
    assert g.threads == 2 and g.choice == 2


# ------------------------------------------------------------------ thread_scope


class SlowManyClock:
    """Advances by a step's cost at every reading: two threads cost 3, one thread 1 (a loaded
    CPU), so the time between a step's start and stop is the cost of the threads in use."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        self.now += 3.0 if torch.get_num_threads() > 1 else 1.0
        return self.now


@pytest.fixture
def two_cores(monkeypatch):
    """Two available cores and torch at two threads; governors made by thread_scope read the
    loaded-CPU clock above (their instances are collected in the list yielded)."""
    made = []

    class Recording(ThreadGovernor):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, clock=SlowManyClock(), **kwargs)
            made.append(self)

    monkeypatch.setattr(threads_mod, "available_cores", lambda: 2)
    monkeypatch.setattr(threads_mod, "ThreadGovernor", Recording)
    torch.set_num_threads(2)
    return made


def test_thread_scope_governs_a_long_loop_and_puts_the_threads_back(two_cores):
    with thread_scope("auto", "cpu", steps=60) as scope:
        assert governed()
        used = []
        for _ in range(60):
            with scope.step():
                used.append(torch.get_num_threads())
    assert len(two_cores) == 1 and scope is two_cores[0]
    assert scope.choice == 1 and used[-1] == 1  # two threads were slower here
    assert torch.get_num_threads() == 2 and not governed()


def test_thread_scope_leaves_short_nested_and_none_loops_alone(two_cores):
    for threads, steps in (("auto", threads_mod.MIN_AUTO_STEPS - 1), (None, 100)):
        with thread_scope(threads, "cpu", steps) as scope:
            assert scope.choice is None and not governed()
            with scope.step():
                assert torch.get_num_threads() == 2
    with claim_threads(), thread_scope("auto", "cpu", 100) as scope:
        assert scope.choice is None
    with thread_scope("auto", "meta", 100) as scope:  # not a CPU loop
        assert scope.choice is None
    assert two_cores == []
    with thread_scope(1, "cpu", 5):  # a fixed count applies, short or nested
        assert torch.get_num_threads() == 1 and governed()
    assert torch.get_num_threads() == 2
    with pytest.raises(ValueError, match="threads must be"):
        with thread_scope("fast", "cpu", 100):
            pass


def test_simulate_governs_its_steps_without_changing_the_result(two_cores):
    import diffcontact as dc

    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(8, seed=0)
    auto = system.simulate(z0, 40)
    assert len(two_cores) == 1 and two_cores[0].choice == 1
    assert torch.get_num_threads() == 2
    fixed = system.simulate(z0, 40, threads=None)
    assert len(two_cores) == 1
    torch.testing.assert_close(auto, fixed, rtol=0, atol=1e-12)
    with claim_threads():  # inside a training step or a planning iteration: left alone
        system.simulate(z0, 40)
    assert len(two_cores) == 1
    with pytest.raises(ValueError, match="threads must be"):
        system.simulate(z0, 40, threads=0)


def test_the_training_callback_claims_the_threads():
    from diffcontact.learning.training.governor import thread_callback

    callback = thread_callback(1, "cpu")
    callback.setup(None, None, "fit")
    assert governed() and torch.get_num_threads() == 1
    callback.teardown(None, None, "fit")
    assert not governed()


def _loop(steps: int) -> list[int]:
    with thread_scope("auto", "cpu", steps=steps) as scope:
        used = []
        for _ in range(steps):
            with scope.step():
                used.append(torch.get_num_threads())
    return used


def test_a_loop_after_a_loaded_one_starts_settled_on_one_thread(two_cores):
    first = _loop(60)
    window = two_cores[0].window
    assert first[:window] == [1] * window and 2 in first  # probed after its first window
    second = _loop(60)
    assert two_cores[1]._settled and second[: 2 * window] == [1] * (2 * window)
    # the probe schedule goes on across loops: the second one probes when the first's
    # interval is used up, not after its own first window
    g1, g2 = two_cores
    probes = [n for _, n, _ in g2.history].count(2)
    assert probes <= 1 and g2.interval >= g1.interval
    assert g2._interval0 == g1._interval0  # a probe that wins or a load change resets to it
    assert torch.get_num_threads() == 2 and not governed()


def test_the_memory_expires_and_a_loop_on_several_threads_clears_it(two_cores, monkeypatch):
    _loop(60)
    assert 2 in threads_mod._SETTLED
    monkeypatch.setattr(threads_mod, "MEMORY_S", 0.0)
    _loop(60)
    assert not two_cores[1]._settled  # too old: measured afresh (and loaded again)
    idle = two_cores[1]
    idle._choice = 2  # as if several threads had won
    threads_mod._remember(idle)
    assert 2 not in threads_mod._SETTLED

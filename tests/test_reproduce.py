"""experiments/reproduce.py: one tiny run end to end, the report, and its helpers."""

import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import diffcontact as dc

pytestmark = pytest.mark.filterwarnings("ignore:.*LeafSpec")

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, EXPERIMENTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # (dataclasses look their module up)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def repro():
    return _load("reproduce")


def test_contact_names_follow_the_contact_numbering(repro):
    names = repro.contact_names("BP5")
    system = dc.load_system("BP5")
    assert len(names) == system.n_contacts == 30
    assert names[0] == "body 1-body 2" and names[9] == "body 4-body 5"
    # body-wall pairs: index = n_pairs + n_walls * i + j (paper-facts.md)
    assert names[10 + 4 * 2 + 3] == "body 3-wall 4"


def test_tables_cover_what_the_issue_asks(repro):
    runs = repro.TABLES
    assert len(runs["mass-ratios"]) == 16 and len(runs["rel-error"]) == 8
    assert {t for t, _ in runs["contact-params"]} == {"CP3", "CP3-e", "BP5-e", "Gyro"}
    for task, models in repro.PAPER_MASS.items():
        true = dc.load_system(task).mass
        assert all(len(v) == len(true) - 1 for v in models.values())
        # the paper's numbers are within 0.5% of the truth of our configs (S.3 swap applied)
        for values in models.values():
            ratios = (true[1:] / true[0]).tolist()
            assert all(abs(v / r - 1) < 5e-3 for v, r in zip(values, ratios, strict=True))


def test_one_tiny_run_end_to_end(repro, tmp_path, capsys):
    out = tmp_path / "repro"
    code = repro.main(
        ["--only", "BP5:CM-CD-CLNN", "--epochs", "1", "--jobs", "1", "--out", str(out),
         "--n-train", "6", "--n-val", "2", "--n-test", "2", "--doc", str(tmp_path / "r.md")]
    )  # fmt: skip
    assert code == 0
    data = json.loads((out / "results.json").read_text())
    run = data["runs"]["BP5/CM-CD-CLNN"]
    assert run["epochs"] == 1 and run["train_seconds"] > 0
    assert len(run["contact_counts"]) == 30 and sum(run["contact_counts"]) > 0
    assert run["mass_ratios"]["true"] == pytest.approx([2.0, 6.0, 8.0, 10.0])
    assert run["mass_first"]["true"] == pytest.approx(0.05) and run["mass_first"]["learned"] > 0
    report = (out / "results.md").read_text()
    assert report == (tmp_path / "r.md").read_text()
    assert "| truth | 2.0000 | 6.0000 | 8.0000 | 10.0000 |" in report
    assert "## Per-contact friction and restitution" in report
    assert "## Test rollout relative error" in report
    # the provenance is this command's (it named the full reproduction's and 800 / 100 / 100)
    assert f"--doc {tmp_path / 'r.md'} --only BP5:CM-CD-CLNN --n-train 6" in report
    assert "(6 / 2 / 2 trajectories" in report and "one run at a time" in report
    # the run is reused: a second invocation trains nothing and gives the same numbers
    assert repro.main(["--only", "BP5:CM-CD-CLNN", "--epochs", "1", "--jobs", "1",
                       "--out", str(out), "--n-train", "6", "--n-val", "2",
                       "--n-test", "2"]) == 0  # fmt: skip
    again = json.loads((out / "results.json").read_text())["runs"]["BP5/CM-CD-CLNN"]
    assert again["mass_ratios"] == run["mass_ratios"]
    assert again["train_seconds"] == run["train_seconds"]
    # the report alone, from results.json
    report = (out / "results.md").read_text()
    (out / "results.md").unlink()
    assert repro.main(["--report-only", "--out", str(out)]) == 0
    assert (out / "results.md").read_text() == report
    capsys.readouterr()


def test_bad_arguments(repro, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        repro.main(["mass", "--out", str(tmp_path)])
    assert exc.value.code == 2 and "unknown table" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        repro.main(["--only", "BP5:XX", "--out", str(tmp_path)])
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        repro.main(["per-contact", "--tasks", "CP3", "--out", str(tmp_path)])
    assert exc.value.code == 2 and "--tasks: no run of CP3" in capsys.readouterr().err
    assert repro.main(["--report-only", "--out", str(tmp_path / "none")]) == 2


def test_cmr_mass_scale_script(tmp_path, capsys):
    from diffcontact.learning.data.generate import generate_dataset

    script = _load("cmr_mass_scale")
    data = tmp_path / "BP5-e"
    generate_dataset("BP5-e", data, n_train=8, n_val=2, n_test=2, progress=False)
    assert script.main([str(data), "--scales", "0.5", "2", "--chunks", "4", "--iters", "2"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| 0.5 |") or
            line.startswith("| 2 |")]  # fmt: skip
    assert len(rows) == 2 and all(" % | " in r for r in rows), out
    # m1 is the scale times the true mass (0.1)
    assert rows[0].split("|")[2].strip() == "0.05" and rows[1].split("|")[2].strip() == "0.2"
    cp3 = tmp_path / "CP3"
    generate_dataset("CP3", cp3, n_train=2, n_val=1, n_test=1, progress=False)
    with pytest.raises(SystemExit) as exc:
        script.main([str(cp3)])
    assert exc.value.code == 2 and "has a true potential" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        script.main([str(data), "--scales", "0"])


def test_report_rewrite_keeps_the_control_section(repro, tmp_path):
    """reproduce.py rewrites results.md; the section of experiments/control.py survives,
    and control.py replaces its own section without touching the rest."""
    control = _load("control")
    assert (control.BEGIN, control.END) in repro.KEPT_SECTIONS
    doc = tmp_path / "results.md"
    doc.write_text("# old report\n")
    control.write_doc(doc, f"{control.BEGIN}\ncontrol table v1\n{control.END}")
    control.write_doc(doc, f"{control.BEGIN}\ncontrol table v2\n{control.END}")
    text = doc.read_text()
    assert "# old report" in text and "v2" in text and "v1" not in text
    kept = repro._kept_sections(doc)
    assert "control table v2" in kept and "# old report" not in kept
    assert repro._kept_sections(tmp_path / "missing.md") == ""


def test_a_doc_is_never_cut_at_a_stray_marker(repro, tmp_path, capsys):
    """A begin marker without its end marker: the section was appended, and the next run
    replaced everything from the stray marker on, hand-written text included. Now the
    scripts refuse before any work, and reproduce.py refuses a file that is not its own
    report (it replaced any file given to --doc)."""
    control, uncertainty, compare = _load("control"), _load("uncertainty"), _load("compare")
    doc = tmp_path / "notes.md"
    for begin in (control.BEGIN, uncertainty.BEGIN, compare.section_markers("models")[0]):
        original = f"intro\n{begin}\nhand-written A\n## Another section\nhand-written B\n"
        doc.write_text(original)
        with pytest.raises(ValueError, match="mend the file by hand"):
            if begin == control.BEGIN:
                control.write_doc(doc, f"{control.BEGIN}\nnew\n{control.END}")
            elif begin == uncertainty.BEGIN:
                uncertainty.write_doc(doc, f"{uncertainty.BEGIN}\nnew\n{uncertainty.END}")
            else:
                compare.write_section(doc, "models", "new")
        assert doc.read_text() == original
    # the command line refuses before any work
    doc.write_text(f"intro\n{control.BEGIN}\nhand-written\n")
    with pytest.raises(SystemExit):
        control.main(["--out", str(tmp_path / "c"), "--doc", str(doc), "--tasks", "throw"])
    assert "mend the file by hand" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()
    notes = tmp_path / "mine.md"
    notes.write_text("# My notes\nimportant text\n")
    with pytest.raises(SystemExit):
        repro.main(["--report-only", "--out", str(tmp_path / "r"), "--doc", str(notes)])
    assert "is not a report of this script" in capsys.readouterr().err
    assert notes.read_text() == "# My notes\nimportant text\n"


def test_chaos_floor_script(tmp_path, capsys):
    """The true system reproduces its own test set (rel 0: error 0); a mass off is not 0."""
    from diffcontact.learning.data.generate import generate_dataset

    script = _load("chaos_floor")
    data = tmp_path / "BP5-e"
    generate_dataset("BP5-e", data, n_train=2, n_val=2, n_test=3, progress=False)
    rows = script.floor(data, [0.0, 1e-2], body=1)
    assert rows[0]["mean"] == 0.0 and rows[0]["median"] == 0.0
    assert rows[1]["mean"] > 0.0
    assert script.main([str(data), "--rel", "1e-3"]) == 0
    assert "| 1e-03 |" in capsys.readouterr().out
    assert script.main([str(tmp_path / "none")]) == 2


def test_learned_physics_with_the_true_parameters_reproduces_the_test_set(tmp_path):
    """The true system with "learned" = true parameters has error 0; a mass off does not;
    per-contact values that the config holds as one number are not mapped (None)."""
    from diffcontact.learning.data.generate import generate_dataset

    script = _load("chaos_floor")
    data = tmp_path / "CP3"
    generate_dataset("CP3", data, n_train=2, n_val=2, n_test=3, progress=False)
    system = dc.load_system("CP3")
    K = system.n_contacts
    # a common factor on all masses changes nothing (the potential follows the masses)
    truth = {"mass": [0.3, 0.6, 0.45], "second_moments": None, "mu": [0.5] * K, "cor": [0.0] * K}
    row = script.learned_physics(data, truth)
    assert row["mean"] < 1e-12 and row["median"] < 1e-12
    off = {**truth, "mass": [0.3, 0.6 * (1 + 1e-2), 0.45]}
    assert script.learned_physics(data, off)["mean"] > 1e-6
    per_contact = {**truth, "mu": [0.5] * (K - 1) + [0.4]}
    assert script.learned_physics(data, per_contact) is None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (exited, not yet reaped) counts as gone
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return True


@pytest.mark.skipif(sys.platform != "linux", reason="reads /proc")
def test_sigterm_stops_the_worker_processes(tmp_path):
    """SIGTERM (timeout, a batch scheduler) to compare.py / reproduce.py with --jobs 2 left
    their spawned workers training, orphaned."""
    script = tmp_path / "pool.py"
    script.write_text(
        "import sys, time\n"
        f"sys.path.insert(0, {str(EXPERIMENTS)!r})\n"
        "from reproduce import job_pool\n"
        "if __name__ == '__main__':\n"
        "    with job_pool(2) as pool:\n"
        "        futures = [pool.submit(time.sleep, 120) for _ in range(2)]\n"
        "        while len(pool._processes) < 2:\n"
        "            time.sleep(0.1)\n"
        "        print(' '.join(map(str, pool._processes)), flush=True)\n"
        "        futures[0].result()\n"
    )
    _stop_and_check([sys.executable, str(script)])


def _stop_and_check(command: list[str]) -> None:
    """Run ``command`` (a pool script printing its two workers' pids once they work),
    SIGTERM it: it must exit with 128 + SIGTERM within 60 s, its workers within 20 s more."""
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
    try:
        workers = [int(p) for p in proc.stdout.readline().split()]
        assert len(workers) == 2 and all(_alive(p) for p in workers)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 128 + signal.SIGTERM
        deadline = time.monotonic() + 20
        while any(_alive(p) for p in workers) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not any(_alive(p) for p in workers)
    finally:
        proc.kill()
        for pid in locals().get("workers", []):
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


@pytest.mark.skipif(sys.platform != "linux", reason="reads /proc")
def test_sigterm_starts_no_queued_job(tmp_path):
    """The workers' training stops at a checkpoint on SIGTERM (a handler, not death), and
    the workers then took the queued runs one after the other: a stopped compare.py went on
    training (2026-11-27, the scalability run). Jobs not started are now cancelled; a job
    the pool had already handed to a worker is stopped the same way after a grace period."""
    script = tmp_path / "pool.py"
    script.write_text(
        "import signal, sys, time\n"
        "from pathlib import Path\n"
        f"sys.path.insert(0, {str(EXPERIMENTS)!r})\n"
        "import reproduce\n"
        "reproduce.STOP_GRACE = 2.0\n"
        "def job(k, folder):\n"
        "    Path(folder, f'started-{k}').write_text('')\n"
        "    def stop(signum, frame):\n"
        "        raise RuntimeError('stopped at a checkpoint')\n"
        "    signal.signal(signal.SIGTERM, stop)\n"
        "    try:\n"
        "        time.sleep(120)\n"
        "    finally:\n"
        "        signal.signal(signal.SIGTERM, signal.SIG_DFL)\n"
        "if __name__ == '__main__':\n"
        "    folder = sys.argv[1]\n"
        "    with reproduce.job_pool(2) as pool:\n"
        "        futures = [pool.submit(job, k, folder) for k in range(6)]\n"
        "        while len(list(Path(folder).glob('started-*'))) < 2:\n"
        "            time.sleep(0.1)\n"
        "        print(' '.join(map(str, pool._processes)), flush=True)\n"
        "        for fut in futures:\n"
        "            fut.result()\n"
    )
    folder = tmp_path / "jobs"
    folder.mkdir()
    _stop_and_check([sys.executable, str(script), str(folder)])
    # the two running, and at most the one the pool had queued to a worker
    assert len(list(folder.glob("started-*"))) <= 3


def test_inline_jobs_run_one_by_one_as_they_are_reached(repro):
    """--jobs 1 ran every job at submission, so the caller stored no result until all had
    run (an interrupted command left nothing to report)."""
    calls = []
    with repro.job_pool(1) as pool:
        futures = [pool.submit(calls.append, k) for k in range(3)]
        assert calls == []  # nothing runs at submission
        for k, fut in enumerate(repro.completed(futures)):
            assert calls == list(range(k + 1))  # this job, and no later one, has run
            assert fut.result() is None
    failing = repro._InlineExecutor().submit(int, "x")
    (fut,) = list(repro.completed([failing]))
    with pytest.raises(ValueError):
        fut.result()


def test_a_dataset_that_cannot_be_made_is_one_line(repro, monkeypatch, tmp_path, capsys):
    """A data folder holding a dataset made with other arguments ended the command with a
    traceback from the worker; now its runs are reported on one line each and skipped."""

    def make_dataset(task, out, *args):
        raise ValueError(f"{out} already holds a dataset made with different arguments")

    monkeypatch.setattr(repro, "make_dataset", make_dataset)
    code = repro.main(["--only", "BP5:CM-CD-CLNN", "--epochs", "1", "--jobs", "1",
                       "--out", str(tmp_path / "repro")])  # fmt: skip
    assert code == 1
    captured = capsys.readouterr()
    assert "Traceback" not in captured.out + captured.err
    assert "data BP5: FAILED: " in captured.out
    assert "BP5 CM-CD-CLNN: not run, its dataset failed (ValueError: " in captured.err

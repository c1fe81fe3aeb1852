"""experiments/compare.py: each experiment on a tiny configuration, its section and plot."""

import importlib.util
import json
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.filterwarnings("ignore:.*LeafSpec")

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
TINY = ["--jobs", "1", "--threads", "1", "--epochs", "1", "--n-train", "4", "--n-val", "2",
        "--n-test", "2", "--eval-steps", "5"]  # fmt: skip


def _load(name):
    spec = importlib.util.spec_from_file_location(name, EXPERIMENTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while it is executed
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def compare():
    return _load("compare")


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    """One output folder and one report for all experiments (they share runs)."""
    root = tmp_path_factory.mktemp("compare")
    doc = root / "results.md"
    doc.write_text("# report\n\nkept text\n")
    return root / "out", doc


def _section(doc: Path, name: str) -> str:
    text = doc.read_text()
    begin = f"<!-- compare {name} results (experiments/compare.py): begin -->"
    end = f"<!-- compare {name} results: end -->"
    assert text.count(begin) == 1 and text.count(end) == 1, name
    return text.split(begin, 1)[1].split(end, 1)[0]


def _results(out: Path, name: str) -> dict:
    return json.loads((out / f"results-{name}.json").read_text())["runs"]


def test_models_table_and_bar_chart(compare, shared, capsys):
    out, doc = shared
    argv = ["models", "--tasks", "BP5-e", "--models", "CM-CD-CLNN", "IN-SP-CP",
            "--out", str(out), "--doc", str(doc), *TINY]  # fmt: skip
    assert compare.main(argv) == 0
    runs = _results(out, "models")
    assert set(runs) == {"BP5-e/CM-CD-CLNN", "BP5-e/IN-SP-CP"}
    for r in runs.values():
        assert r["epochs"] == 1 and r["train_seconds"] > 0 and r["eval_seconds"] > 0
        assert r["rel_err_mean"] > 0 and r["rel_err_ci95"] >= 0
    assert runs["BP5-e/CM-CD-CLNN"]["cor"]["true"][0] == 1.0
    assert runs["BP5-e/IN-SP-CP"]["mu"]["learned"] is None
    body = _section(doc, "models")
    assert "| BP5-e | CM-CD-CLNN | " in body and "| 2.83e-03 (3.64e-04) |" in body  # paper S.5
    assert "| BP5-e | IN-SP-CP | " in body and "ours below every baseline" in body
    png = doc.parent / "figures" / "compare-models.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
    assert "](figures/compare-models.png)" in body
    assert "# report" in doc.read_text() and "kept text" in doc.read_text()
    # rerun: reused (nothing trained), the same numbers; --report-only rewrites the section
    assert compare.main(argv) == 0
    again = _results(out, "models")
    key = "BP5-e/CM-CD-CLNN"
    assert again[key]["rel_err_mean"] == runs[key]["rel_err_mean"] and not again[key]["trained"]
    assert compare.main(["models", "--out", str(out), "--doc", str(doc), "--report-only"]) == 0
    assert _section(doc, "models") == body
    capsys.readouterr()


def test_mismatch_evaluates_lcp_runs_on_both_test_sets(compare, shared, capsys):
    out, doc = shared
    argv = ["mismatch", "--tasks", "BP5-e", "--out", str(out), "--doc", str(doc), *TINY]
    assert compare.main(argv) == 0
    runs = _results(out, "mismatch")
    assert set(runs) == {"BP5-e/CM-CD-CLNN", "BP5-e_LCP/CM-CD-CLNN"}
    assert not runs["BP5-e/CM-CD-CLNN"]["trained"]  # the models experiment's run
    lcp = runs["BP5-e_LCP/CM-CD-CLNN"]
    on_cm = lcp["also_on"]["BP5-e"]
    # (on BP5-e's frictionless contacts CM and LCP agree to ~1e-14, so the two errors may
    # be equal: the evaluation on the CM test set is checked by its own files)
    assert on_cm["rel_err_mean"] > 0
    assert list(out.rglob("BP5-e_LCP*/**/evaluation-on-BP5-e/metrics.json"))
    meta = json.loads((out / "data" / "BP5-e_LCP" / "metadata.json").read_text())
    assert meta["contact_model"] == "LCP"
    body = _section(doc, "mismatch")
    for row in ("| BP5-e | CM / CM |", "| BP5-e | LCP / CM |", "| BP5-e | LCP / LCP |"):
        assert row in body
    assert "5.46e-03 (2.30e-03)" in body and "1.57e-02 (5.00e-03)" in body  # paper S.5
    assert "(0.000, 1.000)" in body  # paper S.4
    # a task beyond the paper's four renders without paper values (it was a KeyError
    # after the training, and --report-only could never report it)
    stored = json.loads((out / "results-mismatch.json").read_text())
    renamed = {k.replace("BP5-e", "BP5"): v for k, v in stored["runs"].items()}
    for r in renamed.values():
        r["also_on"] = {k.replace("BP5-e", "BP5"): v for k, v in r.get("also_on", {}).items()}
    meta = {**stored["meta"], "tasks": ["BP5"]}
    text = compare.render_mismatch(renamed, meta, None)
    assert "| BP5 | LCP / LCP |" in text and "| BP5 | LCP / CM |" in text
    capsys.readouterr()


def test_noise_and_ablation_rows(compare, shared, capsys):
    out, doc = shared
    assert compare.main(["noise", "--tasks", "BP5-e", "--noise", "0", "0.05", "--out", str(out),
                         "--doc", str(doc), *TINY]) == 0  # fmt: skip
    runs = _results(out, "noise")
    assert set(runs) == {"BP5-e/CM-CD-CLNN", "BP5-e_noise0.05/CM-CD-CLNN"}
    assert runs["BP5-e_noise0.05/CM-CD-CLNN"]["trained"]
    meta = json.loads((out / "data" / "BP5-e_noise0.05" / "metadata.json").read_text())
    assert meta["noise_std"] == 0.05
    body = _section(doc, "noise")
    assert "| BP5-e | 0.05 | " in body and "| BP5-e | 0 | " in body
    assert compare.main(["ablation", "--tasks", "BP5-e", "--eps", "0.1", "0.01", "learnable",
                         "--out", str(out), "--doc", str(doc), *TINY]) == 0  # fmt: skip
    runs = _results(out, "ablation")
    assert runs["BP5-e/CMr-CD-CLNN_eps0.1"]["eps"] == pytest.approx(0.1)
    assert runs["BP5-e/CMr-CD-CLNN_epslearnable"]["eps"] > 0
    assert runs["BP5-e/CMr-CD-CLNN"]["eps"] == pytest.approx(0.01)  # the package default
    body = _section(doc, "ablation")
    assert "| BP5-e | 0.1 | " in body and "| BP5-e | 0.01 | " in body and "Learned eps" in body
    capsys.readouterr()


def test_tables_of_rows_not_run_show_the_paper(compare):
    """The default rows, none of them run: the paper's numbers beside `not run`."""
    meta = {"invocations": [{"wall_seconds": 0.0, "command": "c"}], "date": "d", "version": "v",
            "torch": "t", "cpus": 2, "sizes": [800, 100, 100], "tasks": ["CP3", "CP3-e"],
            "noise": [0.0, 0.01, 0.05], "eps": list(compare.ABLATION_EPS)}  # fmt: skip
    noise = compare.render_noise({}, meta, None)
    assert "| CP3 | 0.05 | not run | not run | 0.462, 0.061 |" in noise
    assert "| CP3-e | 0.01 | not run | not run | 0.004, 1.000 |" in noise
    ablation = compare.render_ablation({}, {**meta, "tasks": ["CP3", "Gyro"]}, None)
    assert "| Gyro | learnable | not run | not run | 0.100, 0.861 |" in ablation
    assert "| CP3 | 0.1 | not run | not run | 0.501, 0.180 |" in ablation


def test_an_interrupted_invocation_is_reported(compare, shared, capsys):
    """The results file carries its meta after every run: --report-only shows the rows
    finished so far and says the invocation was interrupted."""
    out, doc = shared
    stored = json.loads((out / "results-noise.json").read_text())
    stored["meta"]["invocations"][-1]["finished"] = False
    (out / "results-noise.json").write_text(json.dumps(stored))
    assert compare.main(["noise", "--out", str(out), "--doc", str(doc), "--report-only"]) == 0
    body = _section(doc, "noise")
    assert ", interrupted)" in body and "| BP5-e | 0.05 | " in body
    capsys.readouterr()


def test_scalability_subset_marks_rows_not_run(compare, shared, capsys):
    out, doc = shared
    argv = ["scalability", "--parts", "size", "rope", "--size-task", "Rope", "--sizes", "3",
            "--ds", "100", "--models", "CM-CD-CLNN", "--out", str(out), "--doc", str(doc),
            *TINY]  # fmt: skip
    assert compare.main(argv) == 0
    runs = _results(out, "scalability")
    assert set(runs) == {"Rope_N3/CM-CD-CLNN", "Rope-D100/CM-CD-CLNN"}
    meta = json.loads((out / "data" / "Rope_N3" / "metadata.json").read_text())
    assert meta["n_train"] == 3 and meta["task"] == "Rope"
    body = _section(doc, "scalability")
    sizes, ropes = body.split("### Training set size")[1].split("### Degrees of freedom")
    row_3 = next(line for line in sizes.splitlines() if line.startswith("| 3 |"))
    assert "not run" not in row_3 and row_3.endswith("| - |")  # the paper has no N = 3
    assert "| 25 | not run | 1.91e-03 (3.06e-04) |" in sizes
    row_100 = next(line for line in ropes.splitlines() if line.startswith("| 100 |"))
    assert "not run" not in row_100.split("|")[2] and "1.97e-03 (4.72e-04)" in row_100
    assert "| 400 | not run | 3.20e-03 (5.69e-04) |" in ropes
    # every section is still there, once, and reproduce.py keeps them all
    repro = _load("reproduce")
    for name in compare.EXPERIMENTS:
        _section(doc, name)
        assert compare.section_markers(name) in repro.KEPT_SECTIONS
    kept = repro._kept_sections(doc)
    assert all(compare.section_markers(n)[1] in kept for n in compare.EXPERIMENTS)
    assert "kept text" not in kept
    capsys.readouterr()


def test_paper_numbers_are_consistent(compare):
    # the D = 400 rope is the paper's default for S.8 and S.9 (the same numbers)
    for m in compare.SCALE_MODELS:
        assert compare.PAPER_SIZE[m][800] == compare.PAPER_ROPE[m][400]
    assert compare.PAPER_NETWORK["CM-CD-CLNN"]["default"] == compare.PAPER_ROPE["CM-CD-CLNN"][400]
    assert set(compare.PAPER_CONTACT_LCP) == set(compare.MISMATCH_TASKS)
    assert compare.Data("CP3", "LCP", 0.01, 25).key == "CP3_LCP_noise0.01_N25"
    assert compare.Run(compare.Data("Gyro"), "CMr-CD-CLNN", eps="0.1").key == (
        "Gyro/CMr-CD-CLNN_eps0.1"
    )


def test_bad_arguments(compare, tmp_path, capsys):
    bad = (["models", "--tasks", "XX"], ["models", "--models", "YY"],
           ["scalability", "--sizes", "0"], ["noise", "--jobs", "0"], ["nothing"],
           ["ablation", "--eps", "x"])  # fmt: skip
    for argv in bad:
        with pytest.raises(SystemExit) as exc:
            compare.main([*argv, "--out", str(tmp_path)])
        assert exc.value.code == 2
    assert compare.main(["noise", "--report-only", "--out", str(tmp_path / "none")]) == 2
    capsys.readouterr()


# ---------------------------------------------------------------- subset runs (no training)


@pytest.fixture
def fake_runs(compare, monkeypatch):
    """``make_dataset`` and ``train_and_evaluate`` replaced (no simulation, no training):
    every run returns a new relative error, so a row shows which invocation made it."""
    made: list[dict] = []

    def make_dataset(data, out, threads, sizes):
        return compare.Data(**data).key

    def train_and_evaluate(spec, out, epochs, threads, eval_steps=None):
        hidden = None if spec["hidden"] is None else tuple(spec["hidden"])
        also_on = tuple(compare.Data(**d) for d in spec["also_on"])
        run = compare.Run(compare.Data(**spec["data"]), spec["model"], spec["eps"], hidden,
                          also_on)  # fmt: skip
        mean = 1.01e-3 * (len(made) + 1)

        def summary(m):
            return {"rel_err_mean": m, "rel_err_ci95": m / 7, "n_nonfinite": 0, "n_test": 2,
                    "eval_seconds": 0.5}  # fmt: skip

        r = {
            "loss_first": 1.0, "loss_last": 0.5, "loss_drop_last10": 0.1, "key": run.key,
            "task": run.data.task, "data": run.data.key, "model": run.model, "epochs": epochs,
            "train_seconds": 2.0, **summary(mean), "skipped_steps": 0,
            "mu": {"true": [0.5], "learned": [0.4]}, "cor": {"true": [0.0], "learned": [0.1]},
            "eps": 0.01, "also_on": {d.key: summary(mean * 1.5) for d in also_on},
            "trained": True, "evaluated": True,
        }  # fmt: skip
        made.append(r)
        return r

    monkeypatch.setattr(compare, "make_dataset", make_dataset)
    monkeypatch.setattr(compare, "train_and_evaluate", train_and_evaluate)
    return made


FAST = ["--jobs", "1", "--epochs", "1"]


# (experiment, the subset arguments of each invocation in turn)
SUBSETS = [
    ("models", [["--tasks", "Gyro", "--models", "CM-CD-CLNN", "IN-SP-CP"],
                ["--tasks", "BP5-e", "--models", "CM-CD-CLNN"],
                ["--tasks", "Gyro", "--models", "MLP-CD-CLNN"],
                ["--tasks", "Gyro", "--models", "CM-CD-CLNN"]]),
    ("mismatch", [["--tasks", "Gyro"], ["--tasks", "CP3"], ["--tasks", "Gyro"]]),
    ("noise", [["--tasks", "CP3", "--noise", "0.05"], ["--tasks", "CP3-e", "--noise", "0"],
               ["--tasks", "CP3", "--noise", "0"]]),
    ("ablation", [["--tasks", "Gyro", "--eps", "learnable"], ["--tasks", "CP3", "--eps", "0.1"],
                  ["--tasks", "Gyro", "--eps", "0.01", "learnable"]]),
    ("scalability", [["--parts", "rope", "--ds", "100", "--models", "IN-SP-CP"],
                     ["--parts", "size", "--size-task", "Rope", "--sizes", "25",
                      "--models", "CM-CD-CLNN"],
                     ["--parts", "network", "--size-task", "Rope", "--models", "CM-CD-CLNN"]]),
]  # fmt: skip


@pytest.mark.parametrize(("experiment", "subsets"), SUBSETS, ids=[s[0] for s in SUBSETS])
def test_a_subset_run_keeps_the_other_rows(compare, fake_runs, experiment, subsets, tmp_path,
                                          capsys):  # fmt: skip
    """A rerun of some tasks (models, noise stds, ...) updated its own rows and dropped the
    other rows of the results file from the section; now it shows them all, each with the
    numbers of its last run, and the header names every invocation."""
    out, doc = tmp_path / "out", tmp_path / "results.md"
    commands = []
    for subset in subsets:
        argv = [experiment, *subset, "--out", str(out), "--doc", str(doc), *FAST]
        assert compare.main(argv) == 0
        commands.append("python experiments/compare.py " + " ".join(argv))
    stored = _results(out, experiment)
    body = _section(doc, experiment)
    # every stored row is in the section with its latest numbers; a superseded one is not
    latest = {r["key"]: r for r in fake_runs}
    assert set(stored) == set(latest)
    for key, r in latest.items():
        assert compare._err(r) in body, key
    for r in fake_runs:
        if r is not latest[r["key"]]:
            assert compare._err(r) not in body, r["key"]
    assert f"Produced by the {len(subsets)} invocations" in body
    assert all(f"`{c}`" in body for c in commands)
    assert f"**{len(latest)} runs;" in body
    # --report-only renders the same section
    assert compare.main([experiment, "--out", str(out), "--doc", str(doc), "--report-only"]) == 0
    assert _section(doc, experiment) == body
    capsys.readouterr()


def test_subset_rows_keep_the_default_order(compare, fake_runs, tmp_path, capsys):
    """Rows of several invocations: the experiment's default order of tasks and models,
    whatever order they ran in."""
    out, doc = tmp_path / "out", tmp_path / "results.md"
    for tasks, models in ((["Gyro"], ["IN-SP-CP"]), (["CP3", "BP5-e"], ["IN-SP-CP", OURS])):
        argv = ["models", "--tasks", *tasks, "--models", *models, "--out", str(out),
                "--doc", str(doc), *FAST]  # fmt: skip
        assert compare.main(argv) == 0
    order = [(t, m) for t in compare.ALL_TASKS for m in compare.ALL_MODELS]
    cells = [line.removeprefix("| ").split(" | ") for line in _section(doc, "models").splitlines()]
    got = [(c[0], c[1]) for c in cells if len(c) > 1 and (c[0], c[1]) in order]
    assert sorted(got, key=order.index) == got
    assert ("Gyro", "IN-SP-CP") in got and ("Gyro", OURS) not in got and len(got) == 5
    noise = ["noise", "--tasks", "CP3", "--out", str(out), "--doc", str(doc), *FAST]
    assert compare.main([*noise, "--noise", "0.05", "0.01"]) == 0
    assert compare.main([*noise, "--noise", "0.02"]) == 0
    stds = [line.split(" | ")[1] for line in _section(doc, "noise").splitlines()
            if line.startswith("| CP3 |")]  # fmt: skip
    assert stds == ["0.01", "0.05", "0.02"]  # Table S.6's order, then the others
    capsys.readouterr()


OURS = "CM-CD-CLNN"


def test_rows_of_another_setup_are_left_out(compare, fake_runs, tmp_path, capsys):
    """The data sizes are no part of a row's key: a row stored by an invocation with other
    sizes is not shown under this one's header (it names their sizes), nor its command."""
    out, doc = tmp_path / "out", tmp_path / "results.md"
    first = ["models", "--tasks", "CP3", "--models", OURS, "--n-test", "7"]
    second = ["models", "--tasks", "Gyro", "--models", OURS]
    for argv in (first, second):
        assert compare.main([*argv, "--out", str(out), "--doc", str(doc), *FAST]) == 0
    body = _section(doc, "models")
    assert "| Gyro | CM-CD-CLNN |" in body and "| CP3 |" not in body
    assert "--n-test 7" not in body and "Produced by `" in body and "**1 runs;" in body
    assert set(_results(out, "models")) == {"CP3/CM-CD-CLNN", "Gyro/CM-CD-CLNN"}
    # a results file of before the set-up was recorded: its rows are the file's set-up
    file = out / "results-models.json"
    stored = json.loads(file.read_text())
    for r in stored["runs"].values():
        del r["setup"]
    for c in stored["meta"]["invocations"]:
        del c["setup"]
    del stored["meta"]["eval_steps"]
    file.write_text(json.dumps(stored))
    assert compare.main(["models", "--out", str(out), "--doc", str(doc), "--report-only"]) == 0
    legacy = _section(doc, "models")
    assert "| CP3 | CM-CD-CLNN |" in legacy and "| Gyro | CM-CD-CLNN |" in legacy
    assert "Produced by the 2 invocations" in legacy
    # a run on it stamps the old rows with the old file's set-up, as they were made
    assert compare.main([*second, "--out", str(out), "--doc", str(doc), *FAST]) == 0
    assert all(r["setup"]["sizes"] == [800, 100, 100] for r in _results(out, "models").values())
    capsys.readouterr()


def test_keys_parse_back_to_their_runs(compare):
    """The report finds the rows of the results file from their keys."""
    Data, Run = compare.Data, compare.Run
    runs = [
        Run(Data("CP3"), OURS),
        Run(Data("Gyro", "LCP"), OURS),
        Run(Data("CP3-e", noise_std=0.05), OURS),
        Run(Data("Rope", n_train=25), "IN-SP-CP"),
        Run(Data("Rope"), OURS, hidden=(512,) * 6),
        Run(Data("Gyro"), "CMr-CD-CLNN", eps="learnable"),
        Run(Data("CP3"), "CMr-CD-CLNN", eps="1e-3"),
        Run(Data("BP5-e", "LCP", 0.01, 50), "CMr-CD-CLNN", "0.1", (64, 64)),
    ]
    for run in runs:
        assert compare._run_of(run.key, {"task": run.data.task, "model": run.model}) == run
    assert compare._run_of("CP3/CM-CD-CLNN", {"task": "CP3", "model": "IN-SP-CP"}) is None
    assert compare._run_of("CP3_x_y/CM-CD-CLNN", {"task": "CP3", "model": OURS}) is None
    assert compare._run_of("CP3/CM-CD-CLNN_epsx", {"task": "CP3", "model": OURS}) is None
    assert compare._run_of("CP3/CM-CD-CLNN", {}) is None


# ---------------------------------------------------------------- the bar chart


def test_lower_bars_cut_on_the_log_axis(compare):
    nan = float("nan")
    lengths, cut = compare.lower_bars([1e-3, 1e-3, 2e-3, nan, 0.0], [5e-4, 3e-3, 1.9e-3, 1.0, 1.0])
    assert lengths == pytest.approx([5e-4, 9e-4, 1.8e-3, 0.0, 0.0])
    assert cut == [False, True, True, False, False]
    with pytest.raises(ValueError, match="2 means but 1 intervals"):
        compare.lower_bars([1.0, 2.0], [0.1])


def test_the_bar_chart_shows_which_lower_bars_are_cut(compare, monkeypatch, tmp_path):
    """A lower error bar reaching below 0.1 x the mean was cut there without a sign, so it
    read as the confidence interval: now its cut part is dashed, ends in a downward
    triangle, and the legend says so. (Artists inspected, not pixels.)"""
    import matplotlib.figure
    import matplotlib.pyplot as plt
    import numpy as np

    saved = []
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda fig, *a, **k: saved.append(fig))
    results = {
        "CP3/A": {"rel_err_mean": 1e-3, "rel_err_ci95": 5e-4},  # whole bar: down to 5e-4
        "CP3/B": {"rel_err_mean": 2e-3, "rel_err_ci95": 3e-3},  # reaches below zero: cut
    }
    compare._figure(results, tmp_path / "f.png", ["CP3"], ["A", "B"])
    (fig,) = saved
    ax = fig.axes[0]
    x_a, x_b = (p.get_x() + p.get_width() / 2 for p in ax.patches)

    def solid_lows(x):  # lowest end of the solid error-bar lines at x
        lows = [
            min(y for _, y in seg)
            for coll in ax.collections
            if coll.get_linestyle()[0][1] is None  # (offset, dashes): solid
            for seg in coll.get_segments()
            if np.allclose([px for px, _ in seg], x)
        ]
        return min(lows)

    assert solid_lows(x_a) == pytest.approx(5e-4)
    assert solid_lows(x_b) == pytest.approx(2e-3)  # the solid bar goes up only
    triangles = [ln for ln in ax.lines if ln.get_marker() == "v"]
    assert [(list(ln.get_xdata()), list(ln.get_ydata())) for ln in triangles] == [
        ([pytest.approx(x_b)], [pytest.approx(2e-4)])
    ]
    dashed = [c for c in ax.collections if c.get_linestyle()[0][1] is not None]
    assert len(dashed) == 1
    (seg,) = dashed[0].get_segments()
    assert sorted(y for _, y in seg) == pytest.approx([2e-4, 2e-3])
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert legend[:2] == ["A", "B"] and "cut" in legend[2] and "0.1 x mean" in legend[2]
    plt.close(fig)
    # no bar cut: no legend line about it
    saved.clear()
    compare._figure({"CP3/A": results["CP3/A"]}, tmp_path / "g.png", ["CP3"], ["A"])
    assert [t.get_text() for t in saved[0].axes[0].get_legend().get_texts()] == ["A"]
    assert not [ln for ln in saved[0].axes[0].lines if ln.get_marker() == "v"]
    plt.close(saved[0])


def test_the_models_section_says_how_cut_bars_are_drawn(compare):
    meta = {"invocations": [{"wall_seconds": 0.0, "command": "c"}], "date": "d", "version": "v",
            "torch": "t", "cpus": 2, "sizes": [800, 100, 100], "tasks": ["CP3"],
            "models": [OURS]}  # fmt: skip
    r = {"rel_err_mean": 1e-3, "rel_err_ci95": 2e-3, "epochs": 1, "skipped_steps": 0,
         "train_seconds": 1.0, "eval_seconds": 1.0}  # fmt: skip
    body = compare.render_models({"CP3/CM-CD-CLNN": r}, meta, "figures/x.png")
    caption = body.split("](figures/x.png)", 1)[1]
    assert "below 0.1 times the mean" in caption and "drawn cut" in caption


def test_a_dataset_that_cannot_be_made_skips_its_runs(compare, fake_runs, monkeypatch, tmp_path,
                                                      capsys):  # fmt: skip
    """A dataset folder holding data made with other arguments (older code) ended the
    command with a traceback from the worker; now that dataset's runs are reported on one
    line each and skipped, the others run, and the exit is 1."""
    make = compare.make_dataset

    def make_dataset(data, out, threads, sizes):
        if data["task"] == "Gyro":
            raise ValueError(f"{out} already holds a dataset made with different arguments")
        return make(data, out, threads, sizes)

    out, doc = tmp_path / "out", tmp_path / "results.md"
    common = ["--models", "CM-CD-CLNN", "--out", str(out), "--doc", str(doc), *FAST]
    assert compare.main(["models", "--tasks", "CP3", *common]) == 0
    stored = json.loads((out / "results-models.json").read_text())
    stored["meta"]["invocations"][-1]["date"] = "2020-01-02T03:04:05+00:00"  # an older run
    (out / "results-models.json").write_text(json.dumps(stored))
    monkeypatch.setattr(compare, "make_dataset", make_dataset)
    # only the failing dataset: nothing trained, the section keeps the date of its rows
    assert compare.main(["models", "--tasks", "Gyro", *common]) == 1
    captured = capsys.readouterr()
    assert "Traceback" not in captured.out + captured.err
    assert "data Gyro: FAILED: " in captured.out and "different arguments" in captured.out
    assert "FAILED Gyro/CM-CD-CLNN: not run, its dataset failed (ValueError: " in captured.err
    assert set(_results(out, "models")) == {"CP3/CM-CD-CLNN"}
    assert "` (2020-01-02; diffcontact" in _section(doc, "models")
    # with another task: that one runs
    made = len(fake_runs)
    assert compare.main(["models", "--tasks", "Gyro", "CP3", *common]) == 1
    assert len(fake_runs) == made + 1 and fake_runs[-1]["key"] == "CP3/CM-CD-CLNN"
    capsys.readouterr()


def test_a_rope_part_run_keeps_the_network_tables_task(compare, fake_runs, tmp_path, capsys):
    """The scalability tables of network and training size show one task: that of the
    last invocation. A later run of the rope part alone (without --size-task, whose
    default is another task) emptied those tables; now they keep the task of the last
    invocation that ran them."""
    out, doc = tmp_path / "out", tmp_path / "results.md"
    common = ["--models", "CM-CD-CLNN", "--out", str(out), "--doc", str(doc), *FAST]
    argv = ["scalability", "--parts", "network", "--size-task", "Rope", *common]
    assert compare.main(argv) == 0
    network = {r["key"]: compare._err(r) for r in fake_runs}
    assert set(network) == {"Rope/CM-CD-CLNN", "Rope/CM-CD-CLNN_hidden512x6"}
    assert compare.main(["scalability", "--parts", "rope", "--ds", "100", *common]) == 0
    body = _section(doc, "scalability")
    assert all(err in body for err in network.values())
    assert compare._err(fake_runs[-1]) in body  # the rope row
    capsys.readouterr()


def test_an_evaluation_asked_for_with_other_steps_is_done_again(compare, monkeypatch, tmp_path):
    """``--eval-steps`` changed on the same ``--out``: the runs' evaluations are redone (they
    were reused, while the header recorded the new value)."""
    import diffcontact.learning.evaluation.evaluate as evaluation

    asked = []

    def evaluate(run, out_dir, *, steps=None, **_):
        asked.append(steps)
        out_dir.mkdir(parents=True, exist_ok=True)
        metrics = {"rel_err_mean": 0.1, "rel_err_ci95": 0.01, "steps": steps or 100}
        (out_dir / "metrics.json").write_text(json.dumps(metrics))

    monkeypatch.setattr(evaluation, "evaluate", evaluate)
    run = tmp_path / "run"
    run.mkdir()
    (run / "model.pt").write_bytes(b"")
    for steps, redone in ((None, True), (None, False), (5, True), (5, False), (7, True),
                          (None, True)):  # fmt: skip
        before = len(asked)
        _, now = compare._evaluate(run, run / "evaluation", None, steps)
        assert now == redone and len(asked) == before + redone, (steps, asked)
    assert asked == [None, 5, 7, None]
    # an evaluation made before the steps were recorded counts as the default's
    (run / "evaluation" / "eval-steps.txt").unlink()
    assert not compare._evaluate(run, run / "evaluation", None, None)[1]
    assert compare._evaluate(run, run / "evaluation", None, 5)[1]

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

"""The Python examples of README.md and docs/*.md run as written, and say what they print.

Each example is the ``n``-th ```` ```python ```` block of its page, run in an empty folder.
Where a page defines a name in its prose (``z0``) or writes a placeholder (``[...]``, a
run folder the reader has), the case below gives a prelude or a textual substitution; the
rest of the block runs unchanged. Blocks not listed are signatures or fragments with
placeholders in every line (e.g. README's ``solve_cone_qp(A, b, mu, d, ...)``).
docs/own-data.md has its own test (tests/test_own_data_doc.py).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

import diffcontact as dc
from diffcontact.cli import main

ROOT = Path(__file__).resolve().parents[1]


def python_blocks(page: str) -> list[str]:
    """The page's ```` ```python ```` blocks, in order."""
    text = (ROOT / page).read_text()
    return re.findall(r"^```python\n(.*?)^```", text, re.S | re.M)


def run_block(
    page: str,
    index: int,
    *,
    prelude: str = "",
    replace: dict[str, str] | None = None,
) -> dict:
    """Run block ``index`` of ``page`` (after ``prelude``) and return its namespace."""
    code = python_blocks(page)[index]
    for old, new in (replace or {}).items():
        assert old in code, f"{page} block {index} no longer contains {old!r}: update this test"
        code = code.replace(old, new)
    namespace: dict = {"__name__": "doc_example"}
    exec(compile(prelude + code, f"{page}[{index}]", "exec"), namespace)
    return namespace


@pytest.fixture(autouse=True)
def _in_empty_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def test_readme_simulation():
    ns = run_block("README.md", 1)
    traj, z0, E = ns["traj"], ns["z0"], ns["E"]
    assert traj.shape == (16, 101, 2, 5, 2) and traj.dtype == torch.float64  # as commented
    assert torch.equal(traj[:, 0], z0)
    assert E.shape == (16, 101)


def test_config_parameters_and_gradients():
    # the page's first block ends by loading CP3 and sampling z0 (its other lines are
    # placeholders: a file of the reader's, a dict with "...")
    first = python_blocks("docs/config.md")[0]
    prelude = "import torch\n" + "".join(
        line + "\n"
        for line in first.splitlines()
        if line.startswith("import") or "CP3" in line or "z0 =" in line
    )
    ns = run_block("docs/config.md", 1, prelude=prelude)
    assert ns["system"].name == "CP3"
    grad = ns["mu"].grad
    assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0
    assert ns["traj"].shape == (16, 101, 2, 3, 2)


def test_architecture_plugins_run_through_the_command_line(capsys):
    ns = run_block("docs/architecture.md", 1)
    try:
        # the block's last comment: generate with the new contact model, train the new model
        sizes = ["--n-train", "8", "--n-val", "2", "--n-test", "2"]
        generate = ["generate", "BP5", "--out", "data", *sizes, "--contact-model", "Frictionless"]
        assert main([*generate, "--quiet"]) == 0
        train = ["train", "data", "--out", "run", "--model", "LearnedRestitution", "--epochs", "2"]
        assert main([*train, "--quiet"]) == 0
        model = dc.learning.load_model("run")
        assert type(model).__name__ == "LearnedRestitution"
        assert 0.0 <= model.metrics()["param/cor"] <= 1.0
    finally:
        dc.contact.unregister_contact_model("Frictionless")
        dc.learning.unregister_model("LearnedRestitution")
    assert "Frictionless" in ns and "LearnedRestitution" in ns


def test_control_example_prints_what_the_page_says(capsys):
    ns = run_block("docs/control.md", 0)
    result = ns["result"]
    text = (ROOT / "docs/control.md").read_text()
    printed = re.search(
        r"it printed `objective ([0-9.]+): velocity\[0\] = \(([-0-9.]+),\s*([-0-9.]+)\)", text
    )
    assert printed, "docs/control.md no longer quotes the example's output: update this test"
    assert float(result.objective) == pytest.approx(float(printed.group(1)), rel=1e-3)
    velocity = torch.tensor([float(printed.group(2)), float(printed.group(3))], dtype=torch.float64)
    assert torch.allclose(result.variables["velocity[0]"].flatten(), velocity, atol=1e-3)
    # "6 of the 16 starts never touched ball 2, so their objective (0.5927, ...)"
    missed = re.search(
        r"(\d+) of the (\d+) starts never touched ball 2, so their objective\s+\(([0-9.]+)", text
    )
    assert missed, "docs/control.md no longer says how many starts missed: update this test"
    per_start = result.start_objective
    assert len(per_start) == int(missed.group(2))
    untouched = (per_start - float(missed.group(3))).abs() < 5e-5
    assert int(untouched.sum()) == int(missed.group(1))
    assert "objective" in capsys.readouterr().out


def test_data_example():
    ns = run_block("docs/data.md", 0)
    assert tuple(ns["train"].chunks.shape) == (800, 5, 2, 5, 2)  # as commented
    assert ns["ds"].system.name == "BP5"


def _states(task: str) -> str:
    """A prelude defining ``z0``: two initial states of ``task``."""
    return f"import diffcontact as dc\nz0 = dc.load_system({task!r}).sample_initial_conditions(2)\n"


def test_training_examples():
    ns = run_block("docs/training.md", 0, prelude=_states("Gyro"))
    assert ns["traj"].shape == (2, 11, *ns["z0"].shape[1:])  # (N, 11, 2, P, dim)
    ns = run_block(
        "docs/training.md", 1,
        prelude=_states("BP5"),
        replace={"mass=[...]": "mass=[1.0, 2.0, 3.0, 4.0, 5.0]", '"runs/BP5-CM"': '"model.pt"'},
    )  # fmt: skip
    assert ns["traj"].shape == (2, 5, 2, 5, 2)  # as commented
    system = ns["system"]
    assert system.parameters().mu.flatten()[0].item() == pytest.approx(0.3)
    assert system.parameters().cor.flatten()[0].item() == pytest.approx(0.8)


def test_evaluation_examples():
    # the run and the dataset the page's examples name, made small
    sizes = ["--n-train", "8", "--n-val", "2", "--n-test", "2"]
    assert main(["generate", "BP5", "--out", "data/BP5", *sizes, "--quiet"]) == 0
    assert main(["train", "data/BP5", "--out", "runs/BP5-CM", "--epochs", "1", "--quiet"]) == 0
    prelude = "import diffcontact as dc\nmy_model = dc.learning.load_model('runs/BP5-CM')\n"
    ns = run_block("docs/evaluation.md", 0, prelude=prelude)
    assert ns["metrics"]["model"] == "CM-CD-CLNN" and Path("eval/mine/metrics.json").is_file()
    prelude += (
        "model = my_model\ntrain_chunks = dc.learning.load_dataset('data/BP5').train.chunks\n"
    )
    ns = run_block("docs/evaluation.md", 1, prelude=prelude)
    assert set(ns["u"]["mu"]) >= {"value", "ci95", "determined", "reason"}

"""Which learned per-contact parameters the data determine: BD5 and BP5 (issue 15).

    python experiments/uncertainty.py --out runs/uncert --doc docs/results.md

For each task (BD5, BP5; one mu and one e_P per contact):

1. ``diffcontact generate TASK`` (800/100/100 trajectories, seed 0) and
   ``diffcontact train`` of CM-CD-CLNN with the package defaults (80 epochs for
   BD5, 60 for BP5, as ``experiments/reproduce.py``); reused when finished,
   resumed when interrupted;
2. :func:`~diffcontact.learning.evaluation.uncertainty.parameter_uncertainty` on
   the 800 training chunks (Laplace standard errors, "determined" flags) and
   :func:`~diffcontact.learning.evaluation.uncertainty.contact_regimes` (how each
   contact's training impacts went under the learned model), with the scan of
   every mu over ``SCAN`` times its learned value;
3. a table per task: learned values with their 95 % intervals next to the truth;
   a parameter is *off* when it misses the truth by more than the tolerance (mu
   0.01, e_P 0.02, mass ratios 0.5 % relative, the criteria of
   docs/results.md), and the summary compares the off parameters with the
   flagged ones.

The tables land in ``OUT/uncertainty.md`` and, with ``--doc``, in a marked
section of that file (the rest is kept). The results are stored in
``OUT/uncertainty.json``; a run of some of the tasks (``--tasks BP5``) replaces
their results and keeps the other tasks' stored ones (made with the same set-up:
model, epochs, data sizes, scan), so the report shows every task, each with the
command and date that made it.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from collections.abc import Iterable, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

TASKS = {"BD5": 80, "BP5": 60}
MODEL = "CM-CD-CLNN"
SIZES = (800, 100, 100)  # generated trajectories: train / val / test
# the scan of every mu: these multiples of its learned value (UncertaintySettings.scan)
SCAN = (0.0, 0.25, 0.5, 0.75, 1.5, 2.0)
BEGIN = "<!-- uncertainty results (experiments/uncertainty.py): begin -->"
END = "<!-- uncertainty results: end -->"
# what the report named as its command before results recorded theirs (uncertainty.json)
DEFAULT_COMMAND = "python experiments/uncertainty.py --out runs/uncert --doc docs/results.md"


def _write(path: Path, text: str) -> None:
    from diffcontact.io import atomic_write_bytes

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, text.encode())


def train_model(task: str, out: Path, epochs: int) -> tuple[Path, Path, float]:
    """Generate the data and train CM-CD-CLNN (reused/resumed); ``(data, run, seconds)``."""
    from diffcontact.learning.data.generate import generate_dataset
    from diffcontact.learning.training.run import train

    data = out / "data" / task
    run = out / task
    if not (data / "metadata.json").is_file():
        n_train, n_val, n_test = SIZES
        generate_dataset(task, data, n_train=n_train, n_val=n_val, n_test=n_test, progress=False)
    learned = run / "learned.json"
    done = learned.is_file() and json.loads(learned.read_text()).get("finished")
    start = time.perf_counter()
    if not done:
        train(data, run, model=MODEL, epochs=epochs, resume=run.exists(), progress=False)
    return data, run, time.perf_counter() - start


def assess(task: str, data: Path, run: Path) -> dict[str, Any]:
    """Uncertainty, regimes and truth of one trained run (plain data)."""
    import torch

    from diffcontact.learning.data import load_dataset
    from diffcontact.learning.evaluation.uncertainty import (
        UncertaintySettings,
        contact_regimes,
        parameter_uncertainty,
    )
    from diffcontact.learning.models.storage import load_model
    from diffcontact.systems import System, load_config

    model = load_model(run).double()
    chunks = load_dataset(data).split("train", dtype=torch.float64).chunks
    start = time.perf_counter()
    u = parameter_uncertainty(model, chunks, settings=UncertaintySettings(scan=SCAN))
    seconds = time.perf_counter() - start
    regimes = contact_regimes(model, chunks)
    system = System(load_config(task))
    truth = system.parameters()
    mass = truth.mass.double()
    return {
        "task": task,
        "uncertainty": u,
        "regimes": regimes,
        "seconds": seconds,
        "contact_names": list(system.contact_names),
        "truth": {
            "mass_ratios": (mass[1:] / mass[0]).tolist(),
            "mu": truth.mu.double().expand(system.n_contacts).tolist(),
            "cor": truth.cor.double().expand(system.n_contacts).tolist(),
        },
    }


def setup(task: str) -> dict[str, Any]:
    """What a task's results depend on besides the code: model, epochs, data sizes, scan.

    A stored result of another set-up is not shown beside this one's (:func:`merge`).
    """
    return {"model": MODEL, "epochs": TASKS.get(task), "sizes": list(SIZES), "scan": list(SCAN)}


def load_results(path: Path) -> list[dict[str, Any]]:
    """The results stored in ``path`` (``OUT/uncertainty.json``; none when it is missing).

    Results stored before each recorded its command and set-up get those of the file:
    its ``meta`` (date, torch, machine), the command the report named then
    (:data:`DEFAULT_COMMAND`) and this script's set-up, which it had unless its
    constants were changed since.

    Raises:
        ValueError: the file is not a results file of this script (the message names it).
    """
    if not path.is_file():
        return []
    try:
        stored = json.loads(path.read_text())
        meta, results = stored["meta"], list(stored["results"])
        legacy = {
            "command": meta.get("command", DEFAULT_COMMAND),
            **{k: meta[k] for k in ("date", "torch", "machine")},
        }
        for r in results:
            r.setdefault("produced", legacy)
            r.setdefault("setup", setup(r["task"]))
    except (ValueError, KeyError, TypeError, AttributeError) as err:
        raise ValueError(
            f"{path} is not a results file of uncertainty.py ({type(err).__name__}: {err}); "
            "move it away or choose another --out"
        ) from None
    return results


def _order(default: Iterable[str], seen: Iterable[str]) -> list[str]:
    """``seen`` without repeats: those in ``default`` in its order, then the others."""
    seen = list(dict.fromkeys(seen))
    first = [x for x in default if x in seen]
    return first + [x for x in seen if x not in first]


def merge(stored: list[dict[str, Any]], new: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The results to report: ``new`` (this invocation's), and the ``stored`` ones of the
    other tasks whose set-up is today's (:func:`setup`), in the order of :data:`TASKS`,
    then any other task in the order first stored."""
    by_task = {r["task"]: r for r in stored if r.get("setup") == setup(r["task"])}
    by_task.update({r["task"]: r for r in new})
    seen = [*(r["task"] for r in stored), *(r["task"] for r in new)]
    return [by_task[t] for t in _order(TASKS, seen) if t in by_task]


def _produced(results: list[dict[str, Any]]) -> str:
    """``Produced by `COMMAND` (DATE; torch ..., machine)``, one clause per invocation that
    made some of ``results`` (each naming its tasks when there are several)."""
    groups: dict[str, tuple[dict[str, Any], list[str]]] = {}
    for r in results:
        p = r["produced"]
        groups.setdefault(json.dumps(p, sort_keys=True), (p, []))[1].append(r["task"])
    clauses = [
        f"`{p['command']}` ("
        + (f"{', '.join(tasks)}; " if len(groups) > 1 else "")
        + f"{p['date']}; torch {p['torch']}, {p['machine']})"
        for p, tasks in groups.values()
    ]
    if len(clauses) > 1:
        clauses = [", ".join(clauses[:-1]) + " and " + clauses[-1]]
    return "Produced by " + clauses[0] + "."


def _off(kind: str, learned: float, true: float, tol: dict[str, float]) -> bool:
    if kind == "mass_ratios":
        return abs(learned / true - 1) > tol["mass_ratio_relative"]
    return abs(learned - true) > tol[kind]


def _cell(entry: dict[str, Any], i: int) -> str:
    value, ci = entry["value"][i], entry["ci95"][i]
    flag = "" if entry["determined"][i] else " **?**"
    if ci is None:
        return f"{value:.3f} (flat){flag}"
    return f"{value:.3f} [{ci[0]:.3f}, {ci[1]:.3f}]{flag}"


def section(results: list[dict[str, Any]]) -> str:
    """The Markdown section of the report: one part per result (task), each made by the
    invocation its ``produced`` names (:func:`merge` keeps those of earlier ones)."""
    lines = [
        BEGIN,
        f"## Which learned parameters the data determine ({', '.join(r['task'] for r in results)})",
        "",
        f"{_produced(results)} "
        "CM-CD-CLNN with one mu and one e_P per contact, trained with the package defaults "
        f"({', '.join(f'{t} {e} epochs' for t, e in TASKS.items())}) on {SIZES[0]} generated "
        "trajectories; then `diffcontact.learning.evaluation.parameter_uncertainty` on the "
        f"{SIZES[0]} training chunks: "
        "Laplace standard errors with the potential network held fixed, and a scan of each "
        f"mu over {', '.join(f'{f:g}' for f in SCAN)} times its learned value "
        '(docs/evaluation.md, "Parameter uncertainty"). A value is shown with its 95 % '
        "interval; **?** marks a parameter reported as not determined (a flat loss, no "
        "sliding impact, a kink, an interval wider than the tolerance, a value the data "
        "would move, or a better value on the scan). "
        "*Off* means the learned value misses the truth by more than the tolerance "
        "(mu 0.01, e_P 0.02, mass ratios 0.5 %). Impacts: training states in which the "
        "contact is active under the learned model, as sliding / sticking / separating.",
        "",
    ]
    for r in results:
        u, reg, truth = r["uncertainty"], r["regimes"], r["truth"]
        tol = u["tolerances"]
        off: set[str] = set()
        flagged: set[str] = set()
        for kind, label in (("mass_ratios", "m"), ("mu", "mu"), ("cor", "e_P")):
            for i, (v, t) in enumerate(zip(u[kind]["value"], truth[kind], strict=True)):
                name = f"{label}{i + 2}/m1" if kind == "mass_ratios" else f"{label}[{i}]"
                if _off(kind, v, t, tol):
                    off.add(name)
                if not u[kind]["determined"][i]:
                    flagged.add(name)
        both, missed, extra = off & flagged, off - flagged, flagged - off
        lines += [
            f"### {r['task']}",
            "",
            f"{len(off)} parameters off, {len(flagged)} flagged; off and flagged: "
            f"{', '.join(sorted(both)) or 'none'}; off but not flagged: "
            f"{', '.join(sorted(missed)) or 'none'}; flagged but not off: "
            f"{', '.join(sorted(extra)) or 'none'}. Mean absolute residual "
            f"{u['residual_mean_abs']:.2e} over "
            f"{u['n_residuals']} residuals, {u['n_parameters']} parameters; "
            f"{r['seconds']:.0f} s.",
            "",
            "| m_i/m_1 | true | learned [95 %] |",
            "|---|---|---|",
        ]
        for i, t in enumerate(truth["mass_ratios"]):
            lines.append(f"| m{i + 2}/m1 | {t:.3f} | {_cell(u['mass_ratios'], i)} |")
        lines += [
            "",
            "| k | contact | impacts (slide/stick/sep) | true mu | learned mu [95 %] "
            "| true e_P | learned e_P [95 %] | why flagged |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for k, name in enumerate(r["contact_names"]):
            why = "; ".join(
                f"{lab}: {u[kind]['reason'][k]}"
                for kind, lab in (("mu", "mu"), ("cor", "e_P"))
                if u[kind]["reason"][k]
            )
            lines.append(
                f"| {k} | {name} | {reg['impacts'][k]} ({reg['sliding'][k]}/"
                f"{reg['sticking'][k]}/{reg['separating'][k]}) | {truth['mu'][k]:.2f} | "
                f"{_cell(u['mu'], k)} | {truth['cor'][k]:.2f} | {_cell(u['cor'], k)} | {why} |"
            )
        lines.append("")
    lines.append(END)
    return "\n".join(lines)


def write_doc(doc: Path, text: str, check_only: bool = False) -> None:
    """Replace the marked section of ``doc`` (or append it), keeping the rest; a stray
    marker is a ``ValueError`` (``diffcontact.io.replace_marked_section``)."""
    from diffcontact.io import replace_marked_section

    replace_marked_section(doc, BEGIN, END, text, check_only=check_only)


def main(argv: Sequence[str] | None = None) -> int:
    """The command line; a stop by Ctrl-C or SIGTERM is one line (an interrupted training
    run resumes from its checkpoint when the command is run again)."""
    from diffcontact.cli_args import run_stoppable

    return run_stoppable(
        _main,
        argv,
        "uncertainty.py",
        "finished runs are kept: run the same command again to continue",
    )


def _main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/uncert", help="output folder")
    parser.add_argument("--doc", default=None, help="Markdown file to put the tables into")
    parser.add_argument("--tasks", nargs="+", choices=tuple(TASKS), default=list(TASKS))
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    if args.doc:  # before any work: a stray marker or an unwritable file
        try:
            write_doc(Path(args.doc), "", check_only=True)
        except (ValueError, OSError) as err:
            parser.error(f"--doc: {err}")
    from diffcontact.io import check_writable_folder

    out = Path(args.out)
    try:
        check_writable_folder(out)
    except OSError as err:
        parser.error(f"--out: {err}")
    try:  # the other tasks' results, kept in the report (before any work: a bad file)
        stored = load_results(out / "uncertainty.json")
    except ValueError as err:
        parser.error(f"--out: {err}")
    import torch

    torch.set_num_threads(1)
    meta = {
        "command": "python experiments/uncertainty.py " + " ".join(argv),
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
        "torch": torch.__version__,
        "machine": f"{platform.machine()} CPU, one torch thread",
    }
    new = []
    for task in args.tasks:
        print(f"{task}: training CM-CD-CLNN ({TASKS[task]} epochs; reused when finished)")
        data, run, train_seconds = train_model(task, out, TASKS[task])
        print(f"{task}: parameter uncertainty")
        r = assess(task, data, run)
        r["train_seconds"] = train_seconds
        new.append({**r, "produced": meta, "setup": setup(task)})
    results = merge(stored, new)
    text = section(results)
    _write(out / "uncertainty.md", text + "\n")
    _write(out / "uncertainty.json", json.dumps({"meta": meta, "results": results}, indent=1))
    if args.doc:
        write_doc(Path(args.doc), text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

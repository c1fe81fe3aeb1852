"""Planning through learned simulators: success rates of billiards and throwing shots.

    python experiments/control.py --out runs/control --doc docs/results.md

For each task (billiards on BP5-e, throwing on BD1-ground):

1. ``diffcontact generate TASK`` (800/100/100 trajectories, seed 0) and
   ``diffcontact train`` of each learned model (CM-CD-CLNN and the baseline
   MLP-CD-CLNN, whose contact network replaces the cone QP) with the package
   defaults for ``--epochs`` epochs (reused when finished; resumed when
   interrupted);
2. ``--targets`` random targets (seed 0; billiards: points on the table where
   the target ball fits, throw: x in [0.3, 2.0] m), planned in ONE batched
   ``optimize`` call per planner: the true system and each trained model;
3. every plan is judged by the ground-truth simulator: a success is a final
   distance to the target of at most ``--radius`` (default 0.05 m; the balls of
   BP5-e have radius 0.1).

Each finished row is kept in ``OUT/results.json`` (written atomically), so an
interrupted run continues where it stopped. The table lands in ``OUT/control.md``
and, with ``--doc``, in a marked section of that file (the rest is kept).
"""

from __future__ import annotations

import argparse
import json
import platform
import shlex
import sys
import time
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

TASKS = {"billiards": "BP5-e", "throw": "BD1-ground"}
MODELS = ("CM-CD-CLNN", "MLP-CD-CLNN")
BEGIN = "<!-- control results (experiments/control.py): begin -->"
END = "<!-- control results: end -->"


def _write(path: Path, text: str) -> None:
    from diffcontact.io import atomic_write_bytes

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, text.encode())


def train_model(task: str, out: Path, epochs: int, model: str) -> tuple[Path, float]:
    """Generate the task's data and train ``model`` on it (reused/resumed);
    ``(run dir, seconds)``."""
    import shutil

    from diffcontact.learning.data.generate import generate_dataset
    from diffcontact.learning.training.run import train

    data = out / "data" / task
    run = out / "runs" / task / model
    learned = run / "learned.json"
    if not (data / "metadata.json").is_file():
        generate_dataset(task, data, n_train=800, n_val=100, n_test=100, progress=False)
    done = learned.is_file() and json.loads(learned.read_text()).get("finished")
    if not (done and (run / "model.pt").is_file()):
        resume = (run / "checkpoints" / "last.ckpt").is_file()
        if not resume and run.exists():
            shutil.rmtree(run)
        train(data, run, model=model, epochs=epochs, resume=resume, progress=False,
              keep_checkpoints=2)  # fmt: skip
    return run, _training_seconds(run)


def _training_seconds(run: Path) -> float:
    """Sum of the per-epoch wall times logged in ``logs/metrics.csv``."""
    import numpy as np

    from diffcontact.learning.evaluation.log import read_training_log

    seconds = read_training_log(run / "logs" / "metrics.csv").get("time/epoch_s")
    return 0.0 if seconds is None else float(np.nansum(seconds))


def plan_row(task: str, planner_spec: str, targets: int, radius: float, iters: int) -> dict:
    """Plan ``targets`` random targets with one planner; the success rate under the truth."""
    import torch

    from diffcontact.control import as_planner
    from diffcontact.control.tasks import plan_billiards, plan_throw, random_targets

    planner = as_planner(planner_spec)
    tg = random_targets(planner, task, targets, seed=0)
    t0 = time.perf_counter()
    if task == "billiards":
        z0 = planner.truth.sample_initial_conditions(targets, seed=1)
        plan = plan_billiards(planner, tg, z0=z0, starts=8, iterations=iters, progress=True)
    else:
        plan = plan_throw(planner, tg, starts=8, iterations=iters, progress=True)
    seconds = time.perf_counter() - t0
    ok = plan.distance_true <= radius
    return {
        "planner": planner.name,
        "targets": targets,
        "success": int(ok.sum()),
        "rate": float(ok.double().mean()),
        "median_distance_true": float(plan.distance_true.median()),
        "median_distance_model": float(plan.distance_model.median()),
        "iterations": plan.result.iterations,
        "seconds": seconds,
        "per_target_true": plan.distance_true.tolist(),
        "threads": torch.get_num_threads(),
    }


def learned_contact_parameters(out: Path, task: str) -> dict[str, tuple[list, list]] | None:
    """``{"mu": (learned, true), "e_P": (learned, true)}`` of the task's trained
    CM-CD-CLNN (``learned.json``) and its config, or None when it is not trained yet."""
    from diffcontact import load_system

    learned_file = out / "runs" / TASKS[task] / MODELS[0] / "learned.json"
    if not learned_file.is_file():
        return None
    learned = json.loads(learned_file.read_text())["learned"]
    truth = load_system(TASKS[task])
    return {
        "mu": (learned["mu"], truth.mu.reshape(-1).tolist()),
        "e_P": (learned["cor"], truth.cor.reshape(-1).tolist()),
    }


def _numbers(xs: list[float]) -> str:
    return ", ".join(f"{x:.3f}" for x in xs[:5]) + (", ..." if len(xs) > 5 else "")


def render(results: dict[str, Any], meta: dict[str, Any], out: Path | None = None) -> str:
    lines = [
        BEGIN,
        "## Planning through learned simulators (billiards, throwing)",
        "",
        f"Produced by `{meta['command']}` ({meta['date']}; torch {meta['torch']}, "
        f"{meta['cpu']}, one torch thread; other work shared the CPU at times, so times are "
        "upper bounds). Targets: "
        f"{meta['targets']} random ones per task (seed 0); each planner plans all of them in "
        "one batched `diffcontact.optimize` call (8 starts per target, Adam, at most "
        f"{meta['iterations']} iterations); every plan is judged by the ground-truth "
        f"simulator: success = final distance to the target <= {meta['radius']:g} m. "
        "Billiards: BP5-e (5 identical balls of radius 0.1 in the unit box), a random layout "
        "per target, cue ball 0, target ball 2, 1 s. Throwing: BD1-ground (a disk of radius "
        "0.1 thrown from rest at (0, 0.5) onto a ground), the disk's centre at x = target "
        "after 1 s. The learned planners are CM-CD-CLNN and the baseline MLP-CD-CLNN (a "
        "contact network in place of the cone QP), each trained by `diffcontact train` for "
        f"{meta['epochs']} epochs on 800 generated trajectories.",
        "",
        "| task | planner | success | median distance (truth) | median distance "
        "(planner's own model) | iterations | planning time | training time |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for task, task_name in TASKS.items():
        for key in ("true", *MODELS):
            row = results.get(f"{task}/{key}")
            if row is None:
                lines.append(
                    f"| {task} ({task_name}) | {key} | not measured yet: rerun the command "
                    "(it resumes) | | | | | |"
                )
                continue
            train_s = results.get(f"{task}/{key}/train_seconds")
            lines.append(
                f"| {task} ({task_name}) | {row['planner']} | {row['success']}/{row['targets']} "
                f"({100 * row['rate']:.0f} %) | {row['median_distance_true']:.4f} | "
                f"{row['median_distance_model']:.4f} | {row['iterations']} | "
                f"{row['seconds'] / 60:.1f} min | "
                + (f"{train_s / 60:.1f} min |" if train_s else "- |")
            )
    learned_rows = []
    for task, task_name in TASKS.items():
        pairs = learned_contact_parameters(out, task) if out is not None else None
        for name, (got, true) in (pairs or {}).items():
            paired = true if len(true) == len(got) else true[:1] * len(got)  # shared truth
            worst = max(abs(g - t) for g, t in zip(got, paired, strict=True))
            learned_rows.append(
                f"| {task_name} | {name} | {_numbers(got)} | {_numbers(true)} | {worst:.3f} |"
            )
    if learned_rows:
        lines += [
            "",
            "The contact parameters the learned CM-CD-CLNN planners plan with (a planner is "
            "only as good as what its training data determined; docs/evaluation.md, "
            '"Parameter uncertainty"; MLP-CD-CLNN has none, its contact network learns the '
            "impulse):",
            "",
            "| task | parameter | learned | truth | largest error |",
            "|---|---|---|---|---|",
            *learned_rows,
        ]
    lines += [
        "",
        "The planner is a local optimiser with 8 starts, so the true system is an upper bound "
        "only in expectation: a miss means its starts found no shot of the allowed speeds "
        "that reaches the target in time from that layout, and a learned model's slightly "
        "different landscape can send some starts to shots the true planner missed.",
        END,
    ]
    return "\n".join(lines)


def write_doc(doc: Path, section: str, check_only: bool = False) -> None:
    """Replace the marked section of ``doc`` (or append it), keeping the rest; a stray
    marker is a ``ValueError`` (``diffcontact.io.replace_marked_section``)."""
    from diffcontact.io import replace_marked_section

    replace_marked_section(doc, BEGIN, END, section, check_only=check_only)


def main(argv: Sequence[str] | None = None) -> int:
    """The command line; a stop by Ctrl-C or SIGTERM is one line (an interrupted training
    run resumes from its checkpoint when the command is run again)."""
    from diffcontact.cli_args import run_stoppable

    return run_stoppable(
        _main,
        argv,
        "control.py",
        "finished rows are kept: run the same command again to continue",
    )


def _main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/control", help="output folder")
    parser.add_argument("--doc", default=None, help="Markdown file to put the table into")
    parser.add_argument("--targets", type=int, default=50, help="random targets per task")
    parser.add_argument("--epochs", type=int, default=60, help="training epochs of each model")
    parser.add_argument("--iterations", type=int, default=60, help="optimiser iterations")
    parser.add_argument("--radius", type=float, default=0.05, help="success radius, m")
    parser.add_argument("--tasks", nargs="+", choices=tuple(TASKS), default=list(TASKS))
    args = parser.parse_args(argv)
    for flag, value in (("--targets", args.targets), ("--epochs", args.epochs),
                        ("--iterations", args.iterations)):  # fmt: skip
        if value < 1:  # (a 0 failed after the training, with the settings saved)
            parser.error(f"{flag} must be >= 1, got {value}")
    if not 0 < args.radius < float("inf"):
        parser.error(f"--radius must be a positive number, got {args.radius}")
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
    import torch

    torch.set_num_threads(1)
    results_file = out / "results.json"
    results: dict[str, Any] = {}
    if results_file.is_file():
        results = json.loads(results_file.read_text())
    settings = {k: getattr(args, k) for k in ("targets", "epochs", "iterations", "radius")}
    if results.get("settings", settings) != settings:
        print(f"control.py: {results_file} holds other settings; use another --out",
              file=sys.stderr)  # fmt: skip
        return 2
    results["settings"] = settings

    def save() -> None:  # merged with rows another invocation (other --tasks) saved meanwhile
        on_disk = json.loads(results_file.read_text()) if results_file.is_file() else {}
        results.update({k: v for k, v in on_disk.items() if k not in results})
        _write(results_file, json.dumps(results, indent=1))

    for task in args.tasks:
        name = TASKS[task]
        specs = [("true", name)]
        for model in MODELS:
            run, seconds = train_model(name, out, args.epochs, model)
            results[f"{task}/{model}/train_seconds"] = seconds
            save()
            specs.append((model, str(run)))
        for key, spec in specs:
            if f"{task}/{key}" in results:
                continue
            print(f"{task}: planning {args.targets} targets with {key}", flush=True)
            results[f"{task}/{key}"] = plan_row(task, spec, args.targets, args.radius,
                                                args.iterations)  # fmt: skip
            save()
    given = sys.argv[1:] if argv is None else list(argv)
    meta = {
        **settings,
        "command": shlex.join(["python", "experiments/control.py", *given]),
        "date": datetime.now(timezone.utc).date().isoformat(),
        "torch": torch.__version__,
        "cpu": f"{platform.machine()} CPU",
    }
    section = render(results, meta, out)
    _write(out / "control.md", section + "\n")
    if args.doc:
        write_doc(Path(args.doc), section)
    print(section)
    return 0


if __name__ == "__main__":
    sys.exit(main())

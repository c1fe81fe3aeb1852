"""``diffcontact evaluate``: argument parsing and the handler.

Building the parser imports neither torch nor matplotlib; the handler imports
:func:`~diffcontact.learning.evaluation.evaluate.evaluate` when it runs.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from diffcontact.cli_args import int_at_least, report_errors

__all__ = ["register_cli"]


def register_cli(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``evaluate RUN_DIR [--out DIR --device cpu|cuda --n-gif 4 ...]`` to a CLI.

    ``subparsers`` is what ``ArgumentParser.add_subparsers()`` returns. The
    handler is set as ``func``; it returns the exit status (0; 2 for bad
    input with a one-line message on stderr; 1 when the evaluation fails).
    """
    p = subparsers.add_parser(
        "evaluate",
        help="evaluate a trained model: rollout error, energy, learned parameters, plots",
        description=(
            "Roll the trained model of RUN_DIR out from every test initial state for "
            "max(horizon, 100 dt), compare with the ground truth and write metrics.json, "
            "rollout.npz, rel_error.png, energy.png, impacts.png, training.png and rollout.gif. On "
            "recorded data the rollout follows the recording and the true parameters and "
            "energy are unknown unless the dataset declares them (generate --true-params)."
        ),
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="training run directory")
    p.add_argument(
        "--out",
        default=None,
        metavar="DIR",
        help="output folder (default RUN_DIR/evaluation; another evaluation there is replaced "
        "only with --force)",
    )
    p.add_argument(
        "--device", choices=("cpu", "cuda"), default="cpu", help="rollout device (default cpu)"
    )
    p.add_argument(
        "--n-gif",
        type=int_at_least(0),
        default=4,
        help="test trajectories in the GIF (default 4; 0: none; at most 16)",
    )
    p.add_argument(
        "--gif-frames",
        type=int_at_least(1),
        default=40,
        help="at most this many GIF frames, evenly spaced over the rollout (default 40)",
    )
    p.add_argument(
        "--steps",
        type=int_at_least(1),
        default=None,
        help="rollout steps (default max(horizon/dt, 100) - 1; recorded data: the recorded "
        "steps, and at most those)",
    )
    p.add_argument(
        "--n-test", type=int_at_least(1), default=None, help="use the first N test trajectories"
    )
    p.add_argument(
        "--data", default=None, metavar="DIR", help="dataset folder (default: run.json's)"
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace the files of another evaluation in the output folder (those of an "
        "evaluation of the same run and data are always replaced)",
    )
    p.add_argument(
        "--no-uncertainty",
        action="store_true",
        help="skip the assessment of how well the training data determine the learned "
        "mass ratios, mu and e_P (physical models; docs/evaluation.md)",
    )
    p.set_defaults(func=_cmd_evaluate)
    return p


def _fmt(x: Any) -> str:
    if x is None:
        return "-"
    return f"{x:.4g}"


def _interval(unc: Mapping[str, Any] | None, i: int) -> str:
    """``[lo, hi]`` of the 95 % interval, ``?`` with the reason when not determined."""
    if unc is None:
        return ""
    i = 0 if len(unc["value"]) == 1 else i  # one shared value
    ci, ok = unc["ci95"][i], unc["determined"][i]
    text = "flat" if ci is None else f"[{ci[0]:.4g}, {ci[1]:.4g}]"
    if ok:
        return f"  {text}"
    return f"  {text} ? {unc['reason'][i]}"  # e.g. "not stable: the data would move it ..."


def _param_rows(
    name: str,
    entry: Mapping[str, Any],
    labels: Sequence[str],
    shared: bool = True,
    unc: Mapping[str, Any] | None = None,
) -> list[str]:
    rows = _param_rows_plain(name, entry, labels, shared, unc)
    summarised = len(rows) == 1 and ("see metrics.json" in rows[0] or "learned values" in rows[0])
    if unc is not None and summarised:
        bad = len(unc["determined"]) - sum(unc["determined"])
        rows[0] += f"; {bad} of {len(unc['determined'])} not determined by the data"
    return rows


def _param_rows_plain(
    name: str,
    entry: Mapping[str, Any],
    labels: Sequence[str],
    shared: bool,
    unc: Mapping[str, Any] | None,
) -> list[str]:
    learned, true = entry.get("learned"), entry.get("true")
    if learned is None:
        return [f"  {name:<16} {'-':>10} {'(not learned)':>10}"]
    if true is None:  # recorded data: no known truth
        if shared and len(set(learned)) <= 1 and learned:
            return [f"  {name:<16} {learned[0]:>10.4f} {'unknown':>10}{_interval(unc, 0)}"]
        if len(learned) <= 12:
            return [
                f"  {lab:<16} {lv:>10.4f} {'unknown':>10}{_interval(unc, i)}"
                for i, (lab, lv) in enumerate(zip(labels, learned, strict=False))
            ]
        return [f"  {name:<16} {len(learned)} learned values; true values unknown"]
    if shared and len(set(learned)) <= 1 and len(set(true)) <= 1 and true:
        return [f"  {name:<16} {learned[0]:>10.4f} {true[0]:>10.4f}{_interval(unc, 0)}"]
    if len(learned) == len(true) and len(true) <= 12:
        return [
            f"  {lab:<16} {lv:>10.4f} {tv:>10.4f}{_interval(unc, i)}"
            for i, (lab, lv, tv) in enumerate(zip(labels, learned, true, strict=True))
        ]
    err = entry.get("max_abs_error", entry.get("max_rel_error"))
    return [
        f"  {name:<16} {len(learned)} learned, {len(true)} true values; "
        f"max error {_fmt(err)} (see metrics.json)"
    ]


def _unfinished(out: Path) -> bool:
    """Whether ``out`` holds an unfinished evaluation: its marker and no ``metrics.json``."""
    from diffcontact.learning.evaluation.evaluate import STARTED

    return (out / STARTED).is_file() and not (out / "metrics.json").exists()


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from diffcontact.learning.evaluation.evaluate import EvaluationInputError

    return report_errors(
        "diffcontact evaluate",
        lambda: _evaluate(args),
        bad_input=EvaluationInputError,
        failures=(RuntimeError, ValueError, OSError),
        failed="evaluation failed: ",
    )


def _evaluate(args: argparse.Namespace) -> int:
    from diffcontact.learning.evaluation.evaluate import DivergedRolloutsWarning, evaluate

    if not args.no_uncertainty and Path(args.run_dir).is_dir():  # (else evaluate's error)
        print(
            "evaluating; for a physical model this includes the parameter uncertainty "
            "(2 rollouts of the training chunks per parameter; --no-uncertainty skips it)",
            flush=True,
        )
    out = Path(args.out) if args.out else Path(args.run_dir) / "evaluation"
    try:
        with warnings.catch_warnings():  # said by the WARNING line below, not twice
            warnings.simplefilter("ignore", DivergedRolloutsWarning)
            m = evaluate(
                args.run_dir,
                args.out,
                data_dir=args.data,
                n_gif=args.n_gif,
                gif_frames=args.gif_frames,
                device=args.device,
                steps=args.steps,
                n_test=args.n_test,
                force=args.force,
                uncertainty=not args.no_uncertainty,
            )
    except KeyboardInterrupt:
        if not _unfinished(out):
            raise  # (the folder is untouched or finished: main says "interrupted")
        print(
            f"diffcontact evaluate: interrupted: {out}{os.sep} is now an unfinished evaluation "
            "(no metrics.json); run the same command again to replace its files",
            file=sys.stderr,
        )
        return 130
    n = m["n_test"]
    print(
        f"{m['task']}: {m['model']}, {n} test {'trajectory' if n == 1 else 'trajectories'} x "
        f"{m['steps']} steps (dt {m['dt']:g} s; ground truth: {m['ground_truth']})"
    )
    if args.n_test is not None and n < args.n_test:
        print(f"  note: --n-test {args.n_test}, but the test split holds {n}: all of them used")
    if m.get("model_note"):
        print(f"  WARNING: {m['model_note']}")
    if m.get("log_note"):
        print(f"  WARNING: {m['log_note']}")
    if m.get("rollout_note"):
        print(f"  note: {m['rollout_note']}")
    if m["n_nonfinite"]:
        print(
            f"  WARNING: {m['n_nonfinite']} of {n} test {'rollout' if n == 1 else 'rollouts'} "
            "diverged (non-finite); left out below"
        )
    if m.get("solver_failures"):
        print(
            f"  (of those, {len(m['solver_failures'])} stopped on a failed contact solve: "
            f"test trajectories {m['solver_failures'][:10]})"
        )
    print(
        f"  relative error   {_fmt(m['rel_err_mean'])} ± {_fmt(m['rel_err_ci95'])} (95% CI), "
        f"final step {_fmt(m['rel_err_final'])}"
    )
    drift = m["energy_rel_drift"]
    if "energy" in m.get("unknown", {}):
        print("  energy drift     unknown (the true masses of the recorded system are unknown)")
    else:
        used = drift.get("n")
        over = "" if used is None or used == n else f"; both over the {used} of {n} finite rollouts"
        print(
            f"  energy drift     model {_fmt(drift['pred'])}, ground truth "
            f"{_fmt(drift['true'])} (true energy, per mean kinetic energy{over})"
        )
    unc = m.get("uncertainty")
    if unc and "error" in unc:
        print(f"  note: {unc['error']}")
        unc = None
    header = f"  {'parameter':<16} {'learned':>10} {'true':>10}"
    print(header + ("  95 % interval (? = not determined by the data)" if unc else ""))
    if "parameters" in m.get("unknown", {}):
        print("  (true values unknown: recorded data; declare them with generate --true-params)")

    def count(key: str) -> int:
        return len(m[key]["true"] if m[key]["true"] is not None else m[key]["learned"] or [])

    labels = [f"m{i + 2}/m1" for i in range(count("mass_ratios"))]
    rows = _param_rows(
        "mass ratios", m["mass_ratios"], labels, shared=False,
        unc=unc and unc["mass_ratios"],
    )  # fmt: skip
    for key, sym in (("mu", "mu"), ("cor", "e_P")):
        rows += _param_rows(
            sym, m[key], [f"{sym}[{k}]" for k in range(count(key))], unc=unc and unc[key]
        )
    if m.get("eps") is not None:
        rows.append(f"  {'eps (CMr)':<16} {_fmt(m['eps']):>10} {'-':>10}")
    print("\n".join(rows))
    print(f"  wrote {out}{os.sep}: {', '.join(m['files'])}")
    return 0

"""``diffcontact billiards`` and ``diffcontact throw``: plan a shot, judge it by the truth.

Building the parser imports no torch; the handlers import
:mod:`diffcontact.control.tasks` when they run.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import sys
import time
from pathlib import Path
from typing import Any

from diffcontact.cli_args import (
    float_in,
    int_at_least,
    one_line_warnings,
    positive_float,
    report_errors,
)

__all__ = ["register_cli"]

_MODEL_HELP = (
    "a run directory or model.pt (plan with the trained model), or a built-in task name "
    "or config file (plan with the true system)"
)


_NEGATIVE_NUMBER = re.compile(
    r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|infinity|nan)$", re.IGNORECASE
)


def _negative_numbers(p: argparse.ArgumentParser) -> None:
    """Let ``p`` take ``-1e300``, ``-2E-3`` or ``-inf`` as a value, as it takes ``-1.5``
    (argparse's own pattern knows only ``-1`` and ``-1.5``: ``--target -1e3 0.5`` was
    refused as "expected 2 arguments"; the target's own check names what is wrong)."""
    if hasattr(p, "_negative_number_matcher"):  # (argparse's, since Python 2.7)
        p._negative_number_matcher = _NEGATIVE_NUMBER


def _common(p: argparse.ArgumentParser, task: str, starts: int, lr: float) -> None:
    p.add_argument("--time", type=positive_float, default=1.0, help="seconds (default 1.0)")
    p.add_argument(
        "--starts",
        type=int_at_least(1),
        default=starts,
        help=f"candidate shots optimised together in one batch (default {starts})",
    )
    p.add_argument("--iterations", type=int_at_least(1), default=60, help="at most (default 60)")
    p.add_argument(
        "--lr", type=positive_float, default=lr, help=f"Adam learning rate (default {lr:g})"
    )
    p.add_argument(
        "--tolerance",
        type=float_in(0.0),
        default=0.005,
        help="stop when the planning model puts the target this close (default 0.005)",
    )
    p.add_argument(
        "--max-speed",
        type=positive_float,
        default=4.0,
        help="bound of each initial velocity component, m/s (default 4)",
    )
    p.add_argument(
        "--json",
        default=None,
        metavar="OUT",
        help="write the plan as JSON (a .json file; an existing file that is not a plan of "
        "billiards or throw is replaced only with --force)",
    )
    p.add_argument("--force", action="store_true", help="replace --json whatever it holds")
    p.add_argument(
        "--gif",
        default=f"{task}.gif",
        metavar="PATH",
        help=f"the shot under the truth (solid) and the planning model (dashed) "
        f"(default {task}.gif)",
    )
    p.add_argument("--no-gif", action="store_true", help="write no GIF")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def register_cli(subparsers: Any) -> None:
    """Add ``billiards`` and ``throw`` to a CLI (``subparsers`` from ``add_subparsers()``)."""
    b = subparsers.add_parser(
        "billiards",
        help="choose the cue ball's velocity so that a ball reaches a target (docs/control.md)",
        description=(
            "Plan a billiards shot by gradient descent through MODEL: all balls at rest "
            "(layout --seed); choose the cue ball's initial velocity so that --ball is at "
            "--target after --time seconds. Prints the shot and the final distance under "
            "the planning model and under the ground-truth simulator."
        ),
    )
    b.add_argument("model", metavar="MODEL", help=_MODEL_HELP)
    b.add_argument(
        "--target", type=float, nargs=2, required=True, metavar=("X", "Y"), help="target point"
    )
    b.add_argument("--cue", type=int_at_least(0), default=0, help="cue ball (default 0)")
    b.add_argument("--ball", type=int_at_least(0), default=2, help="target ball (default 2)")
    b.add_argument(
        "--seed", type=int_at_least(0), default=0, help="layout of the balls (default 0)"
    )
    _common(b, "billiards", 16, 0.05)
    _negative_numbers(b)
    b.set_defaults(func=_cmd_billiards)

    t = subparsers.add_parser(
        "throw",
        help="choose a disk's velocity and spin so that it passes a target (docs/control.md)",
        description=(
            "Plan a throw by gradient descent through MODEL (a bouncing-disk system with "
            "gravity and a ground, e.g. BD1-ground, or a model trained on its data): the "
            "disk starts at rest at --start; choose its initial velocity and spin so that "
            "its centre is at x = --target after --time seconds."
        ),
    )
    t.add_argument("model", metavar="MODEL", help=_MODEL_HELP)
    t.add_argument("--target", type=float, required=True, metavar="X", help="target x")
    t.add_argument(
        "--start",
        type=float,
        nargs=2,
        default=(0.0, 0.5),
        metavar=("X", "Y"),
        help="the disk's centre before the throw (default 0 0.5)",
    )
    t.add_argument(
        "--max-spin", type=positive_float, default=30.0, help="spin bound, rad/s (default 30)"
    )
    _common(t, "throw", 16, 0.1)
    _negative_numbers(t)
    t.set_defaults(func=_cmd_throw)


class _InputError(ValueError):
    pass


# what a plan's JSON holds (``Plan.as_json``): another billiards or throw may replace it
_PLAN_KEYS = frozenset({"task", "variables", "distance_model"})


def _is_plan_json(path: str) -> bool:
    """Whether ``path`` holds a JSON object with :data:`_PLAN_KEYS` (a plan written here)."""
    import json

    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and _PLAN_KEYS <= data.keys()


def _check_paths(args: argparse.Namespace) -> None:
    import os

    from diffcontact.io import check_writable

    suffixes = {"--json": ".json", "--gif": ".gif"}  # (so never the same file)
    for flag, path in (("--json", args.json), ("--gif", None if args.no_gif else args.gif)):
        if path is None:
            continue
        if Path(path).suffix.lower() != suffixes[flag]:  # (a .png got GIF bytes; --json
            # rec.npz replaced a recording)
            raise _InputError(f"{flag} {path!r}: the file name must end in {suffixes[flag]}")
        try:
            check_writable(path)
        except OSError as err:
            raise _InputError(f"cannot write {flag} {path!r}: {err}") from None
        if flag == "--json" and os.path.exists(path) and not args.force:
            if not _is_plan_json(path):
                raise _InputError(
                    f"--json {path!r} exists and is not a plan written by billiards or throw: "
                    "pass --force to replace it, or choose another name"
                )


def _planner(spec: str) -> Any:
    from diffcontact.control.planner import as_planner

    try:
        return as_planner(spec)
    except (ValueError, FileNotFoundError) as err:
        raise _InputError(f"MODEL {spec!r}: {err}") from None


def _report(args: argparse.Namespace, planner: Any, plan: Any, seconds: float) -> int:
    from diffcontact.io import atomic_write_json

    info = plan.as_json(0)
    shot = ", ".join(f"{k} = {_fmt(v)}" for k, v in info["variables"].items())
    res = plan.result
    print(f"{plan.task} with {planner.name}: {shot}")
    if planner.truth_known:
        judged = f"{info['distance_true']:.4g} under the ground truth ({planner.truth.name}"
        judged += (
            f", {planner.truth_contact_model})" if planner.truth_contact_model != "CM" else ")"
        )
    else:
        judged = "unknown under the ground truth (recorded data without true parameters)"
        info["distance_true"] = None
    print(
        f"  final distance to the target: {info['distance_model']:.4g} under the planning "
        f"model, {judged}"
    )
    its = f"{res.iterations} iteration{'s' if res.iterations != 1 else ''}"
    starts = f"{args.starts} start{'s' if args.starts != 1 else ''}"
    print(f"  {its} (stopped: {res.stopped}), {starts}, {seconds:.1f} s")
    if info["distance_model"] > args.tolerance:
        print(
            f"diffcontact {args.command}: warning: target not reached: the best plan ends "
            f"{info['distance_model']:.3g} from it under the planning model (--tolerance "
            f"{args.tolerance:g}); more --starts or --iterations may find one, or no shot "
            "reaches it in --time",
            file=sys.stderr,
        )
    if args.json:
        info.update(planner=planner.name, iterations=res.iterations, seconds=round(seconds, 3))
        atomic_write_json(args.json, info)
        print(f"  wrote {args.json}")
    if not args.no_gif:
        from diffcontact.viz import animate, scene_from_system
        from diffcontact.viz.animation import body_color_name

        title = f"{plan.task}: {planner.name}"
        scene = scene_from_system(planner.truth, title=title)
        if args.command == "billiards":  # the target: a cross (billiards), a line (throw)
            cue, ball = body_color_name(args.cue), body_color_name(args.ball)
            title += f"\ncue ball {args.cue} ({cue}) sends ball {args.ball} ({ball}) to the cross"
            scene = dataclasses.replace(scene, targets=(tuple(args.target),), title=title)
        else:
            scene = dataclasses.replace(scene, target_x=(float(args.target),))
        if planner.truth_known:
            animate(
                plan.traj_true[:1], scene, args.gif, overlay=plan.traj_model[:1],
                labels=("ground truth", "planning model"), dt=planner.dt,
            )  # fmt: skip
        else:  # only the plan: no truth to draw
            animate(plan.traj_model[:1], scene, args.gif, dt=planner.dt)
        print(f"  wrote {args.gif}")
    return 0


def _fmt(v: Any) -> str:
    if isinstance(v, list):
        return "(" + ", ".join(f"{x:.4g}" for x in v) + ")" if len(v) > 1 else f"{v[0]:.4g}"
    return f"{v:.4g}"


def _run(args: argparse.Namespace, plan_fn: Any, **kwargs: Any) -> int:
    _check_paths(args)
    planner = _planner(args.model)
    start = time.perf_counter()
    from diffcontact.control.optimize import ControlError

    try:
        with one_line_warnings(f"diffcontact {args.command}"):
            plan = plan_fn(
                planner,
                args.target,
                time=args.time,
                starts=args.starts,
                iterations=args.iterations,
                lr=args.lr,
                tolerance=args.tolerance,
                max_speed=args.max_speed,
                progress=not args.quiet,
                **kwargs,
            )
    except ControlError as err:
        raise _InputError(str(err)) from None
    return _report(args, planner, plan, time.perf_counter() - start)


def _cmd_billiards(args: argparse.Namespace) -> int:
    def run() -> int:
        from diffcontact.control.tasks import plan_billiards

        return _run(args, plan_billiards, cue=args.cue, ball=args.ball, seed=args.seed)

    return report_errors("diffcontact billiards", run, bad_input=_InputError)


def _cmd_throw(args: argparse.Namespace) -> int:
    def run() -> int:
        from diffcontact.control.tasks import plan_throw

        return _run(args, plan_throw, start=tuple(args.start), max_spin=args.max_spin)

    return report_errors("diffcontact throw", run, bad_input=_InputError)

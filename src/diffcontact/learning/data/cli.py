"""``diffcontact generate``: argument parsing and the handler.

Building the parser imports no torch; the handler imports the dataset
modules when it runs.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

from diffcontact.cli_args import (
    float_in,
    int_at_least,
    one_line,
    one_line_warnings,
    positive_float,
    report_errors,
)
from diffcontact.contact.registry import contact_models
from diffcontact.learning.data.checks import DT_RTOL

__all__ = ["register_cli", "run_generate_cli"]


def register_cli(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``generate`` subcommand to an argparse ``subparsers`` object; return its parser.

    The handler (``args.func``) returns the exit status: 0, 2 for bad input
    (one line on stderr) or 1 when the simulation or writing fails.
    """
    p = subparsers.add_parser(
        "generate",
        help="simulate and chunk a train/val/test dataset (or import recorded trajectories)",
        description=(
            "Simulate full trajectories of a task for the train, val and test splits "
            "(seeds SEED*1000 + 0, 1, 2), pick one chunk per trajectory starting out of "
            "contact (about half containing a contact; --stride: every window instead), "
            "optionally add noise to the chunks, and write train.npz, val.npz, test.npz and "
            "metadata.json to --out. With --from-arrays, split recorded trajectories and "
            "cut every window into a chunk instead (contact flags from the geometry, "
            "velocity jumps, and flags or event times in the file). "
            "Re-running with the same arguments reuses the folder; see docs/data.md."
        ),
    )
    p.add_argument(
        "task",
        metavar="TASK_OR_CONFIG",
        nargs="?",
        default=None,
        help="built-in task (e.g. BP5, CP3) or a .yaml/.json config "
        "(with --from-arrays: the config of the recorded system, like --config)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="dataset folder")
    p.add_argument("--n-train", metavar="N", type=int_at_least(1), default=None, help="default 800")
    p.add_argument("--n-val", metavar="N", type=int_at_least(0), default=None, help="default 100")
    p.add_argument("--n-test", metavar="N", type=int_at_least(0), default=None, help="default 100")
    p.add_argument(
        "--seed", metavar="N", type=int_at_least(0), default=0, help="base seed (default 0)"
    )
    p.add_argument(
        "--noise-std",
        metavar="STD",
        type=float_in(0.0),
        default=None,
        help="Gaussian noise std added to the chunks (default 0; chain pendulum: on the "
        "angles and angular velocities)",
    )
    p.add_argument(
        "--chunk-length",
        metavar="L",
        type=int_at_least(2),
        default=5,
        help="states per chunk (default 5)",
    )
    p.add_argument(
        "--contact-fraction",
        metavar="F",
        type=float_in(0.0, 1.0),
        default=0.5,
        help="target share of chunks containing a contact (default 0.5); with windows, the "
        "share of training draws (a sampling weight); a warning says when it cannot be met",
    )
    p.add_argument(
        "--stride",
        metavar="K",
        type=_stride,
        default=None,
        help="cut every window starting at states 0, K, 2K, ... into a chunk (K at most "
        "T - chunk length + 1; default: 1 with "
        "--from-arrays; 'none' (one chunk per trajectory, the paper's set-up) for simulated "
        "data); 'none' or 0: one chunk per trajectory",
    )
    p.add_argument(
        "--device", choices=("cpu", "cuda"), default=None, help="where to simulate (default cpu)"
    )
    p.add_argument(
        "--contact-model",
        choices=contact_models(),
        default=None,
        help="contact model that simulates the ground truth (default CM); recorded in "
        "metadata.json",
    )
    p.add_argument(
        "--from-arrays",
        metavar="FILE",
        default=None,
        help="recorded trajectories: an .npz with an array 'traj' (N, T, 2, P, d) (optional "
        "'dt' and 'config' entries, as written by `diffcontact simulate`) or an .npy",
    )
    p.add_argument("--config", metavar="CONFIG", default=None, help="config of the recorded system")
    p.add_argument(
        "--val-fraction",
        metavar="F",
        type=_fraction,
        default=None,
        help="with --from-arrays: share for val, in [0, 1) (default 0.1)",
    )
    p.add_argument(
        "--test-fraction",
        metavar="F",
        type=_fraction,
        default=None,
        help="with --from-arrays: share for test, in [0, 1) (default 0.1)",
    )
    p.add_argument(
        "--dt",
        metavar="DT",
        type=positive_float,
        default=None,
        help="with --from-arrays: the recording's time step, checked against the config",
    )
    p.add_argument(
        "--true-params",
        action="store_true",
        help="with --from-arrays: the config's masses, mu and e_P are the recorded system's "
        "true values (evaluation compares the learned ones with them; default: unknown)",
    )
    p.add_argument(
        "--impact-tol",
        metavar="TOL",
        type=float_in(0.0, infinite=True),
        default=None,
        help="with --from-arrays: flag an impact between samples when the velocities jump by "
        "more than TOL times the trajectory's RMS speed beyond what the neighbouring steps "
        "show (default 0.2; inf: off)",
    )
    p.add_argument(
        "--gap-tol",
        metavar="GAP",
        type=float_in(0.0),
        default=None,
        help="with --from-arrays: flag states whose gap (config geometry) is below GAP "
        "(default 0: penetration only)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress and no summary")
    p.set_defaults(func=run_generate_cli)
    return p


def _fraction(text: str) -> float:
    """``--val-fraction``/``--test-fraction``: a number in ``[0, 1)``, the range
    ``dataset_from_arrays`` accepts (1 leaves nothing to train on)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0.0 <= value < 1.0:  # (NaN too)
        raise argparse.ArgumentTypeError(f"must be a finite number in [0, 1), got {value:g}")
    return value


def _stride(text: str) -> int:
    """``--stride``: an integer >= 1, or ``none``/``0`` (0: one chunk per trajectory)."""
    if text.strip().lower() == "none":
        return 0
    return int_at_least(0)(text)


def _config_differs(spec: Any, file_config: Any, traj: Any) -> str | None:
    """How the system of ``--config`` differs from the one stored in an arrays file, on
    the recording's first positions (``None``: the same dt, geometry and constraints;
    masses, friction and restitution may differ)."""
    import torch

    from diffcontact.learning.data.format import structure_mismatch
    from diffcontact.systems import load_system

    given, stored = load_system(spec), load_system(file_config)
    if not math.isclose(given.dt, stored.dt, rel_tol=DT_RTOL, abs_tol=1e-12):
        return f"dt {given.dt!r} against the file's {stored.dt!r}"
    if tuple(given.state_shape) != tuple(stored.state_shape):
        return f"states of shape {tuple(given.state_shape)}, the file's {tuple(stored.state_shape)}"
    if traj.ndim != 5 or 0 in traj.shape[:2]:  # dataset_from_arrays names the shape
        return None
    x = torch.as_tensor(traj[:64, 0, 0], dtype=torch.float64)
    return structure_mismatch(given, stored, x, "--config", "the file's")


def _check_file_config(path: str, config: Any) -> None:
    """The config stored in an arrays file loads; a ``ValueError`` naming the file's entry."""
    from diffcontact.systems import load_system

    try:
        load_system(config)
    except ValueError as err:
        raise ValueError(
            f"{path}: entry 'config' is not a usable config: {one_line(err)}"
        ) from None


def _given(**options: Any) -> dict[str, Any]:
    """The options given on the command line (the functions' defaults apply to the others)."""
    return {key: value for key, value in options.items() if value is not None}


def _cli_generate(args: argparse.Namespace) -> int:
    from diffcontact.learning.data.format import METADATA

    quiet = args.quiet
    if args.task is not None and args.config is not None and args.task != args.config:
        raise ValueError(
            f"give the config once: TASK_OR_CONFIG {args.task!r} and --config {args.config!r}"
        )
    spec = args.task if args.task is not None else args.config
    common = {
        "seed": args.seed,
        "chunk_length": args.chunk_length,
        "contact_fraction": args.contact_fraction,
        "progress": not quiet,
    }
    if args.stride is not None:
        common["stride"] = args.stride or None
    folder = Path(args.out)
    start = time.perf_counter()
    if args.from_arrays is not None:
        from diffcontact.learning.data.arrays import (
            dataset_from_arrays,
            read_arrays_file,
            read_flag_entries,
        )

        for flag, value in (
            ("--n-train", args.n_train), ("--n-val", args.n_val), ("--n-test", args.n_test),
            ("--noise-std", args.noise_std), ("--device", args.device),
            ("--contact-model", args.contact_model),
        ):  # fmt: skip
            if value is not None:
                raise ValueError(
                    f"{flag} does not apply with --from-arrays (split sizes come from "
                    "--val-fraction/--test-fraction; recorded data gets no noise)"
                )
        traj, file_dt, file_config = read_arrays_file(args.from_arrays)
        if (
            args.dt is not None
            and file_dt is not None
            and not math.isclose(args.dt, file_dt, rel_tol=DT_RTOL, abs_tol=1e-12)
        ):
            raise ValueError(
                f"--dt {args.dt!r} contradicts the dt {file_dt!r} stored in {args.from_arrays} "
                "(the recording's own step): leave --dt out, or fix the file"
            )
        contact, event_times = read_flag_entries(args.from_arrays)
        if file_config is not None:
            _check_file_config(args.from_arrays, file_config)
        if spec is None:
            if file_config is None:
                raise ValueError(
                    "--from-arrays needs the system's config: --config CONFIG (a task name "
                    "or a .yaml/.json file)"
                )
            spec = file_config
        elif file_config is not None:
            differs = _config_differs(spec, file_config, traj)
            if differs:  # (also with --quiet, as convert's warnings)
                print(
                    f"diffcontact generate: warning: --config differs from the config stored "
                    f"in {args.from_arrays} "
                    f"({differs}); the dataset uses --config",
                    file=sys.stderr,
                )
        reused = (folder / METADATA).is_file()
        with one_line_warnings("diffcontact generate"):  # velocities, chunkless trajectories
            dataset_from_arrays(
                traj,
                spec,
                folder,
                dt=args.dt if args.dt is not None else file_dt,
                **_given(
                    val_fraction=args.val_fraction,
                    test_fraction=args.test_fraction,
                    impact_tol=args.impact_tol,
                    gap_tol=args.gap_tol,
                ),
                true_parameters=args.true_params,
                contact=contact,
                event_times=event_times,
                **common,
            )
    else:
        from diffcontact.learning.data.generate import generate_dataset

        for flag, value in (
            ("--val-fraction", args.val_fraction),
            ("--test-fraction", args.test_fraction),
            ("--dt", args.dt),
            ("--config", args.config if args.task is None else None),
            ("--impact-tol", args.impact_tol),
            ("--gap-tol", args.gap_tol),
            ("--true-params", True if args.true_params else None),
        ):
            if value is not None:
                raise ValueError(f"{flag} applies only with --from-arrays")
        if spec is None:
            raise ValueError("give TASK_OR_CONFIG (a built-in task or a .yaml/.json config)")
        reused = (folder / METADATA).is_file()  # then it is reused, or the call fails
        generate_dataset(
            spec,
            folder,
            **_given(
                n_train=args.n_train,
                n_val=args.n_val,
                n_test=args.n_test,
                noise_std=args.noise_std,
                device=args.device,
                contact_model=args.contact_model,
            ),
            **common,
        )
    if not quiet:
        _print_summary(folder, reused, time.perf_counter() - start)
    return 0


def _plural(n: int) -> str:
    return "trajectory" if n == 1 else "trajectories"


def _print_summary(folder: Path, reused: bool, elapsed: float) -> None:
    from diffcontact.learning.data.format import METADATA, SPLITS, read_metadata

    meta = read_metadata(folder)
    action = "reused" if reused else f"written in {elapsed:.1f} s"
    print(f"{meta['task']} dataset ({meta['source']}) {action}: {folder}")
    total = with_contact = 0
    for name in SPLITS:
        st = meta["stats"][name]
        n, c = st["n"], st["chunks_with_contact"]
        m = st.get("n_chunks", n)
        total, with_contact = total + m, with_contact + c
        share = f"{100 * c / m:.0f}%" if m else "-"
        k = st["trajectories_with_contact"]
        print(
            f"  {name:5s}: {n} {_plural(n)} x {meta['n_states']} states; {share} of chunks "
            f"contain a contact ({c}/{m}); {k} {_plural(k)} {'has' if k == 1 else 'have'} one"
        )
    share = f"{100 * with_contact / total:.1f}%" if total else "-"
    stride = meta.get("stride")
    cut = "one per trajectory" if stride is None else f"every window, stride {stride}"
    print(
        f"  chunks of {meta['chunk_length']} states ({cut}), noise std {meta['noise_std']:g}; "
        f"{share} of all chunks contain a contact"
    )
    flags = meta.get("contact_flags")
    if flags:
        print(
            f"  states flagged in contact: {flags['total']} (gap {flags['gap']}, velocity jump "
            f"{flags['impact']}, given {flags['given']}, event times {flags['events']})"
        )
    if meta["source"] != "simulated":
        known = "declared true (--true-params)" if meta.get("parameters_known") else "unknown"
        print(f"  physical parameters of the config: {known}")
    files = ", ".join(str(folder / f) for f in (*meta["files"], METADATA))
    print(f"  files: {files}")


def run_generate_cli(args: argparse.Namespace) -> int:
    """Handler of ``diffcontact generate``: 0 on success, 2 on bad input, 1 on failure."""
    return report_errors("diffcontact generate", lambda: _cli_generate(args), bad_input=ValueError)

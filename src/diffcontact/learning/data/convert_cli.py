"""``diffcontact convert``: recorded data in other forms to a ``--from-arrays`` file.

Building the parser imports no torch (nor MuJoCo); the handler imports the
converters (:mod:`.convert`, :mod:`.mujoco`) when it runs.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from diffcontact.cli_args import finite_float, float_in, one_line, report_errors
from diffcontact.io import check_writable

__all__ = ["SOURCES", "register_cli", "run_convert_cli"]

SOURCES = {
    "positions": ("x",),
    "coordinates": ("q", "qdot"),
    "mujoco": ("qpos", "qvel"),
}
"""Each source and the arrays its input .npz holds (``qdot`` is optional)."""


def register_cli(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``convert`` subcommand to an argparse ``subparsers`` object; return its parser."""
    p = subparsers.add_parser(
        "convert",
        help="convert recorded data (positions only, generalised coordinates, MuJoCo "
        "qpos/qvel) into a file for `generate --from-arrays`",
        description=(
            "Turn recorded trajectories into diffcontact's layout traj (N, T, 2, P, d) and "
            "save them with dt and the config as an .npz for `diffcontact generate "
            "--from-arrays`. SOURCE positions: FILE holds x (N, T, P, d), velocities by "
            "second-order finite differences; coordinates: q and optionally qdot of a "
            "built-in system type; mujoco: qpos (N, T, nq) and qvel (N, T, nv) of the model "
            "--model. Prints checks of the result; see docs/own-data.md."
        ),
    )
    p.add_argument(
        "source", choices=sorted(SOURCES), metavar="SOURCE", help="positions, coordinates or mujoco"
    )
    p.add_argument("file", metavar="FILE", help="input .npz (arrays named as above)")
    p.add_argument(
        "--config",
        required=True,
        metavar="CONFIG",
        help="the recorded system: built-in task or .yaml/.json config",
    )
    p.add_argument("--out", required=True, metavar="OUT.npz", help="output file")
    p.add_argument("--force", action="store_true", help="replace --out if it exists")
    p.add_argument(
        "--threshold",
        type=float_in(0.0),
        default=None,
        metavar="A",
        help="positions / coordinates without qdot: the velocity-jump threshold "
        "(an acceleration; default automatic)",
    )
    p.add_argument(
        "--omega-frame",
        choices=("world", "body"),
        default=None,  # world; None tells a given --omega-frame from the default
        help="coordinates, gyroscope: frame of the angular velocity (default world)",
    )
    p.add_argument("--model", metavar="XML", default=None, help="mujoco: the MJCF model file")
    p.add_argument(
        "--bodies",
        nargs="+",
        metavar="NAME|ID",
        default=None,
        help="mujoco: one MuJoCo body name or id (or site:NAME) per diffcontact body, in "
        "its order, each at most once; digits are an id unless a body has that name "
        "(default: all bodies but the world, in the model's order)",
    )
    p.add_argument(
        "--plane",
        default=None,
        metavar="AB",
        help="mujoco, 2D systems: the world axes that become x and y (e.g. xy, xz)",
    )
    p.add_argument(
        "--axes",
        choices=("inertial", "body"),
        default=None,  # inertial; None tells a given --axes from the default
        help="mujoco: axis points along the principal axes (default) or the body frame",
    )
    p.add_argument(
        "--origin",
        nargs=3,
        type=finite_float,
        metavar=("X", "Y", "Z"),
        default=None,
        help="mujoco: world point that becomes the origin (e.g. a pivot)",
    )
    p.add_argument("--quiet", action="store_true", help="no summary")
    p.set_defaults(func=run_convert_cli)
    return p


def _read(path: str, source: str) -> tuple[dict[str, Any], float | None]:
    from diffcontact.io import read_npz

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"input file {path!r} does not exist")
    names = SOURCES[source]

    try:
        arrays, keys = read_npz(p, (*names, "dt"))
        if keys == [""]:
            raise ValueError("an .npy file holds one array; save named arrays with numpy.savez")
    except (OSError, ValueError) as err:
        raise ValueError(
            f"cannot read {path} as .npz (truncated or corrupted?): {one_line(err)}"
        ) from None
    required = [n for n in names if n != "qdot"]
    missing = [n for n in required if n not in arrays]
    if missing:
        raise ValueError(
            f"{path} has no array named {', '.join(map(repr, missing))} for SOURCE {source} "
            f"(found: {', '.join(keys) or 'nothing'}); save with numpy.savez(FILE, "
            + ", ".join(f"{n}=..." for n in names)
            + ")"
        )
    dt = None
    if "dt" in arrays:
        a = arrays.pop("dt")
        if a.size != 1 or a.dtype.kind not in "fiu":
            raise ValueError(f"{path}: entry 'dt' must be one number, got {a.dtype} {a.shape}")
        dt = float(a.reshape(()))
    return arrays, dt


CONTACT_SHARE_WARN = 0.9
"""A conversion with more of its states in contact than this warns (wrong geometry or units)."""


def _cli_convert(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if out.exists() and not args.force:
        raise ValueError(f"--out {args.out} exists; pass --force to replace it")
    if out.suffix != ".npz":
        raise ValueError(f"--out must name an .npz file; got {args.out!r}")
    try:  # before the conversion: a missing or read-only folder named up front
        check_writable(out)
    except OSError as err:
        raise ValueError(f"--out {args.out}: {err}") from None
    mujoco_only = {"--model": args.model, "--bodies": args.bodies, "--plane": args.plane,
                   "--origin": args.origin, "--axes": args.axes}  # fmt: skip
    if args.source != "mujoco":
        given = [flag for flag, value in mujoco_only.items() if value is not None]
        if given:
            verb = "applies" if len(given) == 1 else "apply"
            raise ValueError(f"{', '.join(given)} {verb} only to SOURCE mujoco")
    elif args.model is None:
        raise ValueError("SOURCE mujoco needs --model XML (the MJCF model of the recording)")
    if args.source != "coordinates" and args.omega_frame is not None:  # (was ignored)
        raise ValueError("--omega-frame applies only to SOURCE coordinates")
    if args.source == "mujoco" and args.threshold is not None:
        raise ValueError("--threshold applies only to SOURCE positions and coordinates")
    arrays, file_dt = _read(args.file, args.source)
    if args.threshold is not None and "qdot" in arrays:
        raise ValueError(
            f"--threshold is not used: {args.file} holds qdot, the velocities (it sets the "
            "velocity-jump threshold of finite differences, without qdot)"
        )

    import warnings

    import numpy as np

    from diffcontact import __version__
    from diffcontact.io import atomic_save_npz
    from diffcontact.learning.data import convert
    from diffcontact.learning.data.checks import constraint_violation
    from diffcontact.systems import load_system

    system = load_system(args.config)
    convert._check_dt(file_dt, system)
    extra: dict[str, Any] = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if args.source == "positions":
            z = convert.trajectories_from_positions(
                arrays["x"], config=system, threshold=args.threshold
            )
            extra["velocity_unreliable"] = convert._unreliable(
                arrays["x"], system.dt, args.threshold
            )
        elif args.source == "coordinates":
            z = convert.trajectories_from_coordinates(
                system,
                arrays["q"],
                arrays.get("qdot"),
                omega_frame=args.omega_frame or "world",
                threshold=args.threshold,
            )
            if "qdot" not in arrays:
                extra["velocity_unreliable"] = convert._unreliable(
                    z[:, :, 0], system.dt, args.threshold
                )
        else:
            from diffcontact.learning.data.mujoco import trajectories_from_mujoco

            z = trajectories_from_mujoco(
                args.model,
                arrays["qpos"],
                arrays["qvel"],
                system,
                bodies=args.bodies,
                plane=args.plane,
                axes=args.axes or "inertial",
                origin=args.origin,
            )
    extra = {k: v for k, v in extra.items() if v is not None}
    checks = convert.trajectory_checks(system, z)  # (bad input found here writes nothing)
    notes = [one_line(w.message) for w in caught]
    broken = constraint_violation(system, np.asarray(z)[:, :, 0])
    if broken is not None:
        notes.append(f"{broken}; `diffcontact generate --from-arrays` refuses such data")
    atomic_save_npz(
        out,
        traj=z,
        dt=np.float64(system.dt),
        config=np.str_(json.dumps(system.config.model_dump(mode="json"))),
        source=np.str_(args.source),
        diffcontact_version=np.str_(__version__),
        **extra,
    )
    if checks["share_of_states_in_contact"] > CONTACT_SHARE_WARN:
        notes.append(
            f"{checks['share_of_states_in_contact']:.0%} of the states are in contact (min_gap "
            f"{checks['min_gap']:.3g}): the config's radii or walls, or the units of the "
            "positions, do not match the data (docs/own-data.md, 'What to check')"
        )
    if not args.quiet:
        print(f"{system.name}: converted {args.source} {args.file} -> {out}: traj {z.shape}")
        for note in notes:
            print(f"  warning: {note}")
        if "velocity_unreliable" in extra:
            n = int(extra["velocity_unreliable"].sum())
            print(
                f"  {n} of {z.shape[0] * z.shape[1]} states have finite-difference velocities "
                "next to a velocity jump (saved as velocity_unreliable)"
            )
        print("  checks: " + ", ".join(f"{k} {v:.3g}" for k, v in checks.items()))
        if broken is not None:  # generate would refuse the file: say what to fix instead
            print(
                "  next: fix the config (link lengths, pivot, axis points) or the data's "
                "origin or units as the warning says, and convert again; `diffcontact "
                "generate --from-arrays` refuses this file"
            )
        else:
            print(f"  next: diffcontact generate --from-arrays {out} --out DATASET_DIR")
    else:  # no summary, but the warnings still, one line each on stderr
        for note in notes:
            print(f"diffcontact convert: warning: {note}", file=sys.stderr)
    return 0


def run_convert_cli(args: argparse.Namespace) -> int:
    """Handler of ``diffcontact convert``: 0 on success, 2 on bad input, 1 on failure."""
    return report_errors(
        "diffcontact convert", lambda: _cli_convert(args), bad_input=(ValueError, ImportError)
    )

"""The ``diffcontact`` command line.

Subcommands:

- ``diffcontact demo``: the solver, a simulation, and learning CP3 end to end.
- ``diffcontact simulate TASK_OR_CONFIG``: simulate a built-in task or a config
  file, save the trajectories as ``.npz`` and optionally a GIF.
- ``diffcontact generate``: a train/val/test dataset, simulated or from recorded
  arrays (:mod:`diffcontact.learning.data.cli`);
- ``diffcontact convert``: recorded positions, generalised coordinates or MuJoCo
  ``qpos``/``qvel`` to a ``--from-arrays`` file (:mod:`diffcontact.learning.data.convert_cli`);
- ``diffcontact train``: train a registered model on a dataset
  (:mod:`diffcontact.learning.training.cli`);
- ``diffcontact evaluate``: metrics, plots and a GIF of a trained run
  (:mod:`diffcontact.learning.evaluation.cli`).
- ``diffcontact billiards`` / ``diffcontact throw``: plan a shot through a
  trained model or the true system (:mod:`diffcontact.control.cli`).

Contact-model and model names come from the registries
(:mod:`diffcontact.contact.registry`, :mod:`diffcontact.learning.models.registry`);
building the parser imports neither torch nor Lightning.

Bad input (unknown task, missing file, bad numbers, unwritable output, CUDA
not available) gives a one-line error on stderr and exit status 2. Heavy
imports (torch, matplotlib) happen inside the subcommands.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any, NoReturn

from diffcontact import __version__
from diffcontact.cli_args import (
    non_negative_int,
    one_line,
    one_line_warnings,
    positive_int,
    threads_arg,
)
from diffcontact.contact.registry import contact_models


def _task_names() -> list[str]:
    """The built-in tasks (``diffcontact.list_tasks()``, read without importing torch)."""
    return sorted(p.stem for p in (Path(__file__).parent / "systems" / "tasks").glob("*.yaml"))


EXIT_USAGE = 2


class UsageError(Exception):
    """Bad input from the command line; reported as one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``PROG: error: MESSAGE``) and exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="diffcontact",
        description=(
            "Learn and simulate colliding physical systems with differentiable contact models."
        ),
    )
    parser.add_argument("--version", action="version", version=f"diffcontact {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    demo = sub.add_parser(
        "demo",
        help="run the demo: solver, simulation, then learning CP3 end to end (a few minutes)",
        description=(
            "The contact solver on a ball hitting a wall; a simulated BP5 animation; then a "
            "small CP3 dataset, CM-CD-CLNN trained on it on the CPU, the learned mass ratios, "
            "mu and e_P next to the truth, and the evaluation plots. Writes to --out."
        ),
    )
    demo.add_argument("--out", default="demo_out", help="output folder (default demo_out)")
    demo.add_argument(
        "--no-learning", action="store_true", help="skip the learning part (seconds, not minutes)"
    )
    demo.add_argument(
        "--epochs", type=positive_int, default=None, help="epochs of the learning part (default 40)"
    )
    demo.set_defaults(func=_cmd_demo)

    sim = sub.add_parser(
        "simulate",
        help="simulate a task and save the trajectories (.npz) and optionally a GIF",
        description=(
            "Sample initial conditions of a task, simulate them with the ground-truth "
            "contact model, and save traj (N, steps+1, 2, P, d), energy (N, steps+1), "
            "t (steps+1,) and metadata (config as JSON, seed, task, dt, contact_model, "
            "diffcontact_version) to an .npz file."
        ),
    )
    sim.add_argument(
        "task",
        metavar="TASK_OR_CONFIG",
        help=f"built-in task ({', '.join(_task_names())}) or a path to a .yaml/.json config",
    )
    sim.add_argument("--n", type=positive_int, default=4, help="trajectories (default 4)")
    sim.add_argument(
        "--steps",
        type=positive_int,
        default=None,
        help="time steps per trajectory (default: the task's horizon, horizon/dt - 1)",
    )
    sim.add_argument(
        "--seed", type=non_negative_int, default=0, help="initial-condition seed (default 0)"
    )
    sim.add_argument(
        "--out", default="sim.npz",
        help="output .npz file (default sim.npz); an existing file that an earlier simulate "
        "did not write (a recording) is replaced only with --force",
    )  # fmt: skip
    sim.add_argument("--force", action="store_true", help="replace --out whatever it holds")
    sim.add_argument("--gif", default=None, help="also write an animation to this .gif file")
    sim.add_argument(
        "--energy-plot", default=None, metavar="PNG", help="also plot the energy to this .png"
    )
    sim.add_argument(
        "--contact-model",
        choices=contact_models(),
        default="CM",
        help="contact model from the registry: CM (default), CMr (regularised), LCP, Coulomb, "
        "or one an installed package registers (entry point group diffcontact.contact_models)",
    )
    sim.add_argument(
        "--device", choices=("cpu", "cuda"), default="cpu", help="where to simulate (default cpu)"
    )
    sim.add_argument(
        "--fps", type=positive_int, default=20, help="GIF frames per second (default 20)"
    )
    sim.add_argument(
        "--gif-frames", type=positive_int, default=40,
        help="at most this many GIF frames, evenly spaced over the trajectory (default 40)",
    )  # fmt: skip
    sim.add_argument(
        "--threads", type=threads_arg, default="auto", metavar="N|auto",
        help="torch CPU threads (default auto: 1 or all available cores, whichever the "
        "timed steps show faster; several threads slow down on a loaded CPU)",
    )  # fmt: skip
    sim.add_argument(
        "--cuda-graph", choices=("auto", "on", "off"), default="auto",
        help="with --device cuda, replay one step captured in a CUDA graph (default auto: "
        "where it can; on: insist; off: step by step)",
    )  # fmt: skip
    sim.add_argument("--quiet", action="store_true", help="no progress bar and no summary")
    sim.set_defaults(func=_cmd_simulate)

    # learning subcommands; each module keeps its heavy imports inside its handler
    from diffcontact.learning.data import cli as learning_data
    from diffcontact.learning.data import convert_cli as learning_convert
    from diffcontact.learning.evaluation import cli as learning_evaluate
    from diffcontact.learning.training import cli as learning_train

    learning_data.register_cli(sub)
    learning_convert.register_cli(sub)
    learning_train.register_cli(sub)
    learning_train.register_refit_cli(sub)
    learning_evaluate.register_cli(sub)

    from diffcontact.control import cli as control

    control.register_cli(sub)
    return parser


def _cmd_demo(args: argparse.Namespace) -> int:
    from diffcontact.demo import run_demo

    return run_demo(args.out, learning=not args.no_learning, epochs=args.epochs)


SIMULATE_KEYS = frozenset({"traj", "energy", "t", "config", "task", "contact_model"})
"""Entries of the ``.npz`` that ``diffcontact simulate`` writes (another simulate may
replace such a file without ``--force``)."""


def _written_by_simulate(path: str) -> bool:
    """Whether ``path`` is an ``.npz`` holding :data:`SIMULATE_KEYS` (its index only)."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as archive:
            names = {name.removesuffix(".npy") for name in archive.namelist()}
    except (OSError, zipfile.BadZipFile):
        return False
    return SIMULATE_KEYS <= names


def _check_outputs(args: argparse.Namespace) -> None:
    from diffcontact.io import check_writable

    paths = [("--out", args.out), ("--gif", args.gif), ("--energy-plot", args.energy_plot)]
    seen: dict[str, str] = {}
    suffixes = {"--out": (".npz",), "--gif": (".gif",), "--energy-plot": (".png", ".pdf", ".svg")}
    for flag, path in paths:
        if path is None:
            continue
        # the suffix as pathlib reads it, as animate and plot_energy do: '.gif' (a hidden
        # file's name) has none, and was refused there after the .npz had been written
        name, suffix = Path(path).name, Path(path).suffix.lower()
        if suffix not in suffixes[flag] and name.lower() in suffixes[flag]:
            raise UsageError(f"{flag} {path!r} has no file name before its suffix")
        if suffix not in suffixes[flag] or not str(path).lower().endswith(suffixes[flag]):
            # (an .npz was written as s3.txt)
            raise UsageError(
                f"{flag} {path!r}: the file name must end in {' or '.join(suffixes[flag])}"
            )
        try:
            check_writable(path)
        except OSError as err:
            raise UsageError(f"cannot write {flag} {path!r}: {err}") from None
        if flag == "--out" and os.path.exists(path) and not args.force:
            if not _written_by_simulate(path):
                raise UsageError(
                    f"--out {path!r} exists and was not written by diffcontact simulate (a "
                    "recording?): pass --force to replace it, or choose another name"
                )
        real = os.path.realpath(path)
        if real in seen:
            raise UsageError(f"{flag} and {seen[real]} name the same file {path!r}")
        seen[real] = flag


def _check_size(n: int, steps: int, system: Any) -> None:
    """Refuse a simulation whose steps exceed ``MAX_STATES`` or whose trajectories would
    not fit in half the machine's memory (a typo would fill it), unless lifted."""
    from diffcontact.systems.config import rollout_size_error

    too_large = rollout_size_error(n, steps, system.state_shape, names=("--steps ", "--n "))
    if too_large:
        raise UsageError(too_large)


def _not_written(wrote: list[str], outputs: list[str]) -> str:
    """The ``outputs`` that a simulate stopped part-way did not write (after ``wrote``)."""
    left = [p for p in outputs if p not in wrote]
    return f"not written: {', '.join(left)} (a file of that name is from an earlier run)"


def _cmd_simulate(args: argparse.Namespace) -> int:
    _check_outputs(args)
    import torch

    from diffcontact.io import parse_device

    try:
        parse_device(args.device)
    except ValueError as err:
        raise UsageError(f"--device: {err}") from None
    if args.cuda_graph == "on" and args.device != "cuda":  # (the error named cuda_graph=True)
        raise UsageError(f"--cuda-graph on needs --device cuda, not --device {args.device}")

    import json

    import numpy as np

    from diffcontact.io import atomic_save_npz
    from diffcontact.systems import load_system

    try:
        system = load_system(args.task)
    except (ValueError, OSError) as err:
        raise UsageError(one_line(err)) from None
    steps = args.steps if args.steps is not None else system.default_steps
    if steps <= 0:  # a task whose horizon holds a single state
        raise UsageError(f"--steps: the task's default is {steps}; give --steps explicitly")
    _check_size(args.n, steps, system)

    start = time.perf_counter()
    try:
        z0 = system.sample_initial_conditions(args.n, seed=args.seed, device=args.device)
        with one_line_warnings("diffcontact simulate"):
            traj = system.simulate(
                z0,
                steps=steps,
                contact_model=args.contact_model,
                progress=not args.quiet,
                threads=args.threads,
                cuda_graph={"auto": "auto", "on": True, "off": False}[args.cuda_graph],
            )
    except ValueError as err:  # (simulate's own errors name its Python arguments)
        message = one_line(err).replace("simulate: cuda_graph=True, but", "--cuda-graph on, but")
        raise UsageError(message) from None
    except RuntimeError as err:  # e.g. the contact solver did not converge
        print(
            f"diffcontact simulate: error: simulation failed: {type(err).__name__}: "
            f"{one_line(err)}",
            file=sys.stderr,
        )
        return 1
    with torch.no_grad():
        energy = system.energy(traj)
    elapsed = time.perf_counter() - start

    traj_np = traj.detach().cpu().numpy()
    energy_np = energy.detach().cpu().numpy()
    config = system.config.model_dump(mode="json")
    outputs = [p for p in (args.out, args.gif, args.energy_plot) if p is not None]
    wrote: list[str] = []
    try:
        atomic_save_npz(
            args.out,
            traj=traj_np,
            energy=energy_np,
            t=np.arange(steps + 1, dtype=np.float64) * system.dt,
            config=np.str_(json.dumps(config)),
            task=np.str_(args.task),
            seed=np.int64(args.seed),
            dt=np.float64(system.dt),
            contact_model=np.str_(args.contact_model),
            diffcontact_version=np.str_(__version__),
        )
        wrote.append(args.out)
        if args.gif is not None or args.energy_plot is not None:
            from diffcontact.viz import animate, plot_energy, scene_from_system

            if args.gif is not None:
                animate(
                    traj_np, scene_from_system(system), args.gif, fps=args.fps, dt=system.dt,
                    max_frames=args.gif_frames,
                )  # fmt: skip
                wrote.append(args.gif)
            if args.energy_plot is not None:
                plot_energy(energy_np, system.dt, args.energy_plot, title=system.name)
                wrote.append(args.energy_plot)
    except (OSError, ValueError) as err:  # e.g. a full disk
        # as on Ctrl-C, say which outputs this run wrote (the error named none: the new
        # .npz could be taken for a failed run's, or an earlier run's GIF for this one's)
        said = f"wrote {', '.join(wrote)}; {_not_written(wrote, outputs)}" if wrote else ""
        print(
            f"diffcontact simulate: error: writing {outputs[len(wrote)]} failed: "
            f"{one_line(err)}; {said or 'nothing written'}",
            file=sys.stderr,
        )
        return 1
    except KeyboardInterrupt:
        if not wrote:
            raise  # (nothing written: main says "interrupted")
        # the outputs are written one after the other: say which ones this run replaced,
        # so that a new .npz is not taken for the partner of an earlier run's GIF
        print(
            f"diffcontact simulate: interrupted after writing {', '.join(wrote)}; "
            f"{_not_written(wrote, outputs)}",
            file=sys.stderr,
        )
        return 130

    if not args.quiet:
        e0, e1 = energy_np[:, 0], energy_np[:, -1]
        change = e1 - e0
        print(
            f"{system.name}: {args.n} trajectories x {steps} steps "
            f"(dt {system.dt:g} s, {args.contact_model}, {args.device}) in {elapsed:.2f} s"
        )
        print(f"  traj {tuple(traj_np.shape)} {traj_np.dtype}")
        print(
            f"  energy: E(0) mean {e0.mean():.6g}, E(end) mean {e1.mean():.6g}, "
            f"E(end) - E(0) in [{change.min():.3g}, {change.max():.3g}]"
        )
        print(f"  wrote {', '.join(wrote)}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (also for ``--help``/``--version``)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, usage errors
        code = exc.code
        return code if isinstance(code, int) else (0 if code is None else EXIT_USAGE)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 0
    try:
        return int(args.func(args) or 0)
    except UsageError as err:
        print(f"diffcontact {args.command}: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"diffcontact {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

"""``diffcontact train``: argument parsing and the handler.

Building the parser imports neither torch nor Lightning (the defaults come
from :mod:`~diffcontact.learning.training.options`); the handler imports
:func:`~diffcontact.learning.training.run.train` when it runs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from diffcontact.cli_args import non_negative_int, positive_float, positive_int, report_errors
from diffcontact.learning.models.registry import model_names
from diffcontact.learning.training import options
from diffcontact.learning.training.options import TrainingInputError, TrainingInterrupted

__all__ = ["register_cli", "register_refit_cli", "run_train_cli"]


def _cli_eps(text: str) -> float | str:
    if text == "learnable":
        return text
    try:
        return positive_float(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"expected a positive number or 'learnable', got {text!r}"
        ) from None


def _cli_hidden(text: str) -> tuple[int, ...]:
    try:
        widths = tuple(int(w) for w in text.split(","))
    except ValueError:
        widths = ()
    if not widths or any(w < 1 for w in widths):
        raise argparse.ArgumentTypeError(f"expected positive widths like 256,256,256, got {text!r}")
    return widths


def _cli_option(text: str) -> tuple[str, Any]:
    import json

    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key.strip(), json.loads(value)
    except json.JSONDecodeError:
        return key.strip(), value


def register_cli(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``train`` subcommand to an argparse ``subparsers`` object; return its parser.

    The handler (``args.func``) returns the exit status: 0, 2 for bad input
    (one line on stderr), 1 when training fails, or 130/143 when SIGINT/SIGTERM
    stopped it (after writing a checkpoint; one line on stderr).
    """
    hidden = ",".join(map(str, options.DEFAULT_HIDDEN))
    p = subparsers.add_parser(
        "train",
        help="train a physical model (CM/CMr/LCP/Coulomb-CD-CLNN/CHNN) or a baseline on a dataset",
        description=(
            "Train a learned model (contact model CM, CMr, LCP or Coulomb, true collision "
            "detection, "
            "constrained Lagrangian or Hamiltonian dynamics; or a baseline: MLP-CD-CLNN, "
            "IN-CP-CLNN, IN-SP-CP, docs/training.md) on the chunks of a dataset "
            "folder with the rollout loss (MAE) and AdamW. Writes run.json, checkpoints/ "
            "(last.ckpt and one per epoch), logs/metrics.csv, learned.json (every epoch) "
            "and model.pt (at the end) to --out, which must be new, empty or a run of ours. "
            "Ctrl-C or SIGTERM stops after the running step with a checkpoint (exit status "
            "130/143); --resume continues. See docs/training.md."
        ),
    )
    p.add_argument("data_dir", metavar="DATA_DIR", help="dataset folder (diffcontact generate)")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory")
    p.add_argument(
        "--model", default=options.DEFAULT_MODEL, metavar="NAME",
        help=f"a registered model: {', '.join(model_names())} (default {options.DEFAULT_MODEL})",
    )  # fmt: skip
    p.add_argument(
        "--model-option", action="append", default=[], metavar="KEY=VALUE", type=_cli_option,
        help="an option of the model's factory (repeatable; VALUE is read as JSON if it "
        "parses, else as a string): a registered model's, or a physical model's "
        "LearnedModel option such as penetration_gradient=true",
    )  # fmt: skip
    p.add_argument(
        "--epochs", type=positive_int, default=options.DEFAULT_EPOCHS,
        help=f"epochs (default {options.DEFAULT_EPOCHS})",
    )  # fmt: skip
    p.add_argument(
        "--batch-size", type=positive_int, default=options.DEFAULT_BATCH_SIZE,
        help=f"chunks per batch (default {options.DEFAULT_BATCH_SIZE})",
    )  # fmt: skip
    p.add_argument(
        "--lr", type=positive_float, default=options.DEFAULT_LR,
        help=f"learning rate of the potential network (default {options.DEFAULT_LR:g})",
    )  # fmt: skip
    p.add_argument(
        "--physics-lr", type=positive_float, default=options.DEFAULT_PHYSICS_LR, metavar="LR",
        help=f"learning rate of masses, inertias, mu, e_P (default {options.DEFAULT_PHYSICS_LR:g})",
    )  # fmt: skip
    p.add_argument(
        "--schedule", choices=options.SCHEDULES, default=options.DEFAULT_SCHEDULE,
        help=f"learning-rate schedule: cosine decay to zero over the epochs, or constant "
        f"(default {options.DEFAULT_SCHEDULE})",
    )  # fmt: skip
    p.add_argument(
        "--weight-decay", type=float, default=options.DEFAULT_WEIGHT_DECAY,
        help=f"AdamW weight decay (default {options.DEFAULT_WEIGHT_DECAY:g})",
    )  # fmt: skip
    p.add_argument(
        "--seed", type=non_negative_int, default=options.DEFAULT_SEED,
        help=f"seed (default {options.DEFAULT_SEED})",
    )  # fmt: skip
    p.add_argument(
        "--device",
        default=options.DEFAULT_DEVICE,
        help=f"cpu or cuda (default {options.DEFAULT_DEVICE})",
    )
    p.add_argument(
        "--eps", type=_cli_eps, default=None,
        help=f"CMr regulariser: a positive number (default {options.DEFAULT_EPS:g}) or 'learnable'",
    )  # fmt: skip
    p.add_argument(
        "--dtype",
        default=options.DEFAULT_DTYPE,
        help=f"float32 or float64 (default {options.DEFAULT_DTYPE})",
    )
    p.add_argument(
        "--resume", action="store_true",
        help="continue RUN_DIR from checkpoints/last.ckpt (else the newest readable epoch "
        "checkpoint); a run without a usable checkpoint starts again from the beginning",
    )  # fmt: skip
    p.add_argument(
        "--max-time", type=positive_float, default=None, metavar="MIN",
        help="stop after the epoch that ends after MIN minutes (model.pt is written; warns "
        "that the learning-rate schedule was cut; --resume finishes the run)",
    )  # fmt: skip
    p.add_argument(
        "--hidden", type=_cli_hidden, default=None, metavar="W,W,...",
        help=f"hidden widths of the potential MLP (default {hidden}); for IN-SP-CP, of "
        "its network's MLPs (default 128,128)",
    )  # fmt: skip
    p.add_argument(
        "--steps-per-epoch", type=positive_int, default=None, metavar="K",
        help="optimiser steps per epoch (default: one pass over the chunks for one chunk per "
        "trajectory; for windows, as many steps as one chunk per training trajectory would "
        "take, windows drawn weighted by the contact fraction)",
    )  # fmt: skip
    p.add_argument(
        "--keep-checkpoints", type=positive_int, default=None, metavar="K",
        help="keep only the newest K per-epoch checkpoints (default: all)",
    )  # fmt: skip
    p.add_argument(
        "--potential-dtype", choices=("float32", "float64"), default=None,
        help="run the potential MLP in this dtype inside the rollout (physical models; "
        "float32: about 1.5x faster steps, mechanics and contacts stay in --dtype)",
    )  # fmt: skip
    p.add_argument(
        "--threads", default="auto", metavar="N|auto",
        help="torch CPU threads during training (default auto: 1 or all available cores, "
        "whichever the timed steps show faster; several threads slow down on a loaded CPU)",
    )  # fmt: skip
    p.add_argument("--devices", default="1", help="devices per node for Lightning (default 1)")
    p.add_argument("--num-nodes", type=positive_int, default=1, help="nodes (default 1)")
    p.add_argument("--strategy", default="auto", help="Lightning strategy, e.g. ddp (default auto)")
    p.add_argument(
        "--refit", type=non_negative_int, default=0, metavar="N",
        help="after the last epoch, N Gauss-Newton iterations on the potential network's "
        "output layer and the physical parameters (physical models; 2 is plenty; "
        "docs/training.md, 'Refit'); default 0: none",
    )  # fmt: skip
    p.add_argument(
        "--quiet", action="store_true",
        help="no progress bar: one line per epoch (losses, learned physical parameters)",
    )  # fmt: skip
    p.set_defaults(func=run_train_cli)
    return p


def register_refit_cli(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``refit`` subcommand; its handler returns 0, 2 (bad input) or 1 (failure)."""
    p = subparsers.add_parser(
        "refit",
        help="Gauss-Newton refit of a trained run's potential output layer and parameters",
        description=(
            "Refit a finished run of a physical model (CM/CMr/LCP/Coulomb-CD-CLNN/CHNN) in "
            "place: Gauss-Newton on the potential network's output layer (exact Jacobian) "
            "and the free physical parameters (finite differences), on the mean squared "
            "error of the rolled-out training chunks, each step kept only if it lowers the "
            "validation error. Rewrites model.pt and learned.json, keeps the model before "
            "as model_adam.pt, writes refit.json. See docs/training.md, 'Refit'."
        ),
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="a finished run (diffcontact train)")
    p.add_argument(
        "--iterations", type=non_negative_int, default=2, metavar="N",
        help="the most Gauss-Newton iterations (default 2)",
    )  # fmt: skip
    p.add_argument(
        "--data", default=None, metavar="DATA_DIR",
        help="the dataset (default: the run's, from run.json)",
    )  # fmt: skip
    p.set_defaults(func=_run_refit_cli)
    return p


def _run_refit_cli(args: argparse.Namespace) -> int:
    def work() -> int:
        from diffcontact.learning.training.refit import refit_run

        report = refit_run(args.run_dir, args.iterations, data_dir=args.data)
        if not report.iterations:
            print(f"no iteration was run (--iterations 0): {args.run_dir} is unchanged")
        elif not any(it.get("accepted") for it in report.iterations):
            print(f"no step lowered the validation MSE: {args.run_dir} is unchanged")
        else:
            run = Path(args.run_dir)
            print(
                f"wrote {run / 'model.pt'}, learned.json and refit.json in {run} (model_adam.pt "
                "keeps the model before the refit)"
            )
        return 0

    return report_errors("diffcontact refit", work, bad_input=ValueError)


def run_train_cli(args: argparse.Namespace) -> int:
    """Handler of ``diffcontact train``: 0 on success, 2 on bad input, 1 on failure, 130/143
    when stopped by SIGINT/SIGTERM."""
    try:
        return report_errors(
            "diffcontact train", lambda: _train(args), bad_input=TrainingInputError
        )
    except TrainingInterrupted as stop:
        print(f"diffcontact train: {stop}", file=sys.stderr)
        return stop.exit_status


def _train(args: argparse.Namespace) -> int:
    from diffcontact.learning.models.registry import is_physical_model
    from diffcontact.learning.training.run import train

    if args.potential_dtype is not None and not is_physical_model(args.model):
        raise TrainingInputError(
            f"--potential-dtype applies to the physical models (CM/CMr/LCP/Coulomb-CD-CLNN/"
            f"CHNN), whose potential is a separate network; {args.model} has no such setting"
        )
    devices: Any = args.devices
    if isinstance(devices, str) and devices.isdigit():
        devices = int(devices)
    train(
        args.data_dir,
        args.out,
        model=args.model,
        epochs=args.epochs,
        batch_size=args.batch_size,
        lr=args.lr,
        weight_decay=args.weight_decay,
        physics_lr=args.physics_lr,
        schedule=args.schedule,
        seed=args.seed,
        device=args.device,
        eps=args.eps,
        hidden=args.hidden,
        model_options=dict(args.model_option)
        | ({} if args.potential_dtype is None else {"potential_dtype": args.potential_dtype}),
        dtype=args.dtype,
        resume=args.resume,
        progress=not args.quiet,
        max_time=args.max_time,
        strategy=args.strategy,
        devices=devices,
        num_nodes=args.num_nodes,
        keep_checkpoints=args.keep_checkpoints,
        steps_per_epoch=args.steps_per_epoch,
        threads=args.threads,
        refit=args.refit,
    )
    if not args.quiet:
        print(f"wrote {Path(args.out) / 'model.pt'} and {Path(args.out) / 'learned.json'}")
    return 0

"""``diffcontact train``: argument parsing and the handler.

Kept apart from :mod:`diffcontact.learning.train` so that building the command-line
parser does not import Lightning; the handler imports it when it runs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from diffcontact.cli_args import non_negative_int, positive_float, positive_int
from diffcontact.learning.model import MODELS

DEFAULT_DTYPE = "float64"
# the physical parameters (a handful of numbers) take larger steps than the potential
# network; measured in docs/training.md ("Learning rates")
DEFAULT_PHYSICS_LR = 3e-2
DEFAULT_SCHEDULE = "cosine"


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


def register_cli(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``train`` subcommand to an argparse ``subparsers`` object; return its parser.

    The handler (``args.func``) returns the exit status: 0, 2 for bad input
    (one line on stderr) or 1 when training fails.
    """
    p = subparsers.add_parser(
        "train",
        help="train a CM/CMr-CD-CLNN/CHNN model on a dataset",
        description=(
            "Train a learned model (contact model CM or CMr, true collision detection, "
            "constrained Lagrangian or Hamiltonian dynamics) on the chunks of a dataset "
            "folder with the rollout loss (MAE) and AdamW. Writes run.json, checkpoints/ "
            "(last.ckpt and one per epoch), logs/metrics.csv, learned.json (every epoch) "
            "and model.pt (at the end) to --out. See docs/training.md."
        ),
    )
    p.add_argument("data_dir", metavar="DATA_DIR", help="dataset folder (diffcontact generate)")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory")
    p.add_argument(
        "--model", default="CM-CD-CLNN", metavar="NAME",
        help=f"one of {', '.join(MODELS)} (default CM-CD-CLNN)",
    )  # fmt: skip
    p.add_argument("--epochs", type=positive_int, default=100, help="epochs (default 100)")
    p.add_argument(
        "--batch-size", type=positive_int, default=200, help="chunks per batch (default 200)"
    )
    p.add_argument(
        "--lr", type=positive_float, default=1e-3,
        help="learning rate of the potential network (default 1e-3)",
    )  # fmt: skip
    p.add_argument(
        "--physics-lr", type=positive_float, default=DEFAULT_PHYSICS_LR, metavar="LR",
        help=f"learning rate of masses, inertias, mu, e_P (default {DEFAULT_PHYSICS_LR:g})",
    )  # fmt: skip
    p.add_argument(
        "--schedule", choices=("cosine", "constant"), default=DEFAULT_SCHEDULE,
        help=f"learning-rate schedule: cosine decay to 1%% over the epochs, or constant "
        f"(default {DEFAULT_SCHEDULE})",
    )  # fmt: skip
    p.add_argument(
        "--weight-decay", type=float, default=1e-4, help="AdamW weight decay (default 1e-4)"
    )
    p.add_argument("--seed", type=non_negative_int, default=0, help="seed (default 0)")
    p.add_argument("--device", default="cpu", help="cpu (default) or cuda")
    p.add_argument(
        "--eps", type=_cli_eps, default=0.01,
        help="CMr regulariser: a positive number (default 0.01) or 'learnable'",
    )  # fmt: skip
    p.add_argument(
        "--dtype", default=DEFAULT_DTYPE, help=f"float32 or float64 (default {DEFAULT_DTYPE})"
    )
    p.add_argument(
        "--resume", action="store_true", help="continue RUN_DIR from checkpoints/last.ckpt"
    )
    p.add_argument(
        "--max-time", type=positive_float, default=None, metavar="MIN",
        help="stop after the epoch that ends after MIN minutes",
    )  # fmt: skip
    p.add_argument(
        "--hidden", type=_cli_hidden, default=(256, 256, 256), metavar="W,W,...",
        help="hidden widths of the potential MLP (default 256,256,256)",
    )  # fmt: skip
    p.add_argument(
        "--keep-checkpoints", type=positive_int, default=None, metavar="K",
        help="keep only the newest K per-epoch checkpoints (default: all)",
    )  # fmt: skip
    p.add_argument("--devices", default="1", help="devices per node for Lightning (default 1)")
    p.add_argument("--num-nodes", type=positive_int, default=1, help="nodes (default 1)")
    p.add_argument("--strategy", default="auto", help="Lightning strategy, e.g. ddp (default auto)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_train_cli)
    return p


def _one_line(err: BaseException) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return "; ".join(lines) if lines else type(err).__name__


def run_train_cli(args: argparse.Namespace) -> int:
    """Handler of ``diffcontact train``: 0 on success, 2 on bad input, 1 on failure."""
    devices: Any = args.devices
    if isinstance(devices, str) and devices.isdigit():
        devices = int(devices)
    from diffcontact.learning.train import TrainingInputError, train

    try:
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
            dtype=args.dtype,
            resume=args.resume,
            progress=not args.quiet,
            max_time=args.max_time,
            strategy=args.strategy,
            devices=devices,
            num_nodes=args.num_nodes,
            keep_checkpoints=args.keep_checkpoints,
        )
    except TrainingInputError as err:
        print(f"diffcontact train: error: {_one_line(err)}", file=sys.stderr)
        return 2
    except (RuntimeError, OSError) as err:
        print(f"diffcontact train: error: {type(err).__name__}: {_one_line(err)}", file=sys.stderr)
        return 1
    if not args.quiet:
        print(f"wrote {Path(args.out) / 'model.pt'} and {Path(args.out) / 'learned.json'}")
    return 0

"""The ``diffcontact`` command line."""

from __future__ import annotations

import argparse
import sys

from diffcontact import __version__


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="diffcontact",
        description="Learn and simulate colliding physical systems with differentiable contact models.",
    )
    parser.add_argument("--version", action="version", version=f"diffcontact {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    demo = sub.add_parser("demo", help="run the solver demonstration (a ball hitting a wall)")
    demo.set_defaults(func=_cmd_demo)
    return parser


def _cmd_demo(args: argparse.Namespace) -> int:
    from diffcontact.demo import run_demo

    return run_demo()


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 0
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())

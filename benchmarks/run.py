"""The benchmarks' one entry point: prints timing tables.

    python benchmarks/run.py                 # every suite, quick settings
    python benchmarks/run.py solver [...]    # friction-cone QP vs cvxpylayers (solver.py)
    python benchmarks/run.py simulate [...]  # ground-truth simulation (simulate.py)
    python benchmarks/run.py simulate --compare mujoco  # BP5 against mujoco.rollout
    python benchmarks/run.py train [...]     # seconds per training step per task (train.py)
    python benchmarks/run.py control [...]   # one planning iteration, 1 and 64 starts (control.py)
    python benchmarks/run.py backends [...]  # the solver's torch vs Warp backends (backends.py)
    python benchmarks/run.py contact_models [...]  # one impulse: CM vs CMr vs Coulomb
    python benchmarks/run.py threads [...]   # 1 vs all threads vs auto, idle and loaded
    python benchmarks/run.py fastops [...]  # sums over a short last dim (fastops.py)
    python benchmarks/run.py launches [...]  # torch ops, CUDA launches and syncs per step
    python benchmarks/run.py chain [...]     # what sets a fused launch's time (chain.py)
    python benchmarks/run.py profile_step [...]  # where the read-free step's time goes
    python benchmarks/run.py rollout_growth [...]  # time along a rollout, selected vs padded

Each suite takes its own options (``python benchmarks/run.py SUITE --help``); see
benchmarks/README.md for what is measured.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

SUITES = (
    "solver",
    "simulate",
    "train",
    "control",
    "backends",
    "contact_models",
    "threads",
    "fastops",
    "launches",
    "kernels",
    "chain",
    "profile_step",
    "rollout_growth",
)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0
    if argv and argv[0] in SUITES:
        module = __import__(argv[0])
        return module.main(argv[1:])
    if argv:
        print(f"unknown suite {argv[0]!r}; choose from {', '.join(SUITES)}", file=sys.stderr)
        return 2
    status = 0
    for suite in SUITES:
        status |= __import__(suite).main(["--quick"])
        print()
    return status


if __name__ == "__main__":
    raise SystemExit(main())

"""How CMr's mass-ratio error depends on the (unidentifiable) absolute mass scale.

    python experiments/cmr_mass_scale.py runs/repro/data/BP5-e --scales 0.1 0.3 1

For each scale ``s`` it builds a CMr-CD-CLNN model of the dataset's task with
every mass at ``s`` times its true value, the true ``mu`` and ``e_P`` and a
zero potential, then fits only the mass *ratios* (Adam on the per-body log
masses with their common mode projected out, so the scale stays at ``s``) to
the training chunks, and prints the ratios it ends at and their largest
relative error. CM's loss does not depend on ``s``; CMr's does, because its
regulariser ``eps I`` is added to ``A = J_C M^-1 J_C^T``, which is in units
of inverse mass: what regularises is ``eps * mass``. docs/training.md ("CMr
and the mass scale") quotes this script's output.

Only for tasks without a true potential (BP5-e, BP5): with gravity or springs
the potential's scale is tied to the masses' and a zero potential is wrong.
"""

from __future__ import annotations

import argparse
import sys
import time

import torch

from diffcontact.cli_args import one_line, positive_float, positive_int
from diffcontact.learning.models.physical import LearnedModel
from diffcontact.learning.training.module import rollout_loss
from diffcontact.learning.training.options import TrainingInputError
from diffcontact.learning.training.run import read_training_data
from diffcontact.systems import System, load_config


def fit_ratios(
    system: System,
    chunks: torch.Tensor,
    scale: float,
    *,
    model: str = "CMr-CD-CLNN",
    eps: float = 0.01,
    iters: int = 100,
    lr: float = 3e-3,
) -> tuple[list[float], float]:
    """``(learned mass ratios m_i / m_1, final loss)`` at a fixed mass scale."""
    m = LearnedModel(system.config, model=model, eps=eps, hidden=(4,)).double()
    m.potential = None
    mass = system.mass.double()
    if m.heterogeneous:
        m.set_parameters(mass=scale * mass, mu=system.mu, cor=system.cor)
    else:
        m.set_parameters(mass=scale * mass, mu=system.mu[0], cor=system.cor[0])
    for p in m.parameters():
        p.requires_grad_(False)
    m.log_mass_rel.requires_grad_(True)
    opt = torch.optim.Adam([m.log_mass_rel], lr=lr)
    loss = torch.zeros(())
    for _ in range(iters):
        opt.zero_grad()
        loss = rollout_loss(m, chunks)
        loss.backward()
        m.log_mass_rel.grad -= m.log_mass_rel.grad.mean()  # keep the common scale fixed
        opt.step()
    mass = m.mass().detach()
    return (mass / mass[0]).tolist(), float(loss.detach())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data_dir", help="a dataset folder (diffcontact generate --out)")
    parser.add_argument("--scales", type=positive_float, nargs="+", default=[0.1, 0.3, 1.0])
    parser.add_argument("--model", default="CMr-CD-CLNN", choices=["CMr-CD-CLNN", "CMr-CD-CHNN"])
    parser.add_argument("--eps", type=positive_float, default=0.01)
    parser.add_argument("--chunks", type=positive_int, default=400, help="training chunks used")
    parser.add_argument("--iters", type=positive_int, default=100, help="Adam iterations per scale")
    args = parser.parse_args(argv)
    try:
        meta, train, _ = read_training_data(args.data_dir)
    except TrainingInputError as err:
        parser.error(f"data_dir: {one_line(err)}")
    system = System(load_config(meta["config"]))
    if float(system.gravity.abs().max()) != 0.0 or system.stiffness is not None:
        parser.error(f"{system.name} has a true potential; use a BP5-e or BP5 dataset")
    chunks = train[: args.chunks]
    truth = (system.mass / system.mass[0]).tolist()
    print(f"{system.name}: {args.model}, eps {args.eps}, {len(chunks)} chunks, "
          f"{args.iters} iterations per scale")  # fmt: skip
    print("| mass scale (x truth) | m1 | learned ratios m_i/m_1 | max rel. error | loss |")
    print("|---|---|---|---|---|")
    for s in args.scales:
        t0 = time.perf_counter()
        ratios, loss = fit_ratios(
            system, chunks, s, model=args.model, eps=args.eps, iters=args.iters
        )
        err = max(abs(r / t - 1) for r, t in zip(ratios[1:], truth[1:], strict=True))
        print(
            f"| {s:g} | {s * float(system.mass[0]):.3g} | "
            f"{', '.join(f'{r:.4f}' for r in ratios[1:])} | {100 * err:.3f} % | {loss:.2e} |"
            f"  ({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

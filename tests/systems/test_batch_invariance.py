"""A state's trajectory does not depend on the other states of its batch.

The contact problems of a step are padded to the batch's largest contact count, and a
non-unique compression impulse (two walls on one body) feeds Poisson's bound of the
restitution phase, so a padding-dependent solver path would change the physics. The
solver's iterations ignore padded contacts (interior_point_solve's ``active``) and its
polish does not move along null directions of ``A`` (before that, the corner case below
differed by 6.6e-5). What remains is rounding: LAPACK factorises a padded matrix with
another blocking than the unpadded one (``torch.linalg.cholesky`` / ``lu_factor`` of a
matrix with a decoupled identity block appended are not bitwise equal to those of the
matrix alone), so trajectories are compared to 1e-12, not bitwise.
"""

from __future__ import annotations

import pytest
import torch

import diffcontact as dc

TOL = 1e-12


def _corner_states(system):
    """BP5 states pushed into contact on the first step: body 3 into the corner of walls
    x = 1 and y = 1 (two contacts on one point mass: a non-unique compression impulse),
    and a companion with more contacts (so the first is padded when batched with it)."""
    z = torch.zeros(2, 2, 5, 2, dtype=torch.float64)
    z[:, 0] = torch.tensor([[0.1, 0.1], [0.5, 0.15], [0.2, 0.75], [0.845, 0.845], [0.45, 0.45]])
    z[0, 1, 3] = torch.tensor([1.3, 0.9])
    z[1, 0, 4] = torch.tensor([0.19, 0.19])  # body 4 (r 0.18) near the corner (0, 0)
    z[1, 0, 0] = torch.tensor([0.75, 0.06])  # body 0 (r 0.05) near the floor
    z[1, 1, 4] = torch.tensor([-1.1, -0.8])
    z[1, 1, 0] = torch.tensor([0.2, -1.5])
    z[1, 1, 3] = torch.tensor([1.0, 1.2])
    assert (system.gaps(z[:, 0]) > 0).all()
    return z


def test_corner_state_alone_and_padded():
    system = dc.load_system("BP5")
    z0 = _corner_states(system)
    both = system.simulate(z0, 6)
    alone = system.simulate(z0[:1], 6)
    res = system.resolve_contacts(system.integrate(z0))
    assert res.active.sum(-1).tolist() == [2, 4]  # the first state is padded with 2
    torch.testing.assert_close(both[:1], alone, rtol=0, atol=TOL)


@pytest.mark.parametrize(("task", "seed"), [("BP5", 0), ("BD5", 1)])
def test_trajectories_alone_and_inside_random_batches(task, seed):
    system = dc.load_system(task)
    steps = 8
    pool = system.sample_initial_conditions(96, seed=seed)
    full = system.simulate(pool, steps)
    hit = (system.gaps(full[:, 1:, 0]) < 0).any(-1).any(-1).nonzero().flatten()
    assert hit.numel() >= 8
    gen = torch.Generator().manual_seed(seed)
    for i in hit[:3].tolist():
        alone = system.simulate(pool[i : i + 1], steps)
        torch.testing.assert_close(full[i : i + 1], alone, rtol=0, atol=TOL)
        for size in (5, 23):
            others = torch.randperm(pool.shape[0], generator=gen)[:size]
            others = others[others != i]
            where = int(torch.randint(0, others.numel() + 1, (1,), generator=gen))
            rows = torch.cat([others[:where], torch.tensor([i]), others[where:]])
            batch = system.simulate(pool[rows], steps)
            torch.testing.assert_close(batch[where : where + 1], alone, rtol=0, atol=TOL)


def test_rope_projection_alone_and_inside_a_batch():
    """The rope's position projection stops each state at its own convergence: the
    iterations went on for every state while any state of the batch had a limit left, so
    a state alone and inside a batch differed by up to 1.7e-9 after 60 steps."""
    system = dc.load_system("Rope")
    z0 = system.sample_initial_conditions(24, seed=3)
    full = system.simulate(z0, 60)
    for i in (1, 2, 7):
        alone = system.simulate(z0[i : i + 1], 60)
        torch.testing.assert_close(full[i : i + 1], alone, rtol=0, atol=TOL)

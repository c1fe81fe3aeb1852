"""Results do not change under refactoring: rollouts and training-step gradients.

``tests/data/reference_values.pt`` was written by ``tests/make_reference_values.py``
with the code before issue 10 (contact models and learned models as registered
components; the rope rollouts were rewritten for issue 11, with the restitution warm
start and then with the rope's position projection, see that script's history); this
compares the current code against it. Tolerance 1e-12 (relative to each tensor's
scale): equal bitwise on the machine that wrote the file, and this leaves room for
other BLAS builds' rounding. The training steps' gradients allow 1e-10: the gradient of
the common mass scale is the residual of a near cancellation (it vanishes for an exact
scale invariance), and writing the network's ``grad V`` out by hand
(``PotentialMLP.gradient``, the same formula in another order) moved its rounding by
1.0e-12 of its size; a change of the physics moves it by orders of magnitude more.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
import make_reference_values as ref

REFERENCE = torch.load(ref.OUT, weights_only=True)


def _close(actual: torch.Tensor, expected: torch.Tensor, what: str, tol: float = 1e-12) -> None:
    scale = float(expected.abs().max()) if expected.numel() else 1.0
    torch.testing.assert_close(
        actual.detach(),
        expected,
        rtol=0,
        atol=tol * max(scale, 1e-300),
        msg=lambda m: f"{what}: {m}",
    )


@pytest.mark.parametrize("task", list(ref.ROLLOUTS))
def test_rollout_unchanged(task):
    from diffcontact import load_system

    n, steps = ref.ROLLOUTS[task]
    system = load_system(task)
    traj = system.simulate(system.sample_initial_conditions(n, seed=1), steps)
    _close(traj, REFERENCE["rollouts"][task], task)


@pytest.mark.parametrize("key", sorted(REFERENCE["steps"]))
def test_training_step_unchanged(key):
    task, model_name = key.split("/")
    actual = ref.reference_training_step(task, model_name)
    expected = REFERENCE["steps"][key]
    assert sorted(actual) == sorted(expected)
    for name, value in expected.items():
        _close(actual[name], value, f"{key} {name}", tol=1e-10)

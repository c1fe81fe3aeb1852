"""Every task simulated on CUDA equals the same simulation on the CPU (skipped without a
CUDA device): the geometry, the projection, the impulse and the solver backends all keep
their tensors on the inputs' device."""

import pytest
import torch

import diffcontact as dc

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
]

# (task, scenes, steps): enough steps for every task to reach its contacts or limits
CASES = [
    ("BP5", 8, 60),
    ("BD5", 8, 60),
    ("CP3", 4, 60),
    ("Gyro", 4, 60),
    ("Rope", 4, 10),
    ("Rope-D400", 2, 4),
]


@pytest.mark.parametrize(("task", "n", "steps"), CASES, ids=[c[0] for c in CASES])
@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_simulation_on_cuda_equals_cpu(task, n, steps, backend, monkeypatch):
    if backend == "warp":
        pytest.importorskip("warp")
    monkeypatch.setenv("DIFFCONTACT_SOLVER", backend)
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(n, seed=3)
    cpu = system.simulate(z0, steps=steps)
    gpu = system.simulate(z0.cuda(), steps=steps)
    assert gpu.device.type == "cuda" and gpu.dtype == torch.float64
    # the same float64 arithmetic in another order: differences at rounding, which the
    # contacts (a chaotic map for BP5 and CP3) may grow over the steps
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-6, atol=1e-7)


def test_gradients_on_cuda_equal_cpu():
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(4, seed=5)
    grads = []
    for device in ("cpu", "cuda"):
        z = z0.to(device).clone().requires_grad_(True)
        system.simulate(z, steps=40)[:, -1, 0].sum().backward()
        grads.append(z.grad.cpu())
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-6, atol=1e-7)

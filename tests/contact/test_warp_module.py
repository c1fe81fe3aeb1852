"""The Warp kernels' module is compiled once per float type (skipped without Warp)."""

import pytest
import torch

pytest.importorskip("warp")

from diffcontact.contact import fused


def test_every_kernel_is_registered_together():
    """A kernel left out of ``fused.KERNELS`` would register its overload at its first
    launch, changing the module after it was compiled, and compile all of it again (a
    CPU compile takes seconds, a CUDA one minutes)."""
    wp, kernels = fused._load()
    defined = {name for name, obj in vars(kernels).items() if isinstance(obj, wp.Kernel)}
    assert defined == set(fused.KERNELS)
    for dtype in (torch.float32, torch.float64):
        overloads = fused._overloads(dtype)
        assert set(overloads) == defined
        assert fused._kernel("fused_backward", dtype) is overloads["fused_backward"]

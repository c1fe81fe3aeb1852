"""diffcontact.testing: count_host_reads counts each way a value reaches the host once;
check_gradients judges inputs a function does not depend on."""

import pytest
import torch

from diffcontact.testing import assert_gradients_close, check_gradients, count_host_reads


def test_count_host_reads_counts_each_read_once():
    t = torch.arange(6.0)

    def reads() -> None:
        t.sum().item()  # 1
        bool((t > 2).any())  # 2
        (t > 2).nonzero()  # 3
        t.tolist()  # 4
        t.numpy()  # 5

    assert count_host_reads(reads) == 5
    assert count_host_reads(lambda: (t * 2).sum()) == 0  # no read: nothing counted
    assert count_host_reads(reads, "cuda") == 0  # reads of CPU tensors are not CUDA's
    assert t.tolist() == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]  # the methods are put back
    assert torch.Tensor.tolist is torch._C.TensorBase.tolist


def test_check_gradients_with_an_input_the_function_ignores():
    """A zero gradient for it (autograd's "does not require grad" error before), which
    finite differences confirm; a wrong gradient is still caught."""
    a, b = torch.randn(3, dtype=torch.float64), torch.randn(2, dtype=torch.float64)
    results = assert_gradients_close(lambda x, y: 2 * x, [a, b])
    assert (
        float(results[1].autograd.abs().max())
        == 0
        == float(results[1].finite_difference.abs().max())
    )
    with pytest.raises(AssertionError, match="input 1"):
        assert_gradients_close(lambda x, y: 2 * x + (y.detach() ** 2).sum(), [a, b])
    assert check_gradients(lambda x, y: (2 * x).detach(), [a, b])[0].rel_error > 0.5  # missed


def test_a_check_that_would_check_nothing_is_an_error():
    """Complex inputs only: the default wrt was empty and the check passed vacuously."""
    x = torch.randn(3, dtype=torch.complex128)
    with pytest.raises(ValueError, match="no real floating-point input"):
        assert_gradients_close(lambda a: a.abs(), [x])
    with pytest.raises(ValueError, match="out of range"):
        assert_gradients_close(lambda a: a, [torch.ones(2, dtype=torch.float64)], wrt=[3])
    with pytest.raises(ValueError, match="not torch tensors"):
        assert_gradients_close(lambda a: a, [[1.0]])

"""diffcontact.testing.count_host_reads counts each way a value reaches the host once."""

import torch

from diffcontact.testing import count_host_reads


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

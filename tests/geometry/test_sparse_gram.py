"""``J J^T`` of sparse Jacobian rows by the Warp kernel (``sparse_gram``) against the dense
rows' product (``dense_gram``), and the position projection that uses it."""

import pytest
import torch

import diffcontact as dc
from diffcontact.geometry.base import SparseJacobian, _cat_rows
from diffcontact.geometry.sparse_gram import dense_gram, sparse_gram

pytest.importorskip("warp")

F64 = torch.float64


def _random_rows(n, R, m, dim, P, dtype=F64, seed=0):
    """Rows with repeated points inside a row and zero entries at any point (not the row's
    own: the kernel must not rely on compact rows for its result)."""
    gen = torch.Generator().manual_seed(seed)
    points = torch.randint(0, P, (n, R, m), generator=gen)
    points[:, ::3, 1] = points[:, ::3, 0]  # a point twice in a row: its entries add up
    values = torch.randn(n, R, m, dim, generator=gen, dtype=dtype)
    values[:, 1::4, -1] = 0.0  # unused entries
    return points, values


@pytest.mark.parametrize(("dtype", "tol"), [(torch.float64, 1e-13), (torch.float32, 2e-5)])
@pytest.mark.parametrize("dim", [2, 3])
def test_sparse_gram_equals_the_dense_rows_product(dtype, tol, dim):
    points, values = _random_rows(6, 9, 3, dim, 7, dtype)
    got = sparse_gram(points, values)
    want = dense_gram(points, values, 7)
    assert got.dtype == dtype and got.shape == (6, 9, 9)
    torch.testing.assert_close(got, want, rtol=tol, atol=tol)
    assert torch.equal(got, got.mT)  # exactly symmetric
    assert float(want.abs().max()) > 1.0  # not all zero


def test_sparse_gram_gradient_matches_finite_differences_and_the_dense_one():
    points, values = _random_rows(3, 5, 3, 2, 4)
    values.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v: sparse_gram(points, v), (values,))
    W = torch.randn(3, 5, 5, dtype=F64, generator=torch.Generator().manual_seed(1))
    (got,) = torch.autograd.grad((sparse_gram(points, values) * W).sum(), values)
    (want,) = torch.autograd.grad((dense_gram(points, values, 4) * W).sum(), values)
    torch.testing.assert_close(got, want, rtol=1e-13, atol=1e-13)


def test_sparse_gram_of_a_ropes_rows_and_of_no_rows():
    system = dc.load_system("Rope-D100")
    x = system.sample_initial_conditions(4, seed=1)[:, 0]
    _, jac = system.geometry.gaps_and_rows_all(x)
    points = jac.points.expand(4, *jac.points.shape[-2:])
    values = jac.values[:, :, 0]  # (n, K, m, dim)
    torch.testing.assert_close(
        sparse_gram(points, values), dense_gram(points, values, x.shape[-2]), rtol=1e-13, atol=1e-13
    )
    for n, R in ((0, 4), (3, 0)):
        assert sparse_gram(points[:n, :R], values[:n, :R]).shape == (n, R, R)


def test_padded_entries_stay_on_their_rows_points():
    """Rows of parts with fewer entries are padded at their own last point (zero values), so
    that a row's point range is the points it touches (the kernel skips the pairs of rows
    whose ranges do not overlap)."""
    short = SparseJacobian(torch.tensor([[4, 5], [7, 8]]), torch.ones(2, 1, 2, 2, dtype=F64))
    long_ = SparseJacobian(torch.tensor([[0, 1, 2]]), torch.ones(1, 1, 3, 2, dtype=F64))
    both = _cat_rows([short, long_])
    assert both.points.tolist() == [[4, 5, 5], [7, 8, 8], [0, 1, 2]]
    assert both.values[:2, :, 2].abs().sum() == 0


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_sparse_gram_on_cuda_equals_the_cpu():
    points, values = _random_rows(8, 12, 3, 2, 9)
    W = torch.randn(8, 12, 12, dtype=F64)
    out = []
    for device in ("cpu", "cuda"):
        v = values.to(device).requires_grad_(True)
        A = sparse_gram(points.to(device), v)
        (grad,) = torch.autograd.grad((A * W.to(device)).sum(), v)
        out.append((A.cpu(), grad.cpu()))
    for cpu, cuda in zip(*out, strict=True):
        torch.testing.assert_close(cuda, cpu, rtol=1e-12, atol=1e-12)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("read_free", [False, True])
def test_the_projection_with_the_sparse_gram_on_cuda_equals_the_cpu(read_free, monkeypatch):
    """What ``--sparse-gram-cuda`` switches on: the projection on CUDA with ``sparse_gram``
    (reading, and read-free as in a captured step) gives the CPU's positions."""
    from diffcontact.geometry import sparse_gram as module
    from diffcontact.systems import projection
    from diffcontact.systems.projection import ReadFree, project_positions

    monkeypatch.setattr(module, "DEVICES", {"cpu", "cuda"})
    monkeypatch.setattr(projection, "MIN_DENSE_SIZE", 0)  # the kernel at this small size
    monkeypatch.delenv("DIFFCONTACT_SOLVER", raising=False)
    system = dc.load_system("Rope-D100")
    z0 = system.sample_initial_conditions(8, seed=3)
    traj = system.simulate(z0, 10, position_projection=0, on_tunnelling="ignore")
    x = traj[:, -1, 0]
    M_inv = system.inverse_mass_matrix()
    out = []
    for device in ("cpu", "cuda"):
        rf = None
        if read_free:
            needed = torch.zeros((), dtype=torch.long, device=device)
            rf = ReadFree(64, needed, system._point_masses, system._two_sided)
        geometry = system.geometry.to(device)
        out.append(project_positions(x.to(device), geometry, M_inv.to(device), 10, read_free=rf))
    assert float((out[0] - x).abs().max()) > 1e-4  # it moved
    torch.testing.assert_close(out[1].cpu(), out[0], rtol=1e-9, atol=1e-11)

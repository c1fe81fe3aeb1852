"""``diffcontact.fastops``: the fast sums equal torch's sums, values and gradients."""

import pytest
import torch

from diffcontact.fastops import dot_last, sum_last


@pytest.mark.parametrize("shape", [(5,), (7, 2), (1024, 10, 2), (3, 4, 3), (6, 9), (4, 0)])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_sum_last_equals_torch_sum(shape, dtype):
    x = torch.randn(*shape, dtype=dtype, generator=torch.Generator().manual_seed(0))
    expected = x.sum(-1)
    got = sum_last(x)
    assert got.shape == expected.shape and got.dtype == dtype
    # two summation orders differ by at most (n - 1) eps sum |x_i| each (a relative bound
    # fails where the sum cancels: it did, unseeded, on one draw of (3, 4, 3))
    bound = 2 * shape[-1] * torch.finfo(dtype).eps * x.abs().sum(-1)
    assert bool(((got - expected).abs() <= bound).all())
    if shape[-1] == 2:  # one addition: bitwise the same
        assert torch.equal(got, expected)


@pytest.mark.parametrize("n", [3, 3000])  # below and above the size that switches backward
def test_dot_last_gradients(n):
    a = torch.randn(n, 2, dtype=torch.float64, requires_grad=True)
    b = torch.randn(n, 2, dtype=torch.float64, requires_grad=True)
    w = torch.randn(n, dtype=torch.float64)
    (dot_last(a, b) * w).sum().backward()
    torch.testing.assert_close(a.grad, w[:, None] * b.detach())
    torch.testing.assert_close(b.grad, w[:, None] * a.detach())
    if n == 3:
        assert torch.autograd.gradcheck(lambda u, v: dot_last(u, v), (a, b))


def test_integer_and_bool_fall_back_to_sum():
    x = torch.arange(12).reshape(6, 2)
    assert torch.equal(sum_last(x), x.sum(-1))
    m = torch.tensor([[True, False], [True, True]])
    assert torch.equal(sum_last(m), m.sum(-1))


def test_sum_last_in_inference_mode_then_autograd():
    """The cached vector of ones made under inference mode still works with autograd."""
    from diffcontact import fastops

    fastops._ones.cache_clear()
    with torch.inference_mode():
        sum_last(torch.randn(5000, 2))
    x = torch.randn(5000, 2, requires_grad=True)
    sum_last(x).sum().backward()
    assert torch.equal(x.grad, torch.ones_like(x))


@pytest.mark.parametrize("batch", [(3,), (200, 15), (7, 5, 40)])
def test_left_matmul_equals_matmul_values_and_gradients(batch):
    """Both paths (one product over the batch, or broadcast @) equal G @ X."""
    from diffcontact.fastops import left_matmul

    gen = torch.Generator().manual_seed(0)
    G = torch.randn(4, 6, generator=gen, dtype=torch.float64, requires_grad=True)
    X = torch.randn(*batch, 6, 2, generator=gen, dtype=torch.float64, requires_grad=True)
    W = torch.randn(*batch, 4, 2, generator=gen, dtype=torch.float64)
    got = left_matmul(G, X)
    want = G @ X
    torch.testing.assert_close(got, want, rtol=1e-14, atol=1e-14)
    g_got = torch.autograd.grad((got * W).sum(), (G, X))
    g_want = torch.autograd.grad((want * W).sum(), (G, X))
    for a, b in zip(g_got, g_want, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-13, atol=1e-13)
    batched = G.detach().expand(*batch, 4, 6)  # a batched G takes the plain product
    torch.testing.assert_close(left_matmul(batched, X.detach()), want.detach())


def test_shared_returns_the_broadcast_matrix_only():
    from diffcontact.fastops import shared

    M = torch.randn(4, 4, dtype=torch.float64)
    assert shared(M.expand(7, 4, 4)).shape == (4, 4) and torch.equal(shared(M.expand(7, 4, 4)), M)
    assert shared(M.expand(2, 3, 4, 4)).shape == (4, 4)
    B = torch.randn(7, 4, 4, dtype=torch.float64)
    assert shared(B) is B and shared(M) is M
    J = torch.randn(7, 6, 4, dtype=torch.float64)
    torch.testing.assert_close(J @ shared(M.expand(7, 4, 4)), J @ M.expand(7, 4, 4))


def test_times_matrix_scales_by_a_large_diagonal_and_multiplies_otherwise(monkeypatch):
    """``X @ M``: by ``M``'s diagonal where ``M`` is one large diagonal matrix without a
    gradient (spied: no product), the product otherwise; the same values, and with a
    gradient to ``M`` its full gradient (off-diagonal entries included)."""
    from diffcontact import fastops

    g = torch.Generator().manual_seed(0)
    X = torch.randn(5, 3, 80, generator=g, dtype=torch.float64)
    diagonal = torch.diag(torch.rand(80, generator=g, dtype=torch.float64) + 0.5)
    dense = diagonal + 0.01 * torch.randn(80, 80, generator=g, dtype=torch.float64)
    small = torch.diag(torch.rand(8, generator=g, dtype=torch.float64))
    products = []
    matmul = torch.Tensor.__matmul__
    monkeypatch.setattr(torch.Tensor, "__matmul__", lambda a, b: products.append(1) or matmul(a, b))
    for M, X_, multiplies in ((diagonal, X, False), (dense, X, True), (small, X[..., :8], True)):
        products.clear()
        got = fastops.times_matrix(X_, M.expand(5, *M.shape))
        assert bool(products) == multiplies
        assert torch.equal(got, matmul(X_, M))  # (exact: the product adds zeros)
    M = diagonal.clone().requires_grad_(True)
    fastops.times_matrix(X, M.expand(5, 80, 80)).square().sum().backward()
    M_ref = diagonal.clone().requires_grad_(True)
    matmul(X, M_ref).square().sum().backward()
    torch.testing.assert_close(M.grad, M_ref.grad, rtol=1e-13, atol=1e-13)
    assert float((M.grad - torch.diag(M.grad.diagonal())).abs().max()) > 0  # off-diagonal


def _spd_batch(n: int, size: int, k: int, device: str = "cpu"):
    g = torch.Generator().manual_seed(n + size)
    R = torch.randn(n, size, size, generator=g, dtype=torch.float64)
    A = R @ R.mT + 0.1 * torch.eye(size, dtype=torch.float64)
    B = torch.randn(n, size, k, generator=g, dtype=torch.float64)
    return A.to(device), B.to(device)


def test_spd_solve_solves_and_marks_indefinite_matrices_nan():
    from diffcontact.fastops import spd_solve

    A, B = _spd_batch(16, 5, 3)
    torch.testing.assert_close(spd_solve(A, B), torch.linalg.solve(A, B), rtol=1e-10, atol=1e-12)
    A[3] = -A[3]  # not positive definite: NaN there, no error, the others unchanged
    X = spd_solve(A, B)
    assert X[3].isnan().all() and torch.isfinite(X[torch.arange(16) != 3]).all()
    # broadcasting one matrix over a batch of right-hand sides
    torch.testing.assert_close(spd_solve(A[0], B), torch.linalg.solve(A[0], B))


def test_spd_solve_gradients_match_finite_differences():
    from diffcontact.fastops import spd_solve

    A, B = _spd_batch(3, 4, 2)
    A.requires_grad_(True)
    B.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: spd_solve(0.5 * (a + a.mT), b), (A, B))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cholesky_solve_on_cuda_equals_lapack():
    from diffcontact.fastops import cholesky_solve

    A, B = _spd_batch(64, 6, 2)
    L = torch.linalg.cholesky(A)
    X = cholesky_solve(B.cuda(), L.cuda())  # two triangular solves there
    torch.testing.assert_close(X.cpu(), torch.cholesky_solve(B, L), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_written_out_spd_solve_equals_lapack_and_marks_indefinite_matrices_nan(n, monkeypatch):
    """Small systems in large batches take the written-out factorisation on the CPU: the
    same solutions and the same NaN for a matrix that is not positive definite."""
    from diffcontact import fastops

    written_out = []
    original = fastops._unrolled_spd_solve
    monkeypatch.setattr(
        fastops, "_unrolled_spd_solve", lambda A, B: written_out.append(1) or original(A, B)
    )
    A, B = _spd_batch(2 * fastops._UNROLL_BATCH, n, 2)  # without a gradient: twice as many
    A[5] = -A[5]
    A[7, 0, 0] = 0.0  # a zero pivot
    L, info = torch.linalg.cholesky_ex(A)
    expected = torch.where((info > 0)[:, None, None], torch.nan, torch.cholesky_solve(B, L))
    X = fastops.spd_solve(A, B)
    torch.testing.assert_close(X, expected, rtol=1e-12, atol=1e-12, equal_nan=True)
    assert X[5].isnan().all() and X[7].isnan().all()
    # batch dimensions broadcast as in the LAPACK path
    A2, B2 = _spd_batch(4, n, 1)
    Bb = B2.expand(2 * fastops._UNROLL_BATCH // 4, 4, n, 1)
    torch.testing.assert_close(fastops.spd_solve(A2, Bb), torch.linalg.solve(A2, Bb))
    assert len(written_out) == 2
    # with a gradient from half as many; fewer go to LAPACK
    fastops.spd_solve(A[: fastops._UNROLL_BATCH].requires_grad_(), B[: fastops._UNROLL_BATCH])
    fastops.spd_solve(A[: fastops._UNROLL_BATCH], B[: fastops._UNROLL_BATCH])
    assert len(written_out) == 3


def test_written_out_spd_solve_gradients_match_finite_differences_and_lapack():
    from diffcontact.fastops import _unrolled_spd_solve

    A, B = _spd_batch(3, 3, 2)
    A.requires_grad_(True)
    B.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: _unrolled_spd_solve(0.5 * (a + a.mT), b), (A, B))
    # the same gradients as the LAPACK path (cholesky_ex + cholesky_solve), so a batch
    # crossing the size threshold does not change them
    W = torch.randn(3, 3, 2, dtype=torch.float64)
    mine = torch.autograd.grad((_unrolled_spd_solve(A, B) * W).sum(), (A, B))
    lapack = torch.cholesky_solve(B, torch.linalg.cholesky_ex(A)[0])
    theirs = torch.autograd.grad((lapack * W).sum(), (A, B))
    for got, want in zip(mine, theirs, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    # second derivatives (Hessian-vector products through a rollout)
    assert torch.autograd.gradgradcheck(
        lambda a, b: _unrolled_spd_solve(0.5 * (a + a.mT), b), (A, B)
    )


def test_lu_factor_ex_of_a_batch_of_large_matrices_on_several_threads():
    """torch 2.13's CPU LU (oneMKL) returned wrong factors for batches of matrices of about
    150 rows or more on several threads (pivots of 0); ``fastops.lu_factor_ex`` factorises
    those on one thread and puts the thread count back."""
    from diffcontact.fastops import lu_factor_ex

    gen = torch.Generator().manual_seed(0)
    A = torch.randn(3, 193, 193, dtype=torch.float64, generator=gen)
    B = torch.randn(3, 193, 2, dtype=torch.float64, generator=gen)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        LU, piv, info = lu_factor_ex(A)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert int(piv.min()) >= 1 and not bool(info.any())
    X = torch.linalg.lu_solve(LU, piv, B)
    torch.testing.assert_close(A @ X, B, rtol=0, atol=1e-9)

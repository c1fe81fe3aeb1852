"""cvxpylayers baselines for the benchmark, parametrised like the paper's Listing S.1.

The compression-phase problem of Appendix F::

    minimise_f  0.5 ||A_d f||^2 + sum(f * v)
    subject to  ||f_t,i|| <= mu_i f_n,i  and  f_n,i >= 0     for every contact i

with parameters A_d (C, C) (A = A_d^T A_d), v (C, 1) and mu (K, 1); f is a (C, 1) variable,
as in the listing. Two ways of using it:

* :func:`reference_style` builds a new cvxpy problem and a new CvxpyLayer on every call and
  solves one state at a time, as the paper's code does (Listings S.1-S.3);
* :func:`build_layer` builds the layer once per contact count; the benchmark then calls it
  on a whole batch of parameters.
"""

from __future__ import annotations

import cvxpy as cp
import torch
from cvxpylayers.torch import CvxpyLayer


def build_layer(K: int, d: int, solver_args: dict) -> CvxpyLayer:
    """The paper's compression-phase CvxpyLayer for K contacts of dimension d (Listing S.1)."""
    C = K * d
    f = cp.Variable((C, 1))
    A_d_p = cp.Parameter((C, C))
    v_p = cp.Parameter((C, 1))
    mu_p = cp.Parameter((K, 1))
    objective = cp.Minimize(0.5 * cp.sum_squares(A_d_p @ f) + cp.sum(cp.multiply(f, v_p)))
    constraints = [
        cp.SOC(cp.multiply(mu_p[i], f[i * d]), f[i * d + 1 : i * d + d]) for i in range(K)
    ] + [f[i * d] >= 0 for i in range(K)]
    problem = cp.Problem(objective, constraints)
    return CvxpyLayer(
        problem, parameters=[A_d_p, v_p, mu_p], variables=[f], solver_args=solver_args
    )


def factor(A: torch.Tensor) -> torch.Tensor:
    """A_d with A = A_d^T A_d: the upper Cholesky factor (Listing S.3 without the
    regularisation, since the benchmark's A are positive definite). A: (..., C, C)."""
    return torch.linalg.cholesky(A).mT


def reference_style(
    A: torch.Tensor, b: torch.Tensor, mu: torch.Tensor, d: int, solver_args: dict
) -> torch.Tensor:
    """One state: build the problem and the layer, then solve. A (C, C), b (C,), mu (K,).

    Returns f (C,), differentiable wrt A, b and mu.
    """
    K = mu.shape[-1]
    layer = build_layer(K, d, solver_args)
    (f,) = layer(factor(A), b[:, None], mu[:, None])
    return f[:, 0]


def prebuilt_batched(
    layer: CvxpyLayer, A: torch.Tensor, b: torch.Tensor, mu: torch.Tensor
) -> torch.Tensor:
    """A prebuilt layer on a batch. A (B, C, C), b (B, C), mu (B, K) -> f (B, C)."""
    (f,) = layer(factor(A), b[..., None], mu[..., None])
    return f[..., 0]

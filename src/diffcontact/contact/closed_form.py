"""Starting points for the friction-cone QP that often need no interior point.

:func:`diffcontact.contact.cone_qp.solve_cone_qp` polishes these guesses with its
natural-map Newton steps and keeps a problem's result when the residual reaches the
tolerance; the others go through the interior point as before. Every guess is a
function of one problem alone, so a state's impulse does not depend on its batch.

- :func:`separating_guess`: ``f = 0`` is a minimiser when there is no lower bound and
  every ``b_k`` lies in the dual cone (``mu_k ||b_t,k|| <= b_n,k``: every contact
  separates).
- :func:`single_contact_minimiser`: the exact minimiser of a problem with one active
  contact of dimension d = 1 or 2 whose 2 x 2 block of ``A`` is positive definite
  (a ball on a wall, a pendulum bob on the floor, a disk on the ground).
- A caller's warm start (``solve_cone_qp(warm_start=...)``; the restitution phase
  passes ``e_P`` times the compression impulse).
"""

from __future__ import annotations

import torch
from torch import Tensor


def separating_guess(b: Tensor, mu: Tensor, lower: Tensor, active: Tensor, d: int) -> Tensor:
    """Problems for which ``f = 0`` is a minimiser, (B,) bool.

    Args:
        b: (B, K*d) linear term (inactive contacts arbitrary).
        mu: (B, K) friction coefficients.
        lower: (B, K) lower bounds (0 on inactive contacts).
        active: (B, K) bool.
        d: contact dimension.
    """
    bk = b.reshape(*mu.shape, d)
    if d == 1:
        separating = bk[..., 0] >= 0
    else:
        separating = mu * torch.linalg.vector_norm(bk[..., 1:], dim=-1) <= bk[..., 0]
    return (separating | ~active).all(-1) & (lower == 0).all(-1)


def _objective(f: Tensor, A: Tensor, b: Tensor) -> Tensor:
    """``0.5 f^T A f + b^T f`` for f (B, n, d), A (B, d, d), b (B, d) -> (B, n)."""
    Af = torch.einsum("bij,bnj->bni", A, f)
    return (0.5 * (f * Af) + b[:, None, :] * f).sum(-1)


def single_contact_minimiser(
    A: Tensor, b: Tensor, mu: Tensor, lower: Tensor, active: Tensor, d: int
) -> tuple[Tensor, Tensor]:
    """Closed-form minimiser of the problems with exactly one active contact.

    For ``d = 2`` the feasible set ``{f_n >= l, |f_t| <= mu f_n}`` is the union of its
    interior and three boundary pieces: the two rays ``t (1, +-mu)``, ``t >= l``, and
    the segment ``f_n = l``, ``|f_t| <= mu l``. The minimiser of a strictly convex
    quadratic is the unconstrained one when that is feasible, and otherwise the best
    of the three pieces' own minimisers (each a clamped 1D minimiser), so the
    candidate with the lowest objective is the minimiser. ``d = 1`` is
    ``max(l, -b / a)``. Only problems whose block is positive definite (relative
    determinant above ``1e-8``: the minimiser is unique) are claimed; the Newton
    polish then removes the rounding left by comparing objectives.

    Args:
        A: (B, K*d, K*d) symmetric PSD.
        b: (B, K*d).
        mu: (B, K) >= 0.
        lower: (B, K) >= 0.
        active: (B, K) bool.
        d: contact dimension (other values than 1 and 2 claim no problem).

    Returns:
        f: (B, K*d) the minimiser where claimed (zeros elsewhere).
        claimed: (B,) bool.
    """
    B, C = b.shape
    f = torch.zeros_like(b)
    one = active.sum(-1) == 1
    if d not in (1, 2):
        return f, torch.zeros_like(one)
    k = active.to(torch.int64).argmax(-1)  # (B,) the active contact where there is one
    idx = (k[:, None] * d + torch.arange(d, device=b.device)).view(B, d)  # (B, d)
    Ak = A.gather(1, idx[:, :, None].expand(B, d, C)).gather(2, idx[:, None, :].expand(B, d, d))
    bk = b.gather(1, idx)
    mu_k = mu.gather(1, k[:, None]).squeeze(-1)
    l_k = lower.gather(1, k[:, None]).squeeze(-1)
    a_nn = Ak[:, 0, 0]
    tiny = torch.finfo(b.dtype).tiny
    if d == 1:
        ok = one & (a_nn > tiny)
        fk = torch.maximum(l_k, -bk[:, 0] / torch.where(ok, a_nn, 1)).unsqueeze(-1)
    else:
        a_nt, a_tt = Ak[:, 0, 1], Ak[:, 1, 1]
        det = a_nn * a_tt - a_nt * a_nt
        ok = one & (a_nn > tiny) & (a_tt > tiny) & (det > 1e-8 * a_nn * a_tt)
        safe_det = torch.where(ok, det, 1)
        safe_tt = torch.where(ok, a_tt, 1)
        # unconstrained minimiser -A^-1 b, used where feasible
        free = torch.stack(
            [-(a_tt * bk[:, 0] - a_nt * bk[:, 1]), -(a_nn * bk[:, 1] - a_nt * bk[:, 0])], -1
        ) / safe_det.unsqueeze(-1)
        # the two rays t (1, +-mu), t >= l
        signs = torch.tensor([1.0, -1.0], dtype=b.dtype, device=b.device)
        r = torch.stack(
            [torch.ones(B, 2, dtype=b.dtype, device=b.device), mu_k[:, None] * signs], -1
        )
        rAr = torch.einsum("bni,bij,bnj->bn", r, Ak, r)
        t = -(r * bk[:, None, :]).sum(-1) / torch.where(ok[:, None], rAr, 1)
        rays = torch.maximum(t, l_k[:, None]).unsqueeze(-1) * r  # (B, 2, 2)
        # the segment f_n = l, |f_t| <= mu l
        cap = mu_k * l_k
        ft = (-(bk[:, 1] + a_nt * l_k) / safe_tt).clamp(-cap, cap)
        segment = torch.stack([l_k, ft], -1)
        cands = torch.cat([rays, segment.unsqueeze(1), free.unsqueeze(1)], 1)  # (B, 4, 2)
        q = _objective(cands, Ak, bk)
        feasible = (free[:, 0] >= l_k) & (free[:, 1].abs() <= mu_k * free[:, 0])
        q[:, 3] = torch.where(feasible, q[:, 3], float("inf"))
        best = q.argmin(-1)
        fk = cands.gather(1, best[:, None, None].expand(B, 1, 2)).squeeze(1)
    fk = torch.where(ok[:, None], fk, 0)
    f = f.scatter(1, idx, fk)
    return f, ok

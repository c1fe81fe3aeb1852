"""Batched primal-dual interior-point method (Mehrotra) for the friction-cone QP.

Solves, for a batch of scaled problems (diag(A) ~ 1, |b| ~ 1),

    minimize  0.5 f^T A f + b^T f
    s.t.      G f + s = h,   s in K

where each contact k contributes the constraint block
``s_k = (f_n - l_k, mu_k f_n, f_t)``: one non-negative orthant entry (the lower
bound) and, for d > 1, one second-order cone ``Q^d`` ``{(s0, s1): ||s1|| <= s0}``
(the friction cone, scaled by mu). Dual variables ``z`` live in the same cones.

Each iteration uses Nesterov-Todd scaling ``W`` (diagonal on the orthant,
``eta (2 w w^T - J)`` on each cone), reduces the Newton system to
``(A + G^T W^-2 G) df = rhs`` — ``G^T W^-2 G`` is block diagonal with one d x d
block per contact, and the sum is positive definite even when A is singular —
and solves it twice on one batched Cholesky factorisation: the affine-scaling
predictor, then Mehrotra's corrector with centring ``sigma = (1 - alpha_aff)^3``.
Problems leave the batch as soon as their gap and residuals reach the targets.
The result only needs to identify the active constraints: the natural-map
Newton polish in :mod:`diffcontact.contact.cone_qp` brings it to full accuracy.

An infeasible-start primal-dual method diverges on a problem that is unbounded
below (the dual is infeasible); a primal iterate with ``||f||_inf > blowup`` is
reported as unbounded.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class InteriorPointResult:
    """Per-problem outcome of :func:`interior_point_solve` (batch shape (B,))."""

    f: Tensor  # (B, C)
    solved: Tensor  # (B,) bool: reached the targets
    unbounded: Tensor  # (B,) bool: iterate diverged
    iterations: Tensor  # (B,) int64


def add_block_diag(M: Tensor, blocks: Tensor) -> Tensor:
    """``M + block_diag(blocks)`` without forming the block-diagonal matrix.

    Args:
        M: (B, K*d, K*d).
        blocks: (B, K, d, d).
    """
    B, K, d, _ = blocks.shape
    out = M.clone()
    view = out.view(B, K, d, K, d)
    torch.diagonal(view, dim1=1, dim2=3).add_(blocks.permute(0, 2, 3, 1))
    return out


# --- second-order cone algebra, per block (..., d) ---------------------------------


def _soc_det(x: Tensor) -> Tensor:
    return x[..., 0] ** 2 - (x[..., 1:] ** 2).sum(-1)


def _soc_prod(x: Tensor, y: Tensor) -> Tensor:
    """Jordan product x o y = (x.y, x0 y1 + y0 x1)."""
    return torch.cat(
        [(x * y).sum(-1, keepdim=True), x[..., :1] * y[..., 1:] + y[..., :1] * x[..., 1:]], -1
    )


def _soc_div(x: Tensor, y: Tensor) -> Tensor:
    """Solve x o u = y for u (x in the cone's interior)."""
    u0 = (x[..., 0] * y[..., 0] - (x[..., 1:] * y[..., 1:]).sum(-1)) / _soc_det(x)
    u1 = (y[..., 1:] - x[..., 1:] * u0.unsqueeze(-1)) / x[..., :1]
    return torch.cat([u0.unsqueeze(-1), u1], -1)


def _soc_nt_scaling(s: Tensor, z: Tensor) -> tuple[Tensor, Tensor]:
    """Nesterov-Todd scaling W (symmetric) and its inverse, (..., d, d)."""
    d = s.shape[-1]
    sJs = _soc_det(s).clamp_min(torch.finfo(s.dtype).tiny)
    zJz = _soc_det(z).clamp_min(torch.finfo(s.dtype).tiny)
    sb = s / sJs.sqrt().unsqueeze(-1)
    zb = z / zJz.sqrt().unsqueeze(-1)
    gamma = ((1 + (sb * zb).sum(-1)) / 2).clamp_min(0).sqrt()
    Jzb = torch.cat([zb[..., :1], -zb[..., 1:]], -1)
    wbar = (sb + Jzb) / (2 * gamma).unsqueeze(-1)  # maps zb to sb: (2 w w' - J) zb = sb
    # its Jordan square root v gives the NT scaling: W = eta (2 v v' - J), W z = W^-1 s
    v = wbar.clone()
    v[..., 0] = v[..., 0] + 1
    v = v / (2 * (wbar[..., 0] + 1)).sqrt().unsqueeze(-1)
    eta = (sJs / zJz) ** 0.25
    J = torch.ones(d, dtype=s.dtype, device=s.device)
    J[1:] = -1
    Jmat = torch.diag(J)
    W = eta[..., None, None] * (2 * v.unsqueeze(-1) * v.unsqueeze(-2) - Jmat)
    Jv = v * J
    W_inv = (2 * Jv.unsqueeze(-1) * Jv.unsqueeze(-2) - Jmat) / eta[..., None, None]
    return W, W_inv


def _soc_max_step(x: Tensor, dx: Tensor) -> Tensor:
    """Largest alpha with x + alpha dx in the cone (inf if unlimited), x interior."""
    c = _soc_det(x)
    bq = x[..., 0] * dx[..., 0] - (x[..., 1:] * dx[..., 1:]).sum(-1)
    a = _soc_det(dx)
    disc = bq * bq - a * c
    sq = disc.clamp_min(0).sqrt()
    q = -(bq + torch.where(bq >= 0, sq, -sq))
    # roots of a t^2 + 2 bq t + c: q / a and c / q (c > 0); the smallest positive one
    # is where the line leaves the cone (none if disc < 0). Divisions by zero give
    # +-inf or nan, which the positivity tests below discard.
    r1 = q / a
    r2 = c / q
    inf = torch.full_like(c, float("inf"))
    r1 = torch.where(r1 > 0, r1, inf)
    r2 = torch.where(r2 > 0, r2, inf)
    roots = torch.where(disc < 0, inf, torch.minimum(r1, r2))
    # the cone lies in x0 >= 0: a line through (or, after rounding, next to) the apex
    # has a double root that disc < 0 may hide, and must not jump into the -cone
    return torch.minimum(roots, _orth_max_step(x[..., 0], dx[..., 0]))


def _orth_max_step(x: Tensor, dx: Tensor) -> Tensor:
    ratio = -x / dx
    return torch.where(dx < 0, ratio, float("inf"))


# --- the method -------------------------------------------------------------------


class _Cones:
    """The constraint blocks of a (sub-)batch: G f and G^T z, and h.

    The orthant block is ``f_n - lower >= 0``; the cone block is
    ``(mu f_n + apex, f_t)``, i.e. its apex is shifted down by ``apex`` (used to
    switch off a dummy cone that must never be active).
    """

    def __init__(self, mu: Tensor, lower: Tensor, apex: Tensor, d: int):
        self.mu, self.lower, self.apex, self.d = mu, lower, apex, d

    def G(self, f: Tensor) -> tuple[Tensor, Tensor | None]:
        """G f as (orthant (B,K), cone (B,K,d) or None), f (B,K,d)."""
        gl = -f[..., 0]
        if self.d == 1:
            return gl, None
        gq = -torch.cat([(self.mu * f[..., 0]).unsqueeze(-1), f[..., 1:]], -1)
        return gl, gq

    def GT(self, zl: Tensor, zq: Tensor | None) -> Tensor:
        """G^T z as (B, K, d)."""
        if self.d == 1:
            return -zl.unsqueeze(-1)
        return -torch.cat([(zl + self.mu * zq[..., 0]).unsqueeze(-1), zq[..., 1:]], -1)

    def h(self) -> tuple[Tensor, Tensor | None]:
        hl = -self.lower
        if self.d == 1:
            return hl, None
        hq = torch.zeros(*self.lower.shape, self.d, dtype=hl.dtype, device=hl.device)
        hq[..., 0] = self.apex
        return hl, hq


def _shift_interior(xl: Tensor, xq: Tensor | None, valid: Tensor) -> tuple[Tensor, Tensor | None]:
    """Shift (per problem) into the interior: x + (1 + alpha) e if needed; only the
    ``valid`` (B, K) contacts decide alpha."""
    low = torch.finfo(xl.dtype).min
    alpha = torch.where(valid, -xl, low).amax(-1)
    if xq is not None:
        out = xq[..., 1:].norm(dim=-1) - xq[..., 0]
        alpha = torch.maximum(alpha, torch.where(valid, out, low).amax(-1))
    shift = torch.where(alpha >= 0, 1 + alpha, torch.zeros_like(alpha))
    xl = xl + shift[:, None]
    if xq is not None:
        xq = xq.clone()
        xq[..., 0] = xq[..., 0] + shift[:, None]
    return xl, xq


def interior_point_solve(
    A: Tensor,
    b: Tensor,
    mu: Tensor,
    lower: Tensor,
    d: int,
    *,
    tol: float,
    max_iter: int,
    apex: Tensor | None = None,
    blowup: float = 1e10,
    active: Tensor | None = None,
) -> InteriorPointResult:
    """Run the batched primal-dual method on scaled problems.

    Args:
        A: (B, C, C) symmetric PSD, diag ~ 1.
        b: (B, C), |b| ~ 1.
        mu: (B, K) strictly positive (callers decouple mu = 0 tangents).
        lower: (B, K) bound of the orthant block ``f_n >= lower`` (callers pass a
            negative bound to switch off a constraint the cone already implies).
        d: contact dimension.
        tol: target for the complementarity gap (per cone) and residuals.
        max_iter: iteration cap.
        apex: (B, K) downward shift of each cone's apex (None: no shift).
        active: (B, K) bool, the contacts that take part (None: all). The others are
            held at ``f = 0`` with their slack and dual variables at the cones' identity
            and enter no gap, residual, step length or stopping test, so that a
            problem's iterates do not depend on how far it was padded (the padded
            blocks of ``A`` must be decoupled from the rest).

    Returns:
        An :class:`InteriorPointResult`.
    """
    B, C = b.shape
    K = C // d
    dtype, device = A.dtype, A.device
    valid = torch.ones(B, K, dtype=torch.bool, device=device) if active is None else active
    per_contact = 2 if d > 1 else 1
    n_cones = (valid.sum(-1) * per_contact).clamp_min(1).to(dtype)  # (B,)
    e_q = torch.zeros(d, dtype=dtype, device=device)
    e_q[0] = 1

    def freeze(valid, f, sl, zl, sq, zq):
        """Hold the contacts outside ``valid`` at f = 0, s = z = e."""
        f = torch.where(valid[..., None], f, 0)
        sl, zl = torch.where(valid, sl, 1), torch.where(valid, zl, 1)
        if d > 1:
            sq = torch.where(valid[..., None], sq, e_q)
            zq = torch.where(valid[..., None], zq, e_q)
        return f, sl, zl, sq, zq

    f_all = torch.zeros(B, K, d, dtype=dtype, device=device)
    solved_all = torch.zeros(B, dtype=torch.bool, device=device)
    unbounded_all = torch.zeros(B, dtype=torch.bool, device=device)
    iters_all = torch.full((B,), max_iter, dtype=torch.int64, device=device)
    idx = torch.arange(B, device=device)

    cones = _Cones(mu, lower, torch.zeros_like(lower) if apex is None else apex, d)
    hl, hq = cones.h()

    # initial point: minimise 0.5 f'Af + b'f + 0.5 ||G f - h||^2, z = G f - h, s = -z
    GtG = torch.zeros(B, K, d, d, dtype=dtype, device=device)
    GtG[..., 0, 0] = 1 + (mu * mu if d > 1 else 0)
    if d > 1:
        GtG[..., 1:, 1:] = torch.eye(d - 1, dtype=dtype, device=device)
    rhs = -b + cones.GT(hl, hq).reshape(B, C)
    L = torch.linalg.cholesky(add_block_diag(A, GtG))
    f = torch.cholesky_solve(rhs.unsqueeze(-1), L).reshape(B, K, d)
    gl, gq = cones.G(f)
    zl, zq = gl - hl, (gq - hq if d > 1 else None)
    sl, sq = _shift_interior(-zl, -zq if d > 1 else None, valid)
    zl, zq = _shift_interior(zl, zq, valid)
    f, sl, zl, sq, zq = freeze(valid, f, sl, zl, sq, zq)

    Ab, bb = A, b
    stalled = torch.zeros(B, dtype=torch.bool, device=device)
    plain_only = torch.zeros(B, dtype=torch.bool, device=device)
    prev_res = torch.full((B,), float("inf"), dtype=dtype, device=device)
    prev_size = torch.full((B,), float("inf"), dtype=dtype, device=device)
    for it in range(max_iter):
        gl, gq = cones.G(f)
        rx = (torch.einsum("bij,bj->bi", Ab, f.reshape(-1, C)) + bb).reshape(-1, K, d)
        rx = rx + cones.GT(zl, zq)
        rzl = gl + sl + cones.lower
        rzq = gq + sq - hq if d > 1 else None
        vq = valid[..., None]
        gap = torch.where(valid, sl * zl, 0).sum(-1)
        if d > 1:
            gap = gap + torch.where(valid, (sq * zq).sum(-1), 0).sum(-1)
        res = torch.where(vq, rx, 0).abs().flatten(1).amax(-1)
        res = torch.maximum(res, torch.where(valid, rzl, 0).abs().amax(-1))
        if d > 1:
            res = torch.maximum(res, torch.where(vq, rzq, 0).abs().flatten(1).amax(-1))
        solved = (gap <= tol * n_cones) & (res <= tol)
        diverged = f.abs().flatten(1).amax(-1) > blowup
        # complementarity reached but the residual no longer falls: the scaling has run
        # away (a weakly active cone, its barrier weights ~1/gap) and the Newton systems
        # are too ill-conditioned to make progress; the polish takes over from here
        # (an iterate that keeps growing is heading off to infinity instead: unbounded)
        size = f.abs().flatten(1).amax(-1)
        stuck = (gap <= tol * n_cones) & (res > 0.5 * prev_res) & (size <= 1.5 * prev_size)
        prev_res, prev_size = res, size
        done = solved | diverged | stalled | stuck
        if bool(done.any()):
            ids = idx[done]
            f_all[ids] = f[done]
            solved_all[ids] = solved[done]
            unbounded_all[ids] = diverged[done] & ~solved[done]
            iters_all[ids] = it
            keep = ~done
            idx = idx[keep]
            if idx.numel() == 0:
                break
            f, sl, zl, rx, rzl, gap = f[keep], sl[keep], zl[keep], rx[keep], rzl[keep], gap[keep]
            stalled, plain_only = stalled[keep], plain_only[keep]
            valid, n_cones = valid[keep], n_cones[keep]
            prev_res, prev_size = prev_res[keep], prev_size[keep]
            if d > 1:
                sq, zq, rzq = sq[keep], zq[keep], rzq[keep]
            Ab, bb = Ab[keep], bb[keep]
            cones = _Cones(cones.mu[keep], cones.lower[keep], cones.apex[keep], d)
            hl, hq = cones.h()
        Bn = idx.numel()
        mu_gap = gap / n_cones

        # Nesterov-Todd scaling
        wl = (sl / zl).sqrt()
        lam_l = (sl * zl).sqrt()
        D = torch.zeros(Bn, K, d, d, dtype=dtype, device=device)
        D[..., 0, 0] = 1 / (wl * wl)
        if d > 1:
            W, W_inv = _soc_nt_scaling(sq, zq)
            lam_q = (W @ zq.unsqueeze(-1)).squeeze(-1)
            W_inv2 = W_inv @ W_inv
            S = torch.ones(Bn, K, d, dtype=dtype, device=device)
            S[..., 0] = cones.mu
            D = D + S.unsqueeze(-1) * W_inv2 * S.unsqueeze(-2)
        L, info = torch.linalg.cholesky_ex(add_block_diag(Ab, D))
        if bool((info > 0).any()):
            eye = torch.eye(C, dtype=dtype, device=device)
            jitter = 1e-12 * (1 + D.abs().flatten(1).amax(-1))
            L2, _ = torch.linalg.cholesky_ex(add_block_diag(Ab, D) + jitter[:, None, None] * eye)
            L = torch.where((info > 0)[:, None, None], L2, L)

        def solve(r3l, r3q):
            # u = lambda \ r3 ; H df = -rx + G^T W^-2 (-rz) - G^T W^-1 u
            ul = r3l / lam_l
            vl = (-rzl) / (wl * wl) - ul / wl
            if d > 1:
                uq = _soc_div(lam_q, r3q)
                vq = (W_inv2 @ (-rzq).unsqueeze(-1) - W_inv @ uq.unsqueeze(-1)).squeeze(-1)
            else:
                uq = vq = None
            rhs = -rx + cones.GT(vl, vq)
            df = torch.cholesky_solve(rhs.reshape(Bn, C, 1), L).reshape(Bn, K, d)
            Gl, Gq = cones.G(df)
            # dz = W^-2 (G df + rz) + W^-1 u ; ds = W u - W^2 dz = -(G df + rz), taken in
            # the second form, which does not cancel when W is badly scaled
            dzl = (Gl + rzl) / (wl * wl) + ul / wl
            dsl = -(Gl + rzl)
            if d > 1:
                dzq = (W_inv2 @ (Gq + rzq).unsqueeze(-1) + W_inv @ uq.unsqueeze(-1)).squeeze(-1)
                dsq = -(Gq + rzq)
            else:
                dzq = dsq = None
            return df, dsl, dsq, dzl, dzq

        # primal and dual blocks side by side: one call per cone type
        slz = torch.cat([sl, zl], -1)
        sqz = torch.cat([sq, zq], -2) if d > 1 else None

        valid2 = torch.cat([valid, valid], -1)
        inf = float("inf")

        def max_step(dsl, dsq, dzl, dzq):
            a = _orth_max_step(slz, torch.cat([dsl, dzl], -1))
            a = torch.where(valid2, a, inf).amin(-1)
            if d > 1:
                aq = _soc_max_step(sqz, torch.cat([dsq, dzq], -2))
                a = torch.minimum(a, torch.where(valid2, aq, inf).amin(-1))
            return a

        # predictor
        r3l = -lam_l * lam_l
        r3q = -_soc_prod(lam_q, lam_q) if d > 1 else None
        df, dsl, dsq, dzl, dzq = solve(r3l, r3q)
        alpha = max_step(dsl, dsq, dzl, dzq).clamp(max=1.0)
        sigma = (1 - alpha) ** 3
        # corrector: r3 = -lam o lam + sigma mu e - (W^-1 ds_a) o (W dz_a). Mehrotra's
        # second-order term can make the iteration cycle (seen on rope limits): a problem
        # whose gap grows under it drops the term from then on (``plain_only``). The plain
        # direction is solved for only in an iteration where some problem newly drops it;
        # for those that already have, the term is zeroed, which gives the plain direction.
        r3l = r3l + (sigma * mu_gap)[:, None]
        corr_l = torch.where(plain_only[:, None], 0.0, dsl * dzl)
        if d > 1:
            r3q = r3q.clone()
            r3q[..., 0] = r3q[..., 0] + sigma[:, None] * mu_gap[:, None]
            a_s = (W_inv @ dsq.unsqueeze(-1)).squeeze(-1)
            a_z = (W @ dzq.unsqueeze(-1)).squeeze(-1)
            corr_q = torch.where(plain_only[:, None, None], 0.0, _soc_prod(a_s, a_z))
        mehrotra = solve(r3l - corr_l, r3q - corr_q if d > 1 else None)

        def gap_after(direction):
            _, dsl, dsq, dzl, dzq = direction
            alpha = (0.99 * max_step(dsl, dsq, dzl, dzq)).clamp(max=1.0)
            a = alpha[:, None]
            g = torch.where(valid, (sl + a * dsl) * (zl + a * dzl), 0).sum(-1)
            if d > 1:
                a = a[..., None]
                gq = ((sq + a * dsq) * (zq + a * dzq)).sum(-1)
                g = g + torch.where(valid, gq, 0).sum(-1)
            return g, alpha

        gap_m, alpha = gap_after(mehrotra)
        newly = (gap_m > gap) & ~plain_only
        df, dsl, dsq, dzl, dzq = mehrotra
        if bool(newly.any()):
            plain = solve(r3l, r3q)
            _, alpha_p = gap_after(plain)
            plain_only |= newly
            alpha = torch.where(newly, alpha_p, alpha)
            df, dsl, dsq, dzl, dzq = (
                None if m is None else torch.where(newly.view(-1, *([1] * (m.dim() - 1))), p, m)
                for m, p in zip(mehrotra, plain, strict=True)
            )
        a1 = alpha[:, None]
        f_new = f + a1[..., None] * df
        sl_new, zl_new = sl + a1 * dsl, zl + a1 * dzl
        sq_new = sq + a1[..., None] * dsq if d > 1 else None
        zq_new = zq + a1[..., None] * dzq if d > 1 else None
        f_new, sl_new, zl_new, sq_new, zq_new = freeze(valid, f_new, sl_new, zl_new, sq_new, zq_new)
        ok = torch.isfinite(f_new).flatten(1).all(-1) & torch.isfinite(sl_new * zl_new).all(-1)
        if d > 1:
            ok = ok & torch.isfinite(sq_new * zq_new).flatten(1).all(-1)
            ok = ok & (_soc_det(sq_new) > 0).all(-1) & (_soc_det(zq_new) > 0).all(-1)
        ok = ok & (sl_new > 0).all(-1) & (zl_new > 0).all(-1)
        # a problem whose step breaks down (rounding near the boundary) keeps its last
        # iterate, which the polish can still finish
        stalled |= ~ok
        f = torch.where(ok[:, None, None], f_new, f)
        sl, zl = torch.where(ok[:, None], sl_new, sl), torch.where(ok[:, None], zl_new, zl)
        if d > 1:
            sq = torch.where(ok[:, None, None], sq_new, sq)
            zq = torch.where(ok[:, None, None], zq_new, zq)
    if idx.numel() > 0:  # hit the iteration cap
        f_all[idx] = f
    return InteriorPointResult(f_all.reshape(B, C), solved_all, unbounded_all, iters_all)

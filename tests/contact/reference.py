"""Independent reference for ``diffcontact.contact.solve_cone_qp`` and random test problems.

The reference builds the friction-cone QP afresh with cvxpy and solves it with Clarabel (an
interior-point conic solver) in float64, one problem at a time, sharing no code with the
package under test. For one problem (shapes without batch dims, ``C = K * d``)::

    minimise_f   0.5 f^T A f + b^T f
    subject to   f_n,k >= lower_k                 (lower=None means 0)
                 ||f_t,k|| <= mu_k * f_n,k        (d >= 2; mu_k = 0 is written f_t,k = 0)

where ``f[k*d:(k+1)*d] = (f_n,k, f_t,k)``. Inactive contacts are dropped before the problem is
built, and their entries of the returned ``f`` are zero.

Clarabel alone reaches only about 1e-8 in f on 3-d cones, so :func:`solve_reference` polishes
its answer with Newton's method on the KKT equations of the contact modes Clarabel found and
accepts the result only if every KKT condition holds (then it is a minimiser to rounding
error). The same KKT data certify uniqueness of the minimiser when ``A`` is singular (strict
complementarity plus a nonsingular KKT Jacobian; the argument is in its docstring);
:func:`tilt_spread` is an independent, Clarabel-only check of uniqueness. Generators draw
from a ``numpy.random.Generator``, so every problem is a pure function of its seed.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass

import numpy as np

try:  # the generators work without cvxpy; the solves need it
    import cvxpy as cp
except ImportError:  # pragma: no cover - the tests importorskip cvxpy first
    cp = None

# Clarabel tolerances for the reference: tighter than its defaults (1e-8). Its answer is then
# polished (see solve_reference), so it only has to find the right contact modes.
CLARABEL_TIGHT = {
    "tol_gap_abs": 1e-12,
    "tol_gap_rel": 1e-12,
    "tol_feas": 1e-12,
    "tol_ktratio": 1e-10,
    "max_iter": 400,
}


# --------------------------------------------------------------------------------------------
# problems


@dataclass(frozen=True)
class ConeQP:
    """One friction-cone QP; arrays are float64 numpy, no batch dims.

    A: (C, C) symmetric PSD; b: (C,); mu: (K,); lower: (K,) or None (means 0);
    active: (K,) bool or None (means all active); d: components per contact.
    ``kind`` and ``seed`` only describe where the problem came from.
    """

    A: np.ndarray
    b: np.ndarray
    mu: np.ndarray
    d: int
    lower: np.ndarray | None = None
    active: np.ndarray | None = None
    kind: str = ""
    seed: int = -1

    @property
    def K(self) -> int:
        return self.mu.shape[0]

    @property
    def C(self) -> int:
        return self.b.shape[0]

    def active_mask(self) -> np.ndarray:
        """(K,) bool."""
        return np.ones(self.K, bool) if self.active is None else self.active.astype(bool)

    def active_rows(self) -> np.ndarray:
        """(C,) bool: the entries of f that belong to active contacts."""
        return np.repeat(self.active_mask(), self.d)

    def reduced(self) -> ConeQP:
        """The same problem with the inactive contacts dropped (all remaining are active)."""
        rows = self.active_rows()
        act = self.active_mask()
        return dataclasses.replace(
            self,
            A=self.A[np.ix_(rows, rows)],
            b=self.b[rows],
            mu=self.mu[act],
            lower=None if self.lower is None else self.lower[act],
            active=None,
        )


def stack(problems: list[ConeQP], dtype=None, device=None) -> dict:
    """Batch problems of equal (K, d) into torch tensors for ``solve_cone_qp``.

    Returns dict with A (B, C, C), b (B, C), mu (B, K), lower (B, K) (zeros where a problem
    has none) and active (B, K) bool, plus d.
    """
    import torch

    dtype = torch.float64 if dtype is None else dtype
    K, d = problems[0].K, problems[0].d
    assert all(p.K == K and p.d == d for p in problems), "stack needs equal K and d"

    def t(xs):
        return torch.as_tensor(np.stack(xs), dtype=dtype, device=device)

    return {
        "A": t([p.A for p in problems]),
        "b": t([p.b for p in problems]),
        "mu": t([p.mu for p in problems]),
        "lower": t([np.zeros(K) if p.lower is None else p.lower for p in problems]),
        "active": torch.as_tensor(np.stack([p.active_mask() for p in problems]), device=device),
        "d": d,
    }


# --------------------------------------------------------------------------------------------
# generators


def random_mu(rng: np.random.Generator, K: int, zero_fraction: float = 0.15) -> np.ndarray:
    """(K,) friction coefficients uniform in [0, 1.2], about ``zero_fraction`` exactly 0."""
    mu = rng.uniform(0.0, 1.2, K)
    mu[rng.random(K) < zero_fraction] = 0.0
    return mu


def _random_orthogonal(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, n) Haar-distributed orthogonal matrix."""
    Q, R = np.linalg.qr(rng.standard_normal((n, n)))
    return Q * np.sign(np.diag(R))


def _log_uniform(rng: np.random.Generator, lo: float, hi: float, n: int) -> np.ndarray:
    return np.exp(rng.uniform(np.log(lo), np.log(hi), n))


def random_full_rank_A(rng: np.random.Generator, C: int) -> np.ndarray:
    """(C, C) A = B B^T with B = Q diag(s), Q random orthogonal, s log-uniform in [0.3, 3].

    Full rank with condition number at most 100 and eigenvalues of order one.
    """
    B = _random_orthogonal(rng, C) * _log_uniform(rng, 0.3, 3.0, C)
    A = B @ B.T
    return 0.5 * (A + A.T)


def random_mhat_inv(rng: np.random.Generator, n: int, E: int) -> np.ndarray:
    """(n, n) Mhat_inv of rank n - E, built as in (S.12) and Appendix E.

    M^-1 = L L^T with L = Q diag(s) (s log-uniform in [0.5, 2], so masses within a factor
    16); J_E (E, n) random; Mhat_inv = M^-1 - M^-1 J_E^T (J_E M^-1 J_E^T)^-1 J_E M^-1,
    which equals L (I - P) L^T with P = L^T J_E^T (J_E L L^T J_E^T)^-1 J_E L a projector of
    rank E (it removes E directions).
    """
    L = _random_orthogonal(rng, n) * _log_uniform(rng, 0.5, 2.0, n)
    Minv = L @ L.T
    if E == 0:
        return Minv
    JE = rng.standard_normal((E, n))
    G = Minv @ JE.T
    Mhat = Minv - G @ np.linalg.solve(JE @ G, G.T)
    return 0.5 * (Mhat + Mhat.T)


def random_deficient_A(
    rng: np.random.Generator, C: int, rank: int, E: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Physically built singular A = J Mhat_inv J^T of the given rank (< C).

    J (C, n) random with singular values log-uniform in [0.5, 2] (n = rank + E <= C) or a
    Gaussian J / sqrt(n) (n > C); Mhat_inv from :func:`random_mhat_inv` with E removed
    directions (E drawn in 1..3 unless given). Returns (A (C, C), J (C, n), Mhat_inv (n, n)).
    """
    E = int(rng.integers(1, 4)) if E is None else E
    n = rank + E
    if n <= C:
        U = _random_orthogonal(rng, C)[:, :n]
        J = (U * _log_uniform(rng, 0.5, 2.0, n)) @ _random_orthogonal(rng, n)
    else:
        J = rng.standard_normal((C, n)) / np.sqrt(n)
    Mhat = random_mhat_inv(rng, n, E)
    A = J @ Mhat @ J.T
    return 0.5 * (A + A.T), J, Mhat


def random_problem(
    seed: int,
    *,
    d: int,
    K: int,
    K_pad: int | None = None,
    a_kind: str = "full",
    b_kind: str = "generic",
    lower_kind: str = "none",
    deficiency: int | None = None,
    pad: str = "physical",
) -> ConeQP:
    """One random problem with K active contacts, padded with inactive ones to K_pad.

    a_kind: "full" (:func:`random_full_rank_A`) or "deficient" (:func:`random_deficient_A`
        with rank(A_active) = C - deficiency; deficiency drawn in 1..3 unless given).
    b_kind: "generic" (b ~ N(0, I)) or "physical" (b = J v with v = Mhat_inv p in the range
        of Mhat_inv, i.e. a contact-space velocity of a constraint-consistent motion; this
        makes b orthogonal to null(A), so the problem is bounded; "deficient" only).
    lower_kind: "none" (lower=None) or "random" (about half the contacts get
        lower = e * s with e ~ U(0, 1), s ~ U(0, 2), the others 0). For restitution-phase
        problems built from a compression solution see :func:`restitution_problem`.
    pad: how the K_pad - K inactive contacts look: "physical" (A and b are built for all
        K_pad contacts, the inactive ones sit at random positions) or "zeros" (inactive
        rows/cols of A, entries of b, mu and lower are 0).
    """
    rng = np.random.default_rng(seed)
    K_pad = K if K_pad is None else K_pad
    assert 1 <= K <= K_pad
    C_act, C = K * d, K_pad * d
    act = np.zeros(K_pad, bool)
    act[rng.choice(K_pad, K, replace=False)] = True
    rows = np.repeat(act, d)

    if a_kind == "full":
        A = random_full_rank_A(rng, C)
        J = Mhat = None
    elif a_kind == "deficient":
        r = int(rng.integers(1, 4)) if deficiency is None else deficiency
        r = min(r, C_act - 1) if C_act > 1 else 0
        if r == 0:  # a single one-component contact cannot be deficient
            raise ValueError("deficient A needs K * d >= 2")
        # rank of the full K_pad block is that of the active block: all contacts share J.
        A_full, J, Mhat = random_deficient_A(rng, C, C_act - r)
        A = A_full
    else:
        raise ValueError(f"unknown a_kind {a_kind!r}")

    if b_kind == "generic":
        b = rng.standard_normal(C)
    elif b_kind == "physical":
        if J is None:
            raise ValueError("b_kind='physical' needs a_kind='deficient'")
        v = Mhat @ rng.standard_normal(Mhat.shape[0])
        b = J @ v
        b = b / max(np.linalg.norm(b) / np.sqrt(C), 1e-12)
    else:
        raise ValueError(f"unknown b_kind {b_kind!r}")

    mu = random_mu(rng, K_pad)
    if lower_kind == "none":
        lower = None
    elif lower_kind == "random":
        lower = rng.uniform(0, 1, K_pad) * rng.uniform(0, 2, K_pad)
        lower[rng.random(K_pad) < 0.5] = 0.0
    else:
        raise ValueError(f"unknown lower_kind {lower_kind!r}")

    if pad == "zeros":
        A = A * np.outer(rows, rows)
        b = b * rows
        mu = mu * act
        if lower is not None:
            lower = lower * act
    elif pad != "physical":
        raise ValueError(f"unknown pad {pad!r}")
    kind = f"d={d} K={K}/{K_pad} A={a_kind} b={b_kind} lower={lower_kind} pad={pad}"
    return ConeQP(A=A, b=b, mu=mu, d=d, lower=lower, active=act, kind=kind, seed=seed)


def restitution_problem(p: ConeQP, f_compression: np.ndarray, e: np.ndarray) -> ConeQP:
    """Restitution-phase problem (7) from a compression-phase problem and its solution.

    b_r = b + A f_c (the contact velocity after compression; zero target velocity) and
    lower = e * f_n,c (Poisson's hypothesis). f_compression: (C,); e: (K,) in [0, 1].
    """
    fn = f_compression.reshape(p.K, p.d)[:, 0]
    return dataclasses.replace(
        p,
        b=p.b + p.A @ f_compression,
        lower=e * np.maximum(fn, 0.0),
        kind=p.kind.replace("lower=none", "lower=restitution"),
    )


# --------------------------------------------------------------------------------------------
# reference solve: Clarabel, then a Newton polish of the KKT system of the mode it found


@dataclass
class Reference:
    """The reference answer for one problem (entries of inactive contacts are zero).

    f: (C,) minimiser: Clarabel's, polished to machine precision when ``polished``;
    f_clarabel: (C,) Clarabel's unpolished answer; status: Clarabel's status (cvxpy
    spelling); objective: 0.5 f'Af + b'f at ``f``; v: (C,) A f + b (contact velocity after
    the impulse); modes: per contact one of "inactive", "apex" (f = 0 with lower = 0),
    "<normal>-<friction>" with normal "free" (f_n > lower) or "bound" (f_n = lower) and
    friction "stick" (||f_t|| < mu f_n), "slide" (||f_t|| = mu f_n) or "none" (d = 1 or
    mu = 0: f_t = 0); lam: (K,) friction-cone multiplier (nonzero only when sliding).

    Certificates (see :func:`solve_reference`): ``polished`` (the KKT system of the mode
    was solved and every primal and dual inequality holds), ``margin`` (the smallest
    strict-complementarity quantity, relative; > 0 means nondegenerate), ``jac_cond``
    (condition number of the KKT Jacobian of the mode) and ``unique`` / ``reason``.
    """

    f: np.ndarray
    f_clarabel: np.ndarray
    status: str
    objective: float = np.nan
    v: np.ndarray | None = None
    modes: list[str] = dataclasses.field(default_factory=list)
    lam: np.ndarray | None = None
    polished: bool = False
    margin: float = -np.inf
    jac_cond: float = np.inf
    unique: bool = False
    reason: str = ""


def _require_cvxpy() -> None:
    if cp is None:
        raise ImportError("the reference solver needs cvxpy with Clarabel")


def _constraints(f, mu: np.ndarray, lower: np.ndarray | None, d: int) -> list:
    """cvxpy constraints of one problem with all contacts active (vectorised over contacts).

    f_n >= lower; for d >= 2 one second-order cone (mu_k f_n,k, f_t,k) per contact with
    mu_k > 0 and f_t,k = 0 where mu_k = 0 (a cone without interior would trouble Clarabel).
    """
    K = mu.shape[0]
    lo = np.zeros(K) if lower is None else lower
    F = cp.reshape(f, (K, d), order="C")  # row k = (f_n, f_t) of contact k
    cons = [F[:, 0] >= lo]
    if d == 1:
        return cons
    pos = np.flatnonzero(mu > 0)
    zero = np.flatnonzero(mu == 0)
    if pos.size:
        cons.append(cp.SOC(cp.multiply(mu[pos], F[pos, 0]), F[pos, 1:], axis=1))
    if zero.size:
        cons.append(F[zero, 1:] == 0)
    return cons


def _solve(prob, settings: dict | None = None) -> str:
    """Solve with Clarabel; on a solver failure retry with looser tolerances.

    Near 1e-12 Clarabel sometimes stops for lack of progress (mostly with 3-d cones); the
    polish below does not need more than a few correct digits, so looser retries are fine.
    """
    tries = [CLARABEL_TIGHT if settings is None else settings]
    if settings is None:
        tries += [
            dict(CLARABEL_TIGHT, tol_gap_abs=t, tol_gap_rel=t, tol_feas=t) for t in (1e-10, 1e-8)
        ]
    for s in tries:
        try:
            with warnings.catch_warnings():  # "may be inaccurate": the status says it
                warnings.simplefilter("ignore", UserWarning)
                prob.solve(solver=cp.CLARABEL, **s)
        except cp.error.SolverError:
            continue
        if prob.status in ("optimal", "optimal_inaccurate"):
            return str(prob.status)
    return str(prob.status) if prob.status is not None else "solver_error"


def clarabel_solve(p: ConeQP, settings: dict | None = None) -> tuple[np.ndarray, str]:
    """Clarabel's minimiser (C,) of ``p`` (zeros at inactive contacts; NaN unless optimal)."""
    _require_cvxpy()
    q = p.reduced()
    f = cp.Variable(q.C)
    obj = 0.5 * cp.quad_form(f, cp.psd_wrap(q.A)) + q.b @ f
    prob = cp.Problem(cp.Minimize(obj), _constraints(f, q.mu, q.lower, q.d))
    status = _solve(prob, settings)
    out = np.full(p.C, np.nan)
    if status in ("optimal", "optimal_inaccurate"):
        out = np.zeros(p.C)
        out[p.active_rows()] = np.asarray(f.value, dtype=np.float64)
    return out, status


def _classify(q: ConeQP, f: np.ndarray, tol: float) -> list[str]:
    """Mode of every contact of the all-active problem q at the approximate minimiser f."""
    d, lo = q.d, np.zeros(q.K) if q.lower is None else q.lower
    modes = []
    for k in range(q.K):
        fk = f[k * d : (k + 1) * d]
        if lo[k] == 0.0 and np.linalg.norm(fk) <= tol:
            modes.append("apex")
            continue
        normal = "bound" if fk[0] - lo[k] <= tol else "free"
        if d == 1 or q.mu[k] == 0.0:
            friction = "none"
        elif q.mu[k] * fk[0] - np.linalg.norm(fk[1:]) <= tol:
            friction = "slide"
        else:
            friction = "stick"
        modes.append(f"{normal}-{friction}")
    return modes


def _polish(q: ConeQP, f0: np.ndarray, modes: list[str], iters: int = 30):
    """Newton's method on the KKT equations of the given modes (all contacts active).

    For contact k with v = A f + b and u = f_t / ||f_t||, the equations are
      free normal:  v_n - lam_k mu_k = 0;
      stick:        v_t = 0;          slide: v_t + lam_k u = 0  and  ||f_t|| - mu_k f_n = 0;
    with f_k = 0 at "apex", f_n = lower_k at "bound", f_t = 0 at "none". The unknowns are
    the remaining entries of f and lam_k of sliding contacts. Returns (f, lam, J, res)
    with J the Jacobian at the last iterate and res the final residual norm.
    """
    d, K, C = q.d, q.K, q.C
    lo = np.zeros(K) if q.lower is None else q.lower
    f = f0.copy()
    fixed = np.zeros(C, bool)
    lam_idx = {}
    for k, m in enumerate(modes):
        if m == "apex":
            f[k * d : (k + 1) * d] = 0.0
            fixed[k * d : (k + 1) * d] = True
            continue
        if m.startswith("bound"):
            f[k * d] = lo[k]
            fixed[k * d] = True
        if m.endswith("none") and d > 1:
            f[k * d + 1 : (k + 1) * d] = 0.0
            fixed[k * d + 1 : (k + 1) * d] = True
        if m.endswith("slide"):
            lam_idx[k] = len(lam_idx)
    free = np.flatnonzero(~fixed)
    nf, nl = free.size, len(lam_idx)
    lam = np.zeros(K)
    v = q.A @ f + q.b
    for k in lam_idx:  # initial multipliers from v_t = -lam u
        ft = f[k * d + 1 : (k + 1) * d]
        lam[k] = max(-(v[k * d + 1 : (k + 1) * d] @ ft) / np.linalg.norm(ft), 0.0)

    def system(f, lam):
        v = q.A @ f + q.b
        rows, jac = [], []
        for k, m in enumerate(modes):
            if m == "apex":
                continue
            slide = k in lam_idx
            ft = f[k * d + 1 : (k + 1) * d]
            nt = np.linalg.norm(ft) if d > 1 else 0.0
            u = ft / nt if slide else None
            if m.startswith("free"):
                row = np.zeros(nf + nl)
                row[:nf] = q.A[k * d, free]
                if slide:
                    row[nf + lam_idx[k]] = -q.mu[k]
                rows.append(v[k * d] - lam[k] * q.mu[k])
                jac.append(row)
            if m.endswith("stick") or slide:
                for j in range(1, d):
                    i = k * d + j
                    row = np.zeros(nf + nl)
                    row[:nf] = q.A[i, free]
                    r = v[i]
                    if slide:
                        r += lam[k] * u[j - 1]
                        # d(lam u_j)/d f_t = lam (e_j - u_j u) / ||f_t||
                        dudft = lam[k] * ((np.arange(1, d) == j) - u[j - 1] * u) / nt
                        for jj in range(1, d):
                            row[np.searchsorted(free, k * d + jj)] += dudft[jj - 1]
                        row[nf + lam_idx[k]] = u[j - 1]
                    rows.append(r)
                    jac.append(row)
            if slide:
                row = np.zeros(nf + nl)
                if m.startswith("free"):
                    row[np.searchsorted(free, k * d)] = -q.mu[k]
                for jj in range(1, d):
                    row[np.searchsorted(free, k * d + jj)] = u[jj - 1]
                rows.append(nt - q.mu[k] * f[k * d])
                jac.append(row)
        F = np.array(rows)
        J = np.array(jac).reshape(len(rows), nf + nl)
        return F, J

    F, J = system(f, lam)
    best = np.linalg.norm(F)
    for _ in range(iters):  # stops once the residual no longer halves (rounding level)
        if F.size == 0:
            break
        # least squares: the minimum-norm Newton step, which also converges (to a nearby
        # solution) when the minimiser is not unique and J is singular
        dx = np.linalg.lstsq(J, -F, rcond=1e-13)[0]
        f[free] += dx[:nf]
        for k, i in lam_idx.items():
            lam[k] += dx[nf + i]
        F, J = system(f, lam)
        if np.linalg.norm(F) > 0.5 * best:
            break
        best = np.linalg.norm(F)
    res = float(np.linalg.norm(F)) if F.size else 0.0
    return f, lam, J, res


def solve_reference(p: ConeQP, settings: dict | None = None) -> Reference:
    """Solve one problem: Clarabel (float64, inactive contacts dropped), then polish.

    1. Clarabel solves the conic problem to about 1e-10 (quad_form objective, SOC per
       contact; mu = 0 written as f_t = 0). Alone this is not accurate enough for 1e-7
       comparisons with 3-d cones, where Clarabel stalls near 1e-8 in f.
    2. The contact modes are read off Clarabel's f (tolerance 1e-6 relative) and Newton's
       method solves the KKT equations of those modes (:func:`_polish`) to machine
       precision. The result is accepted (``polished``) only if the residual is at rounding
       level, it moved less than 1e-2 relative from Clarabel's answer, and every primal
       inequality (f_n >= lower, ||f_t|| <= mu f_n) and dual inequality (lam >= 0,
       v_n - lam mu >= 0 at a bound, v_n >= mu ||v_t|| at the apex) holds: then it is a KKT
       point, hence a minimiser (the problem is convex), and the problem is bounded.
    3. Uniqueness (``unique``). If A restricted to the active contacts is nonsingular the
       objective is strictly convex. Otherwise we require strict complementarity
       (``margin`` >= 1e-6: every active inequality has a positive multiplier and every
       inactive one positive slack, relative to the problem scale) and a nonsingular
       Jacobian of the mode's KKT equations (``jac_cond`` <= 1e10). Argument: if g != f*
       were another minimiser, h = g - f* satisfies A h = 0 (q is constant on the convex
       optimal set) and, because every optimal point pairs with the same multipliers,
       strict complementarity keeps every active constraint active along [f*, g]: h_k = 0 at
       apex contacts, h_n = 0 at bound contacts, and at sliding contacts h_k is parallel
       to f_k (the only segments on a cone's boundary are along rays). Then (h, 0) is a
       null vector of the Jacobian, a contradiction. :func:`tilt_spread` is an independent
       Clarabel-only check of the same property.
    """
    f_cl, status = clarabel_solve(p, settings)
    ref = Reference(f=f_cl.copy(), f_clarabel=f_cl, status=status)
    act = p.active_mask()
    ref.modes = ["inactive"] * p.K
    if status not in ("optimal", "optimal_inaccurate"):
        ref.reason = f"Clarabel status {status}"
        return ref
    q = p.reduced()
    rows = p.active_rows()
    fq = f_cl[rows]
    scale_f = max(np.linalg.norm(fq), 1.0)
    modes = _classify(q, fq, 1e-6 * scale_f)
    f, lam, J, res = _polish(q, fq, modes)
    v = q.A @ f + q.b
    scale_v = max(np.linalg.norm(q.b), np.linalg.norm(v), 1.0)
    lo = np.zeros(q.K) if q.lower is None else q.lower

    d = q.d
    primal, dual = [], []  # strict-complementarity quantities
    for k, m in enumerate(modes):
        fk, vk = f[k * d : (k + 1) * d], v[k * d : (k + 1) * d]
        if m == "apex":
            cone = d > 1 and q.mu[k] > 0
            dual.append(vk[0] - (q.mu[k] * np.linalg.norm(vk[1:]) if cone else 0.0))
            continue
        if m.startswith("free"):
            primal.append(fk[0] - lo[k])
        else:
            dual.append(vk[0] - lam[k] * q.mu[k])
        if m.endswith("stick"):
            primal.append(q.mu[k] * fk[0] - np.linalg.norm(fk[1:]))
        elif m.endswith("slide"):
            dual.append(lam[k])
    margin = min([x / scale_f for x in primal] + [x / scale_v for x in dual], default=np.inf)
    moved = np.linalg.norm(f - fq) / scale_f
    ok_res = res <= 1e-11 * scale_v
    ref.jac_cond = float(np.linalg.cond(J)) if J.size else 1.0
    ref.margin = float(margin)
    ref.polished = bool(ok_res and moved <= 1e-2 and margin >= -1e-12)
    if not ref.polished:
        ref.reason = f"polish failed (residual {res:.1e}, moved {moved:.1e}, margin {margin:.1e})"
        return ref

    out = np.zeros(p.C)
    out[rows] = f
    vout = np.zeros(p.C)
    vout[rows] = v
    lam_out = np.zeros(p.K)
    lam_out[act] = lam
    modes_out = list(ref.modes)
    for k, m in zip(np.flatnonzero(act), modes, strict=True):
        modes_out[k] = m
    ref.f, ref.v, ref.lam, ref.modes = out, vout, lam_out, modes_out
    ref.objective = float(0.5 * f @ q.A @ f + q.b @ f)

    w = np.linalg.eigvalsh(q.A)
    if w[0] > 1e-9 * w[-1]:
        ref.unique, ref.reason = True, "A (active block) is nonsingular"
    elif margin >= 1e-6 and ref.jac_cond <= 1e10:
        ref.unique = True
        ref.reason = f"strict complementarity {margin:.1e}, KKT Jacobian cond {ref.jac_cond:.1e}"
    else:
        ref.reason = (
            f"singular A and degenerate or singular KKT (margin {margin:.1e}, "
            f"cond {ref.jac_cond:.1e}): minimiser may be non-unique"
        )
    return ref


# --------------------------------------------------------------------------------------------
# independent uniqueness check with Clarabel only


def null_space(A: np.ndarray, rtol: float = 1e-9) -> np.ndarray:
    """(C, r) orthonormal basis of the numerical null space of symmetric PSD A."""
    w, V = np.linalg.eigh(A)
    return V[:, w <= rtol * max(w[-1], 1e-300)]


def tilt_spread(p: ConeQP, tilt: float = 1e-6, n_random: int = 2, seed: int = 0) -> float:
    """Clarabel-only estimate of the diameter of the optimal set (relative to max(||f*||, 1)).

    q(f) = 0.5 f'Af + b'f is constant on the convex optimal set S, so S - f* lies in
    null(A). Tilting the objective by +-eps c'f (b -> b +- eps c) makes Clarabel return,
    as eps -> 0, a minimiser and a maximiser of c'f over S, so
    ||f(+eps c) - f(-eps c)|| is at least the width of S along c up to O(eps). We tilt
    along every basis vector of null(A) and ``n_random`` random unit vectors, with
    eps = tilt * max(||b||, 1), and return the largest spread. A unique, well-conditioned
    minimiser gives a spread of order ``tilt``; a non-unique one a spread of the size of S
    (typically of order one). Unlike bounding the near-optimal set {q <= p* + slack}
    directly, every solve here is an ordinary, well-posed problem for Clarabel.
    """
    _require_cvxpy()
    q = p.reduced()
    U = null_space(q.A)
    rng = np.random.default_rng(seed)
    R = rng.standard_normal((q.C, n_random))
    dirs = np.concatenate([U, R / np.linalg.norm(R, axis=0)], axis=1)
    eps = tilt * max(np.linalg.norm(q.b), 1.0)
    spread, scale = 0.0, 1.0
    for c in dirs.T:
        fp, sp = clarabel_solve(dataclasses.replace(q, b=q.b + eps * c))
        fm, sm = clarabel_solve(dataclasses.replace(q, b=q.b - eps * c))
        if "optimal" not in sp or "optimal" not in sm:
            return np.inf
        scale = max(scale, np.linalg.norm(fp))
        spread = max(spread, float(np.linalg.norm(fp - fm)))
    return spread / scale


def relative_error(f: np.ndarray, f_ref: np.ndarray, tiny: float = 1e-3) -> float:
    """||f - f_ref|| / max(||f_ref||, tiny); problems here have impulses of order one."""
    return float(np.linalg.norm(f - f_ref) / max(np.linalg.norm(f_ref), tiny))

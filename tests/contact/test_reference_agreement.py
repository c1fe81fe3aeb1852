"""``solve_cone_qp`` against an independent solver (cvxpy + Clarabel) and finite differences.

Forward: random problems (d = 2 and 3; full-rank and physically built singular A; no,
random and restitution-style lower bounds; inactive contacts padded in two ways), batched
into one ``solve_cone_qp`` call per group, must match the reference to 1e-7 relative in
float64, with masked entries exactly 0. Singular problems are used only when
:func:`reference.solve_reference` certifies a unique minimiser (see its docstring).

Gradients: autograd of a random linear loss of f with respect to A, b, mu and lower against
central finite differences of ``solve_cone_qp`` itself and of the (polished) reference, and
against cvxpylayers where cvxpylayers agrees with those finite differences, on a handful of
problems that are away from degenerate points (strict complementarity margin >= 1e-3).
"""

from __future__ import annotations

import dataclasses
import functools
import warnings

import numpy as np
import pytest

torch = pytest.importorskip("torch")
cp = pytest.importorskip(
    "cvxpy", reason="the independent reference needs cvxpy (pip install cvxpy)"
)
pytest.importorskip(
    "clarabel", reason="the independent reference needs Clarabel (pip install clarabel)"
)
if "CLARABEL" not in cp.installed_solvers():
    pytest.skip("cvxpy cannot find the Clarabel solver", allow_module_level=True)

from .reference import (  # noqa: E402
    ConeQP,
    random_problem,
    relative_error,
    restitution_problem,
    solve_reference,
    stack,
    tilt_spread,
)

K_PAD = 30  # every forward batch is padded to 30 contacts
N_PER_GROUP = 16
FORWARD_RTOL = 1e-7
GRAD_RTOL = 1e-4
FD_STEP = 1e-5
A_KINDS = ("full", "deficient")
LOWER_KINDS = ("none", "random", "restitution")
GROUPS = [(d, a, lo) for d in (2, 3) for a in A_KINDS for lo in LOWER_KINDS]


def solver():
    from diffcontact.contact import solve_cone_qp

    return solve_cone_qp


def group_seed(d: int, a_kind: str, lower_kind: str) -> int:
    return 100_000 * d + 10_000 * A_KINDS.index(a_kind) + 1_000 * LOWER_KINDS.index(lower_kind)


def accepted(ref) -> bool:
    return ref.polished and ref.unique


@functools.cache
def problem_group(d: int, a_kind: str, lower_kind: str):
    """N_PER_GROUP certified problems (padded to K_PAD) and their references.

    The first problem has one active contact, the second all K_PAD; the others draw K in
    1..30. Singular problems alternate generic and physical b; padding alternates
    'physical' (inactive contacts carry real data) and 'zeros'. Restitution problems take
    lower = e * f_n of the reference compression solution and b + A f_c.
    """
    base = group_seed(d, a_kind, lower_kind)
    problems, refs, tried = [], [], 0
    for i in range(4 * N_PER_GROUP):
        if len(problems) == N_PER_GROUP:
            break
        tried += 1
        seed = base + i
        rng = np.random.default_rng(seed)
        K = 1 if i == 0 else K_PAD if i == 1 else int(rng.integers(1, K_PAD + 1))
        if a_kind == "deficient" and K * d < 2:
            K = 2
        p = random_problem(
            seed,
            d=d,
            K=K,
            K_pad=K_PAD,
            a_kind=a_kind,
            b_kind="physical" if a_kind == "deficient" and i % 2 else "generic",
            lower_kind="random" if lower_kind == "random" else "none",
            pad="zeros" if i % 3 == 2 else "physical",
        )
        if lower_kind == "restitution":
            rc = solve_reference(p)
            if not accepted(rc):
                continue
            p = restitution_problem(p, rc.f, rng.uniform(0.0, 1.0, K_PAD))
        ref = solve_reference(p)
        if accepted(ref):
            problems.append(p)
            refs.append(ref)
    assert len(problems) == N_PER_GROUP, (
        f"only {len(problems)} of {tried} generated problems certified for {d, a_kind, lower_kind}"
    )
    return problems, refs


def run_solver(problems: list[ConeQP], with_lower: bool, with_active: bool = True) -> np.ndarray:
    T = stack(problems)
    f = solver()(
        T["A"],
        T["b"],
        T["mu"],
        T["d"],
        lower=T["lower"] if with_lower else None,
        active=T["active"] if with_active else None,
    )
    assert f.dtype == torch.float64 and f.shape == T["b"].shape
    return f.detach().numpy()


def check_against_references(f: np.ndarray, problems, refs, rtol=FORWARD_RTOL) -> list[str]:
    """Problems where f disagrees with the reference; masked entries must be exactly 0."""
    bad = []
    for fi, p, r in zip(f, problems, refs, strict=True):
        rows = p.active_rows()
        if np.any(fi[~rows] != 0.0):
            bad.append(f"seed {p.seed} [{p.kind}]: inactive entries not exactly 0")
        err = relative_error(fi[rows], r.f[rows])
        if not err <= rtol:
            bad.append(f"seed {p.seed} [{p.kind}]: relative error {err:.2e} ({r.reason})")
    return bad


# --------------------------------------------------------------------------------------------
# the harness itself


def test_reference_flags_non_unique_minimisers():
    """Two copies of the same contact: any split of the impulse is optimal."""
    J = np.array([[1.0, 0.2], [0.1, 1.0]])
    J = np.vstack([J, J])
    p = ConeQP(A=J @ J.T, b=J @ np.array([-1.0, 0.3]), mu=np.array([1.0, 1.0]), d=2)
    ref = solve_reference(p)
    assert ref.polished and not ref.unique
    assert tilt_spread(p) > 1e-2


def test_reference_certificates_agree_with_clarabel_tilting():
    """Singular problems certified unique show no spread when Clarabel's objective is tilted."""
    for d in (2, 3):
        problems, refs = problem_group(d, "deficient", "none")
        for p, r in list(zip(problems, refs, strict=True))[2:4]:
            assert r.unique
            assert tilt_spread(p) < 1e-3, r.reason


def cvxpylayers_layer(K: int, d: int):
    """A CvxpyLayer of the problem with lower bounds, parametrised like the paper's listing.

    Parameters (A_d (C, C) with A = A_d^T A_d, b (C,), mu (K,), lower (K,)); diffcp with
    Clarabel at tight tolerances inside.
    """
    from cvxpylayers.torch import CvxpyLayer

    C = K * d
    f = cp.Variable(C)
    A_d, b, mu, lo = cp.Parameter((C, C)), cp.Parameter(C), cp.Parameter(K), cp.Parameter(K)
    cons = [cp.SOC(mu[k] * f[k * d], f[k * d + 1 : (k + 1) * d]) for k in range(K)]
    cons += [f[k * d] >= lo[k] for k in range(K)]
    prob = cp.Problem(cp.Minimize(0.5 * cp.sum_squares(A_d @ f) + b @ f), cons)
    tight = {"solve_method": "Clarabel", "tol_gap_abs": 1e-11, "tol_gap_rel": 1e-11}
    tight.update(tol_feas=1e-11, max_iter=400)
    return CvxpyLayer(prob, parameters=[A_d, b, mu, lo], variables=[f], solver_args=tight)


def gradient_problem(
    d: int, K: int, seed: int, a_kind: str = "full", K_pad: int | None = None, lower: bool = True
) -> tuple[ConeQP, object]:
    """A problem with K active contacts (K_pad in all) and mu in [0.2, 1] whose reference is
    nondegenerate: strict complementarity margin >= 1e-3 and a well-conditioned KKT
    Jacobian, so f is smooth in every parameter. With ``lower`` every contact gets a bound
    in [0.02, 0.5] (strictly positive, so central differences in lower stay valid; lower = 0
    is a kink for separating contacts); without it lower is None and separating contacts
    sit at the apex of their cone. Some contact must press beyond its bound and some slide,
    so that no gradient is trivially zero."""
    K_pad = K if K_pad is None else K_pad
    for s in range(seed, seed + 200):
        p = random_problem(s, d=d, K=K, K_pad=K_pad, a_kind=a_kind)
        rng = np.random.default_rng(s + 1)
        lo = rng.uniform(0.02, 0.5, K_pad) if lower else None
        p = dataclasses.replace(p, mu=rng.uniform(0.2, 1.0, K_pad), lower=lo)
        if K_pad == K:
            p = dataclasses.replace(p, active=None)
        ref = solve_reference(p)
        modes = "".join(ref.modes)
        varied = "free" in modes and ("slide" in modes or d == 1)
        if accepted(ref) and ref.margin >= 1e-3 and ref.jac_cond <= 1e6 and varied:
            return p, ref
    raise AssertionError(f"no nondegenerate problem found for d={d}, K={K}")


@pytest.mark.filterwarnings("ignore::UserWarning", "ignore::DeprecationWarning")
def test_reference_matches_cvxpylayers_forward():
    """The reference and the paper-style CvxpyLayer solve the same problem."""
    pytest.importorskip("cvxpylayers", reason="cvxpylayers not installed")
    for d, K, seed in ((2, 4, 11), (3, 3, 12)):
        p, ref = gradient_problem(d, K, seed)
        A_d = torch.linalg.cholesky(torch.as_tensor(p.A)).mT
        args = [A_d, torch.as_tensor(p.b), torch.as_tensor(p.mu), torch.as_tensor(p.lower)]
        (f,) = cvxpylayers_layer(K, d)(*args)
        assert relative_error(f.detach().numpy(), ref.f) < 1e-5


# --------------------------------------------------------------------------------------------
# forward agreement


@pytest.mark.parametrize(("d", "a_kind", "lower_kind"), GROUPS)
def test_forward_matches_reference(d, a_kind, lower_kind):
    problems, refs = problem_group(d, a_kind, lower_kind)
    f = run_solver(problems, with_lower=lower_kind != "none")
    bad = check_against_references(f, problems, refs)
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("d", [1, 2, 3])
def test_forward_defaults_and_batch_dims(d):
    """lower=None, active=None, two leading batch dims, frictionless d = 1 included."""
    problems = [random_problem(900 + 10 * d + i, d=d, K=5) for i in range(6)]
    refs = [solve_reference(p) for p in problems]
    assert all(accepted(r) for r in refs)
    T = stack(problems)
    f = solver()(
        T["A"].reshape(2, 3, 5 * d, 5 * d), T["b"].reshape(2, 3, -1), T["mu"].reshape(2, 3, -1), d
    )
    assert f.shape == (2, 3, 5 * d)
    bad = check_against_references(f.reshape(6, -1).detach().numpy(), problems, refs)
    assert not bad, "\n".join(bad)


def test_inactive_contacts_do_not_influence_active_ones():
    """Replacing every inactive entry of A, b, mu and lower leaves f unchanged."""
    problems, refs = problem_group(2, "full", "random")
    rng = np.random.default_rng(7)
    changed = []
    for p in problems:
        rows = p.active_rows()
        A = p.A * np.outer(rows, rows)  # keep the active block, cut the couplings ...
        G = rng.standard_normal((p.C, p.C))
        A = A + (G @ G.T) * np.outer(~rows, ~rows)  # ... and put any PSD block in their place
        A = 0.5 * (A + A.T)
        changed.append(
            dataclasses.replace(
                p,
                A=A,
                b=np.where(rows, p.b, rng.standard_normal(p.C) * 10),
                mu=np.where(p.active_mask(), p.mu, rng.uniform(0, 2, p.K)),
                lower=np.where(p.active_mask(), p.lower, rng.uniform(0, 5, p.K)),
            )
        )
    f0 = run_solver(problems, with_lower=True)
    f1 = run_solver(changed, with_lower=True)
    assert not check_against_references(f1, changed, refs)
    assert np.max(np.abs(f1 - f0)) <= 1e-9 * max(np.max(np.abs(f0)), 1.0)


def test_non_unique_minimisers_reach_the_optimal_value():
    """With duplicated contacts f is not unique, but the optimal value and A f are."""
    problems, refs = [], []
    for i in range(6):
        d = 2 + i % 2
        p = random_problem(500 + i, d=d, K=6, a_kind="deficient", b_kind="physical")
        # contacts 1 and 2 become exact copies of contact 0 (same rows of A, b and mu)
        A, b, mu = p.A.copy(), p.b.copy(), p.mu.copy()
        idx = np.concatenate([np.arange(d)] * 3 + [np.arange(3 * d, 6 * d)])
        A, b, mu = A[np.ix_(idx, idx)], b[idx], mu[[0, 0, 0, 3, 4, 5]]
        problems.append(dataclasses.replace(p, A=A, b=b, mu=mu, active=None))
        refs.append(solve_reference(problems[-1]))
    for d in (2, 3):
        sel = [i for i in range(6) if problems[i].d == d]
        f = run_solver([problems[i] for i in sel], with_lower=False, with_active=False)
        for fi, i in zip(f, sel, strict=True):
            p, r = problems[i], refs[i]
            assert r.polished, r.reason
            obj = 0.5 * fi @ p.A @ fi + p.b @ fi
            F = fi.reshape(p.K, d)
            viol = max(np.max(np.linalg.norm(F[:, 1:], axis=1) - p.mu * F[:, 0]), -F[:, 0].min())
            assert viol <= 1e-9, f"seed {p.seed}: infeasible by {viol:.1e}"
            assert abs(obj - r.objective) <= 1e-9 * max(1.0, abs(r.objective)), f"seed {p.seed}"
            dv = np.linalg.norm(p.A @ (fi - r.f)) / max(np.linalg.norm(p.A @ r.f), 1e-3)
            assert dv <= FORWARD_RTOL, f"seed {p.seed}: A f differs by {dv:.1e}"


# --------------------------------------------------------------------------------------------
# gradients


def symmetric_directions(p: ConeQP, n: int, rng) -> np.ndarray:
    """(n, C, C) unit symmetric directions keeping A + h E PSD for small h.

    Random symmetric E for nonsingular A; E = G S G^T (A = G G^T) for singular A.
    """
    w, V = np.linalg.eigh(p.A)
    singular = w[0] <= 1e-9 * w[-1]
    G = V * np.sqrt(np.clip(w, 0, None))
    out = []
    for _ in range(n):
        S = rng.standard_normal((p.C, p.C))
        S = S + S.T
        E = G @ S @ G.T if singular else S
        out.append(E / np.linalg.norm(E))
    return np.stack(out)


def autograd_gradients(p: ConeQP, w: np.ndarray):
    """Gradients of w . f wrt (A, b, mu, lower) from one solve_cone_qp call (lower: None
    when the problem has no lower bounds)."""
    A, b, mu = (torch.tensor(x, requires_grad=True) for x in (p.A, p.b, p.mu))
    lo = None if p.lower is None else torch.tensor(p.lower, requires_grad=True)
    act = None if p.active is None else torch.as_tensor(p.active)[None]
    f = solver()(
        A[None], b[None], mu[None], p.d, lower=None if lo is None else lo[None], active=act
    )
    (f[0] @ torch.as_tensor(w)).backward()
    return A.grad.numpy(), b.grad.numpy(), mu.grad.numpy(), None if lo is None else lo.grad.numpy()


def perturbations(p: ConeQP, dirs_A: np.ndarray, h: float):
    """Central-difference perturbations: every entry of b, mu and lower (if any), and the
    directions of A. Returns the perturbed problems (+h then -h per coordinate) and the
    number of coordinates per parameter (b, mu, lower, A)."""
    out = []
    names = ("b", "mu") + (() if p.lower is None else ("lower",))
    for name in names:
        x = getattr(p, name)
        for i in range(x.size):
            for s in (h, -h):
                out.append(dataclasses.replace(p, **{name: x + s * np.eye(x.size)[i]}))
    for E in dirs_A:
        for s in (h, -h):
            out.append(dataclasses.replace(p, A=p.A + s * E))
    return out, (p.C, p.K, 0 if p.lower is None else p.K, len(dirs_A))


def fd_from_values(values: np.ndarray, sizes, h: float):
    """Split central differences (2 values per coordinate) into (g_b, g_mu, g_lower, dA)."""
    g = (values[0::2] - values[1::2]) / (2 * h)
    out, i = [], 0
    for n in sizes:
        out.append(g[i : i + n])
        i += n
    return out


def rel(a, b, floor: float = 1e-8) -> float:
    """||a - b|| / max(||b||, floor)."""
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / max(np.linalg.norm(b), floor))


def compare_gradients(grads, fd, dirs_A) -> dict[str, float]:
    """Relative errors per parameter; a parameter whose true gradient is (nearly) zero is
    measured against 1% of the whole gradient's size instead of its own."""
    gA, gb, gmu, glo = grads
    fd_b, fd_mu, fd_lo, fd_A = fd
    ours = {"b": gb, "mu": gmu, "A": np.einsum("ij,nij->n", gA, dirs_A)}
    theirs = {"b": fd_b, "mu": fd_mu, "A": fd_A}
    if glo is not None:
        ours["lower"], theirs["lower"] = glo, fd_lo
    floor = 1e-2 * np.linalg.norm(np.concatenate(list(theirs.values())))
    return {k: rel(ours[k], theirs[k], floor) for k in ours}


GRAD_CASES = [  # d, K, seed, A, lower bounds
    (2, 3, 21, "full", True),
    (2, 6, 22, "full", False),
    (2, 5, 23, "deficient", True),
    (3, 3, 24, "full", True),
    (3, 5, 25, "full", False),
    (3, 4, 26, "deficient", True),
]


@pytest.mark.parametrize(("d", "K", "seed", "a_kind", "lower"), GRAD_CASES)
def test_gradients_match_finite_differences_of_solver(d, K, seed, a_kind, lower):
    """Autograd vs central differences of solve_cone_qp, all perturbations in one batch."""
    # two inactive contacts, which must get zero gradients
    p, _ = gradient_problem(d, K, 1000 * seed, a_kind, K_pad=K + 2, lower=lower)
    rng = np.random.default_rng(seed)
    w = rng.standard_normal(p.C)
    dirs_A = symmetric_directions(p, 6, rng)
    h = FD_STEP
    batch, sizes = perturbations(p, dirs_A, h)
    f = run_solver(batch, with_lower=lower)
    fd = fd_from_values(f @ w, sizes, h)
    errs = compare_gradients(autograd_gradients(p, w), fd, dirs_A)
    assert max(errs.values()) <= GRAD_RTOL, errs


REF_GRAD_CASES = [(2, 4, 31), (3, 3, 32)]


@functools.cache
def reference_gradient_case(d: int, K: int, seed: int):
    """A nondegenerate all-active problem, loss weights w, 3 random directions per parameter
    and the central differences of w . f_reference along them (h = FD_STEP)."""
    p, _ = gradient_problem(d, K, 1000 * seed)
    rng = np.random.default_rng(seed)
    w = rng.standard_normal(p.C)
    n_dir, h = 3, FD_STEP
    dirs = {
        "b": rng.standard_normal((n_dir, p.C)),
        "mu": rng.standard_normal((n_dir, p.K)),
        "lower": rng.standard_normal((n_dir, p.K)),
        "A": symmetric_directions(p, n_dir, rng),
    }

    def ref_value(**kw) -> float:
        r = solve_reference(dataclasses.replace(p, **kw))
        assert r.polished, r.reason
        return float(r.f @ w)

    fd_ref = {
        name: np.array(
            [
                (
                    ref_value(**{name: getattr(p, name) + h * D})
                    - ref_value(**{name: getattr(p, name) - h * D})
                )
                / (2 * h)
                for D in dirs[name]
            ]
        )
        for name in dirs
    }
    return p, w, dirs, fd_ref


def directional(grads, dirs) -> dict[str, np.ndarray]:
    """Directional derivatives of gradients (gA, gb, gmu, glower) along ``dirs``."""
    gA, gb, gmu, glo = grads
    return {
        "b": dirs["b"] @ gb,
        "mu": dirs["mu"] @ gmu,
        "lower": dirs["lower"] @ glo,
        "A": np.einsum("ij,nij->n", gA, dirs["A"]),
    }


@pytest.mark.parametrize(("d", "K", "seed"), REF_GRAD_CASES)
def test_gradients_match_finite_differences_of_reference(d, K, seed):
    """Autograd vs central differences of the independent reference along random directions
    of A, b, mu and lower."""
    p, w, dirs, fd_ref = reference_gradient_case(d, K, seed)
    floor = 1e-2 * np.linalg.norm(np.concatenate(list(fd_ref.values())))
    ours = directional(autograd_gradients(p, w), dirs)
    errs = {k: rel(v, fd_ref[k], floor) for k, v in ours.items()}
    assert max(errs.values()) <= GRAD_RTOL, f"ours vs reference finite differences: {errs}"


@pytest.mark.filterwarnings("ignore::UserWarning", "ignore::DeprecationWarning")
@pytest.mark.parametrize(("d", "K", "seed"), REF_GRAD_CASES)
def test_gradients_match_cvxpylayers(d, K, seed):
    """Autograd vs cvxpylayers (paper parametrisation, A through its Cholesky factor) for
    every parameter where cvxpylayers agrees with the reference's finite differences."""
    pytest.importorskip("cvxpylayers", reason="cvxpylayers not installed")
    p, w, dirs, fd_ref = reference_gradient_case(d, K, seed)
    floor = 1e-2 * np.linalg.norm(np.concatenate(list(fd_ref.values())))
    A, b, mu, lo = (torch.tensor(x, requires_grad=True) for x in (p.A, p.b, p.mu, p.lower))
    (f,) = cvxpylayers_layer(K, d)(torch.linalg.cholesky(A).mT, b, mu, lo)
    (f @ torch.as_tensor(w)).backward()
    theirs = (A.grad.numpy(), b.grad.numpy(), mu.grad.numpy(), lo.grad.numpy())
    errs_cl = {k: rel(v, fd_ref[k], floor) for k, v in directional(theirs, dirs).items()}
    names = ("A", "b", "mu", "lower")
    agree = [n for n in names if errs_cl[n] <= GRAD_RTOL]
    if len(agree) < len(names):
        warnings.warn(
            f"cvxpylayers disagrees with finite differences for {sorted(set(names) - set(agree))}: "
            f"{errs_cl}; not compared there",
            stacklevel=1,
        )
    ours = autograd_gradients(p, w)
    sym = lambda G: 0.5 * (G + G.T)  # noqa: E731 - only the symmetric part of dA is defined
    full = {"A": (sym(ours[0]), sym(theirs[0])), "b": (ours[1], theirs[1])}
    full |= {"mu": (ours[2], theirs[2]), "lower": (ours[3], theirs[3])}
    floor = 1e-2 * np.linalg.norm(np.concatenate([np.ravel(t) for _, t in full.values()]))
    bad = {n: rel(*full[n], floor) for n in agree if rel(*full[n], floor) > GRAD_RTOL}
    assert not bad, f"ours vs cvxpylayers: {bad}"

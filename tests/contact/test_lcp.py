"""The LCP contact model: forward against an independent LCP solution, gradients, CLI."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
import torch

import diffcontact as dc
from diffcontact.contact import (
    LCP,
    LCPError,
    NewtonLCP,
    create_contact_model,
    lcp_impulse,
    solve_lcp,
    two_phase_impulse,
)
from diffcontact.contact.models import ContactParams
from diffcontact.testing import assert_gradients_close

F64 = torch.float64


# ------------------------------------------------------------------ problems
def random_problem(seed, n, K, d, D=6, n_active=None, dtype=F64):
    """``n`` states with ``K`` (padded) contacts in d-dimensional contact space.

    Returns J_C (n, K*d, D) with zero padded rows, Mhat_inv (n, D, D) SPD, v (n, D),
    mu, cor (n, K), active (n, K) (``n_active[i]`` real contacts, first in order, else
    a random mask with at least one), v_C_star (n, K*d) >= 0 in the normal entries.
    """
    g = torch.Generator().manual_seed(seed)
    if n_active is None:
        active = torch.rand(n, K, generator=g) < 0.7
        active[:, 0] = True
    else:
        active = torch.arange(K)[None, :] < torch.as_tensor(n_active)[:, None]
    J = torch.randn(n, K, d, D, generator=g, dtype=F64)
    J = torch.where(active[:, :, None, None], J, 0).reshape(n, K * d, D)
    X = torch.randn(n, D, D, generator=g, dtype=F64)
    Mi = X @ X.transpose(-1, -2) / D + 0.5 * torch.eye(D, dtype=F64)
    v = torch.randn(n, D, generator=g, dtype=F64)
    mu = 0.1 + torch.rand(n, K, generator=g, dtype=F64)
    cor = torch.rand(n, K, generator=g, dtype=F64)
    star = torch.zeros(n, K, d, dtype=F64)
    star[..., 0] = 0.3 * torch.rand(n, K, generator=g, dtype=F64)
    star = torch.where(active[:, :, None], star, 0).reshape(n, K * d)
    return tuple(
        x.to(dtype) if x.is_floating_point() else x for x in (J, Mi, v, mu, cor, active, star)
    )


# ------------------------------------------------------------------ independent reference
def reference_solutions(J, Mi, v, mu, cor, active, d, m, star=None):
    """All solutions of one state's contact LCP by enumerating complementary bases.

    Built from the physics, contact by contact (numpy, loops), not from lcp.py: normal
    impulse p, m friction multipliers beta on the directions d_j, sliding speed lam.
    Returns a list of contact-space impulses f (K*d,) (zero for padded contacts).
    """
    J, Mi, v, mu, cor = (np.asarray(x, dtype=np.float64) for x in (J, Mi, v, mu, cor))
    act = np.asarray(active)
    K = act.shape[0]
    star = np.zeros(K * d) if star is None else np.asarray(star, dtype=np.float64)
    A = J @ Mi @ J.T
    vC = J @ v
    if d == 2:
        dirs = np.array([[1.0], [-1.0]])
    elif d == 3:
        ang = 2 * np.pi * np.arange(m) / m
        dirs = np.stack([np.cos(ang), np.sin(ang)], 1)
    else:
        dirs = np.zeros((0, 0))
    ks = [k for k in range(K) if act[k]]
    nd = dirs.shape[0]
    w = 1 if d == 1 else nd + 2
    n = w * len(ks)
    # f = G z; the velocity relative to the target is A f + vC - s
    G = np.zeros((K * d, n))
    s = np.zeros(K * d)
    for i, k in enumerate(ks):
        G[k * d, i * w] = 1
        for j in range(nd):
            G[k * d + 1 : k * d + d, i * w + 1 + j] = dirs[j]
        vn = vC[k * d]
        s[k * d] = max(-cor[k] * vn if vn < 0 else 0.0, star[k * d])
        s[k * d + 1 : k * d + d] = star[k * d + 1 : k * d + d]
    AG, r = A @ G, vC - s
    M, q = np.zeros((n, n)), np.zeros(n)
    for i, k in enumerate(ks):
        M[i * w], q[i * w] = AG[k * d], r[k * d]  # normal velocity
        for j in range(nd):  # d_j . tangential velocity + lam
            M[i * w + 1 + j] = dirs[j] @ AG[k * d + 1 : k * d + d]
            M[i * w + 1 + j, i * w + w - 1] = 1
            q[i * w + 1 + j] = dirs[j] @ r[k * d + 1 : k * d + d]
        if d > 1:  # mu p - sum beta
            M[i * w + w - 1, i * w] = mu[k]
            M[i * w + w - 1, i * w + 1 : i * w + 1 + nd] = -1
    sols = []
    for S in itertools.product([False, True], repeat=n):
        S = np.array(S, dtype=bool)
        z = np.zeros(n)
        if S.any():
            sub = M[np.ix_(S, S)]
            if abs(np.linalg.det(sub)) < 1e-12:
                continue
            z[S] = np.linalg.solve(sub, -q[S])
        wv = M @ z + q
        if (z >= -1e-9).all() and (wv >= -1e-9).all():
            sols.append(G @ z)
    return sols


@pytest.mark.parametrize(("d", "m", "K"), [(1, 0, 4), (2, 2, 3), (3, 4, 2), (3, 3, 2)])
def test_forward_matches_enumerated_lcp_solutions(d, m, K):
    J, Mi, v, mu, cor, active, star = random_problem(10 + d + m, 4, K, d)
    directions = max(m, 3)
    for v_C_star in (None, star):
        res = lcp_impulse(J, Mi, v, mu, cor, active, d, v_C_star=v_C_star, directions=directions)
        assert torch.equal(res.f_r, torch.zeros_like(res.f_r))
        f = res.f_c.reshape(4, K, d)
        assert torch.equal(f[~active], torch.zeros_like(f[~active]))  # padded: exact zeros
        torch.testing.assert_close(
            res.v_plus, v + ((J @ Mi).transpose(-1, -2) @ res.f_c[..., None])[..., 0]
        )
        n_pushing = 0
        for i in range(4):
            sols = reference_solutions(
                J[i], Mi[i], v[i], mu[i], cor[i], active[i], d, m,
                None if v_C_star is None else v_C_star[i],
            )  # fmt: skip
            assert sols, "the reference found no solution"
            gap = min(float(np.abs(s - res.f_c[i].numpy()).max()) for s in sols)
            assert gap < 1e-9 * max(1.0, float(res.f_c[i].abs().max())), (i, gap)
            n_pushing += bool(res.f_c[i].abs().max() > 0)
        assert n_pushing >= 2  # not all trivial


def test_solve_lcp_matches_enumeration_on_generic_matrices():
    g = torch.Generator().manual_seed(0)
    n = 5
    X = torch.randn(12, n, n, generator=g, dtype=F64)
    M = X @ X.transpose(-1, -2) + 0.1 * torch.eye(n, dtype=F64)  # P-matrices: unique z
    M = M + 0.5 * (X - X.transpose(-1, -2))  # positive definite, not symmetric
    q = torch.randn(12, n, generator=g, dtype=F64)
    z, status = solve_lcp(M, q, return_status=True)
    assert status.all_converged and status.iterations.max() > 1
    for i in range(12):
        Mi, qi = M[i].numpy(), q[i].numpy()
        found = []
        for S in itertools.product([False, True], repeat=n):
            S = np.array(S, dtype=bool)
            zz = np.zeros(n)
            if S.any():
                zz[S] = np.linalg.solve(Mi[np.ix_(S, S)], -qi[S])
            if (zz >= -1e-12).all() and (Mi @ zz + qi >= -1e-12).all():
                found.append(zz)
        assert len(found) == 1
        np.testing.assert_allclose(z[i].numpy(), found[0], atol=1e-12)


# ------------------------------------------------------------------ gradients
def _sym(t):
    return t + t.transpose(-1, -2)


@pytest.mark.parametrize(("d", "K", "seed"), [(1, 3, 0), (2, 3, 1), (2, 3, 2), (3, 2, 3)])
def test_gradients_match_finite_differences(d, K, seed):
    J, Mi, v, mu, cor, active, star = random_problem(seed, 4, K, d)
    rows = active.repeat_interleave(d, -1)[..., None].to(F64)

    def fn(J, Mi, v, mu, cor):
        res = lcp_impulse(J, Mi, v, mu, cor, active, d, v_C_star=star, directions=5)
        return torch.cat([res.v_plus, res.f_c], -1)

    assert int(fn(J, Mi, v, mu, cor)[..., -K * d :].abs().amax(-1).gt(0).sum()) >= 2
    wrt = [0, 1, 2, 3, 4] if d > 1 else [0, 1, 2, 4]
    assert_gradients_close(
        fn, (J, Mi, v, mu, cor), wrt=wrt, directions={0: lambda t: t * rows, 1: _sym}, rtol=1e-5
    )


def _grads(fn, inputs):
    xs = [x.clone().requires_grad_(True) for x in inputs]
    out = fn(*xs)
    w = torch.linspace(-1, 2, out.numel(), dtype=out.dtype).reshape(out.shape)
    return torch.autograd.grad((w * out).sum(), xs, allow_unused=True)


def _point_mass(*normals_and_tangents):
    """J_C of contacts on one 2D point mass: rows (n, t) per contact."""
    rows = []
    for nx, ny in normals_and_tangents:
        rows += [[nx, ny], [-ny, nx]]
    return torch.tensor(rows, dtype=F64)[None]


def test_degenerate_cases_give_finite_one_sided_gradients():
    act2 = torch.tensor([[True, True]])
    Mi = torch.eye(2, dtype=F64)[None] * 2.0
    mu, cor = torch.full((1, 2), 0.3, dtype=F64), torch.full((1, 2), 0.5, dtype=F64)

    def model(d, active, star=None):
        def fn(J, Mi, v, mu, cor):
            return lcp_impulse(J, Mi, v, mu, cor, active, d, v_C_star=star).v_plus

        return fn

    # 1. zero relative velocity: z = 0; the right derivative (contacts separating)
    J = _point_mass((0.0, 1.0), (0.6, 0.8))
    v0 = torch.zeros(1, 2, dtype=F64)
    fn = model(2, act2)
    grads = _grads(fn, (J, Mi, v0, mu, cor))
    assert all(g is None or bool(torch.isfinite(g).all()) for g in grads)
    w = torch.linspace(-1, 2, 2, dtype=F64)[None]
    torch.testing.assert_close(grads[2], w)  # d v+ / d v = I on the separating side
    up = torch.tensor([[0.0, 1.0]], dtype=F64)  # both contacts separate along +y
    h = 1e-6
    fd = ((w * fn(J, Mi, v0 + h * up, mu, cor)).sum() - (w * fn(J, Mi, v0, mu, cor)).sum()) / h
    assert float(fd) == pytest.approx(float((grads[2] * up).sum()), rel=1e-8)

    # 2. a contact exactly at the boundary of complementarity (z = w = 0): contact 1
    # alone stops the mass, after which contact 2 is exactly at rest
    J1 = torch.tensor([[[1.0, 0.0], [0.6, 0.8]]], dtype=F64)
    v1 = torch.tensor([[-1.0, 0.0]], dtype=F64)
    fn1 = model(1, act2)
    out = lcp_impulse(J1, Mi, v1, mu, cor * 0, act2, 1)
    assert out.f_c[0, 1] == 0 and out.f_c[0, 0] > 0
    assert float((J1 @ out.v_plus[..., None])[0, 1, 0]) == pytest.approx(0, abs=1e-15)
    grads = _grads(fn1, (J1, Mi, v1, mu, cor * 0))
    assert all(g is None or bool(torch.isfinite(g).all()) for g in grads)
    # ... and stick/slip exactly at the cone's boundary: |f_t| = mu p, u_t = 0
    J2 = _point_mass((0.0, 1.0))
    v2 = torch.tensor([[0.45, -1.0]], dtype=F64)  # v_t = -0.45: p = 0.75, mu p = 0.225 ...
    out = lcp_impulse(J2, Mi, v2, mu[:, :1], cor[:, :1], act2[:, :1], 2)
    torch.testing.assert_close(out.f_c, torch.tensor([[0.75, 0.225]], dtype=F64))
    torch.testing.assert_close(out.v_plus, torch.tensor([[0.0, 0.5]], dtype=F64))  # ... sticks
    grads = _grads(model(2, act2[:, :1]), (J2, Mi, v2, mu[:, :1], cor[:, :1]))
    assert all(bool(torch.isfinite(g).all()) for g in grads)

    # 3. duplicate contacts (identical rows of J_C, singular A), d = 1, 2 and 3: the motion
    # is that of one contact, gradients are finite and match finite differences
    for d, J_one in (
        (1, torch.tensor([[[0.0, 1.0, 0.0]]], dtype=F64)),
        (2, torch.tensor([[[0.0, 1.0, 0.0], [1.0, 0.0, 0.3]]], dtype=F64)),
        (3, torch.tensor([[[0.0, 1.0, 0.0], [1.0, 0.0, 0.3], [0.0, 0.2, 1.0]]], dtype=F64)),
    ):
        J_dup = torch.cat([J_one, J_one], 1)
        M3 = torch.diag(torch.tensor([2.0, 1.0, 3.0], dtype=F64))[None]
        v3 = torch.tensor([[0.7, -1.0, 0.2]], dtype=F64)
        single = lcp_impulse(J_one, M3, v3, mu[:, :1], cor[:, :1], act2[:, :1], d).v_plus
        fn_dup = model(d, act2)
        torch.testing.assert_close(fn_dup(J_dup, M3, v3, mu, cor), single, rtol=0, atol=1e-12)
        grads = _grads(fn_dup, (J_dup, M3, v3, mu, cor))
        assert all(bool(torch.isfinite(g).all()) for g in grads if g is not None), d
        assert sum(g is None for g in grads) == (d == 1)  # mu: no friction when d = 1

        # perturbations that keep the duplicates identical (otherwise the larger target
        # wins: a kink, v+ depends on max(e_1, e_2))
        def same(t):
            return t[..., :1].expand_as(t)

        def same_rows(t, d=d):
            return torch.cat([t[:, :d], t[:, :d]], 1)

        assert_gradients_close(
            fn_dup, (J_dup, M3, v3, mu, cor), wrt=[0, 1, 2, 3, 4] if d > 1 else [0, 1, 2, 4],
            directions={0: same_rows, 1: _sym, 3: same, 4: same}, rtol=1e-6,
        )  # fmt: skip


def test_gradients_through_a_simulation_are_finite():
    """The paper's LCP baseline gave NaN gradients everywhere (appendix J); here a
    rollout with friction, resting contacts and restitution differentiates."""
    system = dc.load_system("BP5")
    z0 = system.sample_initial_conditions(4, seed=2)
    p = system.parameters()
    mass = p.mass.clone().requires_grad_(True)
    mu = p.mu.clone().requires_grad_(True)
    cor = p.cor.clone().requires_grad_(True)
    z0 = z0.clone().requires_grad_(True)
    traj = system.simulate(z0, 40, params=p.replace(mass=mass, mu=mu, cor=cor), contact_model="LCP")
    traj[:, -1].pow(2).sum().backward()
    for t in (mass, mu, cor, z0):
        assert bool(torch.isfinite(t.grad).all()) and t.grad.abs().max() > 0


# ------------------------------------------------------------------ LCP vs CM
def test_frictionless_point_masses_lcp_and_cm_coincide():
    """BP5-e (frictionless, e = 1): Newton's and Poisson's hypotheses give the same
    impulses (every contact of a collision compresses, and e is common), so the same
    trajectories; with e = 0 and no penetration compensation both are the same LCP."""
    system = dc.load_system("BP5-e")
    z0 = system.sample_initial_conditions(12, seed=3)
    lcp = system.simulate(z0, 100, contact_model="LCP")
    cm = system.simulate(z0, 100, contact_model="CM")
    assert (lcp[:, 1:] - lcp[:, :-1])[:, :, 1].abs().amax() > 0.1  # velocities jumped
    torch.testing.assert_close(lcp, cm, rtol=0, atol=1e-9)
    p = system.parameters().replace(cor=0.0)
    lcp = system.simulate(z0, 60, params=p, contact_model="LCP", penetration_fraction=0)
    cm = system.simulate(z0, 60, params=p, contact_model="CM", penetration_fraction=0)
    torch.testing.assert_close(lcp, cm, rtol=0, atol=1e-9)


def test_one_frictionless_contact_matches_cm_with_penetration_target():
    """One contact: u_n = max(v_n, -e min(v_n, 0), v_n^*) in both models."""
    J, Mi, v, _, cor, _, star = random_problem(7, 20, 1, 2)
    mu = torch.zeros(20, 1, dtype=F64)
    active = torch.ones(20, 1, dtype=torch.bool)
    star[:, 1] = 0
    for v_C_star in (None, star):
        lcp = lcp_impulse(J, Mi, v, mu, cor, active, 2, v_C_star=v_C_star)
        cm = two_phase_impulse(J, Mi, v, mu, cor, active, 2, v_C_star=v_C_star)
        torch.testing.assert_close(lcp.v_plus, cm.v_plus, rtol=0, atol=1e-10)
        torch.testing.assert_close(lcp.f_c, cm.f_c + cm.f_r, rtol=0, atol=1e-10)


# ------------------------------------------------------------------ batching, dtypes, errors
def test_a_state_gets_the_same_impulse_in_any_batch():
    K, d = 4, 2
    n_active = torch.tensor([1, 4, 2, 3, 4, 1, 2, 3])
    J, Mi, v, mu, cor, active, star = random_problem(5, 8, K, d, n_active=n_active)
    full = lcp_impulse(J, Mi, v, mu, cor, active, d, v_C_star=star)
    g = torch.Generator().manual_seed(0)
    for i in range(8):  # alone, with only its own contacts
        k = int(n_active[i])
        alone = lcp_impulse(
            J[i : i + 1, : k * d], Mi[i : i + 1], v[i : i + 1], mu[i : i + 1, :k],
            cor[i : i + 1, :k], active[i : i + 1, :k], d, v_C_star=star[i : i + 1, : k * d],
        )  # fmt: skip
        torch.testing.assert_close(alone.f_c[0], full.f_c[i, : k * d], rtol=0, atol=1e-12)
        torch.testing.assert_close(alone.v_plus[0], full.v_plus[i], rtol=0, atol=1e-12)
    for _ in range(3):  # random subsets, shuffled
        idx = torch.randperm(8, generator=g)[: int(torch.randint(2, 8, (1,), generator=g))]
        part = lcp_impulse(
            J[idx], Mi[idx], v[idx], mu[idx], cor[idx], active[idx], d, v_C_star=star[idx]
        )
        torch.testing.assert_close(part.f_c, full.f_c[idx], rtol=0, atol=1e-12)


def test_leading_batch_dims_float32_and_devices():
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    J, Mi, v, mu, cor, active, star = random_problem(9, 6, 3, 3)
    ref = lcp_impulse(J, Mi, v, mu, cor, active, 3, v_C_star=star)
    for device in devices:
        for dtype in (torch.float32, torch.float64):
            args = [x.to(device=device, dtype=dtype) if x.is_floating_point() else x.to(device)
                    for x in (J, Mi, v, mu, cor, active, star)]  # fmt: skip
            J_, Mi_, v_, mu_, cor_, act_, star_ = (x.reshape(2, 3, *x.shape[1:]) for x in args)
            res = lcp_impulse(J_, Mi_, v_, mu_, cor_, act_, 3, v_C_star=star_)
            assert res.v_plus.shape == (2, 3, 6) and res.f_c.shape == (2, 3, 9)
            assert res.v_plus.dtype == dtype and res.v_plus.device.type == device
            tol = 1e-12 if dtype == F64 else 1e-4
            torch.testing.assert_close(
                res.f_c.reshape(6, 9).cpu().double(), ref.f_c, rtol=tol, atol=tol
            )
        system = dc.load_system("Gyro")
        z0 = system.sample_initial_conditions(2, seed=0).to(device)
        assert torch.isfinite(system.simulate(z0, 30, contact_model="LCP")).all()


def test_registry_options_and_errors():
    assert isinstance(create_contact_model("LCP"), NewtonLCP)
    assert create_contact_model("LCP", directions=16).directions == 16
    assert LCP().directions == 8
    for bad in (2, 0, 4.5, True, "8"):
        with pytest.raises(ValueError, match="directions must be an integer >= 3"):
            LCP(directions=bad)
    with pytest.raises(ValueError, match="max_pivots must be a positive integer"):
        LCP(max_pivots=0)
    with pytest.raises(ValueError, match="tol must be"):
        LCP(tol=-1.0)
    with pytest.raises(ValueError, match="no option 'eps'; it takes: directions, max_pivots, tol"):
        create_contact_model("LCP", eps=0.1)
    J, Mi, v, mu, cor, active, _ = random_problem(0, 2, 2, 2)
    with pytest.raises(ValueError, match="d must be 1, 2 or 3"):
        lcp_impulse(J, Mi, v, mu, cor, active, 4)
    with pytest.raises(ValueError, match=r"lcp_impulse: mu must have shape \(\.\.\., 2\)"):
        lcp_impulse(J, Mi, v, mu[:, :1], cor, active, 2)
    with pytest.raises(ValueError, match="M must have shape"):
        solve_lcp(torch.zeros(2, 3, dtype=F64), torch.zeros(2, 3, dtype=F64))
    with pytest.raises(ValueError, match="NaN"):
        solve_lcp(torch.full((2, 2), math.nan, dtype=F64), torch.zeros(2, dtype=F64))
    # no solution: a mass squeezed between two walls that both push it out
    J2 = torch.tensor([[[1.0, 0.0], [-1.0, 0.0]]], dtype=F64)
    star = torch.tensor([[0.5, 0.5]], dtype=F64)
    both = torch.ones(1, 2, dtype=torch.bool)
    args = (J2, torch.eye(2, dtype=F64)[None], torch.zeros(1, 2, dtype=F64),
            torch.zeros(1, 2, dtype=F64), torch.zeros(1, 2, dtype=F64), both, 1)  # fmt: skip
    with pytest.raises(LCPError, match=r"1 have no solution \(Lemke's method ended on a ray\)$"):
        lcp_impulse(*args, v_C_star=star)  # (not "raise max_pivots": more pivots cannot help)
    _, status = lcp_impulse(*args, v_C_star=star, return_status=True)
    assert bool(status.unbounded[0]) and not bool(status.converged[0])
    with pytest.raises(dc.contact.ConeQPError):  # System.simulate names the states
        lcp_impulse(*args, v_C_star=star)


def test_resolve_is_the_impulse_function():
    J, Mi, v, mu, cor, active, star = random_problem(3, 3, 2, 3)
    res = LCP(directions=6).resolve(J, Mi, v, ContactParams(mu, cor), active, 3, v_C_star=star)
    ref = lcp_impulse(J, Mi, v, mu, cor, active, 3, v_C_star=star, directions=6)
    assert torch.equal(res.f_c, ref.f_c) and torch.equal(res.v_plus, ref.v_plus)
    # more directions: a rounder cone, a different (not worse) answer
    assert not torch.equal(res.f_c, lcp_impulse(J, Mi, v, mu, cor, active, 3, v_C_star=star).f_c)


# ------------------------------------------------------------------ CLI
def test_generate_and_train_with_lcp_through_the_cli(tmp_path, capsys):
    from diffcontact.cli import main

    data, run = tmp_path / "data", tmp_path / "run"
    code = main(
        ["generate", "BP5-e", "--out", str(data), "--n-train", "4", "--n-val", "2",
         "--n-test", "2", "--seed", "1", "--contact-model", "LCP", "--quiet"]
    )  # fmt: skip
    assert code == 0
    meta = json.loads((data / "metadata.json").read_text())
    assert "LCP" in json.dumps(meta)
    code = main(
        ["train", str(data), "--out", str(run), "--model", "LCP-CD-CLNN", "--epochs", "1",
         "--batch-size", "2", "--hidden", "8", "--quiet"]
    )  # fmt: skip
    assert code == 0, capsys.readouterr().err
    learned = json.loads((run / "learned.json").read_text())
    assert learned["finished"] and learned["global_step"] == 2
    assert all(math.isfinite(x) for x in learned["learned"]["cor"] + learned["learned"]["mu"])


@pytest.mark.parametrize("d", [1, 2, 3])
def test_degenerate_batches_solve_and_give_finite_gradients(d):
    """Many duplicate contacts, states at rest, mu = 0, a singular Mhat_inv: all solved,
    every gradient finite."""
    g = torch.Generator().manual_seed(d)
    n, K, D = 48, 4, 6
    J = torch.randn(n, K, d, D, generator=g, dtype=F64)
    J[:, 1] = J[:, 0]  # duplicates
    J[::2, 3] = J[::2, 0]
    J = J.reshape(n, K * d, D)
    X = torch.randn(n, D, D, generator=g, dtype=F64)
    Mi = X @ X.transpose(-1, -2) / D
    Mi[::3, 0, :] = 0  # singular, like a constrained body
    Mi[::3, :, 0] = 0
    v = torch.randn(n, D, generator=g, dtype=F64)
    v[::4] = 0  # at rest
    mu = torch.rand(n, K, generator=g, dtype=F64)
    mu[::5] = 0
    cor = torch.rand(n, K, generator=g, dtype=F64)
    active = torch.rand(n, K, generator=g) < 0.8
    inputs = [x.requires_grad_(True) for x in (J, Mi, v, mu, cor)]
    res, status = lcp_impulse(*inputs, active, d, return_status=True)
    assert status.all_converged
    (res.v_plus.pow(2).sum() + res.f_c.sum()).backward()
    for x in inputs:
        assert x.grad is None or bool(torch.isfinite(x.grad).all())


@pytest.mark.parametrize("mu", [0.5, 0.0])
def test_a_contact_landing_without_slip_is_differentiated_sticking(mu):
    """A ball landing straight down (tangential velocity exactly 0): the friction variables
    never enter Lemke's basis, and the backward pass differentiated the frictionless piece
    (d vx+ / d vx0 = 1), valid on neither side; with friction the contact sticks for any
    small vx0 (0 on both sides, as CM and Coulomb give). Without friction: 1."""
    system = dc.load_system({"type": "bouncing_masses", "masses": [0.3], "radii": [0.1],
                             "walls": [[0, 1, 0]], "gravity": 0.0, "mu": mu, "cor": 0.5,
                             "dt": 0.01, "horizon": 1.0})  # fmt: skip
    z0 = torch.tensor([[[[0.0, 0.0999]], [[0.0, -1.0]]]], dtype=F64)

    def vx_plus(z, model="LCP"):
        out = system.resolve_contacts(z, contact_model=model, penetration_fraction=0.0)
        return out.z[0, 1, 0, 0]

    x = z0.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(vx_plus(x), x)
    h, e = 1e-6, torch.zeros_like(z0)
    e[0, 1, 0, 0] = h
    with torch.no_grad():
        right = (vx_plus(z0 + e) - vx_plus(z0)) / h
        left = (vx_plus(z0) - vx_plus(z0 - e)) / h
    want = 0.0 if mu > 0 else 1.0
    assert float(right) == pytest.approx(want, abs=1e-8)
    assert float(left) == pytest.approx(want, abs=1e-8)
    assert float(grad[0, 1, 0, 0]) == pytest.approx(want, abs=1e-12)
    assert float(torch.autograd.grad(vx_plus(x, "Coulomb"), x)[0][0, 1, 0, 0]) == pytest.approx(
        want, abs=1e-12
    )


def test_a_rolling_disk_s_rollout_gradient_matches_finite_differences():
    """BD1-ground: a disk that lands and rolls has slip exactly 0 at its contact; LCP's
    derivative of the rollout to z0 was 7.5e-3 off the finite differences."""
    from diffcontact.mechanics import disk_points_2d

    system = dc.load_system("BD1-ground", mu=0.3, cor=0.6)
    t = lambda *values: torch.tensor(values if len(values) > 1 else values[0], dtype=F64)  # noqa: E731
    z0 = disk_points_2d(t(0.0, 0.14), t(0.4), t(0.0, -1.5), t(25.0))[None]
    weights = torch.linspace(0.5, 1.5, 26 * z0[0].numel(), dtype=F64)

    def loss(z):
        traj = system.simulate(z, 25, contact_model="LCP", penetration_fraction=None)
        return (traj.flatten() * weights).sum()

    x = z0.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(loss(x), x)
    direction = torch.randn(z0.shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    h = 1e-6
    with torch.no_grad():
        fd = (loss(z0 + h * direction) - loss(z0 - h * direction)) / (2 * h)
    assert float((grad * direction).sum()) == pytest.approx(float(fd), rel=1e-6)


def test_newton_s_law_can_add_energy_in_simultaneous_impacts_and_poisson_s_cannot():
    """A documented model difference (docs/contact-models.md): frictionless elastic
    billiards without penetration compensation, so that only impulses change the
    energy. Newton's restitution, applied to each of several coupled contacts, can add
    kinetic energy; CM's two phases (each restitution impulse at most e times its
    compression) never do."""
    system = dc.load_system("BP5", cor=1.0, mu=0.0)
    z0 = system.sample_initial_conditions(256, seed=0)
    gain = {}
    for model in ("CM", "LCP"):
        traj = system.simulate(
            z0, 100, contact_model=model, penetration_fraction=0.0, on_tunnelling="ignore"
        )
        energy = system.energy(traj)
        gain[model] = float(((energy[:, 1:] - energy[:, :-1]) / energy[:, :1]).max())
    assert gain["CM"] < 1e-12
    assert gain["LCP"] > 0.01


def test_a_simulation_the_lcp_cannot_resolve_says_why():
    """A disk wedged in a corner and against another disk (BD5, mu 2, fast): the Newton
    LCP has no solution; simulate blamed an ill-conditioned cone QP, and LCP's own message
    said to raise max_pivots."""
    system = dc.load_system("BD5", mu=2.0)
    z0 = system.sample_initial_conditions(8, seed=5)
    z0[:, 1] *= 3
    with pytest.raises(dc.contact.ConeQPError) as err:
        system.simulate(z0, 100, contact_model="LCP", on_tunnelling="ignore")
    text = str(err.value)
    assert "state 4" in text and "Newton LCP has no solution" in text
    assert "solve_cone_qp" not in text and "max_pivots" not in text
    system.simulate(z0[4:5], 100, contact_model="CM", on_tunnelling="ignore")  # CM resolves it


def test_stick_is_checked():
    M, q = torch.eye(3, dtype=F64), -torch.ones(3, dtype=F64)
    good = (torch.tensor([False, True, False]), torch.tensor([0, 2, 2]))
    torch.testing.assert_close(solve_lcp(M, q, stick=good), torch.ones(3, dtype=F64))
    for bad in ((good[0],), (good[0].long(), good[1]), (good[0], torch.tensor([0, 3, 2]))):
        with pytest.raises(ValueError, match="stick"):
            solve_lcp(M, q, stick=bad)

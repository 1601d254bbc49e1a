"""Every backend against Clarabel (a second solver) and a brute-force grid for N = 2."""

import numpy as np
import pytest

from fusion_opt import FusionInputError, bci
from fusion_opt.backends import REGISTRY, closed_form, newton
from fusion_opt.criteria import evaluate
from fusion_opt.fusion import information
from fusion_opt.scaling import scale
from studies.backends import instance

SUITE = [(n, N, kind) for n, N in ((2, 2), (3, 2), (4, 3), (2, 5), (3, 8), (6, 4))
         for kind in ("random", "ill-conditioned")]


def _problem(seed, n, N, kind, criterion):
    rng = np.random.default_rng(seed)
    return scale(information(instance(rng, N, n, kind)), criterion)


def _rel(f, f_ref, criterion):
    return abs(f - f_ref) / abs(f_ref) if criterion == "trace" else abs(f - f_ref)


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
@pytest.mark.parametrize("n,N,kind", SUITE)
def test_backends_match_clarabel(n, N, kind, criterion):
    sp = _problem(n * 100 + N, n, N, kind, criterion)
    ref = evaluate(sp.Ys, REGISTRY["clarabel"](sp.Ys, sp.M, criterion).w, criterion, sp.M).f
    for name in ("newton", "slsqp") + (("closed-form",) if N == 2 else ()):
        sol = REGISTRY[name](sp.Ys, sp.M, criterion)
        w = np.maximum(sol.w, 0) / np.maximum(sol.w, 0).sum()
        ev = evaluate(sp.Ys, w, criterion, sp.M)
        assert _rel(ev.f, ref, criterion) < 1e-6, name
        tol = 1e-5 if name == "slsqp" else 1e-9  # slsqp: its ftol; exact ones: rounding
        assert newton.relative_gap(ev.f, ev.g, w, criterion) < tol, name


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
def test_closed_form_matches_grid(criterion):
    sp = _problem(7, 3, 2, "random", criterion)
    ws = np.linspace(0, 1, 20001)
    f = evaluate(sp.Ys, np.stack([ws, 1 - ws], -1), criterion, sp.M).f
    w = closed_form.solve(sp.Ys, sp.M, criterion).w
    assert abs(w[0] - ws[np.argmin(f)]) <= 1e-4
    assert evaluate(sp.Ys, w, criterion, sp.M).f <= f.min() + 1e-15


def test_newton_exact_when_hessian_singular():
    # n = 2: n(n+1)/2 = 3 < N = 12, so H is singular and the weights are not unique.
    sp = _problem(3, 2, 12, "random", "trace")
    sol = newton.solve_one(sp.Ys, sp.M, "trace")
    assert sol.converged[0] and sol.rel_gap[0] <= newton.TOL
    batched = newton.solve(sp.Ys[None], sp.M[None], "trace")
    f = [evaluate(sp.Ys, w, "trace", sp.M).f for w in (sol.w[0], batched.w[0])]
    assert abs(f[0] - f[1]) <= 1e-13 * abs(f[1])


def test_newton_zero_failures_on_many_ill_conditioned():
    rng = np.random.default_rng(11)
    for k in range(60):
        n, N, crit = (2, 4, 6)[k % 3], (3, 7, 16)[k // 3 % 3], ("trace", "logdet")[k % 2]
        sp = scale(information(instance(rng, N, n, "ill-conditioned")), crit)
        assert newton.solve_one(sp.Ys, sp.M, crit).converged[0]


def test_closed_form_rejects_more_than_two_nodes():
    covs = np.stack([np.eye(2)] * 3)
    with pytest.raises(FusionInputError, match="N = 2"):
        bci(np.zeros((3, 2)), covs, backend="closed-form")


def test_diagonalisations_agree():
    rng = np.random.default_rng(2)
    P = instance(rng, 2, 4, "random")
    lam, T = closed_form.diagonalise_covariances(P[0], P[1])
    assert np.allclose(T @ np.diag(1 / lam) @ T.T, P[0]) and np.allclose(T @ T.T, P[1])
    lam2, _ = closed_form.diagonalise_information(*np.linalg.inv(P))
    assert np.allclose(np.sort(lam), np.sort(lam2))


def test_closed_form_on_ill_conditioned_pairs_matches_batched_newton():
    # Regression: a Cholesky factor of Y_b alone (cond ~1e13) gave negative eigenvalues.
    rng = np.random.default_rng(3)
    for k in range(80):
        crit = ("trace", "logdet")[k % 2]
        sp = _problem(rng.integers(1 << 30), (4, 6)[k // 2 % 2], 2, "ill-conditioned", crit)
        f_cf = evaluate(sp.Ys, closed_form.solve(sp.Ys, sp.M, crit).w, crit, sp.M).f
        w_nt = newton.solve(sp.Ys[None], sp.M[None], crit).w[0]
        f_nt = evaluate(sp.Ys, w_nt, crit, sp.M).f
        assert f_cf <= f_nt + 1e-12 * max(abs(f_nt), 1.0)

"""The "clarabel-direct" backend against CVXPY's Clarabel, the exact minimum for N = 2 (exact
arithmetic), and its mapping of Clarabel's statuses (the same as the CVXPY backend's)."""

from fractions import Fraction

import clarabel
import numpy as np
import pytest
from conftest import instance, objective
from test_fusion_optimality import TABLE1_PAIR
from test_rules_exact import as_objective, exact, inv, pair_minimum, pair_objective

import fusion_opt as fo
from fusion_opt.backends import REGISTRY, clarabel_direct
from fusion_opt.scaling import conic_problem

KINDS = ("random", "ill-conditioned")


def _covs(seed, n, N, kind):
    return instance(np.random.default_rng(seed), N, n, kind)


def _close(f, f_ref, criterion, rtol=1e-6):
    """Relative for "trace"; absolute for "logdet" (a relative error of det P)."""
    scale = abs(f_ref) if criterion == "trace" else 1.0
    return abs(f - f_ref) <= rtol * scale


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("n", [1, 2, 4, 6])
def test_matches_cvxpy_clarabel(n, kind, criterion):
    for N in (2, 3, 5, 8):
        covs = _covs([n, N, len(kind)], n, N, kind)
        means = np.zeros((N, n))
        direct = fo.bci(means, covs, criterion, "clarabel-direct", polish=False)
        ref = fo.bci(means, covs, criterion, "clarabel", polish=False)
        # unpolished: the solver's own weights, certified to its tolerance (not to 1e-10,
        # so the status may say optimal_inaccurate)
        assert _close(direct.objective + direct.gap, direct.objective, criterion, rtol=1e-3)
        assert direct.backend == "clarabel-direct"
        assert _close(direct.objective, ref.objective, criterion), (N, direct.weights)


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("n", [1, 2, 4, 6])
def test_pair_matches_exact_minimum(n, kind, criterion):
    covs = _covs([n, 7, len(kind)], n, 2, kind)
    r = fo.bci(np.zeros((2, n)), covs, criterion, "clarabel-direct", polish=False)
    # exact arithmetic, not a float grid: inverting twice lost 2.2e-6 nats on the
    # ill-conditioned logdet pair at n = 4 (an AMD EPYC; less on the machines before)
    assert _close(r.objective, pair_minimum(covs, criterion), criterion)
    # r's f at r's weights, exactly: within the rounding of the input's own Cholesky
    # factors (eps cond(P_i), cond up to 6e10 here: 3.5e-7 nats at that pair)
    Ya, Yb = (inv(exact(P)) for P in covs)
    wa, wb = (Fraction(float(x)) for x in r.weights)
    f_w = as_objective(pair_objective(Ya, Yb, wa, wb, criterion), criterion)
    assert _close(r.objective, f_w, criterion)


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
def test_solves_the_table1_pair_that_fails_with_chordal_decomposition(criterion):
    r = fo.bci(np.zeros((2, 4)), TABLE1_PAIR, criterion, "clarabel-direct", polish=False)
    grid = np.linspace(0.0, 1.0, 100_001)
    f = objective(TABLE1_PAIR, np.stack([grid, 1 - grid], axis=1), criterion)
    assert r.objective == pytest.approx(f.min(), rel=1e-6, abs=1e-8)


def test_polished_result_and_batch_equal_newton():
    covs = _covs(5, 3, 4, "random").reshape(1, 4, 3, 3)
    means = np.random.default_rng(5).standard_normal((1, 4, 3))
    r = fo.fuse_batch(means, covs, "bci", "logdet", "clarabel-direct")
    q = fo.bci(means[0], covs[0], "logdet", "newton")
    assert r.status[0] == "optimal" and abs(r.objective[0] - q.objective) <= 1e-12
    assert np.allclose(r.mean[0], q.mean, rtol=1e-8)


def test_equal_data_give_identical_weights_whatever_was_solved_before():
    sps = [conic_problem(_covs(s, 3, 5, "random"))
           for s in (1, 2)]
    first = clarabel_direct.solve(*sps[0], "trace").w
    clarabel_direct.solve(*sps[1], "trace")
    assert np.array_equal(clarabel_direct.solve(*sps[0], "trace").w, first)


_REAL_SOLVER = clarabel.DefaultSolver


class _StatusSolver:
    """clarabel.DefaultSolver whose solution reports a forced status (and maybe NaN x)."""

    status, nan = "Solved", False

    def __init__(self, *args):
        self._solver = _REAL_SOLVER(*args)

    def solve(self):
        sol = self._solver.solve()
        forced = self

        class Solution:
            status = getattr(clarabel.SolverStatus, forced.status)
            x = np.full(len(sol.x), np.nan) if forced.nan else sol.x

            def __getattr__(self, name):
                return getattr(sol, name)

        return Solution()


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
@pytest.mark.parametrize("raw,status", [
    ("InsufficientProgress", "solver_error"), ("NumericalError", "solver_error"),
    ("MaxIterations", "user_limit"), ("PrimalInfeasible", "infeasible"),
    ("AlmostDualInfeasible", "unbounded_inaccurate")])
def test_failure_statuses_raise_like_the_cvxpy_backend(raw, status, criterion, monkeypatch):
    sp = conic_problem(_covs(3, 2, 3, "random"))
    REGISTRY["clarabel"](*sp, criterion)  # compile CVXPY's program unpatched
    monkeypatch.setattr(_StatusSolver, "status", raw)
    monkeypatch.setattr(clarabel, "DefaultSolver", _StatusSolver)  # CVXPY calls it too
    errors = {}
    for backend in ("clarabel-direct", "clarabel"):
        with pytest.raises(fo.FusionSolverError) as info:
            REGISTRY[backend](*sp, criterion)
        errors[backend] = info.value
    assert errors["clarabel-direct"].backend == "clarabel-direct"
    assert errors["clarabel-direct"].status == errors["clarabel"].status == status
    assert raw in errors["clarabel-direct"].detail


def test_almost_solved_is_inaccurate_and_nan_weights_fail(monkeypatch):
    sp = conic_problem(_covs(4, 2, 3, "random"))
    monkeypatch.setattr(clarabel, "DefaultSolver", _StatusSolver)
    monkeypatch.setattr(_StatusSolver, "status", "AlmostSolved")
    sol = REGISTRY["clarabel-direct"](*sp, "trace")
    assert sol.status == "optimal_inaccurate" and 0 < sol.solver_time <= sol.solve_time
    monkeypatch.setattr(_StatusSolver, "nan", True)
    with pytest.raises(fo.FusionSolverError, match="clarabel-direct"):
        REGISTRY["clarabel-direct"](*sp, "trace")

"""The CVXPY programs are built once per shape and re-solved without recompiling."""

import cvxpy as cp
import numpy as np
import pytest
from conftest import random_instance
from cvxpy.reductions.solvers.solving_chain import SolvingChain

import fusion_opt as fo
from fusion_opt import programs


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
def test_second_solve_of_same_shape_reuses_compiled_problem(criterion, monkeypatch):
    programs.clear_cache()
    calls = []
    original = SolvingChain.apply
    monkeypatch.setattr(SolvingChain, "apply",
                        lambda self, *a, **k: calls.append(1) or original(self, *a, **k))
    rng = np.random.default_rng(0)
    fo.bci(*random_instance(rng, 4, 3), criterion, "clarabel")
    prog = programs.program(4, 3, criterion, cp.CLARABEL)
    assert len(calls) == 1 and prog.solves == 1
    r = fo.bci(*random_instance(rng, 4, 3), criterion, "clarabel")  # new data, same shape
    assert programs.program(4, 3, criterion, cp.CLARABEL) is prog
    assert len(calls) == 1 and prog.solves == 2  # no new canonicalisation
    assert r.status == "optimal"
    assert prog.problem.is_dpp()


def test_other_shape_builds_its_own_program():
    programs.clear_cache()
    rng = np.random.default_rng(1)
    fo.bci(*random_instance(rng, 2, 3), backend="clarabel")
    fo.bci(*random_instance(rng, 3, 3), backend="clarabel")
    assert {k[:3] for k in programs._CACHE} == {(2, 3, "trace"), (3, 3, "trace")}


@pytest.mark.parametrize("backend", ["clarabel", "scs"])
def test_equal_data_give_bit_identical_results_whatever_was_solved_before(backend):
    """The first (compiling) solve and later ones take one path, and no solver state is
    carried over, so a study's numbers do not depend on which worker ran what."""
    programs.clear_cache()
    rng = np.random.default_rng(2)
    inst, other = random_instance(rng, 4, 5), random_instance(rng, 4, 5)
    first = fo.bci(*inst, backend=backend, polish=False)
    fo.bci(*other, backend=backend, polish=False)
    again = fo.bci(*inst, backend=backend, polish=False)
    np.testing.assert_array_equal(first.weights, again.weights)


def test_clarabel_retries_without_chordal_decomposition(monkeypatch):
    """A solve that fails with decomposition (as one Table 1 log-det pair did) is tried
    once more without it, for both Clarabel backends."""
    import clarabel

    programs.clear_cache()
    rng = np.random.default_rng(3)
    inst = random_instance(rng, 3, 4)
    expected = fo.bci(*inst, backend="clarabel").objective
    real_solve, seen = cp.Problem.solve, []

    def flaky(self, *args, **kwargs):
        seen.append(kwargs.get("chordal_decomposition_enable", True))
        if seen[-1]:
            raise cp.SolverError("InsufficientProgress")
        return real_solve(self, *args, **kwargs)

    monkeypatch.setattr(cp.Problem, "solve", flaky)
    r = fo.bci(*inst, backend="clarabel")
    assert seen == [True, False] and r.status == "optimal"
    assert r.objective == pytest.approx(expected, rel=1e-12)

    real_solver, used = clarabel.DefaultSolver, []

    def direct(P, q, A, b, cones, settings):
        used.append(settings.chordal_decomposition_enable)
        if used[-1]:
            raise RuntimeError("InsufficientProgress")
        return real_solver(P, q, A, b, cones, settings)

    monkeypatch.setattr(clarabel, "DefaultSolver", direct)
    r = fo.bci(*inst, backend="clarabel-direct")
    assert used == [True, False] and r.status == "optimal"
    assert r.objective == pytest.approx(expected, rel=1e-12)

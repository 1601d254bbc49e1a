"""Every backend through the public API against Clarabel (a second solver) and the
certificate; closed-form only for pairs."""

import numpy as np
import pytest
from conftest import instance

import fusion_opt as fo
import fusion_opt.core

SUITE = [(n, N, kind) for n, N in ((2, 2), (3, 2), (4, 3), (2, 5), (3, 8), (6, 4))
         for kind in ("random", "ill-conditioned")]


def _rel(f, f_ref, criterion):
    return abs(f - f_ref) / abs(f_ref) if criterion == "trace" else abs(f - f_ref)


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
@pytest.mark.parametrize("n,N,kind", SUITE)
def test_backends_agree_with_clarabel(n, N, kind, criterion):
    rng = np.random.default_rng(n * 100 + N)
    covs, means = instance(rng, N, n, kind), rng.standard_normal((N, n))
    ref = fo.bci(means, covs, criterion, "clarabel")
    names = ["newton", "clarabel-direct", "scs", "slsqp"] + (["closed-form"] if N == 2 else [])
    for name in names:
        r = fo.bci(means, covs, criterion, name)
        assert r.backend == name and r.status == "optimal", name
        assert _rel(r.objective, ref.objective, criterion) < 1e-10, name
        scale = abs(r.objective) if criterion == "trace" else 1.0
        assert r.gap <= fo.core.OPTIMAL_RTOL * scale, name
        assert np.allclose(r.mean, ref.mean, rtol=1e-6, atol=1e-8 * np.abs(ref.mean).max())


def test_closed_form_rejects_more_than_two_nodes():
    covs = np.stack([np.eye(2)] * 3)
    with pytest.raises(fo.FusionInputError, match="N = 2"):
        fo.bci(np.zeros((3, 2)), covs, backend="closed-form")


def test_unpolished_backends_report_their_own_certificate():
    """polish=False returns the solver's weights; their certificate says how good they are,
    and the status follows it."""
    covs = instance(np.random.default_rng(1), 5, 3, "random")
    r = fo.bci(np.zeros((5, 3)), covs, backend="clarabel", polish=False)
    p = fo.bci(np.zeros((5, 3)), covs, backend="clarabel")
    assert r.gap >= p.gap and p.status == "optimal"
    assert (r.status == "optimal") == (r.gap <= fo.core.OPTIMAL_RTOL * abs(r.objective))
    assert abs(fo.optimality_gap(covs, r.weights) - r.gap) <= 1e-12 * abs(r.objective)


def test_threads_fusing_with_clarabel_each_get_their_own_problem_solved(monkeypatch):
    """Two threads fuse problems of one shape through CVXPY's cached program: the second
    loads its data while the first waits just before its solve (up to 0.5 s). Unlocked, the
    first solved the second's problem (fuzz of 2026-11-29); each must get the weights its
    problem gets alone."""
    import threading

    from fusion_opt.backends import cvxpy_backends

    rng = np.random.default_rng(7)
    problems = [(rng.standard_normal((4, 3)), instance(rng, 4, 3, "random")) for _ in range(2)]
    alone = [fo.bci(m, P, "trace", "clarabel", polish=False).weights for m, P in problems]
    assert not np.allclose(*alone, atol=1e-3)  # the mix-up would show
    waiting, loaded = threading.Event(), threading.Event()
    set_data, solve = cvxpy_backends.set_data, cvxpy_backends._solve

    def late_set_data(prog, Ys, M):
        set_data(prog, Ys, M)
        if threading.current_thread().name == "second":
            loaded.set()

    def slow_solve(prog, solver, options):
        if threading.current_thread().name == "first":
            waiting.set()
            loaded.wait(0.5)  # the second thread's data arrive here unless it is held off
        solve(prog, solver, options)

    monkeypatch.setattr(cvxpy_backends, "set_data", late_set_data)
    monkeypatch.setattr(cvxpy_backends, "_solve", slow_solve)
    out = {}

    def fuse(k):
        out[k] = fo.bci(*problems[k], "trace", "clarabel", polish=False).weights

    first = threading.Thread(target=fuse, args=(0,), name="first")
    second = threading.Thread(target=fuse, args=(1,), name="second")
    first.start()
    assert waiting.wait(30)
    second.start()
    first.join(60)
    second.join(60)
    for k in (0, 1):
        np.testing.assert_array_equal(out[k], alone[k])

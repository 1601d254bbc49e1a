"""The API as a user meets it: one convention for the growth factor, results that say what
they hold, warmup, the memory limits, and the fallback of an uncertified native solve."""

import re
from pathlib import Path

import numpy as np
import pytest
from conftest import random_instance

import fusion_opt as fo
from fusion_opt import core
from fusion_opt.backends import newton
from fusion_opt.prepare import MAX_CONDITION

MEANS, COVS = random_instance(np.random.default_rng(0), 3, 4)
P = [0.9, 0.6, 0.8, 0.7]


@pytest.mark.parametrize("call", [
    lambda kw: fo.mbci(MEANS, COVS, P, **kw),
    lambda kw: fo.fuse(MEANS, COVS, method="mbci", p_detect=P, **kw),
    lambda kw: fo.fuse_batch(MEANS[None], COVS[None], "mbci", p_detect=P, **kw),
])
def test_growth_is_the_inverse_of_chi_everywhere(call):
    by_growth, by_chi = call({"growth": 1.25}), call({"chi": 0.8})
    np.testing.assert_array_equal(by_growth.cov, by_chi.cov)
    with pytest.raises(fo.FusionInputError, match="exactly one of chi"):
        call({"growth": 1.25, "chi": 0.8})
    with pytest.raises(fo.FusionInputError, match="growth must be >= 1"):
        call({"growth": 0.5})


def test_detection_scales_take_growth_too():
    np.testing.assert_array_equal(fo.detection_scales(P, growth=2.0),
                                  fo.detection_scales(P, 0.5))
    with pytest.raises(fo.FusionInputError, match="exactly one of chi"):
        fo.detection_scales(P)


def test_processing_node_takes_growth():
    node = fo.ProcessingNode(["a", "b"], threshold=1.0, p_detect={"a": 0.9, "b": 0.5},
                             growth=1.1)
    assert node.chi == pytest.approx(1 / 1.1)


def test_results_say_what_their_weights_are():
    r = fo.fuse(MEANS, COVS, method="naive")
    assert r.weights_are == "gain_shares" and "gain shares" in repr(r)
    assert r.status == fo.Status.CLOSED_FORM and r.backend is None
    b = fo.bci(MEANS, COVS)
    assert b.weights_are == "ci_weights" and "CI weights" in repr(b)


def test_batch_repr_is_a_summary_and_iterations_are_integers():
    r = fo.fuse_batch(np.repeat(MEANS[None], 500, 0), np.repeat(COVS[None], 500, 0))
    assert r.iterations.dtype == np.int64 and len(repr(r)) < 400 and "B=500" in repr(r)


def test_a_rule_refuses_a_backend():
    with pytest.raises(fo.FusionInputError, match="no weight solver"):
        fo.fuse(MEANS, COVS, method="naive", backend="clarabel")


def test_warmup_fuses_a_problem_of_the_shape():
    assert fo.warmup(3, 4) >= 0.0
    with pytest.raises(fo.FusionInputError, match="n must be an integer"):
        fo.warmup(0, 4)


def test_conic_memory_limit_refuses_before_allocating():
    covs = np.broadcast_to(np.eye(200), (3, 200, 200))
    with pytest.raises(fo.FusionSolverError, match=r"'clarabel'.*n = 200.*GiB") as err:
        fo.bci(np.zeros((3, 200)), covs, backend="clarabel")
    assert err.value.status == "memory_limit"


def test_limits_are_settable_and_checked(monkeypatch):
    monkeypatch.setattr(fo.limits, "working_memory", fo.limits.working_memory)
    fo.limits.working_memory = 1e3
    with pytest.raises(fo.FusionSolverError, match="working_memory"):
        fo.bci(MEANS, COVS)
    for bad in (-1, 10**400, float("nan"), True, "1e9"):  # 10**400: past the float range
        with pytest.raises(ValueError, match="limits.working_memory must be a positive"):
            fo.limits.working_memory = bad
    fo.limits.working_memory = np.int64(2**33)
    assert fo.limits.working_memory == 2.0**33
    with pytest.raises(AttributeError, match="no limit 'working_memroy'"):
        fo.limits.working_memroy = 1e9  # misspelt: would change nothing


def _spoiled(real):
    """core.fuse_exact, whose one result then holds a vertex that is not the optimum,
    reported as uncertified (the fused estimate and objective stay the optimum's)."""
    def spoiled(*args):
        code = real(*args)
        W, stats = args[10], args[15]
        W[:] = np.eye(W.shape[1])[0]
        stats[:, 2] = 1.0
        return code
    return spoiled


def test_an_uncertified_native_solve_is_rescued_from_clarabels_weights(monkeypatch):
    """If the compiled solve ends above OPTIMAL_RTOL (rounding on a hard problem), the
    core solves again from Clarabel's weights and keeps the better certificate."""
    monkeypatch.setattr(core, "fuse_exact", _spoiled(core.fuse_exact))
    r = fo.bci(MEANS, COVS)
    monkeypatch.undo()
    ref = fo.bci(MEANS, COVS, backend="clarabel")
    assert r.status == "optimal" and r.objective == pytest.approx(ref.objective, rel=1e-12)
    np.testing.assert_allclose(r.weights, ref.weights, atol=1e-6)


def test_no_rescue_where_clarabel_is_over_its_memory_limit(monkeypatch):
    """Where Clarabel's KKT system would exceed fo.limits.conic_memory (at n = 150 tens
    of GiB) the uncertified native result stands, reported optimal_inaccurate, and
    Clarabel is not called (the rescue of a spoiled result at n = 150 was killed for
    memory)."""
    monkeypatch.setattr(core, "fuse_exact", _spoiled(core.fuse_exact))
    monkeypatch.setattr(core, "_conic", lambda *args: pytest.fail("Clarabel was called"))
    monkeypatch.setattr(fo.limits, "conic_memory", 1.0)
    r = fo.bci(MEANS, COVS)
    assert r.status == "optimal_inaccurate" and r.gap >= 0.0


@pytest.mark.parametrize("n", [core.RESCUE_MAX_N, core.RESCUE_MAX_N + 1])
def test_no_rescue_above_rescue_max_n(monkeypatch, n):
    """Clarabel's rescue runs up to RESCUE_MAX_N (its solve grows as n^6: 72 s at n = 64,
    where a fuzz's rescue of a result it could not improve took 150-200 s); above, the
    uncertified native result stands, optimal_inaccurate, with its own gap."""
    calls, conic = [], core._conic
    monkeypatch.setattr(core, "fuse_exact", _spoiled(core.fuse_exact))
    monkeypatch.setattr(core, "_conic", lambda *args: calls.append(n) or conic(*args))
    covs = np.stack([np.diag(np.linspace(1.0, 2.0, n)[::(-1) ** i]) for i in range(2)])
    r = fo.bci(np.zeros((2, n)), covs)
    assert calls == [n] * (n <= core.RESCUE_MAX_N)
    rescued = n <= core.RESCUE_MAX_N
    assert r.status == ("optimal" if rescued else "optimal_inaccurate") and r.gap >= 0.0


def test_readme_examples_run():
    """Every python block of the README runs as written (Stone Soup's only with its extra)."""
    text = Path(__file__).parents[1].joinpath("README.md").read_text()
    for block in re.findall(r"```python\n(.*?)```", text, re.S):
        if "stonesoup" in block:
            pytest.importorskip("stonesoup")
        exec(compile(block, "README.md", "exec"), {})


def test_one_compiled_specialisation_whatever_the_inputs_flags():
    """Read-only inputs (an Estimates' arrays), MBCI's own scales, a batch, and weights of
    any flags given to optimality_gap reach the compiled path as the same array types as
    plain calls, so it is compiled once (15 s
    each otherwise) and a study pays the compilation once."""
    est = fo.Estimates(MEANS, COVS)
    fo.bci(MEANS, COVS)
    fo.bci(est.means, est.covs, "logdet")
    fo.mbci(est.means, est.covs, P, growth=1.1)
    fo.fuse_batch(np.stack([est.means] * 3), np.stack([est.covs] * 3), "mbci", p_detect=P,
                  chi=0.9)
    assert len(core.fuse_exact.signatures) == 1, core.fuse_exact.signatures
    weights = fo.bci(MEANS, COVS).weights  # read-only
    fo.fuse(MEANS, COVS, method="naive")  # the core's call of prepare from Python
    fo.optimality_gap(COVS, np.array(weights))
    kernels = (core.prepare, newton.certificate)
    before = [set(k.signatures) for k in kernels]
    for w in (weights, np.stack([weights, weights], 1)[:, 0]):  # read-only, strided
        fo.optimality_gap(est.covs, w)
    assert [set(k.signatures) for k in kernels] == before
    assert len(core.prepare.signatures) == 1, core.prepare.signatures


@pytest.mark.parametrize("backend", ["newton", "closed-form", "clarabel-direct"])
def test_results_own_read_only_arrays_not_shared_with_the_next_call(backend):
    """One problem reuses per-thread scratch arrays: a result must keep arrays of its own
    that the next fusion of the same shape cannot overwrite."""
    rng = np.random.default_rng(5)
    covs = [rng.standard_normal((2, 3, 3)) for _ in range(2)]
    covs = [A @ A.transpose(0, 2, 1) + 0.1 * np.eye(3) for A in covs]
    first = fo.bci(np.zeros((2, 3)), covs[0], backend=backend)
    kept = [first.weights.copy(), first.mean.copy(), first.cov.copy()]
    second = fo.bci(np.ones((2, 3)), covs[1], backend=backend)
    for name, before in zip(("weights", "mean", "cov"), kept, strict=True):
        a, b = getattr(first, name), getattr(second, name)
        assert not a.flags.writeable and not np.shares_memory(a, b)
        np.testing.assert_array_equal(a, before)
        with pytest.raises(ValueError):
            a[...] = 0.0


@pytest.mark.parametrize("backend", ["newton", "clarabel"])
def test_covariances_near_the_largest_double_fuse(backend):
    """Regression: symmetrising (P + P^T) / 2 overflowed for entries near 1.8e308, and the
    nodes were refused as "not positive definite (smallest eigenvalue nan)". By hand: CI
    of 1e308 I and 0.5e308 I takes the smaller node whole; the naive fusion is 1e308 / 3."""
    P = np.stack([1e308 * np.eye(2), 0.5e308 * np.eye(2)])
    r = fo.bci(np.zeros((2, 2)), P, backend=backend)
    np.testing.assert_array_equal(r.weights, [0.0, 1.0])
    np.testing.assert_array_equal(r.cov, 0.5e308 * np.eye(2))
    np.testing.assert_allclose(fo.fuse(np.zeros((2, 2)), P, method="naive").cov,
                               1e308 / 3 * np.eye(2), rtol=1e-15)


@pytest.mark.parametrize("method", ["bci", "naive", "ei", "fast-ci", "known-cross"])
def test_singular_covariances_are_refused_by_every_method(method):
    """Regression: 5 ones(2, 2), singular, passed the compiled Cholesky with a pivot of
    rounding size; the rules then raised LinAlgError and bci returned a singular fused
    covariance. Rank-1 covariances v v^T as rounded were accepted 10 % of the time."""
    covs = np.stack([5.0 * np.ones((2, 2)), np.eye(2)])
    args = {"cross": np.zeros((2, 2, 2, 2))} if method == "known-cross" else {}
    with pytest.raises(fo.FusionInputError,
                       match=r"covs of node 0 is (not positive definite|numerically singular)"):
        fo.fuse(np.zeros((2, 2)), covs, method, **args)
    rng = np.random.default_rng(0)
    for _ in range(200):
        v = rng.standard_normal((3, 1))
        with pytest.raises(fo.FusionInputError, match="covs of node 0 is"):
            fo.bci(np.zeros((2, 3)), np.stack([v @ v.T, np.eye(3)]))


def test_nodes_far_apart_in_scale_fuse_exactly():
    """Regression: a node 1e320 away from the others had its |P|_F overflow to inf (the
    squares), which made the best-vertex rule's bound NaN: log det returned the vertex
    [1, 0, 0], 0.45 nats above the optimum, as optimal_inaccurate; 1e-200 I beside
    1e140 I underflowed it to 0 and was refused as not positive definite. By hand: a and b
    mirror each other, so w = (1/2, 1/2, 0) and P = (5/8 1e160)^-1 I."""
    a, b, c = np.diag([1.0, 4.0]) * 1e-160, np.diag([4.0, 1.0]) * 1e-160, np.eye(2) * 1e160
    r = fo.bci(np.zeros((3, 2)), np.stack([a, b, c]), "logdet")
    assert r.status == fo.Status.OPTIMAL
    np.testing.assert_allclose(r.weights, [0.5, 0.5, 0.0], atol=1e-15)
    assert r.objective == pytest.approx(2 * np.log(1.6e-160), abs=1e-12)
    r = fo.bci(np.zeros((2, 2)), np.stack([1e-200 * np.eye(2), 1e140 * np.eye(2)]))
    np.testing.assert_array_equal(r.cov, 1e-200 * np.eye(2))


def test_means_near_the_largest_double_fuse():
    """Regression: means of +-1e308 overflowed the least-squares right-hand side and the
    fusion was refused as overflowing; the fused mean is that of means / 2^1022, times
    2^1022 (P sum_i w_i Y_i m_i computed here in scaled units)."""
    rng = np.random.default_rng(1)
    A = rng.standard_normal((3, 3, 3))
    covs = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(3)
    means = np.full((3, 3), 1e308) * np.array([1.0, -1.0, 1.0])[:, None]
    r = fo.bci(means, covs)
    Y = np.linalg.inv(covs)
    info = np.einsum("i,ijk->jk", r.weights, Y)
    ref = np.linalg.solve(info, np.einsum("i,ijk,ik->j", r.weights, Y, means / 2.0**1022))
    np.testing.assert_allclose(r.mean, ref * 2.0**1022, rtol=1e-12)


def test_masked_long_double_and_pair_names():
    """Regression: a masked array's hidden values were fused; a long double beyond
    float64 became 0 or inf and was refused as "not positive definite" or "non-finite";
    fuse(method="ci") named m_a and P_b, which its caller never passed."""
    eye2 = np.stack([np.eye(2)] * 2)
    masked = np.ma.masked_array([[1e6, 0.0], [1.0, 1.0]], mask=[[1, 0], [0, 0]])
    with pytest.raises(fo.FusionInputError, match="means is a masked array"):
        fo.fuse(masked, eye2, "naive")
    for scale, shown in (("1e-4000", "1e-4000"), ("1e4000", "1e[+]4000")):
        with pytest.raises(fo.FusionInputError, match=f"beyond float64's range, {shown} at"):
            fo.bci(np.zeros((2, 2)), eye2.astype(np.longdouble) * np.longdouble(scale))
    r = fo.bci(np.zeros((2, 2)), eye2.astype(np.longdouble) * np.longdouble("1e-310"))
    np.testing.assert_array_equal(r.cov, 1e-310 * np.eye(2))
    with pytest.raises(fo.FusionInputError, match=r"^covs shape \(2, 2, 2\) does not match "
                                                  r"means shape \(3, 2\)$"):
        fo.fuse(np.zeros((3, 2)), eye2, "ci")


def test_warmup_checks_the_memory_limit_before_allocating():
    """Regression: warmup(100000, 3) allocated a 75 GiB identity first (MemoryError)."""
    for n, N in ((100000, 3), (2, 10**9)):
        with pytest.raises(fo.FusionSolverError, match="memory_limit"):
            fo.warmup(n, N)


def test_slsqp_beyond_its_nodes_and_clarabel_beyond_memory_are_refused_before_solving():
    """Regressions: SLSQP at N = 3000 ran past 10 minutes (its steps cost O(N^3)) and at
    N = 20000 raised scipy's MemoryError for 31 GiB; Clarabel's estimate, half the measured
    peak, let n = 90 (about 8.5 GB) pass the 4 GiB limit."""
    from fusion_opt.backends.slsqp import MAX_NODES

    for N in (MAX_NODES + 1, 3000, 20000):
        means, covs = np.zeros((N, 2)), np.broadcast_to(np.eye(2), (N, 2, 2))
        with pytest.raises(fo.FusionSolverError, match=rf"'node_limit': N = {N} nodes"):
            fo.bci(means, covs, backend="slsqp")
        with pytest.raises(fo.FusionSolverError, match=rf"'node_limit': N = {N} nodes"):
            fo.fuse_batch(means[None], covs[None], backend="slsqp")
        with pytest.raises(fo.FusionSolverError, match=rf"'node_limit': N = {N} nodes"):
            fo.warmup(2, N, backend="slsqp")
    covs = np.broadcast_to(np.eye(2), (MAX_NODES, 2, 2))
    assert fo.bci(np.zeros((MAX_NODES, 2)), covs, backend="slsqp").status == fo.Status.OPTIMAL
    with pytest.raises(fo.FusionSolverError, match=r"memory_limit.*n = 90.*conic_memory"):
        fo.bci(np.zeros((2, 90)), np.stack([np.eye(90)] * 2), backend="clarabel")


def test_a_node_of_condition_beyond_the_limit_is_refused_at_once():
    """Regression: one node diag(1, 1, 1e-300) among 1000 took the polish 11 s (102 s at
    N = 3000) and returned optimal_inaccurate far from the optimum. Its condition, 1e300,
    is past MAX_CONDITION: refused, naming its eigenvalues."""
    covs = np.broadcast_to(np.eye(3), (1000, 3, 3)).copy()
    covs[0] = np.diag([1.0, 1.0, 1e-300])
    with pytest.raises(fo.FusionInputError,
                       match=r"covs of node 0 is numerically singular: eigenvalues 1e-300 to 1"):
        fo.bci(np.zeros((1000, 3)), covs)


def test_the_condition_limit_is_said_as_it_is_applied():
    """Soak 1: prepare refuses a covariance by |P|_F tr(P^-1) (the squared Frobenius norm
    of its inverse Cholesky factor), but the message and README named |P|_F |P^-1|_F,
    up to sqrt(n) times smaller: eigenvalues (1, l, l, l) at 5e13 by that measure (a noise-
    free Kalman filter's covariance after 4,322 steps) were refused "above 7.04e13". The
    message gives the estimate applied, against one computed here from numpy's inverse."""
    lam = np.sqrt(3.0) / 5e13
    Q = np.linalg.qr(np.random.default_rng(4).standard_normal((4, 4)))[0]
    P = (Q * [1.0, lam, lam, lam]) @ Q.T
    P = 0.5 * (P + P.T)
    inverse = np.linalg.inv(P)
    assert np.linalg.norm(P) * np.linalg.norm(inverse) < MAX_CONDITION
    applied = np.linalg.norm(P) * np.trace(inverse)
    assert applied > 1.1 * MAX_CONDITION
    with pytest.raises(fo.FusionInputError, match=r"covs of node 1 is numerically singular") \
            as info:
        fo.bci(np.zeros((2, 4)), np.array([np.eye(4), P]))
    said = re.search(r"\|P\|_F tr\(P\^-1\), (\S+), is above the limit 7\.04e\+13",
                     str(info.value))
    assert said is not None, str(info.value)
    assert float(said.group(1)) == pytest.approx(applied, rel=0.05)


def test_a_refused_covariance_is_called_singular_or_indefinite_as_it_is():
    """Fuzz I6: diag(1e-300, 1e300) is positive definite, but its smallest eigenvalue,
    scaled to its largest, is 0 in float64: it is numerically singular, not "not positive
    definite (smallest eigenvalue 0)"; an indefinite one is called so, by fusion and by an
    Estimates alike."""
    wide = np.array([np.diag([1e-300, 1e300]), np.eye(2)])
    singular = (r"covs of (node|estimate) 0.* is numerically singular: its smallest "
                r"eigenvalue, 0, is within float64's rounding of 0 beside its largest, 1e\+300")
    with pytest.raises(fo.FusionInputError, match=singular):
        fo.bci(np.zeros((2, 2)), wide)
    with pytest.raises(fo.FusionInputError, match=singular):
        fo.Estimates(np.zeros((2, 2)), wide)
    indefinite = np.array([[[1.0, 2.0], [2.0, 1.0]], np.eye(2)])
    with pytest.raises(fo.FusionInputError, match=r"covs of node 0 is not positive definite "
                                                  r"\(smallest eigenvalue -1\)"):
        fo.bci(np.zeros((2, 2)), indefinite)
    with pytest.raises(fo.FusionInputError, match=r"is not positive definite \(smallest "
                                                  r"eigenvalue -1\)"):
        fo.Estimates(np.zeros((2, 2)), indefinite)


@pytest.mark.parametrize("method", ["bci", "naive"])
def test_a_batch_beyond_memory_is_refused_before_anything_is_copied(method):
    """Regression: fuse_batch of 10^8 broadcast problems copied 3 GB for 7.5 s, then raised
    numpy's MemoryError; fuse at n = 10000 copied 1.6 GB before its limit was checked."""
    B = 10**8
    means = np.broadcast_to(np.zeros(2), (B, 2, 2))
    covs = np.broadcast_to(np.eye(2), (B, 2, 2, 2))
    role = "method" if method == "naive" else "backend"  # a rule has no backend to name
    want = "naive" if method == "naive" else "newton"
    with pytest.raises(fo.FusionSolverError, match=rf"^{role} '{want}' failed with status "
                                                   r"'memory_limit'.*the arrays of 100000000"):
        fo.fuse_batch(means, covs, method)


def test_known_cross_beyond_memory_is_refused_before_its_joint_is_made(monkeypatch):
    """Its whitened joint covariance and Cholesky factor are (N n)^2 each: at N = 2,000,
    n = 6, 2.3 GB besides the user's cross; the limit is checked before any of it."""
    from fusion_opt.limits import batch_bytes, joint_bytes

    N, n = 20, 6
    copy = 8.0 * (N * n) ** 2  # of the caller's cross, counted with the arrays
    assert batch_bytes(1, N, n) + copy < 2e5 < joint_bytes(n, N)
    monkeypatch.setattr(fo.limits, "working_memory", 2e5)
    cross = np.zeros((N, N, n, n))
    cross[np.arange(N), np.arange(N)] = np.eye(n)
    with pytest.raises(fo.FusionSolverError, match=r"^method 'known-cross' failed with status "
                                                   r"'memory_limit'.*whitened joint"):
        fo.fuse(np.zeros((N, n)), np.tile(np.eye(n), (N, 1, 1)), "known-cross", cross=cross)
    monkeypatch.setattr(fo.limits, "working_memory", 2 * joint_bytes(n, N))
    r = fo.fuse(np.zeros((N, n)), np.tile(np.eye(n), (N, 1, 1)), "known-cross", cross=cross)
    np.testing.assert_allclose(r.cov, np.eye(n) / N, rtol=1e-14)


def _peak_bytes(call) -> int:
    """The peak of Python-tracked allocations (numpy's included) while call() runs."""
    import tracemalloc

    tracemalloc.start()
    try:
        call()
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak


def test_optimality_gap_and_detection_shapes_are_refused_before_allocating(monkeypatch):
    """Fuzz M1: optimality_gap allocated 668 MiB for 3e6 nodes where fo.bci refuses them
    by fusion_opt.limits; M2: p_detect of 3e7 rows for one problem (a broadcast view: no
    memory) took 1.4 GB and 5-10 s before its shape was refused, and a (1e5, 1e4) view ran
    detection_scales out of memory. Each is refused now with under 1 MB allocated; within
    the limits optimality_gap still answers (uniform weights on identical nodes: gap 0)."""
    monkeypatch.setattr(fo.limits, "working_memory", 2**28)
    N, E = 3_000_000, np.eye(2)
    covs, w = np.broadcast_to(E, (N, 2, 2)), np.broadcast_to(1.0 / N, (N,))

    def refused(call, error, match):
        def run():
            with pytest.raises(error, match=match):
                call()
        assert _peak_bytes(run) < 2**20

    refused(lambda: fo.optimality_gap(covs, w), fo.FusionSolverError,
            r"memory_limit.*N = 3000000.*working_memory")
    p = np.broadcast_to(0.5, (30_000_000, 2))
    refused(lambda: fo.fuse_batch(np.zeros((1, 2, 2)), np.array([[E, E]]), "mbci",
                                  p_detect=p, chi=0.5), fo.FusionInputError,
            r"p_detect and chi must be a scalar, \(2,\) or \(1, 2\), got \(30000000, 2\)")
    refused(lambda: fo.mbci(np.zeros((2, 2)), np.array([E, E]), p, chi=0.5),
            fo.FusionInputError, r"must be a scalar or \(2,\), got \(30000000, 2\)")
    refused(lambda: fo.detection_scales(np.broadcast_to(0.5, (10**5, 10**4)), 0.5),
            fo.FusionInputError, r"shape \(100000, 10000\).*array_memory")
    assert fo.optimality_gap(covs[:1000], w[:1000] * 3000) == 0.0


def test_memory_that_is_allocated_at_once_is_counted_at_once(monkeypatch):
    """Fuzz O7: the batch's arrays and the solver's work arrays were each held to
    working_memory alone, so optimality_gap at n = 1, N = 3e6 peaked at 500 MiB under a
    256 MiB limit; O1: detection scales below 2^-1000 are recomputed from logs in arrays
    the count of 4 numbers a scale left out (2.3 times the limit). Both refused now, with
    little allocated; a smaller low-scale problem still gets its scales."""
    monkeypatch.setattr(fo.limits, "working_memory", 256 * 2**20)
    N = 3_000_000

    def gap():
        with pytest.raises(fo.FusionSolverError, match="arrays of 1 problem and the weight"):
            fo.optimality_gap(np.broadcast_to(np.eye(1), (N, 1, 1)), np.full(N, 1.0 / N))
    assert _peak_bytes(gap) < 64 * 2**20  # the weights it was given (24 MB) and little else
    monkeypatch.setattr(fo.limits, "array_memory", 64 * 2**20)
    chi = np.ones(8)
    chi[0] = 2.0**-1005  # one scale below 2^-1000: the path from logs

    p = np.zeros((240_000, 8))  # 15 MB; the scales and their copies, 4 numbers each, fit

    def low():
        with pytest.raises(fo.FusionInputError, match="a scale below 2.-1000 among them"):
            fo.detection_scales(p, chi)
    assert _peak_bytes(low) <= 64 * 2**20  # within the limit (2.3 times it before)
    s = fo.detection_scales(np.zeros((10, 8)), chi)
    assert s.shape == (10, 8) and (s[:, 1:] == chi[0]).all() and (s[:, 0] > 0).all()


@pytest.mark.parametrize("N, n, method", [
    (2, 1, "bci"), (2, 1, "fast-ci"), (2, 1, "ici"), (2, 2, "bci"), (2, 2, "fast-ci"),
    (2, 2, "ici"), (3, 4, "bci"), (3, 4, "fast-ci")])
def test_a_batch_allocates_no_more_than_its_memory_estimate(N, n, method):
    """Fuzz U9: `limits.batch_bytes` counted arrays per node only, and a batch at n = 1, 2
    (whose per-problem results weigh as much as its nodes) peaked at 1.2-1.7 times the
    estimate the memory limits are checked with. Measured: the peak of Python-tracked
    allocations (numpy's) of a fuse_batch of 5,000 problems (ici only at N = 2, the pairs
    it fuses), its inputs broadcast so that their copies count; the compiled solver's own
    work arrays are counted apart (`working_bytes`) and are not tracked here."""
    from fusion_opt.limits import batch_bytes

    B = 5000
    means, covs = np.broadcast_to(0.0, (B, N, n)), np.broadcast_to(np.eye(n), (B, N, n, n))
    fo.fuse_batch(means, covs, method)  # compiled, loaded and called once before measuring
    assert _peak_bytes(lambda: fo.fuse_batch(means, covs, method)) <= batch_bytes(B, N, n)


def test_an_overflow_names_the_problem_and_what_overflowed():
    """Regression: "the fused estimate overflows" for a batch, without the problem, where
    only the trace of 1e308 I (the objective) overflows."""
    covs = np.tile(np.eye(2), (3, 2, 1, 1))
    covs[2] *= 1e308
    with pytest.raises(fo.FusionInputError,
                       match=r"^problem 2: the fused objective \(its trace\) overflows"):
        fo.fuse_batch(np.zeros((3, 2, 2)), covs)


@pytest.mark.parametrize("backend", [None, "newton", "slsqp", "clarabel"])
def test_the_memory_check_refuses_exactly_the_sizes_over_one_limit(backend, monkeypatch):
    """over_memory refuses exactly where the batch's arrays and the solver's work arrays,
    allocated at once, together pass working_memory (fuzz O7: each was compared alone, so
    1.9 times the limit passed), and where Clarabel's passes conic_memory: at limits around
    each estimate and their sum, for a rule (backend None), a native, SLSQP and a conic
    backend."""
    from fusion_opt import core
    from fusion_opt.limits import batch_bytes, conic_bytes, working_bytes

    req = core.request("naive" if backend is None else "bci", "trace", backend, {})
    n, N, B = 3, 5, 7
    arrays, work = batch_bytes(B, N, n), working_bytes(n, N, backend)
    solver = () if backend is None else (work,)
    for limit in sorted({arrays, work, arrays + work}):
        for lim in (np.nextafter(limit, 0), limit):
            monkeypatch.setattr(fo.limits, "working_memory", lim)
            monkeypatch.setattr(fo.limits, "conic_memory", 2.0**60)
            over = arrays + sum(solver) > lim
            assert (core.over_memory(req, n, N, B) is not None) == over, (lim, backend)
    if backend == "clarabel":
        monkeypatch.setattr(fo.limits, "conic_memory", np.nextafter(conic_bytes(n, N), 0))
        assert core.over_memory(req, n, N, B)[2] == "conic_memory"


def test_a_list_nested_past_the_recursion_limit_is_refused_by_name():
    """Fuzz K16: the check for booleans inside nested lists recursed once a level, and a
    list nested 3,000 deep raised RecursionError from every array argument."""
    x = 1.0
    for _ in range(3000):
        x = [x]
    with pytest.raises(fo.FusionInputError, match="^means must be an array of real numbers"):
        fo.bci(x, x)
    with pytest.raises(fo.FusionInputError, match="ids must be"):
        fo.Estimates(np.zeros((1, 1)), np.eye(1)[None], x)
    deep_bool = True
    for _ in range(3000):
        deep_bool = [deep_bool]
    with pytest.raises(fo.FusionInputError, match="boolean"):
        fo.bci([[0.0, deep_bool]], np.eye(2)[None])


def test_a_known_cross_batch_counts_the_copy_of_its_cross(monkeypatch):
    """Fuzz L9: fuse_batch copied a float32 or read-only cross whole (B (N n)^2 doubles)
    where the memory check counted one problem's joint."""
    from fusion_opt.limits import batch_bytes, joint_bytes

    B, N, n = 50, 3, 4
    monkeypatch.setattr(fo.limits, "working_memory",
                        batch_bytes(B, N, n) + 2 * joint_bytes(n, N))
    cross = np.zeros((B, N, N, n, n), dtype=np.float32)
    cross[:, np.arange(N), np.arange(N)] = np.eye(n)
    with pytest.raises(fo.FusionSolverError, match=r"memory_limit.*the arrays of 50 problems"):
        fo.fuse_batch(np.zeros((B, N, n)), np.tile(np.eye(n), (B, N, 1, 1)), "known-cross",
                      cross=cross)

"""Every kind of bad input raises FusionInputError with a message that names it."""

import numpy as np
import pytest
from conftest import random_instance

import fusion_opt as fo
from trackers import metrics, models, resampling
from trackers.rbpf import RBPF

rng = np.random.default_rng(0)
MEANS, COVS = random_instance(rng, 3, 4)


def _with(array, index, value):
    a = array.copy()
    a[index] = value
    return a


def _asym():
    c = COVS.copy()
    c[2, 0, 1] += 0.1
    return c


def _not_pd():
    c = COVS.copy()
    c[1] = np.diag([1.0, -1.0, 1.0])
    return c


CASES = [
    ("shapes", lambda: fo.bci(MEANS[:, :2], COVS), r"covs shape .* does not match"),
    ("N = 0", lambda: fo.bci(np.zeros((0, 3)), np.zeros((0, 3, 3))), r"N = 0"),
    ("means ndim", lambda: fo.bci(MEANS[0], COVS), r"means must have shape \(N, n\)"),
    ("covs not square", lambda: fo.bci(MEANS, COVS[:, :, :2]), r"covs must have shape"),
    ("nan mean", lambda: fo.bci(_with(MEANS, (1, 2), np.nan), COVS), r"means .*non-finite"),
    ("inf cov", lambda: fo.bci(MEANS, _with(COVS, (3, 0, 0), np.inf)), r"covs .*non-finite"),
    ("asymmetric", lambda: fo.bci(MEANS, _asym()), r"covs of node 2 is not symmetric"),
    ("not PD", lambda: fo.bci(MEANS, _not_pd()), r"covs of node 1 is not positive definite"),
    ("p > 1", lambda: fo.mbci(MEANS, COVS, [0.5, 1.2, 0.5, 0.5], 0.9),
     r"p_detect of node 1 must lie in \[0, 1\]"),
    ("p < 0", lambda: fo.mbci(MEANS, COVS, -0.1, 0.9), r"p_detect of node 0"),
    ("chi = 0", lambda: fo.mbci(MEANS, COVS, 0.9, [1.0, 1.0, 0.0, 1.0]),
     r"chi of node 2 must lie in \(0, 1\]"),
    ("chi > 1", lambda: fo.mbci(MEANS, COVS, 0.9, 1.5), r"chi of node 0"),
    ("p length", lambda: fo.mbci(MEANS, COVS, [0.9, 0.8], 0.9), r"p_detect must be a scalar"),
    ("criterion", lambda: fo.bci(MEANS, COVS, criterion="det"), r"criterion must be one of"),
    ("backend", lambda: fo.bci(MEANS, COVS, backend="gurobi"), r"backend must be one of"),
    ("method", lambda: fo.fuse(MEANS, COVS, method="magic"), r"method must be one of"),
    ("ci needs 2", lambda: fo.fuse(MEANS, COVS, method="ci"), r"'ci' fuses 2 nodes"),
    ("ci pair", lambda: fo.ci(MEANS[0], COVS[0], MEANS[1, :2], COVS[1]), r"m_a has shape"),
    ("ci covs pair", lambda: fo.ci(MEANS[0], COVS[0], MEANS[1], COVS[1, :2]), r"P_a has shape"),
    ("ci mean ndim", lambda: fo.ci(MEANS[:2], COVS[0], MEANS[:2], COVS[1]),
     r"m_a and m_b must have shape \(n,\), got \(2, 3\)"),
    ("ci cov shape", lambda: fo.ci(MEANS[0], COVS[0, :2, :2], MEANS[1], COVS[1, :2, :2]),
     r"P_a and P_b must have shape \(n, n\) = \(3, 3\) .* got \(2, 2\)"),
    ("ci empty", lambda: fo.ci(np.zeros(0), np.zeros((0, 0)), np.zeros(0), np.zeros((0, 0))),
     r"m_a and m_b are empty \(n = 0\)"),
    ("not numbers", lambda: fo.bci([["a", "b"]], COVS[:1, :2, :2]), r"means must be an array"),
    ("gap weights", lambda: fo.optimality_gap(COVS, [0.5, 0.5], "trace"), r"weights must have"),
    ("gap simplex", lambda: fo.optimality_gap(COVS, [0.5, 0.5, 0.5, -0.5]),
     r"weights must be >= 0, got -0\.5 at node 3"),
    # fuzz I7, I8: a number beyond float64 is named as such; an empty p_detect by its name
    ("int beyond float64", lambda: fo.mbci(MEANS, COVS, 10**400, 0.9),
     r"p_detect has a value beyond float64's range, 10000000\.\.\. \(401 digits\)"),
    ("empty p_detect", lambda: fo.detection_scales(np.zeros((2, 0)), 0.5),
     r"p_detect must hold one value per node, got shape \(2, 0\) \(no node\)"),
]


@pytest.mark.parametrize("name,call,message", CASES, ids=[c[0] for c in CASES])
def test_bad_input_raises_named_error(name, call, message):
    with pytest.raises(fo.FusionInputError, match=message):
        call()


def test_input_error_is_a_value_error():
    assert issubclass(fo.FusionInputError, ValueError)


def test_tiny_asymmetry_within_tolerance_is_accepted():
    c = COVS.copy()
    c[0, 0, 1] *= 1 + 1e-12
    assert fo.bci(MEANS, c).status == "optimal"


def test_solver_failure_names_backend_and_status(monkeypatch):
    import cvxpy as cp

    def fail(self, *args, **kwargs):
        raise cp.SolverError("boom")

    monkeypatch.setattr(cp.Problem, "solve", fail)
    with pytest.raises(fo.FusionSolverError, match=r"'clarabel' failed with status") as err:
        fo.bci(MEANS, COVS, backend="clarabel")
    assert err.value.backend == "clarabel" and err.value.status == "solver_error"


def test_solver_error_survives_pickling():
    """Studies run in process pools: the error must arrive whole, not break the pool."""
    import pickle

    err = pickle.loads(pickle.dumps(fo.FusionSolverError("scs", "infeasible", "detail")))
    assert (err.backend, err.status) == ("scs", "infeasible")
    assert "detail" in str(err)
    err = pickle.loads(pickle.dumps(fo.FusionSolverError("ei", "numerical_error", role="method")))
    assert (err.backend, err.role, str(err)) == (
        "ei", "method", "method 'ei' failed with status 'numerical_error'")


def test_results_and_estimates_stay_read_only_when_pickled_or_copied_and_compare_by_identity():
    """Fuzz of 2026-11-29: numpy gives an unpickled or deep-copied array back writeable, so a
    pickled result's cov could be written in place (a frozen result with a non-PD
    covariance); and the dataclasses' generated == compared arrays, which raised numpy's
    "truth value of an array is ambiguous" for two results of one fusion. A Group of
    `associate` (a processing node's `groups`) too (fuzz5 2: its arrays came back
    writeable)."""
    import copy
    import pickle

    objects = (fo.bci(MEANS, COVS), fo.fuse_batch(MEANS[None], COVS[None]),
               fo.Estimates(MEANS, COVS, None, 1.0, "a"),
               fo.associate({"a": fo.Estimates(MEANS[:1], COVS[:1]),  # a Group (fuzz5 2)
                             "b": fo.Estimates(MEANS[:1], COVS[:1])}, 1.0)[0])
    for obj in objects:
        for made in (pickle.loads(pickle.dumps(obj)), copy.copy(obj), copy.deepcopy(obj)):
            assert type(made) is type(obj)
            arrays = {k: v for k, v in vars(obj).items() if isinstance(v, np.ndarray)}
            assert len(arrays) >= 3
            for name, value in arrays.items():
                got = getattr(made, name)
                assert not got.flags.writeable, (type(obj).__name__, name)
                assert np.array_equal(got, value) and got.dtype == value.dtype
            assert made != obj and made == made and hash(made) != hash(obj)
            assert obj in [made, obj] and made not in [obj]


_I = np.eye(2)


@pytest.mark.parametrize("name, call", [
    ("p_detect", lambda: fo.fuse(np.zeros((2, 2)), [_I, 2 * _I], "mbci", p_detect=[True, 0.5],
                                 chi=0.5)),
    ("means", lambda: fo.fuse([[True, 0.0], [0.0, 0.0]], [_I, _I])),
    ("covs", lambda: fo.fuse(np.zeros((2, 2)), [[[True, 0.0], [0.0, 1.0]], _I])),
    ("means", lambda: fo.Estimates([[True, 0.0]], [_I])),
    ("m_a", lambda: fo.ci([True, 0.0], _I, [0.0, 0.0], _I)),
    ("p_detect", lambda: fo.detection_scales([True, 0.5], 0.5)),
    ("weights", lambda: fo.optimality_gap(np.stack([_I, _I]), [np.True_, 0.0])),
])
def test_a_boolean_inside_a_list_is_refused_not_read_as_a_number(name, call):
    """Fuzz E7: numpy reads [True, 0.5] as [1.0, 0.5]; a boolean scalar or array was refused
    already, a boolean among numbers was used as 1 or 0."""
    with pytest.raises(fo.FusionInputError,
                       match=rf"^{name} must be an array of real numbers, got a boolean in it"):
        call()


def test_real_numbers_that_numpy_keeps_as_objects_are_read_as_floats():
    """Fuzz I7: Fractions (and ints beyond int64 but within float64) were refused as "objects
    (ragged or not numbers)"; they are numbers, each rounded once to float64 (as
    Estimates' time already was)."""
    from fractions import Fraction
    exact = fo.mbci(MEANS, COVS, [0.9, 0.8, 0.7, 0.6], 0.5)
    given = fo.mbci(MEANS, COVS, [Fraction(9, 10), 0.8, Fraction(7, 10), 0.6], Fraction(1, 2))
    np.testing.assert_array_equal(given.weights, exact.weights)
    assert fo.optimality_gap(COVS, [Fraction(1, 4)] * 4) == fo.optimality_gap(COVS, [0.25] * 4)
    with pytest.raises(fo.FusionInputError, match="got objects"):
        fo.mbci(MEANS, COVS, [Fraction(9, 10), "x", 0.7, 0.6], 0.5)


_TD, _TD_UNIT = np.timedelta64(5), np.timedelta64(2, "s")


@pytest.mark.parametrize("name, call", [
    ("n", lambda v: fo.warmup(v, 2)),
    ("n_nodes", lambda v: fo.detection_scales(0.5, 0.5, n_nodes=v)),
    ("min_sources", lambda v: fo.ProcessingNode(["a", "b"], method="bci", threshold=1.0,
                                                min_sources=v)),
    ("memory", lambda v: fo.ProcessingNode(["a", "b"], method="bci", threshold=1.0, memory=v)),
    ("dims", lambda v: fo.associate({"a": fo.Estimates([[0.0, 0.0]], [np.eye(2)])}, 1.0,
                                    dims=[v])),
    ("n", lambda v: fo.Estimates.empty(v)),
    ("n_particles", lambda v: _rbpf(n_particles=v)),
    ("clutter_density", lambda v: _rbpf(clutter_density=v)),
    ("dt", lambda v: models.turn_model(0.0, 0.05, 0.01, v)),
    ("c", lambda v: metrics.ospa([[0.0, 0.0]], [[1.0, 0.0]], c=v, p=2)),
    ("threshold", lambda v: resampling.end_of_step(np.zeros(3), v, np.random.default_rng(0))),
])
@pytest.mark.parametrize("value", [_TD, _TD_UNIT], ids=["no unit", "seconds"])
def test_a_timedelta64_is_no_number(name, call, value):
    """Fuzz U3: numpy registers np.timedelta64 as an integer, so the scalar checks took
    np.timedelta64(5) as 5 (particles, nodes, ...) and one with a unit raised TypeError in
    float() or int(). Both are refused by name (`validation.is_real`, `is_integer`)."""
    with pytest.raises(fo.FusionInputError, match=name):
        call(value)


def _rbpf(**kwargs):
    return RBPF(models.turn_model(0.0, 0.05, 0.01, 0.1), np.zeros(4), np.eye(4),
                rng=np.random.default_rng(0), **kwargs)


def test_a_set_is_no_sequence_wherever_items_are_numbered():
    """Fuzz U11, at its depth: a set's order, which numbers sources, targets and ids, changes
    between processes with the hash seed, so `is_sequence` refuses it for every caller."""
    from fusion_opt.validation import is_sequence

    assert all(map(is_sequence, ([1], (1,), iter([1]), np.arange(2))))
    assert not any(map(is_sequence, ({1}, frozenset([1]), {"a": 1}, "ab", np.array(1))))
    with pytest.raises(fo.FusionInputError, match="ids must be a sequence of id sequences"):
        metrics.id_switches({(1, 2), (3, 3)})

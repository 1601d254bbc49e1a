"""Estimates: what it holds, that it is validated on construction by field (with the node,
time and track id of the culprit), and m = 0."""

import numpy as np
import pytest

import fusion_opt as fo

M = np.array([[0.0, 1.0], [2.0, 3.0]])
C = np.array([np.eye(2), [[2.0, 0.5], [0.5, 1.0]]])


def test_holds_read_only_copies_with_default_ids():
    means = M.copy()
    e = fo.Estimates(means, C, time=2, node="radar")
    means[0, 0] = 99.0
    assert e.means[0, 0] == 0.0 and not e.means.flags.writeable
    assert e.ids.tolist() == [0, 1] and e.ids.dtype == np.int64
    assert (len(e), e.n, e.time, e.node) == (2, 2, 2.0, "radar")
    assert e.take([1]).ids.tolist() == [1] and e.take([1]).node == "radar"


def test_covariances_are_symmetrised_within_the_tolerance():
    P = np.array([[1.0, 0.5], [0.5 + 1e-12, 1.0]])
    e = fo.Estimates(M[:1], P[None])
    np.testing.assert_array_equal(e.covs[0], e.covs[0].T)


def test_empty_and_its_hint():
    e = fo.Estimates.empty(4, time=1.0, node="a")
    assert (len(e), e.n, e.means.shape, e.covs.shape) == (0, 4, (0, 4), (0, 4, 4))
    with pytest.raises(fo.FusionInputError, match=r"Estimates.empty\(n\)"):
        fo.Estimates([], [], [])


@pytest.mark.parametrize("kwargs, match", [
    (dict(covs=C[:1]), r"covs must have shape \(2, 2, 2\)"),
    (dict(covs=C * [[[1.0]], [[-1.0]]]), r"covs of estimate 1 \(id 1\) is not positive"),
    (dict(means=M + [[0.0, np.inf], [0.0, 0.0]]), r"means has a non-finite value inf"),
    (dict(means=M.astype(complex)), "means must be an array of real numbers, got complex"),
    (dict(ids=[3, 3]), r"ids must be unique within one Estimates, got \[3, 3\]"),
    (dict(ids=["a", "b"]), "ids must be integers .*got strings"),
    (dict(ids=[[1, 2], [3]]), "ids must be integers .*array of real numbers"),
    (dict(ids=[1.5, 2.0]), "ids must be integers"),
    (dict(ids=[1]), r"ids must have shape \(2,\)"),
    (dict(time=float("nan")), "time must be a finite real number"),
    (dict(node=["unhashable"]), "node must be hashable"),
])
def test_a_bad_field_is_refused_by_name(kwargs, match):
    args = dict(means=M, covs=C, ids=None, time=None, node=None) | kwargs
    with pytest.raises(fo.FusionInputError, match=match):
        fo.Estimates(**args)


def test_errors_name_the_node_the_time_and_the_track_id():
    bad = C.copy()
    bad[1, 0, 1] = 3.0  # not symmetric
    with pytest.raises(fo.FusionInputError, match=r"^Estimates of node 'radar3' at time 1.5: "
                                                    r"covs of estimate 1 \(id 17\) is not sym"):
        fo.Estimates(M, bad, [7, 17], time=1.5, node="radar3")

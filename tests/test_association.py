"""Association of estimates across nodes: hand-made cases for both rules."""

import numpy as np
import pytest

import fusion_opt as fo
from fusion_opt.association import associate


def _sets(groups):
    return sorted(sorted(g) for g in groups)


@pytest.mark.parametrize("method", ["nearest", "assignment"])
def test_two_targets_three_nodes(method):
    means = [np.array([[0.0, 0.0], [5.0, 5.0]]),
             np.array([[5.1, 4.9], [0.1, -0.1]]),
             np.array([[0.05, 0.0]])]
    groups = associate(means, threshold=1.0, method=method)
    assert _sets(groups) == [[(0, 0), (1, 1), (2, 0)], [(0, 1), (1, 0)]]


@pytest.mark.parametrize("method", ["nearest", "assignment"])
def test_far_estimates_stay_single_and_one_per_node(method):
    means = [np.array([[0.0, 0.0], [0.3, 0.0]]), np.array([[10.0, 0.0]]), np.zeros((0, 2))]
    groups = associate(means, threshold=1.0, method=method)
    # the two close estimates come from the same node: they must not be joined
    assert _sets(groups) == [[(0, 0)], [(0, 1)], [(1, 0)]]


def test_nearest_takes_the_closest_pair_first():
    means = [np.array([[0.0]]), np.array([[0.5]]), np.array([[0.45]])]
    groups = associate(means, threshold=1.0, method="nearest")
    assert _sets(groups) == [[(0, 0), (1, 0), (2, 0)]]
    means = [np.array([[0.0]]), np.array([[0.5]]), np.array([[0.45]]), np.array([[0.52]])]
    # nodes 1 and 3 are closest (0.02): joined; then 2 with them (0.05/0.07); then node 0
    assert _sets(associate(means, threshold=1.0)) == [[(0, 0), (1, 0), (2, 0), (3, 0)]]


def test_dims_select_the_compared_components():
    means = [np.array([[0.0, 0.0, 9.0]]), np.array([[0.1, 0.0, -9.0]])]
    assert len(associate(means, 1.0)) == 2
    assert len(associate(means, 1.0, dims=[0, 1])) == 1


def test_bad_input():
    with pytest.raises(fo.FusionInputError, match="threshold"):
        associate([np.zeros((1, 2))], threshold=0.0)
    with pytest.raises(fo.FusionInputError, match="method"):
        associate([np.zeros((1, 2))], threshold=1.0, method="magic")
    with pytest.raises(fo.FusionInputError, match="node 1"):
        associate([np.zeros((1, 2)), np.array([[np.nan, 0.0]])], threshold=1.0)

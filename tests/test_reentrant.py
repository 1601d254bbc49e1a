"""A fusion that starts while another of the same shape runs in the same thread (from a
signal handler, or from the user code an argument's __array__ runs) gets arrays of its own:
both return what each returns alone (fuzz8 3, 4)."""

import numpy as np
import pytest
from conftest import instance

import fusion_opt as fo
from fusion_opt import core


def _problem(seed: int, N: int = 3, n: int = 3, scale: float = 1.0):
    rng = np.random.default_rng(seed)
    return rng.standard_normal((N, n)), scale * instance(rng, N, n, "random")


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
def test_a_fusion_inside_the_exact_kernel_call_changes_neither_result(monkeypatch, criterion):
    """The kernel's call stands for the moment a signal handler fuses (fuzz8 4: 763 of
    20,000 results of a loop interrupted by a fusing SIGALRM handler were wrong, most the
    handler's result returned as the loop's)."""
    outer, inner = _problem(1), _problem(2, scale=1e3)
    alone = fo.bci(*outer, criterion), fo.bci(*inner, criterion)
    kernel, inside = core.fuse_exact, []

    def interrupted(*args):
        if not inside:  # the outer call's kernel: fuse another problem first, once
            inside.append(None)
            inside[0] = fo.bci(*inner, criterion)
        return kernel(*args)

    monkeypatch.setattr(core, "fuse_exact", interrupted)
    got = fo.bci(*outer, criterion)
    for r, ref in ((got, alone[0]), (inside[0], alone[1])):
        np.testing.assert_array_equal(r.weights, ref.weights)
        np.testing.assert_array_equal(r.cov, ref.cov)
        assert r.objective == ref.objective and r.gap == ref.gap


def test_a_cross_argument_whose_conversion_fuses_gives_the_plain_result():
    """fuzz8 3: known-cross converts its cross after `prepare` has filled the arrays; a
    lazy cross (a dask array under the synchronous scheduler) whose computation fuses a
    problem of the same shape gave a wrong estimate, with no error."""
    rng = np.random.default_rng(5)
    N, n = 3, 3
    G = 0.3 * rng.standard_normal((N * n, N * n))
    joint = G @ G.T + np.eye(N * n)
    cross = joint.reshape(N, n, N, n).transpose(0, 2, 1, 3).copy()
    covs, means = np.stack([cross[i, i] for i in range(N)]), rng.standard_normal((N, n))
    other = _problem(6, scale=1e3)

    class Lazy:
        def __array__(self, dtype=None, copy=None):
            fo.bci(*other)  # a step of the user's pipeline fuses something of this shape
            return cross

    plain = fo.fuse(means, covs, "known-cross", cross=cross)
    lazy = fo.fuse(means, covs, "known-cross", cross=Lazy())
    np.testing.assert_array_equal(lazy.mean, plain.mean)
    np.testing.assert_array_equal(lazy.cov, plain.cov)

"""The Stone Soup study prototype: one run is seeded (same seed, same run) and leaves numpy's
global random state alone."""

import numpy as np
import pytest

pytest.importorskip("stonesoup")

from studies.stonesoup_prototype import POSITION, Scenario, run_once  # noqa: E402

SHORT = Scenario(steps=12)


def _arrays(run):
    for step in run.steps:
        yield step.truth_ids
        yield step.truth
        yield from step.detections
        for e in step.tracks:
            yield from (e.means, e.covs, e.ids)


def test_same_seed_same_run_and_the_global_state_untouched():
    global_state = np.random.get_state  # noqa: NPY002 - read only, to see it is not used
    before = global_state()[1].copy()
    a, b, c = run_once(3, SHORT), run_once(3, SHORT), run_once(4, SHORT)
    assert np.array_equal(before, global_state()[1])
    assert all(np.array_equal(x, y) for x, y in zip(_arrays(a), _arrays(b), strict=True))
    assert not all(np.array_equal(x, y) for x, y in zip(_arrays(a), _arrays(c), strict=False))


def test_a_run_has_the_truth_and_each_sensors_estimates_per_step():
    run = run_once(0, SHORT)
    assert len(run.steps) == SHORT.steps and run.seconds > 0
    for k, step in enumerate(run.steps):
        assert step.time == k * SHORT.dt
        assert step.truth.shape == (len(SHORT.targets), 4)
        assert step.truth_ids.tolist() == list(range(len(SHORT.targets)))
        assert [e.node for e in step.tracks] == ["sensor0", "sensor1"]
        assert all(e.time == step.time and e.n == 4 for e in step.tracks)
        assert all(d.shape[1] == 2 for d in step.detections)
    np.testing.assert_array_equal(run.steps[0].truth, np.array(SHORT.targets))
    last = run.steps[-1]  # the reliable sensor tracks every target by now
    assert len(last.tracks[0]) == len(SHORT.targets)
    err = np.abs(np.sort(last.tracks[0].means[:, POSITION], 0)
                 - np.sort(last.truth[:, POSITION], 0))
    assert err.max() < 5 * SHORT.noise_sd[0]

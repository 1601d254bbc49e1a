"""The tracker protocol shared by KalmanFilter, RBPF and RBMCDA: step(scan, time) ->
Estimates, empty scans, and refusals that leave the tracker unchanged."""

import numpy as np
import pytest

from fusion_opt import Estimates, FusionInputError
from trackers import kalman, rbmcda, rbpf, scenarios


def make(kind, name=None):
    cfg = scenarios.Table2Config()
    model, (m0, P0) = cfg.filter_model(), cfg.prior()
    rng = np.random.default_rng(5)
    if kind == "kf":
        return kalman.KalmanFilter(model, m0, P0, name=name)
    if kind == "rbpf":
        return rbpf.RBPF(model, m0, P0, rng=rng, name=name)
    return rbmcda.RBMCDA(model, m0, P0, rng=rng, dt=cfg.dt, name=name)


KINDS = ["kf", "rbpf", "rbmcda"]


@pytest.mark.parametrize("kind", KINDS)
def test_empty_scans_in_every_form_step_alike(kind):
    a, b = make(kind), make(kind)
    for scan_a, scan_b in (([], np.empty((0, 2))), ([[0.1, 0.2]], np.array([[0.1, 0.2]])),
                           (np.zeros((0, 2)), [])):
        ea, eb = a.step(scan_a), b.step(scan_b)
        assert isinstance(ea, Estimates) and ea.n == 4
        np.testing.assert_array_equal(ea.means, eb.means)
        np.testing.assert_array_equal(ea.covs, eb.covs)
        np.testing.assert_array_equal(ea.ids, eb.ids)
    assert a.steps == 3


@pytest.mark.parametrize("kind", KINDS)
def test_a_steps_estimates_are_what_the_checked_constructor_makes(kind):
    """step() builds its Estimates without the constructor's checks, from the covariances
    `_checks.step_estimates` checked and symmetrised (`_checks.report`): bit for bit what
    the checked constructor makes of them, read-only, and not the tracker's own state (an
    Estimates a step returned stays as it was after later steps)."""
    f, rng = make(kind, name="n"), np.random.default_rng(11)
    kept = []
    for k in range(40):
        scan = rng.normal([0.5, 0.5], 0.3, size=(int(rng.integers(0, 3)), 2))
        e = f.step(scan, time=0.01 * (k + 1))
        again = Estimates(e.means, e.covs, e.ids, e.time, e.node)
        for name in ("means", "covs", "ids"):
            np.testing.assert_array_equal(getattr(e, name), getattr(again, name))
            assert getattr(e, name).dtype == getattr(again, name).dtype
            assert not getattr(e, name).flags.writeable
        kept.append((e, e.means.copy(), e.covs.copy(), e.ids.copy()))
    assert any(len(e) for e, *_ in kept)
    for e, means, covs, ids in kept:
        for got, want in ((e.means, means), (e.covs, covs), (e.ids, ids)):
            np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("kind", KINDS)
def test_time_and_name_are_stamped(kind):
    f = make(kind, name="node 3")
    e = f.step([], time=0.5)
    assert (e.time, e.node) == (0.5, "node 3")
    if kind != "rbmcda":
        assert f.step([]).time is None
        return
    g = make(kind)  # RBMCDA's clock where no time is given: (k + 1) dt
    assert [g.step([]).time for _ in range(2)] == [0.01, 0.02]


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize(("scan", "time", "match"), [
    (None, None, "scan must be an array-like"),
    ("0.1 0.2", None, "scan must be an array of real numbers"),
    ([[0.1, 0.2j]], None, "complex"),
    ([[0.1, np.inf]], None, "non-finite"),
    (np.zeros((1, 3)), None, r"shape \(k, 2\)"),
    ([], "1.0", "time must be a real number"),
    ([], np.nan, "time must be a finite real number"),
    ([], True, "time must be a real number"),
])
def test_refused_step_leaves_the_tracker_unchanged(kind, scan, time, match):
    f = make(kind)
    f.step([[0.3, -0.2]])
    with pytest.raises(FusionInputError, match=match):
        f.step(scan, time=time)
    assert f.steps == 1
    g = make(kind)
    g.step([[0.3, -0.2]])
    e_f, e_g = f.step([[0.31, -0.2]]), g.step([[0.31, -0.2]])
    np.testing.assert_array_equal(e_f.means, e_g.means)


@pytest.mark.parametrize("kind", KINDS)
def test_unhashable_name_is_refused_at_construction(kind):
    # a generic np.timedelta64 raises ValueError from hash(), which escaped raw (fuzz4)
    for name in (["a"], np.timedelta64(5)):
        with pytest.raises(FusionInputError, match="name must be hashable"):
            make(kind, name=name)


@pytest.mark.parametrize("kind", KINDS)
def test_a_0d_integer_array_time_beyond_2_53_is_refused_not_rounded(kind):
    """Fuzz4: np.array(2^53 + 1) was stamped 2^53 (np.int64 of it was refused); the same
    refusal now, and a 0-d array of 2^53 or of a float is a time as before."""
    f = make(kind)
    for t in (np.array(2**53 + 1), np.array(2**53 + 1, dtype=np.uint64)):
        with pytest.raises(FusionInputError, match=r"time 9007199254740993 is an integer "
                                                   r"beyond 2\^53"):
            f.step([], time=t)
    assert f.step([], time=np.array(2**53)).time == 2.0**53
    assert f.step([], time=np.array(2.0**60)).time == 2.0**60


@pytest.mark.parametrize("kind", KINDS)
def test_a_step_back_in_time_is_refused_and_changes_nothing(kind):
    """Fuzz I10: time 1 after time 5 was stamped as given; each filter predicts its model's
    dt forward at every step, so it is refused, before the state changes."""
    f = make(kind)
    f.step([[0.3, -0.2]], time=5.0)
    with pytest.raises(FusionInputError, match=r"time = 1.0 is before the previous step's, "
                                               r"5.0: steps go forward in time"):
        f.step([[0.31, -0.2]], time=1.0)
    assert f.steps == 1
    assert f.step([], time=5.0).time == 5.0  # the same time again is a step forward of 0


def test_rbmcda_refuses_a_clock_time_before_the_last_given_one_and_changes_nothing():
    """Fuzz K3: with time=None RBMCDA stamps its clock (k + 1) dt; after time=100 a step
    without one was stamped 0.02 (time going back), and a later time=50 was accepted,
    checked against the clock instead of the 100 stamped before."""
    f = make("rbmcda")
    f.step([], time=100.0)
    with pytest.raises(FusionInputError, match=r"^time: without one, step 2 is stamped with "
                                               r"its clock time 2 x dt = 0.02, before the time "
                                               r"of the step before it, 100"):
        f.step([])
    assert f.steps == 1
    with pytest.raises(FusionInputError, match="time = 50.0 is before the previous step's"):
        f.step([], time=50.0)
    assert f.step([], time=100.0).time == 100.0 and f.steps == 2


def test_outputs_and_simulated_data_compare_by_identity():
    """fuzz6 2: the filters' run outputs and the simulators' data, frozen dataclasses of
    arrays, raised numpy's "truth value ... ambiguous" for == and a TypeError for hash();
    == is identity, as for an Estimates."""
    cfg = scenarios.Table2Config()
    model, (m0, P0) = cfg.filter_model(), cfg.prior()
    scans = [np.array([[0.1, 0.2]])] * 3

    def table1():
        return scenarios.simulate_table1(scenarios.Table1Config(), np.random.default_rng(3))

    makers = (lambda: kalman.run(scans, model, m0, P0),
              lambda: rbpf.run(scans, model, m0, P0, rng=np.random.default_rng(1)),
              lambda: rbmcda.run(scans, model, m0, P0, rng=np.random.default_rng(1),
                                 dt=cfg.dt),
              table1, lambda: table1().nodes[0],
              lambda: scenarios.simulate_table2(cfg, np.random.default_rng(3)))
    for make in makers:
        a, b = make(), make()
        assert a == a and hash(a) == hash(a)
        assert a != b and hash(a) != hash(b)  # equal contents, two objects


@pytest.mark.parametrize("kind", KINDS)
def test_a_tracker_keeps_its_own_prior_when_the_caller_reuses_its_arrays(kind):
    """fuzz8 2: KalmanFilter kept the caller's m0 and P0 as its state, RBMCDA a view of them
    for every birth: refilling the caller's buffers after building the tracker changed
    its steps."""
    cfg = scenarios.Table2Config()
    model, (m0, P0) = cfg.filter_model(), cfg.prior()
    m0, P0 = np.array(m0, dtype=float), np.array(P0, dtype=float)

    def build(m, P):
        if kind == "kf":
            return kalman.KalmanFilter(model, m, P)
        if kind == "rbpf":
            return rbpf.RBPF(model, m, P, rng=np.random.default_rng(5))
        return rbmcda.RBMCDA(model, m, P, rng=np.random.default_rng(5), dt=cfg.dt,
                             birth_prob=0.5)

    reference, reused = build(m0.copy(), P0.copy()), build(m0, P0)
    m0[:], P0[:] = 100.0, np.diag(np.full(len(m0), 1e-3))  # the caller's next prior
    for scan in ([[0.3, 0.2]], [[0.31, 0.21], [2.0, -1.0]], []):
        a, b = reference.step(scan), reused.step(scan)
        np.testing.assert_array_equal(a.means, b.means)
        np.testing.assert_array_equal(a.covs, b.covs)

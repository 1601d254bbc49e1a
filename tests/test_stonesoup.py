"""fusion_opt.stonesoup against Stone Soup itself: conversions, fuse_states, the optimal
Chernoff updater (Stone Soup's ChernoffUpdater at the same weight is the peer reference) and
the tracker adapter."""

import copy
import subprocess
import sys
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest

stonesoup = pytest.importorskip("stonesoup")

from conftest import random_spd  # noqa: E402
from stonesoup.dataassociator.neighbour import GNNWith2DAssignment  # noqa: E402
from stonesoup.deleter.time import UpdateTimeStepsDeleter  # noqa: E402
from stonesoup.hypothesiser.distance import DistanceHypothesiser  # noqa: E402
from stonesoup.initiator.simple import MultiMeasurementInitiator  # noqa: E402
from stonesoup.measures import Mahalanobis  # noqa: E402
from stonesoup.mixturereducer.gaussianmixture import CovarianceIntersection  # noqa: E402
from stonesoup.models.measurement.linear import LinearGaussian  # noqa: E402
from stonesoup.models.transition.linear import (  # noqa: E402
    CombinedLinearGaussianTransitionModel,
    ConstantVelocity,
)
from stonesoup.predictor.kalman import KalmanPredictor  # noqa: E402
from stonesoup.simulator.simple import (  # noqa: E402
    MultiTargetGroundTruthSimulator,
    SimpleDetectionSimulator,
)
from stonesoup.tracker.simple import MultiTargetTracker  # noqa: E402
from stonesoup.types.detection import Detection, GaussianDetection  # noqa: E402
from stonesoup.types.hypothesis import SingleHypothesis  # noqa: E402
from stonesoup.types.prediction import (  # noqa: E402
    GaussianStatePrediction,
    TaggedWeightedGaussianStatePrediction,
)
from stonesoup.types.state import GaussianState, State  # noqa: E402
from stonesoup.types.track import Track  # noqa: E402
from stonesoup.types.update import GaussianStateUpdate  # noqa: E402
from stonesoup.updater.chernoff import ChernoffUpdater  # noqa: E402
from stonesoup.updater.kalman import KalmanUpdater  # noqa: E402

import fusion_opt as fo  # noqa: E402
from fusion_opt import stonesoup as fs  # noqa: E402

T0 = datetime(2024, 5, 17, 9, 30, 12, 345678)


def _pair(rng, n=4, log10_range=(-1.0, 1.0)):
    """A measurement (GaussianDetection with the feeder's identity model) and a prediction."""
    A, B = random_spd(rng, n, log10_range), random_spd(rng, n, log10_range)
    a, b = rng.standard_normal(n), rng.standard_normal(n)
    measurement = GaussianDetection(a.reshape(-1, 1), A, timestamp=T0,
                                    measurement_model=LinearGaussian(n, list(range(n)), A))
    return measurement, GaussianStatePrediction(b.reshape(-1, 1), B, timestamp=T0)


def _ci(a, A, b, B, omega):
    """Independent reference: CI with weight omega on (a, A), 1 - omega on (b, B)."""
    D = np.linalg.inv(omega * np.linalg.inv(A) + (1 - omega) * np.linalg.inv(B))
    return D @ (omega * np.linalg.solve(A, a) + (1 - omega) * np.linalg.solve(B, b)), D


# --- import and time -------------------------------------------------------------------------

def test_import_fusion_opt_does_not_import_stonesoup():
    code = "import sys, fusion_opt; assert 'stonesoup' not in sys.modules, 'imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("epoch", [fs.EPOCH, datetime(2024, 1, 1), T0])
def test_timestamps_survive_the_round_trip_to_the_microsecond(epoch):
    rng = np.random.default_rng(0)
    for us in rng.integers(-2**31 * 10**6, 2**31 * 10**6, size=200):
        t = epoch + timedelta(microseconds=int(us))
        assert fs.to_datetime(fs.to_seconds(t, epoch), epoch) == t
    assert fs.to_seconds(T0 + timedelta(seconds=2.5), T0) == 2.5
    assert fs.to_seconds(None) is None and fs.to_datetime(None) is None


def test_aware_timestamps_need_an_aware_epoch():
    t = datetime(2024, 1, 1, 12, tzinfo=UTC)
    epoch = datetime(1970, 1, 1, tzinfo=UTC)
    assert fs.to_datetime(fs.to_seconds(t, epoch), epoch) == t
    with pytest.raises(fo.FusionInputError, match="naive"):
        fs.to_seconds(t)
    with pytest.raises(fo.FusionInputError, match="timestamp"):
        fs.to_seconds(3.0)
    with pytest.raises(fo.FusionInputError, match="epoch"):
        fs.to_datetime(1.0, epoch="2024")
    with pytest.raises(fo.FusionInputError, match="seconds"):
        fs.to_datetime(float("nan"))
    # fuzz I4: an int beyond float64 was a TypeError from numpy's isfinite
    with pytest.raises(fo.FusionInputError, match=r"seconds = 10000000\.\.\. \(401 digits\) "
                       r"after 1970-01-01 00:00:00 is beyond the dates a datetime holds"):
        fs.to_datetime(10**400)


# --- conversions -----------------------------------------------------------------------------

def _states(rng, m=3, n=4, t=T0):
    kinds = [GaussianState, GaussianStatePrediction, GaussianDetection]
    return [kinds[i % 3](rng.standard_normal((n, 1)), random_spd(rng, n), timestamp=t)
            for i in range(m)]


def test_states_round_trip_keeps_vector_covariance_and_timestamp():
    rng = np.random.default_rng(1)
    states = _states(rng)
    e = fs.to_estimates(states, epoch=T0, node="radar")
    assert (e.time, e.node, e.ids.tolist()) == (0.0, "radar", [0, 1, 2])
    back = fs.to_states(e, epoch=T0)
    for s, b in zip(states, back, strict=True):
        assert isinstance(b, GaussianState) and b.timestamp == s.timestamp
        np.testing.assert_array_equal(b.state_vector, s.state_vector)
        np.testing.assert_array_equal(b.covar, s.covar)


def test_estimates_round_trip_through_tracks_keeps_every_field():
    rng = np.random.default_rng(2)
    covs = np.stack([random_spd(rng, 4) for _ in range(3)])
    e = fo.Estimates(rng.standard_normal((3, 4)), covs, ids=[7, 3, 12], time=12.345678,
                     node="fused")
    ids = fs.TrackIds()
    tracks = fs.to_tracks(e, epoch=T0, track_ids=ids)
    assert [t.id for t in tracks] == ["7", "3", "12"]
    assert all(t.timestamp == T0 + timedelta(seconds=12.345678) for t in tracks)
    back = fs.to_estimates(tracks, epoch=T0, node=e.node, track_ids=ids)
    for name in ("means", "covs", "ids"):
        np.testing.assert_array_equal(getattr(back, name), getattr(e, name))
    assert (back.time, back.node) == (e.time, e.node)


def test_track_ids_stay_within_int64():
    """Fuzz I9: after the int64 maximum was bound, the next Stone Soup id got 2^63, which
    to_estimates refused later as an id the user never gave; now it gets the smallest free
    integer, and an integer beyond int64 is refused where it is given."""
    ids = fs.TrackIds()
    ids.track_id(2**63 - 1)
    ids.track_id(0)
    assert ids.int_id("a") == 1 and ids.int_id("b") == 2 and ids.int_id("a") == 1
    with pytest.raises(fo.FusionInputError, match="int_id must fit in a signed 64-bit integer"):
        ids.track_id(2**63)


def test_tracks_round_trip_keeps_stone_soup_ids_and_latest_states():
    rng = np.random.default_rng(3)
    tracks = [Track(_states(rng, 2, t=None)[:1] + [s]) for s in _states(rng, 3)]
    ids = fs.TrackIds()
    e = fs.to_estimates(tracks, epoch=T0, track_ids=ids)
    assert e.ids.tolist() == [0, 1, 2] and ids.track_id(1) == tracks[1].id
    back = fs.to_tracks(e, epoch=T0, track_ids=ids)
    for t, b in zip(tracks, back, strict=True):
        assert b.id == t.id and b.timestamp == t.timestamp
        np.testing.assert_array_equal(b.state_vector, t.state_vector)
        np.testing.assert_array_equal(b.covar, t.covar)
    # the same tracks again (here from a generator) keep their ids; a new one gets the next
    again = fs.to_estimates((t for t in tracks[::-1] + [Track(_states(rng, 1))]), track_ids=ids)
    assert again.ids.tolist() == [2, 1, 0, 3]


def test_conversion_refusals_name_the_argument():
    rng = np.random.default_rng(4)
    states = _states(rng, 2)
    bad = [
        ([], "holds no state"),
        ("abc", "sequence"),
        ([states[0], Track([states[1]])], "mixes"),
        ([states[0], _states(rng, 1, t=T0 + timedelta(seconds=1))[0]], r"items\[1\] is at"),
        ([states[0], State([1.0, 2.0, 3.0, 4.0])], r"items\[1\].*no Gaussian summary"),
        ([states[0], _states(rng, 1, n=3)[0]], r"items\[1\] has mean"),
        ([Track()], r"items\[0\] is a Track with no state"),
        ([GaussianState([1.0, 2.0], [[1.0, 0.0], [0.0, -1.0]])], "items: covs.*positive"),
    ]
    for items, match in bad:
        with pytest.raises(fo.FusionInputError, match=match):
            fs.to_estimates(items)
    with pytest.raises(fo.FusionInputError, match="estimates must be"):
        fs.to_states(states)
    ids = fs.TrackIds()
    ids.int_id("5")
    with pytest.raises(fo.FusionInputError, match="already bound"):
        ids.track_id(5)
    # fuzz E4: an AttributeError from a dict given as track_ids
    with pytest.raises(fo.FusionInputError, match="track_ids must be a TrackIds, got dict"):
        fs.to_tracks(fs.to_estimates(states), track_ids={})


def test_the_tracker_wrapper_refuses_odd_tracks_by_name():
    """Fuzz E4: a TypeError from comparing an aware state time with a naive step time, and a
    ValueError from ordering new tracks by a mean that holds a string."""
    eye = np.eye(2)
    aware = T0.replace(tzinfo=UTC)
    track = Track([GaussianState([1.0, 2.0], eye, timestamp=aware - timedelta(seconds=1)),
                   GaussianState([1.0, 2.0], eye, timestamp=aware)])
    with pytest.raises(fo.FusionInputError, match="does not compare with the step's time"):
        fs.StoneSoupTracker([(T0, [track])], 2).step()
    tracks = [Track([GaussianState(np.array([["a"], ["2"]], dtype=object), eye, timestamp=T0)]),
              Track([GaussianState([1.0, 2.0], eye, timestamp=T0)])]
    with pytest.raises(fo.FusionInputError, match=r"tracks\[0\]'s mean must be an array of "
                                                  r"real numbers"):
        fs.StoneSoupTracker([(T0, tracks)], 2).step()


@pytest.mark.parametrize("where", ["prediction", "noise"])
@pytest.mark.parametrize("bad", [(2 + 5j) * np.eye(2), np.array([["1", "0"], ["0", "1"]],
                                                                 dtype=object)])
def test_chernoff_updater_refuses_a_covariance_that_is_not_real(where, bad):
    """Fuzz E3: a complex covariance lost its imaginary part (a ComplexWarning only), strings
    became numbers; both gave a measurement prediction."""
    from fusion_opt.stonesoup import OptimalChernoffUpdater

    noise = bad if where == "noise" else np.eye(2)
    model = LinearGaussian(ndim_state=2, mapping=[0, 1], noise_covar=noise)
    prediction = GaussianStatePrediction(np.zeros((2, 1)),
                                         bad if where == "prediction" else 2 * np.eye(2),
                                         timestamp=T0)
    name = "predicted_state.covar" if where == "prediction" else "measurement_model.noise_covar"
    with pytest.raises(fo.FusionInputError, match=rf"^{name} must be an array of real numbers"):
        OptimalChernoffUpdater(measurement_model=model).predict_measurement(prediction, model)


# --- fuse_states -----------------------------------------------------------------------------

@pytest.mark.parametrize("method, args", [
    ("bci", {}), ("ci", {}), ("naive", {}), ("fast-ci", {}), ("ifci", {}), ("ici", {}), ("ei", {}),
    ("mbci", {"p_detect": [0.9, 0.7], "chi": 0.8}),
])
@pytest.mark.parametrize("criterion", ["trace", "logdet"])
def test_fuse_states_equals_fuse_on_the_converted_arrays(method, args, criterion):
    rng = np.random.default_rng(5)
    states = _states(rng, 2)
    fused = fs.fuse_states(states, method=method, criterion=criterion, **args)
    e = fs.to_estimates(states)
    ref = fo.fuse(e.means, e.covs, method=method, criterion=criterion, **args)
    np.testing.assert_allclose(np.ravel(fused.state_vector), ref.mean, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(fused.covar, ref.cov, rtol=1e-12, atol=1e-12)
    assert isinstance(fused, GaussianState) and fused.timestamp == T0
    np.testing.assert_allclose(fused.metadata["weights"], ref.weights, rtol=1e-9, atol=1e-12)
    assert fused.metadata["gap"] == fused.metadata["fusion_result"].gap >= 0


def test_fuse_states_takes_tracks_and_many_nodes():
    rng = np.random.default_rng(6)
    states = _states(rng, 5)
    fused = fs.fuse_states([Track([s]) for s in states])
    ref = fo.bci(fs.to_estimates(states).means, fs.to_estimates(states).covs)
    np.testing.assert_allclose(fused.covar, ref.cov, rtol=1e-12, atol=1e-12)


def test_fuse_states_refusals():
    rng = np.random.default_rng(7)
    states = _states(rng, 3)
    with pytest.raises(fo.FusionInputError, match="method must be"):
        fs.fuse_states(states, method="nope")
    with pytest.raises(fo.FusionInputError, match="2 nodes"):
        fs.fuse_states(states, method="ci")
    with pytest.raises(fo.FusionInputError, match=r"states: covs"):
        fs.fuse_states([states[0], GaussianState([0.0] * 4, np.diag([1.0, 1.0, 1.0, 0.0]),
                                                 timestamp=T0)])
    with pytest.raises(fo.FusionInputError, match=r"states\[1\] is at"):
        fs.fuse_states([states[0], _states(rng, 1, t=None)[0]])


# --- how ChernoffUpdater maps omega ----------------------------------------------------------

@pytest.mark.parametrize("omega", [0.1, 0.5, 0.9])
def test_chernoff_updater_gives_omega_to_the_measurement(omega):
    """Stone Soup: D = (omega A^-1 + (1 - omega) B^-1)^-1, A the measurement's covariance,
    B the prediction's; innovation covariance A / (1 - omega) + B / omega."""
    measurement, prediction = _pair(np.random.default_rng(8))
    a, A = np.ravel(measurement.state_vector), np.asarray(measurement.covar)
    b, B = np.ravel(prediction.state_vector), np.asarray(prediction.covar)
    hypothesis = SingleHypothesis(prediction, measurement)
    post = ChernoffUpdater(measurement_model=None, omega=omega).update(hypothesis)
    d, D = _ci(a, A, b, B, omega)
    np.testing.assert_allclose(post.covar, D, rtol=1e-10)
    np.testing.assert_allclose(np.ravel(post.state_vector), d, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(hypothesis.measurement_prediction.covar,
                               A / (1 - omega) + B / omega, rtol=1e-12)
    merged = CovarianceIntersection.merge_components(measurement, prediction,
                                                     weights=[omega, 1 - omega])
    np.testing.assert_allclose(merged.covar, D, rtol=1e-10)
    # and fo.fuse on the stack [measurement, prediction] puts weights[0] on the measurement
    r = fo.fuse(np.stack([a, b]), np.stack([A, B]), method="ci")
    np.testing.assert_allclose(r.cov, _ci(a, A, b, B, r.weights[0])[1], rtol=1e-10)


# --- OptimalChernoffUpdater ------------------------------------------------------------------

@pytest.mark.parametrize("criterion", ["trace", "logdet"])
def test_optimal_updater_equals_chernoff_updater_at_the_optimal_weight(criterion):
    rng = np.random.default_rng(9)
    updater = fs.OptimalChernoffUpdater(measurement_model=None, criterion=criterion)
    for _ in range(30):
        measurement, prediction = _pair(rng, n=int(rng.integers(2, 7)))
        post = updater.update(SingleHypothesis(prediction, measurement))
        omega = post.metadata["omega"]
        w_star = fo.ci(np.ravel(measurement.state_vector), measurement.covar,
                       np.ravel(prediction.state_vector), prediction.covar,
                       criterion=criterion).weights[0]
        assert omega == pytest.approx(w_star, abs=1e-8)
        # Stone Soup's own innovation covariance divides by 1 - omega (ZeroDivisionError at
        # omega = 1, where the optimum often is): give it the measurement prediction
        ref = ChernoffUpdater(measurement_model=None, omega=omega).update(
            SingleHypothesis(prediction, measurement,
                             measurement_prediction=post.hypothesis.measurement_prediction))
        assert type(post) is type(ref) is GaussianStateUpdate
        assert post.timestamp == ref.timestamp and post.hypothesis.prediction is prediction
        scale = np.abs(ref.covar).max()
        np.testing.assert_allclose(post.covar, ref.covar, rtol=0, atol=1e-10 * scale)
        np.testing.assert_allclose(post.state_vector, ref.state_vector, rtol=1e-10,
                                   atol=1e-10 * np.abs(ref.state_vector).max())
        assert 0 <= post.metadata["gap"] <= 1e-9 * abs(post.metadata["fusion_result"].objective)
        if 1e-3 < omega < 1 - 1e-3:  # same innovation covariance where no clipping applies
            mp = updater.predict_measurement(prediction, measurement.measurement_model)
            mp_ref = ChernoffUpdater(measurement_model=None, omega=omega).predict_measurement(
                prediction, measurement.measurement_model)
            np.testing.assert_allclose(mp.covar, mp_ref.covar, rtol=1e-6)
            np.testing.assert_array_equal(mp.state_vector, mp_ref.state_vector)


@pytest.mark.parametrize("criterion", ["trace", "logdet"])
def test_optimal_updater_is_never_worse_than_omega_one_half(criterion):
    rng = np.random.default_rng(10)
    f = {"trace": np.trace, "logdet": lambda P: np.linalg.slogdet(P)[1]}[criterion]
    updater = fs.OptimalChernoffUpdater(measurement_model=None, criterion=criterion,
                                        backend="closed-form")
    gains = []
    for _ in range(200):
        measurement, prediction = _pair(rng, n=int(rng.integers(2, 7)), log10_range=(-2, 2))
        opt = updater.update(SingleHypothesis(prediction, measurement))
        half = ChernoffUpdater(measurement_model=None).update(
            SingleHypothesis(prediction, measurement))
        assert f(opt.covar) <= f(half.covar) + 1e-9 * abs(f(half.covar))
        gains.append(f(half.covar) - f(opt.covar))
    assert np.median(gains) > 0  # and strictly better on most pairs


def test_optimal_updater_keeps_the_prediction_type_and_clips_the_innovation_weight():
    rng = np.random.default_rng(11)
    measurement, _ = _pair(rng)
    # a birth-like prediction far less certain than the measurement: omega* = 1
    prediction = TaggedWeightedGaussianStatePrediction(
        np.zeros((4, 1)), 1e6 * np.eye(4), weight=0.25, tag="t", timestamp=T0)
    updater = fs.OptimalChernoffUpdater(measurement_model=None)
    post = updater.update(SingleHypothesis(prediction, measurement))
    assert post.metadata["omega"] == 1.0
    assert (type(post).__name__, post.weight, post.tag) == (
        "TaggedWeightedGaussianStateUpdate", 0.25, "t")
    np.testing.assert_allclose(post.covar, measurement.covar, rtol=1e-12)
    w = fs.INNOVATION_OMEGA_MIN
    mp = updater.predict_measurement(prediction, measurement.measurement_model)
    np.testing.assert_allclose(mp.covar, measurement.covar / w + prediction.covar / (1 - w))
    np.testing.assert_array_equal(
        updater.predict_measurement(prediction, measurement.measurement_model,
                                    measurement_noise=False).covar, prediction.covar)


def test_optimal_updater_refusals():
    with pytest.raises(fo.FusionInputError, match="criterion"):
        fs.OptimalChernoffUpdater(measurement_model=None, criterion="det")
    with pytest.raises(fo.FusionInputError, match="backend"):
        fs.OptimalChernoffUpdater(measurement_model=None, backend="cplex")
    _, prediction = _pair(np.random.default_rng(12))
    updater = fs.OptimalChernoffUpdater(measurement_model=None)
    position_model = LinearGaussian(4, [0, 2], np.eye(2))
    with pytest.raises(fo.FusionInputError, match="noise_covar"):
        updater.predict_measurement(prediction, position_model)
    plain = Detection(np.zeros((4, 1)), timestamp=T0,
                      measurement_model=LinearGaussian(4, [0, 1, 2, 3], np.eye(4)))
    with pytest.raises(fo.FusionInputError, match="no Gaussian summary"):
        updater.update(SingleHypothesis(prediction, plain))


# --- StoneSoupTracker ------------------------------------------------------------------------

def _stone_soup_tracker():
    model = LinearGaussian(4, (0, 2), np.eye(2))
    cv = CombinedLinearGaussianTransitionModel([ConstantVelocity(0.01)] * 2)
    updater = KalmanUpdater(model)
    associator = GNNWith2DAssignment(
        DistanceHypothesiser(KalmanPredictor(cv), updater, Mahalanobis(), missed_distance=3))
    initiator = MultiMeasurementInitiator(
        prior_state=GaussianState(np.zeros(4), np.diag([0.0, 1.0, 0.0, 1.0])),
        measurement_model=model, deleter=UpdateTimeStepsDeleter(2),
        data_associator=associator, updater=updater, min_points=2)
    return MultiTargetTracker(initiator=initiator, deleter=UpdateTimeStepsDeleter(3),
                              detector=None, data_associator=associator, updater=updater)


def _scans(steps=25, seed=0):
    """Seeded detections of two crossing targets with clutter, from Stone Soup's simulators."""
    truth = MultiTargetGroundTruthSimulator(
        transition_model=CombinedLinearGaussianTransitionModel([ConstantVelocity(0.01)] * 2,
                                                               seed=seed),
        initial_state=GaussianState(np.zeros(4), np.eye(4), timestamp=T0), number_steps=steps,
        birth_rate=0, death_probability=0, seed=seed + 1,
        preexisting_states=[np.array([-10.0, 1, -10, 1]), np.array([-10.0, 1, 10, -1])])
    sim = SimpleDetectionSimulator(
        groundtruth=truth, measurement_model=LinearGaussian(4, (0, 2), np.eye(2), seed=seed + 2),
        meas_range=np.array([[-30, 30], [-30, 30]]), detection_probability=0.9,
        clutter_rate=1.0, seed=seed + 3)
    return [(t, set(d)) for t, d in sim]


def _by_mean(means):
    return means[np.lexsort(means.T[::-1])]


def test_adapter_gives_the_wrapped_trackers_tracks_step_by_step():
    scans = _scans()
    tracker = _stone_soup_tracker()
    reference = copy.deepcopy(tracker)
    reference.detector = scans  # the reference runs as Stone Soup runs it: iterating
    node = fs.StoneSoupTracker(tracker, ndim=4, epoch=T0, node="s1")
    seen = {}
    for k, ((time, tracks), scan) in enumerate(zip(reference, scans, strict=True)):
        e = node.step(scan)
        assert (e.time, e.node, e.n) == (k * 1.0, "s1", 4)
        ref = [t for t in tracks if t.timestamp == time]
        assert len(e) == len(ref)
        if ref:
            ref_means = np.array([np.ravel(t.state_vector) for t in ref])
            np.testing.assert_allclose(_by_mean(e.means), _by_mean(ref_means), rtol=1e-12)
        for i, m, P in zip(e.ids, e.means, e.covs, strict=True):  # ids follow the track
            sid = node.track_ids.track_id(i)
            track = next(tr for tr in tracker.tracks if tr.id == sid)
            np.testing.assert_array_equal(np.ravel(track.state_vector), m)
            np.testing.assert_allclose(P, track.covar, rtol=1e-15, atol=1e-15)
            assert seen.setdefault(sid, i) == i
        assert e.ids.tolist() == sorted(e.ids.tolist())
    assert len(seen) >= 2


def test_adapter_replays_an_iterable_and_a_tracker_with_its_detector():
    scans = _scans(steps=15, seed=5)
    live = _stone_soup_tracker()
    live.detector = scans
    node = fs.StoneSoupTracker(live, ndim=4, epoch=T0)
    steps = [node.step(None) for _ in scans]
    with pytest.raises(StopIteration):
        node.step(None)
    # a record of (time, tracks) holding the final Tracks: each step reports their states then
    # (from their first state on, which precedes the step the initiator confirmed them at)
    record = [(T0 + timedelta(seconds=k), set(live.tracks)) for k in range(len(scans))]
    replay = fs.StoneSoupTracker(record, ndim=4, epoch=T0).run([None] * len(scans))
    for a, b in zip(steps[-3:], replay[-3:], strict=True):
        live_ids = {i for i in a.ids if node.track_ids.track_id(i) in {t.id for t in live.tracks}}
        assert len(b) == len(live_ids)
        np.testing.assert_array_equal(_by_mean(b.means), _by_mean(
            a.means[np.isin(a.ids, list(live_ids))]))


def test_adapter_empty_steps_float_times_and_refusals():
    node = fs.StoneSoupTracker(_stone_soup_tracker(), ndim=4, epoch=T0, node=3)
    e = node.step((2.5, []))
    assert (len(e), e.n, e.time, e.node) == (0, 4, 2.5, 3)
    with pytest.raises(fo.FusionInputError, match="scan must be"):
        node.step([T0, []])
    with pytest.raises(fo.FusionInputError, match="scan is None"):
        node.step(None)
    with pytest.raises(fo.FusionInputError, match="tracker must be"):
        fs.StoneSoupTracker(object(), ndim=4)
    with pytest.raises(fo.FusionInputError, match="ndim"):
        fs.StoneSoupTracker([], ndim=0)
    with pytest.raises(fo.FusionInputError, match="update_tracker"):
        fs.StoneSoupTracker([], ndim=4).step((T0, []))
    wrong = fs.StoneSoupTracker([(T0, {Track(_states(np.random.default_rng(0), 1))})], ndim=6)
    with pytest.raises(fo.FusionInputError, match="dimension 4"):
        wrong.step(None)


def test_a_network_mixes_a_stone_soup_tracker_and_one_of_ours():
    """A Stone Soup MultiTargetTracker and our KalmanFilter track one target from the same
    simulated detections (Stone Soup's state order [x, vx, y, vy]); a processing node
    associates and fuses their reports at every step, as fo.bci fuses the two alone."""
    from trackers.kalman import KalmanFilter
    from trackers.models import LinearGaussian as OurModel

    truth = MultiTargetGroundTruthSimulator(
        transition_model=CombinedLinearGaussianTransitionModel([ConstantVelocity(0.01)] * 2,
                                                               seed=1),
        initial_state=GaussianState(np.zeros(4), np.eye(4), timestamp=T0), number_steps=12,
        birth_rate=0, death_probability=0, seed=2,
        preexisting_states=[np.array([0.0, 1.0, 0.0, 0.5])])
    scans = [(t, set(d)) for t, d in SimpleDetectionSimulator(
        groundtruth=truth, measurement_model=LinearGaussian(4, (0, 2), np.eye(2), seed=3),
        meas_range=np.array([[-30, 30], [-30, 30]]), detection_probability=1.0,
        clutter_rate=0.0, seed=4)]
    cv = np.array([[1.0, 1.0], [0.0, 1.0]])
    q = 0.01 * np.kron(np.eye(2), [[1 / 3, 1 / 2], [1 / 2, 1]])  # ConstantVelocity(0.01)
    model = OurModel(np.kron(np.eye(2), cv), q, np.array([[1.0, 0, 0, 0], [0, 0, 1, 0]]),
                     np.eye(2))
    ours = KalmanFilter(model, np.zeros(4), np.diag([10.0, 1.0, 10.0, 1.0]), name="kf")
    fusion = fo.ProcessingNode(["ss", "kf"], method="bci", threshold=5.0, dims=[0, 2])
    net = fo.Network({"ss": fs.StoneSoupTracker(_stone_soup_tracker(), ndim=4, epoch=T0),
                      "kf": ours}, {"fusion": fusion})
    fused_steps = 0
    for k, (time, detections) in enumerate(scans):
        z = np.array([np.ravel(d.state_vector) for d in detections]).reshape(-1, 2)
        out = net.step({"ss": (time, detections), "kf": z}, time=k * 1.0)
        assert len(out["fusion"]) >= 1 and out["fusion"].time == k * 1.0
        if len(out["ss"]) == 1:  # both report the target: one fused track, as fo.bci
            ref = fo.bci(np.concatenate([out["ss"].means, out["kf"].means]),
                         np.concatenate([out["ss"].covs, out["kf"].covs]))
            assert len(out["fusion"]) == 1
            np.testing.assert_allclose(out["fusion"].means[0], ref.mean, rtol=1e-12)
            np.testing.assert_allclose(out["fusion"].covs[0], ref.cov, rtol=1e-12)
            fused_steps += 1
    assert fused_steps >= 8


def _gaussian(mean, t=T0):
    return GaussianState(np.array(mean).reshape(-1, 1), np.eye(len(mean)), timestamp=t)


@pytest.mark.parametrize("call, match", [
    (lambda: fs.to_estimates([GaussianState(np.array([[1 + 1j], [2]]), np.eye(2),
                                            timestamp=T0)]), "got complex numbers"),
    (lambda: fs.to_datetime(1e12), "beyond the dates a datetime holds"),
    (lambda: fs.to_states(fo.Estimates(np.zeros((1, 2)), np.eye(2)[None], time=1e15)),
     "beyond the dates"),
    (lambda: fs.StoneSoupTracker([(T0, [_gaussian([1.0, 2.0])])], ndim=2).step(),
     "must be Stone Soup Tracks, got \\['GaussianState'\\]"),
    (lambda: fs.StoneSoupTracker([T0], ndim=2).step(), "must be \\(time, tracks\\) pairs"),
    (lambda: fs.to_estimates([Track([_gaussian([1.0, 2.0])], id=["x"])]), "must be hashable"),
    (lambda: fs.StoneSoupTracker([(T0, [Track([_gaussian([1.0, 2.0])], id=["x"])])],
                                 ndim=2).step(), "must be hashable"),  # fuzz of 2026-11-29
    (lambda: fs.to_estimates([Track([_gaussian([1.0, 2.0])])], track_ids={}),
     "track_ids must be a TrackIds"),
    (lambda: fs.TrackIds().track_id(1.7), "int_id must be an integer"),
    (lambda: fs.StoneSoupTracker([], ndim=2, node=[1]), "node must be hashable"),
    (lambda: fs.StoneSoupTracker([], ndim=10**12), "^ndim = 1000000000000: ")])
def test_adapter_refuses_by_name(call, match):
    """Regression: a complex mean lost its imaginary part (a ComplexWarning only); the
    others raised OverflowError, AttributeError, TypeError or silently made '1' of 1.7."""
    with pytest.raises(fo.FusionInputError, match=match):
        call()


def test_optimal_chernoff_updater_takes_a_measurement_of_another_time():
    """Regression: a prediction and a measurement of different timestamps were refused
    ("the states of one Estimates share one time"); ChernoffUpdater fuses them, and the
    update is stamped with the measurement's time (its docstring)."""
    model = LinearGaussian(ndim_state=2, mapping=(0, 1), noise_covar=np.eye(2))
    up = fs.OptimalChernoffUpdater(measurement_model=model)
    pred = GaussianStatePrediction(np.array([[1.0], [2.0]]), 2 * np.eye(2), timestamp=T0)
    later = T0 + timedelta(seconds=1)
    det = GaussianDetection(np.array([[1.5], [2.5]]), np.eye(2), timestamp=later,
                            measurement_model=model)
    update = up.update(SingleHypothesis(pred, det))
    assert update.timestamp == later and update.metadata["omega"] == 1.0  # I beats 2 I
    np.testing.assert_array_equal(update.state_vector.ravel(), [1.5, 2.5])


def test_a_tracker_whose_track_has_no_gaussian_state_is_refused_as_such():
    """Fuzz K7: a Track of plain States (no covariance) was refused as "the mean of track
    't5' must be an array of real numbers, got objects", read before the Gaussian summary
    was checked; now the summary's own message, as fuse_states gives it."""
    track = Track([State(np.array([[1.0], [2.0]]), timestamp=T0)], id="t5")
    with pytest.raises(fo.FusionInputError, match=r"tracks\[0\] \(State\) has no Gaussian "
                                                  r"summary \(mean and covar\)"):
        fs.StoneSoupTracker([(T0, [track])], 2).step()

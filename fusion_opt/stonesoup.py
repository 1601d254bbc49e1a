"""Stone Soup interoperability: optimal, certified covariance intersection for Stone Soup users.

Stone Soup's covariance intersection (`ChernoffUpdater`, `CovarianceIntersection`) fuses with a
fixed weight (omega = 0.5, or equal weights). Here the weight is the optimum of the CI program
of fusion-opt, with its certificate:

    fused = fuse_states([state_a, state_b, ...], method="bci")      # a GaussianState
    updater = OptimalChernoffUpdater(measurement_model=None)        # for ChernoffUpdater(...)
    node_tracker = StoneSoupTracker(stone_soup_tracker, ndim=4)     # .step(scan) -> Estimates

How the two libraries' conventions map onto each other:

- A state is one row of `Estimates`: its `mean` (Stone Soup's (n, 1) column) is a row of
  `means` (m, n), its `covar` the matching (n, n) of `covs`. Any state with `mean` and `covar`
  converts (GaussianState and its Prediction, Update and Detection kinds, ParticleState, ...);
  a Track gives its latest state. The order of state components is Stone Soup's, unchanged
  (e.g. [x, vx, y, vy] for two ConstantVelocity models).
- Time: `Estimates.time = (timestamp - epoch).total_seconds()` and back
  `timestamp = epoch + timedelta(seconds=time)`, exact to the microsecond within 2**32 s
  (136 years) of the epoch. The default epoch is EPOCH = 1970-01-01 (naive); give an aware
  epoch for aware timestamps. No timestamp (None) is time None.
- Track ids: Stone Soup's `Track.id` (a string) and the integer ids of `Estimates` are bound
  one-to-one by a `TrackIds`, in the order first seen.
- ChernoffUpdater's omega is the weight of the measurement, `hypothesis.measurement`
  (covariance A), and 1 - omega that of the prediction (B): D = (omega A^-1 +
  (1 - omega) B^-1)^-1. Fusing the stack [measurement, prediction], omega = weights[0].

This module imports Stone Soup (the optional extra `fusion-opt[stonesoup]`); `import fusion_opt`
does not.
"""

from __future__ import annotations

import itertools
from collections.abc import Hashable, Iterable, Mapping
from datetime import datetime, timedelta
from functools import lru_cache

import numpy as np

try:
    from stonesoup.base import Property
    from stonesoup.types.prediction import MeasurementPrediction
    from stonesoup.types.state import GaussianState
    from stonesoup.types.track import Track
    from stonesoup.types.update import Update
    from stonesoup.updater.base import Updater
except ImportError as exc:  # pragma: no cover - depends on the install
    raise ImportError("fusion_opt.stonesoup needs Stone Soup: pip install "
                      "'fusion-opt[stonesoup]'") from exc

from . import BACKENDS, FusionInputError, FusionResult, fuse
from .estimates import Estimates
from .limits import estimates_bytes, fits
from .validation import hashable, is_integer, is_real, real_array, safe_repr, short_repr

__all__ = ["EPOCH", "OptimalChernoffUpdater", "StoneSoupTracker", "TrackIds", "fuse_states",
           "to_datetime", "to_estimates", "to_seconds", "to_states", "to_tracks"]

_INT64_MAX = 2**63 - 1
EPOCH = datetime(1970, 1, 1)
CRITERIA = ("trace", "logdet")
# The Chernoff innovation covariance A / (1 - omega) + B / omega is unbounded at omega = 0 or 1,
# where the optimal weight often lies (one estimate better in every direction); it is evaluated
# at omega clipped to [INNOVATION_OMEGA_MIN, 1 - INNOVATION_OMEGA_MIN]. The update is not.
INNOVATION_OMEGA_MIN = 1e-3


# --- time ------------------------------------------------------------------------------------

def to_seconds(timestamp: datetime | None, epoch: datetime = EPOCH) -> float | None:
    """Seconds from `epoch` to `timestamp` (a datetime), as Estimates.time; None stays None."""
    if timestamp is None:
        return None
    if not isinstance(timestamp, datetime):
        raise FusionInputError(f"timestamp must be a datetime or None, got {safe_repr(timestamp)}")
    _check_epoch(epoch)
    try:
        return (timestamp - epoch) / timedelta(seconds=1)
    except TypeError:
        raise FusionInputError(f"timestamp {timestamp} and epoch {epoch} must both be naive or "
                               f"both timezone-aware") from None


def to_datetime(seconds: float | None, epoch: datetime = EPOCH) -> datetime | None:
    """The datetime `seconds` after `epoch` (Estimates.time to a Stone Soup timestamp)."""
    if seconds is None:
        return None
    if not is_real(seconds) or isinstance(seconds, float | np.floating) \
            and not np.isfinite(seconds):
        raise FusionInputError(f"seconds must be a finite real number or None, got "
                               f"{safe_repr(seconds)}")
    _check_epoch(epoch)
    try:  # an int beyond float64 (10**400) overflows in float(), as a date beyond 9999 does
        return epoch + timedelta(seconds=float(seconds))
    except OverflowError:
        raise FusionInputError(f"seconds = {short_repr(seconds)} after {epoch} is beyond "
                               "the dates a datetime holds (years 1 to 9999)") from None


def _check_epoch(epoch) -> None:
    if not isinstance(epoch, datetime):
        raise FusionInputError(f"epoch must be a datetime, got {safe_repr(epoch)}")


# --- track ids -------------------------------------------------------------------------------

class TrackIds:
    """A one-to-one map between Stone Soup track ids (strings) and Estimates ids (integers).

    A Stone Soup id seen first gets the next free integer (0, 1, 2, ..., one past the largest
    bound, or the smallest unbound one once that would pass int64, which Estimates' ids
    are); an integer seen first (an Estimates made by fusion-opt, turned into Tracks) gets
    the string str(id), and must fit int64. Keep one TrackIds per source to keep its ids
    persistent across steps and round trips.
    """

    def __init__(self):
        self._to_int: dict[Hashable, int] = {}
        self._to_str: dict[int, Hashable] = {}
        self._next = 0

    def int_id(self, track_id: Hashable) -> int:
        """The integer bound to Stone Soup id `track_id` (bound now if new)."""
        if not hashable(track_id):
            raise FusionInputError(f"track id {safe_repr(track_id)} must be hashable (a string)")
        if track_id not in self._to_int:
            free = self._next if self._next <= _INT64_MAX else \
                next(i for i in itertools.count() if i not in self._to_str)
            self._bind(track_id, free)
        return self._to_int[track_id]

    def track_id(self, int_id: int) -> Hashable:
        """The Stone Soup id bound to integer `int_id` (str(int_id), bound now, if new)."""
        if not is_integer(int_id):
            raise FusionInputError(f"int_id must be an integer, got {safe_repr(int_id)}")
        int_id = int(int_id)
        if not -_INT64_MAX - 1 <= int_id <= _INT64_MAX:  # fuzz I9: refused later, unnamed
            raise FusionInputError(f"int_id must fit in a signed 64-bit integer (as Estimates' "
                                   f"ids), got {safe_repr(int_id)}")
        if int_id not in self._to_str:
            self._bind(str(int_id), int_id)
        return self._to_str[int_id]

    def _bind(self, track_id: Hashable, int_id: int) -> None:
        if track_id in self._to_int:
            raise FusionInputError(f"track id {safe_repr(track_id)} is already bound to "
                                   f"{self._to_int[track_id]}, not {int_id}")
        self._to_int[track_id], self._to_str[int_id] = int_id, track_id
        self._next = max(self._next, int_id + 1)

    def __contains__(self, track_id: Hashable) -> bool:
        """Whether Stone Soup id `track_id` is bound (an unhashable one never is: `int_id`
        refuses it by name, where a dict lookup raised TypeError: fuzz of 2026-11-29)."""
        return hashable(track_id) and track_id in self._to_int

    def __len__(self) -> int:
        return len(self._to_int)


# --- conversions -----------------------------------------------------------------------------

def _gaussian_summary(items, name: str, one_time: bool = True):
    """(means (m, n), covs (m, n, n), common timestamp, the Tracks or None) of a sequence of
    states or of Tracks; their timestamps may differ only if not one_time (then the first
    is returned)."""
    if isinstance(items, str | bytes | Mapping) or not isinstance(items, Iterable):
        raise FusionInputError(f"{name} must be a sequence of Stone Soup states or Tracks, got "
                               f"{type(items).__name__}")
    items = list(items)
    if not items:
        raise FusionInputError(f"{name} holds no state")
    tracks = [isinstance(x, Track) for x in items]
    if any(tracks) and not all(tracks):
        raise FusionInputError(f"{name} mixes Tracks and states: give one kind")
    states = [_latest(x, f"{name}[{i}]") if tracks[0] else x for i, x in enumerate(items)]
    means, covs = zip(*(_mean_covar(s, f"{name}[{i}]") for i, s in enumerate(states)),
                      strict=True)
    for i, (m, P) in enumerate(zip(means, covs, strict=True)):
        if m.shape != means[0].shape or P.shape != (m.size, m.size):
            raise FusionInputError(f"{name}[{i}] has mean {m.shape} and covar {P.shape}; "
                                   f"{name}[0] has mean {means[0].shape}")
    stamps = [s.timestamp for s in states]
    for i, t in enumerate(stamps):
        if one_time and t != stamps[0]:
            raise FusionInputError(f"{name}[{i}] is at {t} but {name}[0] at {stamps[0]}: the "
                                   f"states of one Estimates share one time")
    return np.stack(means), np.stack(covs), stamps[0], items if tracks[0] else None


def _latest(track: Track, name: str):
    if len(track) == 0:
        raise FusionInputError(f"{name} is a Track with no state")
    return track.state


def _mean_covar(state, name: str) -> tuple[np.ndarray, np.ndarray]:
    if not (hasattr(state, "mean") and hasattr(state, "covar")):
        raise FusionInputError(f"{name} ({type(state).__name__}) has no Gaussian summary "
                               f"(mean and covar)")
    mean = real_array(state.mean, f"{name}'s mean")  # a complex one is refused, not cut
    covar = real_array(state.covar, f"{name}'s covar")
    if mean.ndim not in (1, 2) or (mean.ndim == 2 and mean.shape[1] != 1):
        raise FusionInputError(f"{name} has a mean of shape {mean.shape}, not (n, 1)")
    return mean.reshape(-1), covar


def to_estimates(items, *, epoch: datetime = EPOCH, node: Hashable | None = None,
                 track_ids: TrackIds | None = None) -> Estimates:
    """Stone Soup states, or Tracks, all at one timestamp, as one `Estimates`.

    Row i is items[i] (a Track: its latest state). ids: for Tracks, `track_ids.int_id(track.id)`
    (a fresh TrackIds if None: 0, 1, ... in the given order); for states 0, 1, ....
    time = seconds from `epoch` to the common timestamp; node is stored as given. Covariances
    are symmetrised, as every Estimates' are: one asymmetric by rounding (a Kalman update
    leaves a few ulps) comes back as (P + P^T) / 2.
    """
    means, covs, stamp, tracks = _gaussian_summary(items, "items")
    if track_ids is not None and not isinstance(track_ids, TrackIds):
        raise FusionInputError(f"track_ids must be a TrackIds, got {type(track_ids).__name__}")
    if tracks is not None:
        track_ids = TrackIds() if track_ids is None else track_ids
        ids = [track_ids.int_id(t.id) for t in tracks]
    else:
        ids = None
    try:
        return Estimates(means, covs, ids, to_seconds(stamp, epoch), node)
    except FusionInputError as exc:
        raise FusionInputError(f"items: {exc}") from None


def to_states(estimates: Estimates, *, epoch: datetime = EPOCH) -> list[GaussianState]:
    """One GaussianState per estimate (mean as an (n, 1) StateVector), stamped
    epoch + estimates.time."""
    _check_estimates(estimates)
    stamp = to_datetime(estimates.time, epoch)
    return [GaussianState(np.array(m).reshape(-1, 1), np.array(P), timestamp=stamp)
            for m, P in zip(estimates.means, estimates.covs, strict=True)]


def to_tracks(estimates: Estimates, *, epoch: datetime = EPOCH,
              track_ids: TrackIds | None = None) -> list[Track]:
    """One single-state Track per estimate, with Stone Soup id `track_ids.track_id(id)`
    (str(id) if track_ids is None)."""
    if track_ids is not None and not isinstance(track_ids, TrackIds):
        raise FusionInputError(f"track_ids must be a TrackIds, got {type(track_ids).__name__}")
    ids = track_ids if track_ids is not None else TrackIds()
    return [Track([s], id=ids.track_id(i))
            for s, i in zip(to_states(estimates, epoch=epoch), estimates.ids, strict=True)]


def _check_estimates(estimates) -> None:
    if not isinstance(estimates, Estimates):
        raise FusionInputError(f"estimates must be a fusion_opt.Estimates, got "
                               f"{type(estimates).__name__}")


# --- fusion ----------------------------------------------------------------------------------

def fuse_states(states, method: str = "bci", criterion: str = "trace",
                backend: str | None = None, **method_args) -> GaussianState:
    """Fuse Stone Soup states (or Tracks' latest states) at one timestamp with any rule of
    `fusion_opt.fuse` (its method, criterion, backend and method_args, e.g. p_detect and chi
    for "mbci"; backend None is fuse's default, and the rules without weights take none);
    states[i] is node i.

    Returns a GaussianState at the common timestamp whose attribute `metadata` holds
    "weights" (N,), "gap" (the optimality certificate) and "fusion_result" (the FusionResult).
    """
    means, covs, stamp, _ = _gaussian_summary(states, "states")
    try:
        Estimates(means, covs)
    except FusionInputError as exc:
        raise FusionInputError(f"states: {exc}") from None
    result = fuse(means, covs, method=method, criterion=criterion, backend=backend,
                  **method_args)
    fused = GaussianState(np.array(result.mean).reshape(-1, 1), np.array(result.cov),
                          timestamp=stamp)
    fused.metadata = {"weights": np.array(result.weights), "gap": result.gap,
                      "fusion_result": result}
    return fused


class OptimalChernoffUpdater(Updater):
    """Stone Soup's ChernoffUpdater with the optimal weight: a drop-in for
    `ChernoffUpdater(measurement_model=..., omega=...)` in the "tracks as measurements" pattern
    (e.g. inside a PHDUpdater, with Tracks2GaussianDetectionFeeder), without omega.

    For each hypothesis it fuses the measurement (a, A) and the prediction (b, B) by pairwise CI
    with the weight omega that minimises tr D ("trace") or log det D ("logdet"),
    D = (omega A^-1 + (1 - omega) B^-1)^-1, as ChernoffUpdater(omega=omega) would. The update's
    attribute `metadata` holds "omega" (ChernoffUpdater's convention: the measurement's weight),
    "gap" (the certificate: the criterion at omega exceeds its minimum by at most gap) and
    "fusion_result". The innovation covariance of `predict_measurement` is ChernoffUpdater's,
    A / (1 - omega) + B / omega, at the optimal omega of (A = the measurement model's
    noise_covar, B) clipped to [INNOVATION_OMEGA_MIN, 1 - INNOVATION_OMEGA_MIN].
    """

    criterion: str = Property(default="trace", doc='"trace" or "logdet": what omega minimises')
    backend: str = Property(default="newton", doc="A weight solver of fusion_opt.BACKENDS "
                            '(default the exact compiled one; "clarabel" is the conic '
                            'reference)')

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        if self.criterion not in CRITERIA:
            raise FusionInputError(f"criterion must be one of {CRITERIA}, got "
                                   f"{safe_repr(self.criterion)}")
        if self.backend not in BACKENDS:
            raise FusionInputError(f"backend must be one of {BACKENDS}, got "
                                   f"{safe_repr(self.backend)}")

    def fuse_pair(self, measurement, prediction) -> FusionResult:
        """Optimal CI of [measurement, prediction] (states with mean and covar)."""
        means, covs, _, _ = _gaussian_summary([measurement, prediction],
                                              "[measurement, prediction]", one_time=False)
        return fuse(means, covs, method="ci", criterion=self.criterion, backend=self.backend)

    @lru_cache  # noqa: B019 - as ChernoffUpdater: a repeated (prediction, model) is not re-solved
    def predict_measurement(self, predicted_state, measurement_model=None,
                            measurement_noise=True, **kwargs):
        """ChernoffUpdater's measurement prediction (the predicted state, cross covariance B)
        with the innovation covariance at the optimal omega of (noise_covar, B)."""
        measurement_model = self._check_measurement_model(measurement_model)
        B = real_array(predicted_state.covar, "predicted_state.covar")  # complex: refused
        if measurement_noise:
            A = real_array(measurement_model.noise_covar, "measurement_model.noise_covar")
            if A.shape != B.shape:
                raise FusionInputError(
                    f"measurement_model.noise_covar {A.shape} must match the predicted covar "
                    f"{B.shape}: Chernoff fusion takes whole states as measurements")
            omega = fuse(np.zeros((2, len(B))), np.stack([A, B]), method="ci",
                         criterion=self.criterion, backend=self.backend).weights[0]
            omega = float(np.clip(omega, INNOVATION_OMEGA_MIN, 1 - INNOVATION_OMEGA_MIN))
            innovation = A / (1 - omega) + B / omega
        else:
            innovation = B
        return MeasurementPrediction.from_state(
            predicted_state, predicted_state.state_vector, innovation,
            timestamp=predicted_state.timestamp, cross_covar=predicted_state.covar)

    def update(self, hypothesis, force_symmetric_covariance=False, **kwargs):
        """The CI posterior of hypothesis.measurement and hypothesis.prediction at the optimal
        omega, of the prediction's Update type, stamped with the measurement's time."""
        if hypothesis.measurement_prediction is None:
            hypothesis.measurement_prediction = self.predict_measurement(
                hypothesis.prediction,
                measurement_model=hypothesis.measurement.measurement_model, **kwargs)
        result = self.fuse_pair(hypothesis.measurement, hypothesis.prediction)
        covar = np.array(result.cov)
        if force_symmetric_covariance:
            covar = 0.5 * (covar + covar.T)
        posterior = Update.from_state(
            hypothesis.prediction, state_vector=np.array(result.mean).reshape(-1, 1),
            covar=covar, hypothesis=hypothesis, timestamp=hypothesis.measurement.timestamp)
        posterior.metadata = {"omega": float(result.weights[0]), "gap": result.gap,
                              "fusion_result": result}
        return posterior


# --- a Stone Soup tracker in a fusion-opt network --------------------------------------------

class StoneSoupTracker:
    """A Stone Soup tracker as a network tracker: `.step(scan) -> Estimates`.

    `tracker` is a Stone Soup Tracker (any with `update_tracker`, e.g. MultiTargetTracker,
    PointProcessMultiTargetTracker), or any iterable of (time, tracks): a Stone Soup tracker
    with its detector, a generator, a list of recorded steps. What `scan` is:

    - None: advance the iterable by one step (its next (time, tracks));
    - (time, detections): the detections of one step, given to
      `tracker.update_tracker(time, detections)`; time is a datetime or seconds from `epoch`.

    The step's Estimates hold the tracks with a state at the step's time (that state; a track
    the tracker holds but did not carry to this time is not reported), ordered by id. Ids are
    persistent per Stone Soup track (`track_ids` maps them back; tracks new in one step are
    numbered in the order of their means, so a seeded run gives the same ids), time is
    seconds from `epoch` and node is `node`. `ndim` is the state dimension n (reported even on
    a step without tracks). State components keep Stone Soup's order. A step past the end of
    the iterable raises StopIteration.

    `track_ids` keeps every Stone Soup id it has seen, so that an id stays persistent and
    maps back however long its track was away: about 170 bytes per track ever seen (soak of
    2026-11-29: 40,000 steps of 5 tracks alive, one new every 2 steps, 84 B a step). A Stone
    Soup Track keeps every state it was given, which grows faster unless its tracker trims it.
    """

    def __init__(self, tracker, ndim: int, *, epoch: datetime = EPOCH,
                 node: Hashable | None = None):
        if not (hasattr(tracker, "update_tracker") or isinstance(tracker, Iterable)):
            raise FusionInputError(f"tracker must be a Stone Soup Tracker or an iterable of "
                                   f"(time, tracks), got {type(tracker).__name__}")
        if not is_integer(ndim) or ndim < 1:
            raise FusionInputError(f"ndim must be an integer >= 1, got {safe_repr(ndim)}")
        fits(f"ndim = {safe_repr(ndim)}", estimates_bytes(1, ndim))  # as a step's Estimates
        _check_epoch(epoch)
        if node is not None and not hashable(node):
            raise FusionInputError(f"node must be hashable (a name), got {safe_repr(node)}")
        self.tracker, self.ndim, self.epoch, self.node = tracker, int(ndim), epoch, node
        self.track_ids = TrackIds()
        self._steps = None

    def step(self, scan=None) -> Estimates:
        """The tracks after one step of the wrapped tracker (see the class for `scan`)."""
        time, tracks = self._advance(scan)
        return self._estimates(time, tracks)

    def run(self, scans) -> list[Estimates]:
        """[step(scan) for scan in scans]."""
        return [self.step(scan) for scan in scans]

    def _advance(self, scan):
        if scan is None:
            if self._steps is None:
                try:
                    self._steps = iter(self.tracker)
                except (AttributeError, TypeError) as exc:
                    raise FusionInputError(f"scan is None but the tracker cannot be iterated "
                                           f"by itself ({exc}); give (time, detections)") from None
            step = next(self._steps)
            if not (isinstance(step, tuple | list) and len(step) == 2
                    and isinstance(step[1], Iterable)):
                raise FusionInputError(f"the tracker's steps must be (time, tracks) pairs, got "
                                       f"{type(step).__name__}")
            return step
        if not (isinstance(scan, tuple) and len(scan) == 2):
            raise FusionInputError(f"scan must be None or (time, detections), got "
                                   f"{type(scan).__name__}")
        if not hasattr(self.tracker, "update_tracker"):
            raise FusionInputError("scan (time, detections) needs a Stone Soup tracker with "
                                   "update_tracker; this one only iterates: give scan None")
        time, detections = scan
        if isinstance(detections, str | bytes) or not isinstance(detections, Iterable):
            raise FusionInputError(f"scan's detections must be a collection of Stone Soup "
                                   f"detections, got {type(detections).__name__}")
        if not isinstance(time, datetime):
            time = to_datetime(time, self.epoch)
        return self.tracker.update_tracker(time, set(detections))

    def _estimates(self, time, tracks) -> Estimates:
        seconds = to_seconds(time, self.epoch)
        tracks = list(tracks)
        if not all(isinstance(t, Track) for t in tracks):
            raise FusionInputError("the tracker's tracks must be Stone Soup Tracks, got "
                                   f"{sorted({type(t).__name__ for t in tracks})}")
        states = {t: s for t in tracks if (s := _state_at(t, time)) is not None}
        if not states:
            return Estimates.empty(self.ndim, seconds, self.node)
        # every state's Gaussian summary checked (with its message) before any is used
        means, covs, _, _ = _gaussian_summary(list(states.values()), "tracks")
        if means.shape[1] != self.ndim:
            raise FusionInputError(f"the tracker's states have dimension {means.shape[1]}, "
                                   f"not ndim = {self.ndim}")
        row = dict(zip(states, range(len(states)), strict=True))
        new = [t for t in states if t.id not in self.track_ids]  # numbered by their means
        for t in sorted(new, key=lambda t: tuple(means[row[t]])):
            self.track_ids.int_id(t.id)
        alive = sorted(states, key=lambda t: self.track_ids.int_id(t.id))
        order = [row[t] for t in alive]
        means, covs = means[order], covs[order]
        ids = [self.track_ids.int_id(t.id) for t in alive]
        try:
            return Estimates(means, covs, ids, seconds, self.node)
        except FusionInputError as exc:
            raise FusionInputError(f"tracks: {exc}") from None


def _state_at(track: Track, time):
    """The state of `track` at `time`, or None (searched from the latest state back)."""
    for state in reversed(track.states):
        if state.timestamp == time:
            return state
        try:
            if time is None or state.timestamp is None or state.timestamp < time:
                return None
        except TypeError:  # a timezone-aware datetime and a naive one do not compare
            raise FusionInputError(f"track {safe_repr(track.id)} has a state at "
                                   f"{safe_repr(state.timestamp)}, "
                                   f"which does not compare with the step's time {safe_repr(time)} "
                                   "(one timezone-aware, the other naive?)") from None
    return None

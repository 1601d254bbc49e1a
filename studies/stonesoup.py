"""Stone Soup's multi-sensor setting: Stone Soup trackers per sensor, their tracks fused at a
processing node by Stone Soup's ChernoffUpdater (omega = 0.5) and by fusion-opt's rules.

Everything before the processing node is Stone Soup's, as in its track-to-track fusion
examples: a MultiTargetGroundTruthSimulator of targets whose paths cross (nearly constant
velocity, ConstantVelocity noise q per axis), one SimpleDetectionSimulator per sensor (its
own detection probability p_D, clutter points per scan uniform over `region`, position
noise sd per axis) and one MultiTargetTracker per sensor (Kalman filter, Mahalanobis gate,
global nearest neighbour, MultiMeasurementInitiator, deletion after `max_misses` scans
without an update; on a miss a track carries its prediction). Each tracker runs through
`fusion_opt.stonesoup.StoneSoupTracker`, so every scan gives each sensor's tracks as
`fusion_opt.Estimates`. States are Stone Soup's [x, vx, y, vy] in m and m/s; position is
components (0, 2).

The processing node, at every scan: `fo.associate` groups the sensors' tracks by position
(fusion.association, fusion.threshold; once per scan, so every rule fuses the same groups);
a group of fewer than fusion.min_sources sensors is dropped, a group of one is passed on
as it is, and each rule of [rules] fuses every group of two or more, given as Stone Soup
GaussianStates:

- "chernoff": Stone Soup's own ChernoffUpdater(omega), as in its tracks-as-measurements
  pattern: the first member (in sensor order) is the prediction (b, B) and each further
  member, a GaussianDetection with its covariance as the noise of an identity
  LinearGaussian model (what Tracks2GaussianDetectionFeeder makes), updates it in turn:
  D = (omega A^-1 + (1 - omega) B^-1)^-1, d = D (omega A^-1 a + (1 - omega) B^-1 b).
  For three sensors omega = 0.5 gives them weights 1/4, 1/4, 1/2.
- "optimal-chernoff": fusion_opt.stonesoup.OptimalChernoffUpdater in the same pattern:
  each pairwise update at the omega minimising tr D or log det D.
- "bci", "mbci", "fast-ci", "ifci", "naive": `fusion_opt.stonesoup.fuse_states` on all
  members at once (`fo.fuse`); BCI minimises tr or log det of (sum_i w_i P_i^-1)^-1 over
  the simplex; MBCI does so with P_i / s_i, s_i = p_i + (1 - p_i) chi prod_{j != i}
  (p_j + (1 - p_j) chi), p the members' p_D and chi = 1 / fusion.growth.

The node keeps no state between scans (as fusion-opt's ProcessingNode): it fuses each
scan's tracks afresh. Stone Soup's own example instead feeds the tracks, as detections, to
a GM-PHD tracker whose updater is the ChernoffUpdater, so its fused tracks also carry the
node's own prediction; that is not reproduced here.

Scores per row (each sensor's tracker, then each rule), over the scans of one run (c =
metrics.cutoff, p = metrics.order, position only):

- OSPA and GOSPA (alpha = 2) by trackers.metrics, scan means; beside them, Stone Soup's
  OSPAMetric and GOSPAMetric (measure Euclidean on (0, 2)) on the same states. GOSPA
  agrees; Stone Soup's OSPA assigns on d_c, not on d_c^p, so with p > 1 its value is >=
  ours where the two assignments differ. The agreement is measured and reported.
- cardinality error: scan mean of |n_estimated - n_targets|;
- matched pairs: at each scan trackers.metrics.match (the optimal assignment on d_c,
  pairs closer than c); position RMSE = sqrt(mean ||e_pos||^2) and ANEES = mean 4-dof
  NEES (m - x)^T P^-1 (m - x) over all matched pairs of the run; "in band": whether the
  run's ANEES lies in the chi-square 95% interval of the mean of K independent chi2(4)
  values (K the run's matched pairs; the pairs of one track are correlated in time, so
  the band is nominal);
- fused trace: mean of tr P (full state, the criterion of the trace rules) over the
  groups of two or more (a sensor's row: its members of those groups);
- time per fusion: the wall time of one rule call on one group, from the members'
  GaussianStates to the fused state (Stone Soup objects built inside it count), the
  median over the run's groups (robust to the pauses of a shared machine), after
  fo.warmup of the compiled kernels.

Paired differences (rule - baseline over the same runs, Student t) against
fusion.baseline, Stone Soup's ChernoffUpdater at omega = 0.5. Run FIGURE_RUN also returns
the scenario (truth, detections, tracks, the fused estimates of figure.rule) for the
scenario figure; the OSPA-over-time figure is drawn from every run's per-scan OSPA.

Seeding: Stone Soup draws from numpy's global RandomState unless each simulator and model
is given its own seed. Every random part here gets one (an `np.random.RandomState` inside
Stone Soup), drawn from the run's SeedSequence; the global state is neither used nor
touched, so a run depends on (seed, run index) only.
"""

from __future__ import annotations

import itertools
import time as clock
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib import colormaps
from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
from stonesoup.deleter.time import UpdateTimeStepsDeleter
from stonesoup.hypothesiser.distance import DistanceHypothesiser
from stonesoup.initiator.simple import MultiMeasurementInitiator
from stonesoup.measures import Euclidean, Mahalanobis
from stonesoup.metricgenerator.ospametric import GOSPAMetric, OSPAMetric
from stonesoup.models.measurement.linear import LinearGaussian
from stonesoup.models.transition.linear import (
    CombinedLinearGaussianTransitionModel,
    ConstantVelocity,
)
from stonesoup.predictor.kalman import KalmanPredictor
from stonesoup.simulator.simple import MultiTargetGroundTruthSimulator, SimpleDetectionSimulator
from stonesoup.tracker.simple import MultiTargetTracker
from stonesoup.types.detection import Clutter, GaussianDetection
from stonesoup.types.hypothesis import SingleHypothesis
from stonesoup.types.prediction import GaussianStatePrediction
from stonesoup.types.state import GaussianState, State
from stonesoup.updater.chernoff import ChernoffUpdater
from stonesoup.updater.kalman import KalmanUpdater

import fusion_opt as fo
from fusion_opt import stonesoup as fs
from fusion_opt.association import METHODS as ASSOCIATIONS
from fusion_opt.validation import safe_repr
from trackers import kalman, metrics
from trackers.scenarios import check_reach

from . import config as configs
from . import plotting, stats
from .plotting import new_figure
from .runner import FIGURE_RUN

START = datetime(2024, 1, 1)
POSITION = (0, 2)  # Stone Soup's [x, vx, y, vy]
NDIM = 4
RULE_METHODS = ("chernoff", "optimal-chernoff", "bci", "mbci", "fast-ci", "ifci", "naive")
WITH_CRITERION = ("optimal-chernoff", "bci", "mbci")
SOLVED = ("optimal-chernoff", "bci", "mbci")  # rules whose weights a backend solves
SENSOR_COLUMNS = ("ospa", "gospa", "card_err", "rmse", "anees", "in_band", "trace")
RULE_COLUMNS = (*SENSOR_COLUMNS, "us_per_fusion")
HEADERS = {"ospa": "OSPA (m)", "gospa": "GOSPA (m)", "card_err": "card. error",
           "rmse": "pos. RMSE (m)", "anees": "ANEES (4-dof)", "in_band": "runs in band",
           "trace": "fused tr P", "us_per_fusion": "µs / fusion"}
PAIRED = ("ospa", "gospa", "rmse", "trace")
NAMED = ("rules",)  # a --config's [rules] replaces the default's whole (config.load)


# ---------------------------------------------------------------------- configuration

@dataclass(frozen=True)
class Scenario:
    """One run's setting (every field is one of [scenario]). targets: [x, vx, y, vy] at
    t = 0 (m, m/s); the defaults meet near the origin at t = 40 s. Per sensor: p_detect,
    clutter_rate (points per scan, uniform over region [[x0, x1], [y0, y1]] in m) and
    noise_sd [sd_x, sd_y] (position noise sd per axis, m: unequal axes make the sensors'
    covariances differ in shape, as a radar's range and cross-range errors do). q: the
    ConstantVelocity noise diffusion coefficient per axis (m^2 / s^3) of the truth and of
    the trackers. gate: the trackers' Mahalanobis missed distance; min_points: detections
    that confirm a track; max_misses: scans without an update before a track is deleted."""

    steps: int = 80
    dt: float = 1.0
    q: float = 0.001
    targets: tuple = ((-40.0, 1.0, -20.0, 0.5), (-40.0, 1.0, 20.0, -0.5), (0.0, 0.0, -40.0, 1.0))
    p_detect: tuple = (0.95, 0.7, 0.85)
    clutter_rate: tuple = (1.0, 5.0, 2.0)
    noise_sd: tuple = ((1.0, 3.0), (3.0, 1.0), (2.0, 2.0))
    region: tuple = ((-80.0, 80.0), (-80.0, 80.0))
    gate: float = 3.0
    min_points: int = 3
    max_misses: int = 5

    def __post_init__(self):
        _positive_fields(self, ("steps", "dt", "q", "gate", "min_points", "max_misses"))
        if not self.targets or any(len(x) != NDIM for x in self.targets):
            raise ValueError(f"targets must be a non-empty list of [x, vx, y, vy], got "
                             f"{safe_repr(self.targets)}")
        if len(self.p_detect) < 2:
            raise ValueError(f"p_detect must give two or more sensors, got "
                             f"{safe_repr(self.p_detect)}")
        for name in ("clutter_rate", "noise_sd"):
            if len(getattr(self, name)) != len(self.p_detect):
                raise ValueError(f"{name} must give one value per sensor ({len(self.p_detect)}"
                                 f", as p_detect), got {safe_repr(getattr(self, name))}")
        for name, ok, rule in (("p_detect", lambda v: 0 < v <= 1, "in (0, 1]"),
                               ("clutter_rate", lambda v: v >= 0, ">= 0"),
                               ("noise_sd", lambda v: len(v) == 2 and 0 < min(v)
                                and max(v) <= 1e100, "[sd_x, sd_y], each in (0, 1e100]")):
            for i, v in enumerate(getattr(self, name)):
                if not ok(v):
                    raise ValueError(f"{name}[{i}] must be {rule}, got {safe_repr(v)}")
        if not self.steps * self.dt <= 1e10:  # Stone Soup's timestamps: datetimes, to 9999
            raise ValueError(f"steps x dt must be at most 1e10 s, got {self.steps} x "
                             f"{safe_repr(self.dt)}")
        if len(self.region) != 2 or any(len(r) != 2 or not r[0] < r[1] for r in self.region):
            raise ValueError(f"region must be [[x0, x1], [y0, y1]] with x0 < x1 and y0 < y1, "
                             f"got {safe_repr(self.region)}")
        sd = min(min(v) for v in self.noise_sd)
        for i, (x, vx, y, vy) in enumerate(self.targets):
            if not np.isfinite([x, vx, y, vy]).all():
                raise ValueError(f"targets[{i}] must be finite, got {safe_repr(self.targets[i])}")
            check_reach(f"targets[{i}]", [x, y], float(np.hypot(vx, vy)), self.steps * self.dt,
                        sd, "the smallest noise_sd")

    @property
    def sensors(self) -> int:
        return len(self.p_detect)


def _positive_fields(obj, names) -> None:
    for name in names:
        if not getattr(obj, name) > 0:
            raise ValueError(f"{name} must be > 0, got {safe_repr(getattr(obj, name))}")


def scenario(config: dict) -> Scenario:
    """The [scenario] table as a Scenario (checked by it)."""
    return configs.build(Scenario, config["scenario"], "scenario")


def sensor_names(sc: Scenario) -> list[str]:
    return [f"sensor {s + 1}" for s in range(sc.sensors)]


def check(config: dict) -> None:
    """Refuse, with a ConfigError naming the field, anything in config this study cannot
    run: called on the whole merged configuration before anything runs."""
    configs.fields(config, "", ("runs", "seed", "backend", "scenario", "fusion", "rules",
                                "metrics", "figure"))
    configs.run_fields(config)
    sc = scenario(config)
    points = sum(sc.clutter_rate) + sc.sensors * len(sc.targets)  # detections per scan
    # one scan's Stone Soup detections (about 2 KB each) and every scan's positions kept
    configs.fits("scenario.clutter_rate and steps",
                 2048.0 * points + 16.0 * 4 * sc.steps * points)
    configs.backend("backend", config["backend"], nodes=sc.sensors)
    _check_track_covariances(sc)
    _check_rules(config["rules"], sensor_names(sc))
    fusion = configs.fields(config["fusion"], "fusion", ("association", "threshold",
                                                         "min_sources", "growth", "baseline"))
    configs.choice("fusion.association", fusion["association"], ASSOCIATIONS)
    configs.number("fusion.threshold", fusion["threshold"], above=0)
    configs.integer("fusion.min_sources", fusion["min_sources"], low=1, high=sc.sensors)
    configs.number("fusion.growth", fusion["growth"], low=1,
                   why="MBCI's chi^-1, the covariance growth over a missed detection")
    configs.choice("fusion.baseline", fusion["baseline"], list(config["rules"]))
    metrics = configs.table(config["metrics"], "metrics", {
        "cutoff": lambda w, x: configs.number(w, x, above=0),
        "order": lambda w, x: configs.number(w, x, low=1)})
    if not abs(metrics["order"] * np.log10(metrics["cutoff"])) <= 100:  # OSPA sums them
        raise configs.ConfigError(                                   # to this power
            f"metrics.cutoff ^ metrics.order must lie in 1e-100..1e100, got "
            f"{safe_repr(metrics['cutoff'])} ^ {safe_repr(metrics['order'])}")
    figure = configs.fields(config["figure"], "figure", ("rule",))
    configs.choice("figure.rule", figure["rule"], list(config["rules"]))


def _check_track_covariances(sc: Scenario) -> None:
    """A track's covariances at each sensor, exact (trackers.kalman, Joseph's form): started
    at the measurement's covariance in position and the initiator's velocity variance 1,
    updated at min_points - 1 more scans, then predicted through max_misses - 1 missed
    ones (at max_misses it is deleted before it is reported); each must be one a fusion
    accepts (fuzz H11: q = 1e30 gave velocity variances 1e29 times the positions' and
    failed every run at the fusion)."""
    interval = timedelta(seconds=sc.dt)
    A, Q = _cv(sc.q).matrix(time_interval=interval), _cv(sc.q).covar(time_interval=interval)
    H = np.eye(NDIM)[list(POSITION)]
    for s, sd in enumerate(sc.noise_sd):
        R = np.diag(np.square(sd))
        P, covs = H.T @ R @ H + np.diag([0.0, 1.0, 0.0, 1.0]), []
        updates = min(sc.min_points - 1, sc.steps)  # a run has no more scans than steps
        for k in range(updates + min(sc.max_misses - 1, sc.steps)):  # (10^7: fuzz N9)
            P = kalman.predict(np.zeros(NDIM), P, A, Q)[1]
            if k < updates:
                P = kalman.update(np.zeros(NDIM), P, np.zeros(2), H, R)[1]
            covs.append(P)
        configs.fusable(f"scenario.q = {sc.q:.3g}, dt = {sc.dt:.3g}, noise_sd[{s}] = "
                        f"{list(sd)}: a track's covariance over min_points updates and "
                        f"max_misses predictions is not one a fusion accepts", covs)


def _check_rules(rules, sensors: list[str]) -> None:
    """[rules]: name -> {method, criterion (optimal-chernoff, bci, mbci), omega (chernoff)}."""
    if not isinstance(rules, dict) or not rules:
        raise configs.ConfigError(f"[rules] must name at least one fusion rule, got "
                                  f"{safe_repr(rules)}")
    for name, spec in rules.items():
        where = f"rules.{name}"
        if name in sensors:
            raise configs.ConfigError(f"{where}: a rule may not be named as a sensor's row "
                                      f"{sensors}")
        configs.fields(spec, where, ("method",), ("criterion", "omega"))
        method = configs.choice(f"{where}.method", spec["method"], RULE_METHODS)
        needs = {"criterion"} if method in WITH_CRITERION else set()
        needs |= {"omega"} if method == "chernoff" else set()
        configs.fields(spec, where, ("method", *sorted(needs)))
        if "criterion" in needs:
            configs.choice(f"{where}.criterion", spec["criterion"], fs.CRITERIA)
        if "omega" in needs:
            configs.number(f"{where}.omega", spec["omega"], above=0, high=1,
                           why="Stone Soup's weight of the measurement")
            if spec["omega"] == 1:
                raise configs.ConfigError(f"{where}.omega must be < 1: Stone Soup's "
                                          "innovation covariance divides by 1 - omega")


# --------------------------------------------------------------------------- scenario

@dataclass(frozen=True)
class Scan:
    """One scan: time (s from the start), the targets' states (m, 4), and per sensor its
    detections split into target-originated (k, 2) and clutter (l, 2) positions, and its
    tracker's Estimates."""

    time: float
    truth: np.ndarray
    detections: tuple[np.ndarray, ...]
    clutter: tuple[np.ndarray, ...]
    tracks: tuple[fo.Estimates, ...]


@dataclass(frozen=True)
class Simulation:
    """The scans of one run."""

    scenario: Scenario
    scans: tuple[Scan, ...] = field(repr=False)


def simulate(sc: Scenario, seed: np.random.SeedSequence) -> Simulation:
    """Simulate and track one run of sc, every random part seeded from `seed`."""
    seeds = iter(int(s) for s in seed.generate_state(2 + 2 * sc.sensors))
    truth = _truth(sc, seeds)
    feeds = itertools.tee(truth, 1 + sc.sensors)  # lock-step copies of one ground truth
    sensors = [_sensor(sc, s, feeds[1 + s], seeds) for s in range(sc.sensors)]
    trackers = [fs.StoneSoupTracker(_tracker(sc, sim.measurement_model), ndim=NDIM,
                                    epoch=START, node=name)
                for sim, name in zip(sensors, sensor_names(sc), strict=True)]
    streams = [iter(sim) for sim in sensors]
    scans = []
    for now, paths in feeds[0]:
        sensor_scans = [next(stream) for stream in streams]
        scans.append(Scan(
            time=(now - START).total_seconds(),
            truth=np.array([np.ravel(p[-1].state_vector) for p in paths]).reshape(-1, NDIM),
            detections=tuple(_positions(d for d in dets if not isinstance(d, Clutter))
                             for _, dets in sensor_scans),
            clutter=tuple(_positions(d for d in dets if isinstance(d, Clutter))
                          for _, dets in sensor_scans),
            tracks=tuple(tr.step(scan) for tr, scan in zip(trackers, sensor_scans,
                                                           strict=True))))
    return Simulation(sc, tuple(scans))


def _cv(q: float, seed: int | None = None) -> CombinedLinearGaussianTransitionModel:
    return CombinedLinearGaussianTransitionModel([ConstantVelocity(q), ConstantVelocity(q)],
                                                 seed=seed)


def _truth(sc: Scenario, seeds) -> MultiTargetGroundTruthSimulator:
    return MultiTargetGroundTruthSimulator(
        transition_model=_cv(sc.q, next(seeds)),
        initial_state=GaussianState(np.zeros(NDIM), np.eye(NDIM), timestamp=START),
        timestep=timedelta(seconds=sc.dt), number_steps=sc.steps,
        birth_rate=0.0, death_probability=0.0,
        preexisting_states=[np.array(x, dtype=float) for x in sc.targets], seed=next(seeds))


def _sensor(sc: Scenario, s: int, truth, seeds) -> SimpleDetectionSimulator:
    model = LinearGaussian(ndim_state=NDIM, mapping=POSITION,
                           noise_covar=np.diag(np.square(sc.noise_sd[s])), seed=next(seeds))
    return SimpleDetectionSimulator(
        groundtruth=truth, measurement_model=model, meas_range=np.array(sc.region),
        detection_probability=sc.p_detect[s], clutter_rate=sc.clutter_rate[s],
        seed=next(seeds))


def _tracker(sc: Scenario, model: LinearGaussian) -> MultiTargetTracker:
    """A Kalman multi-target tracker of one sensor (filters draw no random numbers), its
    update in Joseph's form (as trackers.kalman's: P - K S K^T lost positive definiteness
    at dt = 1e6, fuzz H16)."""
    predictor = KalmanPredictor(_cv(sc.q))
    updater = KalmanUpdater(model, use_joseph_cov=True)
    hypothesiser = DistanceHypothesiser(predictor, updater, Mahalanobis(),
                                        missed_distance=sc.gate)
    associator = GNNWith2DAssignment(hypothesiser)
    initiator = MultiMeasurementInitiator(
        prior_state=GaussianState(np.zeros(NDIM), np.diag([0.0, 1.0, 0.0, 1.0])),
        measurement_model=model, deleter=UpdateTimeStepsDeleter(2), data_associator=associator,
        updater=updater, min_points=sc.min_points)
    return MultiTargetTracker(initiator=initiator, deleter=UpdateTimeStepsDeleter(sc.max_misses),
                              detector=None, data_associator=associator, updater=updater)


def _positions(detections) -> np.ndarray:
    """(k, 2) measured positions, in a fixed order (Stone Soup gives a set)."""
    z = np.array([np.ravel(d.state_vector) for d in detections]).reshape(-1, 2)
    return z[np.lexsort(z.T[::-1])] if len(z) else z


# ---------------------------------------------------------------------------- fusion

Rule = Callable[[list, tuple], GaussianState]  # (members' GaussianStates, sensor indices)


def make_rules(config: dict) -> dict[str, Rule]:
    """{rule name: fuse(states, sensors) -> GaussianState} of [rules] (module docstring)."""
    p, growth, backend = (scenario(config).p_detect, config["fusion"]["growth"],
                          config["backend"])
    rules = {}
    for name, spec in config["rules"].items():
        method = spec["method"]
        if method == "chernoff":
            rules[name] = _sequential(ChernoffUpdater(measurement_model=None,
                                                      omega=spec["omega"]))
        elif method == "optimal-chernoff":
            rules[name] = _sequential(fs.OptimalChernoffUpdater(
                measurement_model=None, criterion=spec["criterion"], backend=backend))
        else:
            rules[name] = _fuse_states(method, spec.get("criterion", "trace"),
                                       backend if method in SOLVED else None, p, growth)
    return rules


def _sequential(updater) -> Rule:
    """Stone Soup's tracks-as-measurements pattern: the first member is the prediction and
    each further one, as a GaussianDetection with an identity LinearGaussian model of its
    own covariance (as Tracks2GaussianDetectionFeeder makes it), updates it in turn."""
    def fuse(states, sensors):
        first = states[0]
        fused = GaussianStatePrediction(first.state_vector, first.covar,
                                        timestamp=first.timestamp)
        for s in states[1:]:
            z = GaussianDetection(s.state_vector, s.covar, timestamp=s.timestamp,
                                  measurement_model=LinearGaussian(
                                      NDIM, list(range(NDIM)), np.asarray(s.covar)))
            fused = updater.update(SingleHypothesis(fused, z))
        return fused
    return fuse


def _fuse_states(method, criterion, backend, p_detect, growth) -> Rule:
    """fusion_opt.stonesoup.fuse_states on all members; MBCI with the members' p_D."""
    def fuse(states, sensors):
        extra = {"p_detect": [p_detect[s] for s in sensors], "growth": growth} \
            if method == "mbci" else {}
        return fs.fuse_states(states, method=method, criterion=criterion, backend=backend,
                              **extra)
    return fuse


@dataclass
class Fused:
    """One row's estimates over the scans: per scan (means (k, 4), covs (k, 4, 4)), the
    trace of each fused group of two or more, and the seconds of each fusion."""

    means: list = field(default_factory=list)
    covs: list = field(default_factory=list)
    traces: list = field(default_factory=list)
    seconds: list = field(default_factory=list)


def fuse_run(config: dict, sim: Simulation) -> dict[str, Fused]:
    """Every rule's fused estimates at every scan of sim (module docstring), and each
    sensor's tracks with the traces of its members of the groups of two or more."""
    sc, fusion = sim.scenario, config["fusion"]
    names = sensor_names(sc)
    rules = make_rules(config)
    rows = {name: Fused() for name in [*names, *rules]}
    for scan in sim.scans:
        reports = {s: e for s, e in enumerate(scan.tracks)}
        groups = [g for g in fo.associate(reports, fusion["threshold"], fusion["association"],
                                          dims=list(POSITION))
                  if len(g) >= fusion["min_sources"]]
        for s, name in enumerate(names):
            rows[name].means.append(scan.tracks[s].means)
            rows[name].covs.append(scan.tracks[s].covs)
        out = {name: ([], []) for name in rules}
        stamp = fs.to_datetime(scan.time, START)
        for g in groups:
            if len(g) == 1:
                for name in rules:
                    out[name][0].append(g.means[0])
                    out[name][1].append(g.covs[0])
                continue
            for s, P in zip(g.sources, g.covs, strict=True):
                rows[names[s]].traces.append(float(np.trace(P)))
            states = [GaussianState(m.reshape(-1, 1), P, timestamp=stamp)
                      for m, P in zip(g.means, g.covs, strict=True)]
            for name, rule in rules.items():
                t0 = clock.perf_counter()
                state = rule(states, g.sources)
                rows[name].seconds.append(clock.perf_counter() - t0)
                mean, cov = np.ravel(state.state_vector).astype(float), np.asarray(state.covar,
                                                                                  float)
                rows[name].traces.append(float(np.trace(cov)))
                out[name][0].append(mean)
                out[name][1].append(cov)
        for name, (means, covs) in out.items():
            rows[name].means.append(np.array(means).reshape(-1, NDIM))
            rows[name].covs.append(np.array(covs).reshape(-1, NDIM, NDIM))
    return rows


# ---------------------------------------------------------------------------- scoring

def scores(config: dict, sim: Simulation, row: Fused) -> dict:
    """The scores of one row over the scans of one run (module docstring), with its OSPA
    per scan and its agreement with Stone Soup's metric generators."""
    c, p = config["metrics"]["cutoff"], config["metrics"]["order"]
    pos = list(POSITION)
    ospa, gospa, matched, truths, nees = [], [], [], [], []
    for scan, means, covs in zip(sim.scans, row.means, row.covs, strict=True):
        X, Y = means[:, pos], scan.truth[:, pos]
        errors = metrics.set_errors(X, Y, c, p, 2.0)
        ospa.append(errors.ospa)
        gospa.append(errors.gospa)
        est, targets = errors.rows, errors.cols
        matched.append(X[est])
        truths.append(Y[targets])
        if len(est):
            nees.append(metrics.nees(means[est], scan.truth[targets], covs[est]))
    matched, truths = np.concatenate(matched), np.concatenate(truths)
    card = np.abs(metrics.cardinality_error([len(m) for m in row.means],
                                            [len(scan.truth) for scan in sim.scans]))
    nees = np.concatenate(nees) if nees else np.zeros(0)
    ss_ospa, ss_gospa = stonesoup_metrics(sim, row, c, p)
    anees = float(nees.mean()) if nees.size else float("nan")
    band = metrics.anees_bounds(NDIM, nees.size) if nees.size else (np.nan, np.nan)
    out = {"ospa": float(np.mean(ospa)), "gospa": float(np.mean(gospa)),
           "card_err": float(np.mean(card)),
           "rmse": metrics.rmse(matched, truths) if len(matched) else np.nan,
           "anees": anees,
           "in_band": float(band[0] <= anees <= band[1]) if nees.size else np.nan,
           "matched": int(nees.size),
           "trace": float(np.mean(row.traces)) if row.traces else float("nan"),
           "ss_ospa": float(np.mean(ss_ospa)), "ss_gospa": float(np.mean(ss_gospa)),
           "ospa_max_diff": float(np.max(np.abs(np.subtract(ss_ospa, ospa)))),
           "gospa_max_diff": float(np.max(np.abs(np.subtract(ss_gospa, gospa)))),
           "ospa_scans_differ": int(np.sum(np.abs(np.subtract(ss_ospa, ospa)) > 1e-9 * c)),
           "ospa_t": ospa,
           # NaN where the rule fused nothing in the run (shown as "-"): a missing key
           # ended the report in a KeyError (fuzz H1: steps = 1, fusion.threshold = 0.01)
           "us_per_fusion": 1e6 * float(np.median(row.seconds)) if row.seconds else np.nan}
    return out


def stonesoup_metrics(sim: Simulation, row: Fused, c: float, p: float):
    """Stone Soup's OSPAMetric and GOSPAMetric (measure Euclidean on the position) of the
    row's estimates against the truth, per scan: two lists of floats."""
    measure = Euclidean(mapping=POSITION)
    tracks, truths = [], []
    for scan, means in zip(sim.scans, row.means, strict=True):
        stamp = fs.to_datetime(scan.time, START)
        tracks += [State(m.reshape(-1, 1), timestamp=stamp) for m in means]
        truths += [State(x.reshape(-1, 1), timestamp=stamp) for x in scan.truth]
    ospa = OSPAMetric(c=c, p=p, measure=measure).compute_over_time(
        tracks, list(range(len(tracks))), truths, list(range(len(truths))))
    gospa = GOSPAMetric(c=c, p=p, measure=measure).compute_over_time(
        tracks, list(range(len(tracks))), truths, list(range(len(truths))))
    ospa = ospa.value if isinstance(ospa.value, list) else [ospa]
    gospa = gospa.value if isinstance(gospa.value, list) else [gospa]
    return [float(m.value) for m in ospa], [float(m.value["distance"]) for m in gospa]


def warm(config: dict, sensors: int) -> None:
    """Load the compiled kernels of every fused shape, so no fusion is timed with them."""
    for criterion in fs.CRITERIA:
        for N in range(2, sensors + 1):
            fo.warmup(NDIM, N, criterion, config["backend"])


def run_one(config: dict, index: int, seed: np.random.SeedSequence) -> tuple[dict, dict]:
    """(scores of every row, figure data or None) of one run; the figure data is run
    FIGURE_RUN's."""
    sc = scenario(config)
    warm(config, sc.sensors)
    sim = simulate(sc, seed)
    rows = fuse_run(config, sim)
    result = {name: scores(config, sim, row) for name, row in rows.items()}
    return result, figure_data(config, sim, rows) if index == FIGURE_RUN else None


def figure_data(config: dict, sim: Simulation, rows: dict[str, Fused]) -> dict:
    """What the scenario figure draws of one run: the true paths (J, T, 2), per sensor its
    target detections and clutter (rows (x, y)) and its tracks as rows (scan, id, x, y),
    and the fused positions of figure.rule as rows (scan, x, y)."""
    pos = list(POSITION)
    truth = np.stack([scan.truth[:, pos] for scan in sim.scans], axis=1)
    sensors = []
    for s in range(sim.scenario.sensors):
        tracks = [np.column_stack([np.full(len(e), k), e.ids, e.means[:, pos]])
                  for k, e in enumerate(scan.tracks[s] for scan in sim.scans)]
        sensors.append({"detections": np.concatenate([scan.detections[s] for scan in sim.scans]),
                        "clutter": np.concatenate([scan.clutter[s] for scan in sim.scans]),
                        "tracks": np.concatenate(tracks)})
    fused = rows[config["figure"]["rule"]].means
    return {"truth": truth, "sensors": sensors,
            "fused": np.concatenate([np.column_stack([np.full(len(m), k), m[:, pos]])
                                     for k, m in enumerate(fused)])}


# ----------------------------------------------------------------------------- report

def report(config: dict, results: list[dict], out: Path, figure: dict | None) -> None:
    """stonesoup.md, its tables as stonesoup.csv, stonesoup_paired.csv and
    stonesoup_agreement.csv, the OSPA-over-time figure from every run, and the scenario
    figure of run FIGURE_RUN (if stored)."""
    out = Path(out)
    sc = scenario(config)
    sensors, rules = sensor_names(sc), list(config["rules"])
    summary = stats.summarise(results, sensors, SENSOR_COLUMNS)
    summary |= stats.summarise(results, rules, RULE_COLUMNS)
    paired = _paired(config, results)
    stats.write_rows(out / "stonesoup.csv", [
        {"row": row, **{f"{c}_{s}": v for c in RULE_COLUMNS
                        for s, v in zip(("mean", "low", "high"),
                                        summary[row].get(c, (None,) * 3), strict=True)}}
        for row in [*sensors, *rules]])
    stats.write_rows(out / "stonesoup_paired.csv", [
        {"rule": rule, "measure": col, **d} for rule, cols in paired.items()
        for col, d in cols.items()])
    stats.write_rows(out / "stonesoup_agreement.csv", _agreement_rows(results))
    lines = _markdown(config, summary, paired, results)
    _ospa_figure(config, results, out / "stonesoup_ospa.png")
    lines += ["", "![OSPA over time per rule](stonesoup_ospa.png)"]
    if figure is not None:
        _scenario_figure(config, figure, out / "stonesoup_scenario.png")
        lines += ["", f"![run {FIGURE_RUN}: scenario](stonesoup_scenario.png)"]
    (out / "stonesoup.md").write_text("\n".join(lines) + "\n")


def _paired(config, results) -> dict:
    """{rule: {measure: stats.paired(rule, baseline)}} for every rule but the baseline."""
    base = config["fusion"]["baseline"]
    return {rule: {col: stats.paired([r[rule][col] for r in results],
                                     [r[base][col] for r in results]) for col in PAIRED}
            for rule in config["rules"] if rule != base}


def _markdown(config, summary, paired, results) -> list[str]:
    sc, m, fusion = scenario(config), config["metrics"], config["fusion"]
    n, base = len(results), fusion["baseline"]
    matched = int(np.median([r[base]["matched"] for r in results]))
    band = "none: the median run matched no estimate to a target"
    if matched:
        low, high = metrics.anees_bounds(NDIM, matched)
        band = f"[{low:.3g}, {high:.3g}]"
    sensors = "; ".join(f"{name}: p_D {p}, clutter {lam} / scan, sd_x {sd[0]} m, sd_y {sd[1]} m"
                        for name, p, lam, sd in zip(sensor_names(sc), sc.p_detect,
                                                    sc.clutter_rate, sc.noise_sd, strict=True))
    rules = "; ".join(f"{name}: {_describe(spec)}" for name, spec in config["rules"].items())
    lines = [f"# Stone Soup's multi-sensor setting ({n} runs, seed {config['seed']}, backend "
             f"{config['backend']})", "",
             f"{len(sc.targets)} crossing targets, {sc.steps} scans of {sc.dt} s; {sensors}. "
             f"Association {fusion['association']} under {fusion['threshold']} m, groups of "
             f"fewer than {fusion['min_sources']} sensors dropped; MBCI growth "
             f"{fusion['growth']}. Rules: {rules}.", "",
             f"Mean and 95% interval over runs. OSPA and GOSPA (alpha = 2) on position, c = "
             f"{m['cutoff']} m, p = {m['order']}; card. error: mean |n_est - n_true|; pos. RMSE "
             "and ANEES (mean 4-dof NEES) over the estimates matched to a target (closer than "
             f"c); runs in band: share of runs whose ANEES lies in the 95% chi-square band of "
             f"its matched count (the median run's band: {band}; nominal, the NEES of one "
             "track are correlated in time); fused tr P: mean trace of the full covariance "
             "(m^2 and m^2/s^2) over the groups of two or more (a sensor: its members of "
             "those groups); µs / fusion: median wall time of one rule call on one group, "
             "Stone Soup states in and out. " + stats.INTERVAL_NOTE, "",
             "| row | " + " | ".join(HEADERS[c] for c in RULE_COLUMNS) + " |",
             "|---" * (len(RULE_COLUMNS) + 1) + "|"]
    for row, cols in summary.items():
        cells = [stats.fmt(*cols[c]) if c in cols else "-" for c in RULE_COLUMNS]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    lines += ["", f"Paired differences, rule minus {base} (negative: lower than {base}), "
              "mean [95% Student t], and the share of runs where the rule is lower:", "",
              "| rule | OSPA | GOSPA | pos. RMSE | fused tr P | fused tr P (%) |",
              "|---|---|---|---|---|---|"]
    base_trace = np.mean([r[base]["trace"] for r in results])
    for rule, cols in paired.items():
        cells = [f"{stats.fmt(d['mean_diff'], d['low'], d['high'], 3)} ({stats.fmt_share(d)})"
                 if d["runs"] else "-" for d in cols.values()]  # no run defines it: "-"
        t = cols["trace"]
        pct = stats.fmt(*(100 * np.array([t["mean_diff"], t["low"], t["high"]]) / base_trace),
                        3)
        lines.append(f"| {rule} | " + " | ".join(cells) + f" | {pct} |")
    lines += ["", *_agreement(config, results)]
    return lines


def _describe(spec: dict) -> str:
    method = spec["method"]
    if method == "chernoff":
        return f"Stone Soup's ChernoffUpdater, omega = {spec['omega']}"
    if method == "optimal-chernoff":
        return f"OptimalChernoffUpdater ({spec['criterion']})"
    return f"fuse_states {method}" + (f" ({spec['criterion']})" if "criterion" in spec else "")


def _agreement_rows(results) -> list[dict]:
    """Per row: our OSPA and GOSPA and Stone Soup's OSPAMetric and GOSPAMetric (means over
    the runs of the run means), and how often and by how much they differ over every scan
    of every run."""
    rows = []
    for row in results[0]:
        v = [r[row] for r in results]
        rows.append({"row": row, **{c: float(np.mean([x[c] for x in v]))
                                    for c in ("ospa", "ss_ospa", "gospa", "ss_gospa")},
                     "scans_ospa_differs": sum(x["ospa_scans_differ"] for x in v),
                     "scans": sum(len(x["ospa_t"]) for x in v),
                     "max_ospa_diff": max(x["ospa_max_diff"] for x in v),
                     "max_gospa_diff": max(x["gospa_max_diff"] for x in v)})
    return rows


def _agreement(config, results) -> list[str]:
    """The table of `_agreement_rows`, with its note."""
    m = config["metrics"]
    lines = [f"Our metrics beside Stone Soup's metric generators on the same estimates (c = "
             f"{m['cutoff']} m, p = {m['order']}; run means, mean over runs). GOSPAMetric "
             "assigns on d_c^p, as ours; OSPAMetric assigns on d_c, so with p > 1 it can "
             "exceed ours at the scans where the two assignments differ:", "",
             "| row | OSPA ours | OSPA Stone Soup | GOSPA ours | GOSPA Stone Soup | scans where "
             "OSPA differs | max OSPA diff (m) | max GOSPA diff (m) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in _agreement_rows(results):
        lines.append(
            f"| {r['row']} | " + " | ".join(f"{r[c]:.6g}" for c in
                                            ("ospa", "ss_ospa", "gospa", "ss_gospa"))
            + f" | {r['scans_ospa_differs']} of {r['scans']} | {r['max_ospa_diff']:.2g} | "
            f"{r['max_gospa_diff']:.2g} |")
    return lines


# ---------------------------------------------------------------------------- figures

RULE_STYLES = [("-", "o"), ("--", "s"), (":", "^"), ("-.", "v"), ("-", "D"), ("--", "x"),
               (":", "+"), ("-.", "*")]
SENSOR_STYLES = [(0, (1, 1)), (0, (4, 2)), (0, (6, 2, 1, 2)), (0, (1, 3))]


def _ospa_figure(config, results, path: Path) -> None:
    """Mean OSPA over the runs at each scan per row (sensors grey), and each rule's paired
    mean difference to the baseline over time; a rule keeps its colour, line style and
    marker in both panels, and markers are staggered so that coinciding lines stay
    visible."""
    sc = scenario(config)
    base = config["fusion"]["baseline"]
    series = {row: np.mean([r[row]["ospa_t"] for r in results], axis=0)
              for row in results[0]}
    t = sc.dt * np.arange(len(series[base]))  # scan k at k dt
    fig, axes = new_figure(1, 2, width=13)
    fig.set_size_inches(13, 5.2)
    for k, name in enumerate(sensor_names(sc)):
        axes[0].plot(t, series[name], color=str(0.3 + 0.15 * (k % 4)), lw=1.2,
                     ls=SENSOR_STYLES[k % len(SENSOR_STYLES)], label=name)
    every = max(1, len(t) // 10)
    colours = colormaps["tab10"].colors
    for k, rule in enumerate(config["rules"]):
        ls, marker = RULE_STYLES[k % len(RULE_STYLES)]
        style = dict(color=colours[k % len(colours)], ls=ls, marker=marker, ms=5, lw=1.2,
                     markevery=(k * max(1, every // len(config["rules"])) % every, every),
                     fillstyle="none", label=rule)
        axes[0].plot(t, series[rule], **style)
        axes[1].plot(t, series[rule] - series[base], **style)
    axes[1].axhline(0, color="k", lw=0.6)
    # before the first tracks are confirmed OSPA is c for every row; keep the scale of the
    # rest, where the rows differ
    settled = t >= sc.dt * (sc.min_points + 1)
    top = max(s[settled].max() for s in series.values()) if settled.any() else None
    c = config["metrics"]["cutoff"]
    axes[0].set(xlabel="time (s)", ylabel="OSPA (m)", ylim=(0, None if top is None
                                                             else min(c, 1.1 * top)),
                title=f"mean OSPA over {len(results)} runs (c = {c} m, p = "
                      f"{config['metrics']['order']}; the first scans, before tracks are "
                      "confirmed, reach c)")
    axes[0].title.set_fontsize(9)
    axes[1].set(xlabel="time (s)", ylabel=f"OSPA minus {base} (m)",
                title=f"paired mean difference to {base} (below 0: lower OSPA)")
    axes[1].title.set_fontsize(9)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=5, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


VIEW_MARGIN = 12.0  # m around the true paths in the scenario figure
LEGEND_ORDER = ("true path", "start", "target measurements", "clutter", "tracks", "fused")


def _scenario_figure(config, figure, path: Path) -> None:
    """One panel per sensor (truth, its target detections, clutter and tracks) and one of
    the fused estimates of figure.rule; equal aspect, positions in m."""
    sc = scenario(config)
    truth = np.array(figure["truth"], dtype=float).reshape(len(sc.targets), -1, 2)
    panels = len(figure["sensors"]) + 1
    cols = 2 if panels > 2 else panels
    rows = -(-panels // cols)
    fig, axes = new_figure(rows, cols, width=6.0 * cols)
    fig.set_size_inches(6.0 * cols, 5.6 * rows + 0.8)
    names = sensor_names(sc)
    for ax, s, d in zip(axes, range(sc.sensors), figure["sensors"], strict=False):
        clutter = np.array(d["clutter"], dtype=float).reshape(-1, 2)
        dets = np.array(d["detections"], dtype=float).reshape(-1, 2)
        ax.plot(clutter[:, 0], clutter[:, 1], "x", color="0.6", ms=3, mew=0.7, label="clutter")
        ax.plot(dets[:, 0], dets[:, 1], ".", color="tab:blue", ms=3,
                label="target measurements")
        tracks = np.array(d["tracks"], dtype=float).reshape(-1, 4)
        for k, i in enumerate(np.unique(tracks[:, 1])):
            tr = tracks[tracks[:, 1] == i]
            ax.plot(tr[:, 2], tr[:, 3], "-", color="tab:orange", lw=1.3,
                    label="tracks" if k == 0 else None)
        _draw_truth(ax, truth)
        ax.set_title(f"{names[s]}: p_D {sc.p_detect[s]}, clutter {sc.clutter_rate[s]} / scan, "
                     f"sd_x {sc.noise_sd[s][0]} m, sd_y {sc.noise_sd[s][1]} m, "
                     f"{len(np.unique(tracks[:, 1]))} tracks", fontsize=9)
    ax = axes[sc.sensors]
    fused = np.array(figure["fused"], dtype=float).reshape(-1, 3)
    ax.plot(fused[:, 1], fused[:, 2], ".", color="tab:green", ms=3,
            label=f"fused estimates ({config['figure']['rule']})")
    _draw_truth(ax, truth)
    ax.set_title(f"processing node: {config['figure']['rule']}", fontsize=9)
    # the view: the targets' area (clutter falls over all of region)
    low, high = truth.reshape(-1, 2).min(0) - VIEW_MARGIN, truth.reshape(-1, 2).max(0) + VIEW_MARGIN
    low = np.maximum(low, [sc.region[0][0], sc.region[1][0]])
    high = np.minimum(high, [sc.region[0][1], sc.region[1][1]])
    for ax in axes[:panels]:
        ax.set(aspect="equal", xlim=(low[0], high[0]), ylim=(low[1], high[1]),
               xlabel="x (m)", ylabel="y (m)")
    for ax in axes[panels:]:
        ax.set_visible(False)
    handles = {h.get_label(): h for h in plotting.path_handles()}
    for ax in axes[:panels]:
        for h, label in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(label, h)
    order = sorted(handles, key=lambda k: next((i for i, p in enumerate(LEGEND_ORDER)
                                                if k.startswith(p)), len(LEGEND_ORDER)))
    fig.legend([handles[k] for k in order], order, loc="lower center", ncol=6, fontsize=9,
               markerscale=2, frameon=False)
    fig.suptitle(f"Run {FIGURE_RUN} of seed {config['seed']}: {len(sc.targets)} targets, "
                 f"{sc.steps} scans of {sc.dt} s\n(view: the targets' area; clutter falls "
                 f"over x in {list(sc.region[0])} m, y in {list(sc.region[1])} m)",
                 fontsize=10)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _draw_truth(ax, truth: np.ndarray) -> None:
    """True paths (J, T, 2), each with its start and an arrowhead near its end."""
    for xy in truth:
        plotting.path(ax, xy, arrows=1, at=[0.97])

"""Prototype of the `stonesoup` study: one seeded run of Stone Soup's own multi-sensor setting.

Every part is Stone Soup's, as in its track-to-track fusion tutorial: a
MultiTargetGroundTruthSimulator of targets that cross (nearly constant velocity), one
SimpleDetectionSimulator per sensor (its own detection probability, clutter rate and
measurement noise) and one MultiTargetTracker per sensor (Kalman filter, Mahalanobis gating,
global nearest neighbour, multi-measurement initiation). Each tracker runs as a network
tracker through `fusion_opt.stonesoup.StoneSoupTracker`, so a run gives, per step, the ground
truth and each sensor's tracks as `fusion_opt.Estimates`: what a ProcessingNode will fuse.

States are Stone Soup's [x, vx, y, vy] (positions at components 0 and 2); time is seconds
from the run's start. Ground truth has no covariance, so it is returned as arrays, not
Estimates.

Seeding: Stone Soup draws from numpy's global RandomState unless each simulator and model is
given its own seed. Every random part here gets one (`np.random.RandomState` inside Stone
Soup), derived from the run's seed by `np.random.SeedSequence`; the global state is neither
used nor touched, so the same seed gives the same run.

Not registered in the CLI; `python -m studies.stonesoup_prototype` runs and times it.
"""

from __future__ import annotations

import itertools
import time as clock
from dataclasses import dataclass, field
from datetime import datetime, timedelta

import numpy as np
from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
from stonesoup.deleter.time import UpdateTimeStepsDeleter
from stonesoup.hypothesiser.distance import DistanceHypothesiser
from stonesoup.initiator.simple import MultiMeasurementInitiator
from stonesoup.measures import Mahalanobis
from stonesoup.models.measurement.linear import LinearGaussian
from stonesoup.models.transition.linear import (
    CombinedLinearGaussianTransitionModel,
    ConstantVelocity,
)
from stonesoup.predictor.kalman import KalmanPredictor
from stonesoup.simulator.simple import MultiTargetGroundTruthSimulator, SimpleDetectionSimulator
from stonesoup.tracker.simple import MultiTargetTracker
from stonesoup.types.state import GaussianState
from stonesoup.updater.kalman import KalmanUpdater

from fusion_opt import Estimates
from fusion_opt.stonesoup import StoneSoupTracker

START = datetime(2024, 1, 1)
POSITION = (0, 2)  # Stone Soup's [x, vx, y, vy]


@dataclass(frozen=True)
class Scenario:
    """One run's setting. Targets are [x, vx, y, vy] at t = 0; the defaults would meet at the
    origin at t = 40 s and, with the process noise, pass within a few noise sd of each other.
    Per sensor: detection probability, clutter points per scan (uniform over `region`) and
    position-noise standard deviation."""

    steps: int = 80
    dt: float = 1.0
    q: float = 0.001  # ConstantVelocity noise diffusion coefficient per axis
    targets: tuple = ((-40.0, 1.0, -20.0, 0.5), (-40.0, 1.0, 20.0, -0.5), (0.0, 0.0, -40.0, 1.0))
    p_detect: tuple = (0.95, 0.7)
    clutter_rate: tuple = (1.0, 5.0)
    noise_sd: tuple = (1.0, 1.5)
    region: tuple = ((-80.0, 80.0), (-80.0, 80.0))
    gate: float = 3.0  # Mahalanobis missed distance of the trackers
    min_points: int = 3  # detections to confirm a track
    max_misses: int = 5  # steps without an update before a track is deleted

    @property
    def sensors(self) -> int:
        return len(self.p_detect)


@dataclass(frozen=True)
class Step:
    """One step: time (s from the start), the targets' ids (m,) and states (m, 4), each
    sensor's detections as positions (k, 2) and its tracker's Estimates."""

    time: float
    truth_ids: np.ndarray
    truth: np.ndarray
    detections: tuple[np.ndarray, ...]
    tracks: tuple[Estimates, ...]


@dataclass(frozen=True)
class Run:
    """The steps of one seeded run and its wall time in seconds."""

    seed: int
    scenario: Scenario
    steps: tuple[Step, ...] = field(repr=False)
    seconds: float


def run_once(seed: int, scenario: Scenario = Scenario()) -> Run:
    """Simulate and track one run of `scenario` from `seed` (see the module docstring)."""
    t0 = clock.perf_counter()
    seeds = iter(np.random.SeedSequence(seed).generate_state(2 + 2 * scenario.sensors))
    truth = _truth(scenario, seeds)
    feeds = itertools.tee(truth, 1 + scenario.sensors)  # lock-step copies of one ground truth
    sensors = [_sensor(scenario, s, feeds[1 + s], seeds) for s in range(scenario.sensors)]
    trackers = [StoneSoupTracker(_tracker(scenario, sim.measurement_model), ndim=4, epoch=START,
                                 node=f"sensor{s}") for s, sim in enumerate(sensors)]
    scans = [iter(sim) for sim in sensors]
    ids: dict = {}
    steps = []
    for now, paths in feeds[0]:
        sensor_scans = [next(scan) for scan in scans]
        steps.append(Step(
            time=(now - START).total_seconds(),
            truth_ids=np.array([ids.setdefault(p, len(ids)) for p in paths], dtype=np.int64),
            truth=np.array([np.ravel(p[-1].state_vector) for p in paths]).reshape(-1, 4),
            detections=tuple(_positions(d) for _, d in sensor_scans),
            tracks=tuple(tr.step(scan) for tr, scan in zip(trackers, sensor_scans, strict=True)),
        ))
    return Run(seed, scenario, tuple(steps), clock.perf_counter() - t0)


def _cv(q: float, seed=None) -> CombinedLinearGaussianTransitionModel:
    return CombinedLinearGaussianTransitionModel([ConstantVelocity(q), ConstantVelocity(q)],
                                                 seed=None if seed is None else int(seed))


def _truth(sc: Scenario, seeds) -> MultiTargetGroundTruthSimulator:
    return MultiTargetGroundTruthSimulator(
        transition_model=_cv(sc.q, next(seeds)),
        initial_state=GaussianState(np.zeros(4), np.eye(4), timestamp=START),
        timestep=timedelta(seconds=sc.dt), number_steps=sc.steps,
        birth_rate=0.0, death_probability=0.0,
        preexisting_states=[np.array(x, dtype=float) for x in sc.targets], seed=int(next(seeds)))


def _sensor(sc: Scenario, s: int, truth, seeds) -> SimpleDetectionSimulator:
    model = LinearGaussian(ndim_state=4, mapping=POSITION,
                           noise_covar=sc.noise_sd[s] ** 2 * np.eye(2), seed=int(next(seeds)))
    return SimpleDetectionSimulator(
        groundtruth=truth, measurement_model=model, meas_range=np.array(sc.region),
        detection_probability=sc.p_detect[s], clutter_rate=sc.clutter_rate[s],
        seed=int(next(seeds)))


def _tracker(sc: Scenario, model: LinearGaussian) -> MultiTargetTracker:
    """A Kalman multi-target tracker of one sensor (filters do not draw random numbers)."""
    predictor, updater = KalmanPredictor(_cv(sc.q)), KalmanUpdater(model)
    hypothesiser = DistanceHypothesiser(predictor, updater, Mahalanobis(),
                                        missed_distance=sc.gate)
    associator = GNNWith2DAssignment(hypothesiser)
    initiator = MultiMeasurementInitiator(
        prior_state=GaussianState(np.zeros(4), np.diag([0.0, 1.0, 0.0, 1.0])),
        measurement_model=model, deleter=UpdateTimeStepsDeleter(2), data_associator=associator,
        updater=updater, min_points=sc.min_points)
    return MultiTargetTracker(initiator=initiator, deleter=UpdateTimeStepsDeleter(sc.max_misses),
                              detector=None, data_associator=associator, updater=updater)


def _positions(detections) -> np.ndarray:
    """(k, 2) measured positions of a scan, in a fixed order (Stone Soup gives a set)."""
    z = np.array([np.ravel(d.state_vector) for d in detections]).reshape(-1, 2)
    return z[np.lexsort(z.T[::-1])] if len(z) else z


if __name__ == "__main__":
    runs = [run_once(seed) for seed in range(3)]
    for run in runs:
        counts = [[len(e) for e in step.tracks] for step in run.steps]
        print(f"seed {run.seed}: {run.seconds:.2f} s, {len(run.steps)} steps, tracks per "
              f"sensor (mean) {np.mean(counts, axis=0).round(2).tolist()}")

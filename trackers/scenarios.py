"""Simulators for the paper's two scenarios (DESIGN §3) and for the crossing targets of the
network example, with every parameter in a frozen configuration dataclass whose defaults
are the DESIGN values (the example's: studies/configs/network.toml).

Time convention (both scenarios): step k = 0..T-1 is at time t_k = (k + 1) dt. A target's
initial state x0 is its state at its birth time (0 for the Table 1 target); its truth is
propagated exactly, x(t_k) = expm(F(a_k) dt) x(t_{k-1}), with the turn rate a_k of the
schedule at t_k (plus turn_noise_sd N(0, 1) inside each turn window, as in the RBMCDA
toolbox demos); the truth has no other process noise unless ``truth_process_noise`` is set.
A target born at b and dying at e is alive at the steps with b < t_k <= e (grid-rounded).
The filters' prior m0, P0 is at time 0, so their first action is a predict to t_0.

Measurements carry their step, time and true origin: the target's id (0, 1, ...) or
``CLUTTER`` (-1). ``NodeData.scans`` is what the filters take.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from fusion_opt import FusionInputError
from fusion_opt.prepare import MAX_CONDITION
from fusion_opt.validation import is_real, is_sequence, safe_repr, wide_float
from trackers import _checks
from trackers.models import LinearGaussian, discretize, turn_F, turn_L, turn_model

_EPS = float(np.finfo(float).eps)

#: Origin label of a clutter measurement.
CLUTTER = -1

_PI = float(np.pi)


@dataclass(frozen=True, eq=False)  # == is identity, as for an Estimates
class NodeData:
    """The measurements of one monitoring node over T steps.

    values (M, d): all measurements, ordered by step; step (M,) int step index;
    time (M,) float time of each; origin (M,) int true origin (target id or CLUTTER);
    scans: tuple of T arrays (k_t, d), the measurements of each step (what the filters take);
    origins: tuple of T int arrays (k_t,), the origins of each step's measurements.
    """

    values: np.ndarray
    step: np.ndarray
    time: np.ndarray
    origin: np.ndarray
    scans: tuple
    origins: tuple


def _node_data(values, step, origin, times) -> NodeData:
    values = np.asarray(values, dtype=float).reshape(-1, 2)
    step = np.asarray(step, dtype=int)
    origin = np.asarray(origin, dtype=int)
    order = np.argsort(step, kind="stable")
    values, step, origin = values[order], step[order], origin[order]
    cuts = np.searchsorted(step, np.arange(1, len(times)))
    return NodeData(
        values=values,
        step=step,
        time=times[step],
        origin=origin,
        scans=tuple(np.split(values, cuts)),
        origins=tuple(np.split(origin, cuts)),
    )


def _uniform_in(region, size, rng):
    (x0, x1), (y0, y1) = region
    return np.column_stack([rng.uniform(x0, x1, size), rng.uniform(y0, y1, size)])


def _turn_rates(times, windows, base_rate, noise_sd, rng):
    """a_k for each step: base_rate, replaced by rate + noise_sd N(0,1) inside each window."""
    a = np.full(times.shape, float(base_rate))
    for start, end, rate in windows:
        inside = (times >= start - 1e-9) & (times <= end + 1e-9)
        a[inside] = rate + noise_sd * rng.standard_normal(int(inside.sum()))
    return a


def _propagate(x0, rates, dt, q, process_noise, rng):
    """Exact propagation of x0 through len(rates) steps with turn rates ``rates``."""
    X = np.empty((len(rates), 4))
    x = np.asarray(x0, dtype=float)
    cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}
    for k, a in enumerate(rates):
        if a not in cache:  # constant-rate stretches reuse one matrix exponential
            cache[a] = discretize(turn_F(a), turn_L(), q * np.eye(2), dt)
        A, Q = cache[a]
        x = A @ x
        if process_noise:
            x = x + rng.multivariate_normal(np.zeros(4), Q)
        X[k] = x
    return X


def _spawn(rng: np.random.Generator, k: int) -> list[np.random.Generator]:
    """k independent child generators of rng (one per part of a run)."""
    try:
        return rng.spawn(k)
    except TypeError:  # a bit generator made without a SeedSequence cannot spawn
        raise FusionInputError("rng must be able to spawn streams (numpy.random.default_rng"
                               "(seed) can); this one's bit generator has no SeedSequence"
                               ) from None


def _check_rates(name: str, rates, q: float, dt: float, noise_sd: float = 0.0) -> None:
    """Each turn rate (rad/s) gives a coordinated-turn step of dt that float64 holds, and
    so do the rates drawn around them, rate + noise_sd N(0, 1): checked at the largest
    |rate| + 40 noise_sd (a standard normal beyond 40 has probability below 1e-340), as
    |F|_1 and the step's size grow with |rate|."""
    for i, a in enumerate(rates):
        try:
            discretize(turn_F(a), turn_L(), q * np.eye(2), dt)
        except FusionInputError as exc:
            raise FusionInputError(f"{name}: turn rate {i} = {safe_repr(a)}: {exc}") from None
    if noise_sd == 0.0 or len(rates) == 0:  # no window: no rate is drawn
        return
    worst = max(abs(a) for a in rates) + 40.0 * noise_sd
    try:
        discretize(turn_F(worst), turn_L(), q * np.eye(2), dt)
    except FusionInputError as exc:
        raise FusionInputError(f"turn_noise_sd = {safe_repr(noise_sd)}: the drawn turn rates reach "
                               f"about {worst:.3g} rad/s: {exc}") from None


def _float_fields(cfg) -> None:
    """Each field whose default is a float, given as another real number (`is_real`: a
    Python or numpy int, a Fraction, a float16 or float32, a long double), held as the
    nearest float64: a TOML integer of 2^70 reached numpy as an object and raised
    TypeError (fuzz N7), numpy's ints wrap (O6), a Fraction reached np.sqrt and a float16
    overflowed inside a check (U4). One that float64 does not hold (past its range, or
    nonzero below its smallest number) is refused by name."""
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if isinstance(f.default, float) and is_real(value) and type(value) is not float:
            x = wide_float(value)
            lost = np.isinf(x) and not (isinstance(value, np.floating) and np.isinf(value)) \
                or x == 0.0 and value != 0
            if lost:
                raise FusionInputError(f"{f.name} = {safe_repr(value)} is beyond float64's "
                                       "range")
            object.__setattr__(cfg, f.name, x)


def _check_shared(cfg) -> None:
    """The fields both scenario configurations have: time grid, motion, detection, filter;
    a run's arrays (about 5 + 12 per node floats a step) must fit fusion_opt.limits."""
    _checks.positive("dt", cfg.dt)
    _checks.positive_int("n_steps", cfg.n_steps)
    if not np.isfinite(cfg.dt * wide_float(cfg.n_steps)):
        raise FusionInputError(f"dt x n_steps must be a finite time, got {cfg.dt} x "
                               f"{safe_repr(cfg.n_steps)}")
    _checks.positive("q", cfg.q)
    _check_region("region", cfg.region)
    _checks.nonnegative("turn_noise_sd", cfg.turn_noise_sd)
    _checks.boolean("truth_process_noise", cfg.truth_process_noise)
    p = _checks.finite_array("p_detect", cfg.p_detect, ndim=1)
    if p.size == 0:
        raise FusionInputError("p_detect must hold one detection probability per node, "
                               "got none (no nodes)")
    for i, p_i in enumerate(cfg.p_detect):
        _checks.probability(f"p_detect[{i}]", p_i)
    _checks.positive_int("n_particles", cfg.n_particles)
    _checks.probability("clutter_prior", cfg.clutter_prior)
    _checks.positive("clutter_density", cfg.clutter_density)
    _checks.positive("prior_cov", cfg.prior_cov)
    _checks.probability("resample_threshold", cfg.resample_threshold)
    _checks.fits(f"n_steps = {cfg.n_steps}", 8.0 * cfg.n_steps * (5 + 12 * len(cfg.p_detect)))


def _check_prior_ratio(prior_cov: float, r: float, r_name: str) -> None:
    """The filters' first update leaves positions at about the measurement variance r and
    velocities at prior_cov: a covariance of condition about prior_cov / r, which the
    fusion refuses above MAX_CONDITION (7e13; float64 holds it positive definite only up
    to about 1/eps: a Table 1 run at 2e19 failed at a filter's second step, and runs at
    1e14 at the fusion, fuzz H3 / H4)."""
    ratio = prior_cov / r
    if not ratio <= MAX_CONDITION:
        raise FusionInputError(
            f"prior_cov / {r_name} = {ratio:.3g}: after a first update the filters' "
            f"covariance has about that condition (positions near {r_name}, velocities "
            f"near prior_cov), beyond the {MAX_CONDITION:.2g} a fusion accepts")


MAX_REACH = 1e12  # positions are resolved to within eps x 1e12 = 2.2e-4 measurement sd


def check_reach(name: str, position, speed: float, duration: float, sd: float,
                sd_name: str) -> None:
    """Refuse a target whose path leaves the coordinates float64 resolves at the noise:
    from position (2,) at speed (m/s, which turns keep) for duration (s) it stays within
    reach = max|position| + speed x duration, where float64 rounds positions to eps x
    reach. Accepted up to MAX_REACH measurement sds, where that rounding is 2.2e-4 sd (a
    Table 1 target at 1e12 m, 4.5e12 sds, gave the scores of one at 1e10 m to 3-4 digits;
    at 1e30 m the fusion met covariances that were not positive definite, at 1e300 m a
    figure overflowed: fuzz H14, H17)."""
    with np.errstate(over="ignore", invalid="ignore"):
        reach = float(np.max(np.abs(position))) + speed * max(duration, 0.0)
    if not reach <= MAX_REACH * sd:
        raise FusionInputError(
            f"{name}: the target reaches {reach:.3g} m from the origin, {reach / sd:.3g} "
            f"times {sd_name} = {sd:.3g}, where float64 rounds positions to "
            f"{reach * _EPS:.3g} m; the scenarios accept up to {MAX_REACH:.0e} sds, where the "
            f"rounding is {MAX_REACH * _EPS:.1e} sd (centre the coordinates on the targets; a "
            f"noise sd below 1e-12 of the paths' extent is beyond float64)")


def _check_region(name, region):
    r = _checks.finite_array(name, region, shape=(2, 2))
    if np.any(r[:, 1] <= r[:, 0]):
        raise FusionInputError(f"{name} must be ((xmin, xmax), (ymin, ymax)) with min < max")
    with np.errstate(over="ignore"):
        if not np.isfinite(r[:, 1] - r[:, 0]).all():
            raise FusionInputError(f"{name}'s width overflows float64: {r.tolist()}")
    return r


def _check_windows(name, windows) -> tuple[tuple[float, float, float], ...]:
    """Turn windows as a tuple of (start, end, rate), finite, start <= end."""
    w = _checks.finite_array(name, windows)
    if w.size == 0:
        return ()
    if w.ndim != 2 or w.shape[1] != 3:
        raise FusionInputError(f"{name} must be a sequence of (start, end, rate), got shape "
                               f"{w.shape}")
    if np.any(w[:, 1] < w[:, 0]):
        raise FusionInputError(f"{name} must be (start, end, rate) with start <= end")
    return tuple(tuple(float(v) for v in row) for row in w)


# ----------------------------------------------------------------------------- Table 1


@dataclass(frozen=True)
class Table1Config:
    """One target, two monitoring nodes (DESIGN §3, Table 1). Times in s, rates in rad/s."""

    dt: float = 0.025
    n_steps: int = 960
    q: float = 0.1
    r: float = 0.05
    x0: tuple[float, ...] = (-4.0, -0.2, 1.0, 0.0)
    turn_windows: tuple[tuple[float, float, float], ...] = (
        (1.0, 3.0, _PI / 4.2),
        (3.5, 5.5, -_PI / 4.2),
        (8.0, 10.5, -_PI / 5.2),
        (14.0, 16.5, -_PI / 5.2),
        (19.0, 21.0, -_PI / 4.2),
        (21.5, 23.5, _PI / 4.2),
    )
    turn_noise_sd: float = 0.01
    truth_process_noise: bool = False
    p_detect: tuple[float, ...] = (0.9, 0.7)
    clutter_fraction: float = 0.5
    region: tuple[tuple[float, float], tuple[float, float]] = ((-5.0, 5.0), (-4.0, 4.0))
    # Filter settings (RBPF at each node).
    n_particles: int = 20
    clutter_prior: float = 0.5
    clutter_density: float = 1 / 80
    prior_cov: float = 0.1
    resample_threshold: float = 0.25

    def __post_init__(self) -> None:
        _float_fields(self)
        _check_shared(self)
        _checks.positive("r", self.r)
        x0 = _checks.finite_array("x0", self.x0, shape=(4,))
        _check_windows("turn_windows", self.turn_windows)
        _checks.probability("clutter_fraction", self.clutter_fraction)
        self.filter_model()  # dt, q and r give a model float64 holds
        _check_prior_ratio(self.prior_cov, self.r, "r")
        _check_rates("turn_windows", [w[2] for w in self.turn_windows], self.q, self.dt,
                     self.turn_noise_sd)
        check_reach("x0", x0[:2], float(np.hypot(*x0[2:])), self.n_steps * self.dt,
                    float(np.sqrt(self.r)), "sqrt(r)")

    def filter_model(self) -> LinearGaussian:
        """The filters' model: constant velocity (a = 0), Qc = q I2, R = r I2."""
        return turn_model(0.0, self.q, self.r, self.dt)

    def prior(self) -> tuple[np.ndarray, np.ndarray]:
        """The filters' prior (m0, P0) at time 0: x0 and prior_cov I4."""
        return np.array(self.x0, dtype=float), self.prior_cov * np.eye(4)

    def times(self) -> np.ndarray:
        return self.dt * np.arange(1, self.n_steps + 1)


@dataclass(frozen=True, eq=False)  # == is identity, as for an Estimates
class Table1Data:
    """One simulated run of Table 1.

    times (T,); truth (T, 4) target state at each step; turn_rates (T,) the a_k used;
    nodes: one NodeData per monitoring node (node a, node b, ...); target id is 0.
    """

    times: np.ndarray
    truth: np.ndarray
    turn_rates: np.ndarray
    nodes: tuple[NodeData, ...]


def simulate_table1(config: Table1Config, rng: np.random.Generator) -> Table1Data:
    """Simulate the truth and every node's measurements for one run of Table 1.

    Each node, each step: no measurement with probability 1 - p_D; otherwise one
    measurement, clutter (uniform on the region) with probability clutter_fraction and
    H x + N(0, r I2) otherwise. Nodes draw from independent child generators of ``rng``.
    """
    if not isinstance(config, Table1Config):
        raise FusionInputError(f"config must be a Table1Config, got {type(config).__name__}")
    rng = _checks.generator("rng", rng)
    truth_rng, *node_rngs = _spawn(rng, 1 + len(config.p_detect))
    times = config.times()
    rates = _turn_rates(times, config.turn_windows, 0.0, config.turn_noise_sd, truth_rng)
    truth = _propagate(config.x0, rates, config.dt, config.q, config.truth_process_noise,
                       truth_rng)
    sd = np.sqrt(config.r)
    nodes = []
    T = config.n_steps
    for p_d, nrng in zip(config.p_detect, node_rngs, strict=True):
        detected = nrng.random(T) < p_d
        clutter = nrng.random(T) < config.clutter_fraction
        noise = sd * nrng.standard_normal((T, 2))
        fake = _uniform_in(config.region, T, nrng)
        values = np.where(clutter[:, None], fake, truth[:, :2] + noise)
        steps = np.flatnonzero(detected)
        origin = np.where(clutter[steps], CLUTTER, 0)
        nodes.append(_node_data(values[steps], steps, origin, times))
    return Table1Data(times, truth, rates, tuple(nodes))


# ----------------------------------------------------------------------------- Table 2


@dataclass(frozen=True)
class TargetSpec:
    """A true target: initial state x0 (4,) at its birth time, alive on (birth, death]; turn
    rate ``turn_rate`` outside the windows and (start, end, rate) + noise inside them.
    Validated on construction; x0 and the windows are stored as tuples of floats."""

    x0: tuple[float, ...]
    birth: float
    death: float
    turn_windows: tuple[tuple[float, float, float], ...] = ()
    turn_rate: float = 0.0

    def __post_init__(self) -> None:
        x0 = _checks.finite_array("x0", self.x0, shape=(4,))
        object.__setattr__(self, "x0", tuple(float(v) for v in x0))
        birth = _checks.finite("birth", self.birth)
        death = _checks.finite("death", self.death)
        if not death > birth:
            raise FusionInputError(f"death must be > birth, got birth {birth}, death {death}")
        object.__setattr__(self, "birth", birth)
        object.__setattr__(self, "death", death)
        object.__setattr__(self, "turn_windows", _check_windows("turn_windows",
                                                               self.turn_windows))
        object.__setattr__(self, "turn_rate", _checks.finite("turn_rate", self.turn_rate))


_T1_RATE = _PI / (2 * 0.51)


def _target_spec(i: int, tg) -> TargetSpec:
    """targets[i] as a TargetSpec (a TOML table or array gives its fields)."""
    if isinstance(tg, TargetSpec):
        return tg
    try:
        return TargetSpec(**tg) if isinstance(tg, Mapping) else TargetSpec(*tg)
    except TypeError as err:
        raise FusionInputError(f"targets[{i}] is not a valid TargetSpec: {err}") from None
    except FusionInputError as err:
        raise FusionInputError(f"targets[{i}]: {err}") from None


@dataclass(frozen=True)
class Table2Config:
    """Unknown number of targets, seven monitoring nodes (DESIGN §3, Table 2)."""

    dt: float = 0.01
    n_steps: int = 500
    q: float = 0.1
    meas_sd: float = 0.05
    region: tuple[tuple[float, float], tuple[float, float]] = ((-2.0, 2.0), (-2.0, 2.0))
    targets: tuple[TargetSpec, ...] = (
        TargetSpec((0.0, 1.0, 1.0, 0.0), 0.0, 5.0,
                   ((0.5, 1.0, _T1_RATE), (2.0, 2.5, _T1_RATE), (3.5, 4.0, _T1_RATE))),
        TargetSpec((0.0, -1.0, 0.1, 1.0), 1.0, 3.5),
        TargetSpec((-1.0, 0.0, 1.0, 0.1), 1.0, 3.0),
        TargetSpec((-1.0, 1.0, 1.0, 0.0), 1.0, 4.0, turn_rate=1.0),
    )
    turn_noise_sd: float = 0.01
    truth_process_noise: bool = False
    p_detect: tuple[float, ...] = (0.8, 0.8, 0.9, 0.75, 0.95, 0.9, 0.85)
    clutter_rate: float = 0.1
    # Filter settings (RBMCDA at each node).
    n_particles: int = 20
    birth_prob: float = 0.01
    lifetime_shape: float = 2.0
    lifetime_scale: float = 0.5
    clutter_prior: float = 0.05
    clutter_density: float = 1 / 16
    prior_cov: float = 10.0
    resample_threshold: float = 0.25

    def __post_init__(self) -> None:
        _float_fields(self)
        _check_shared(self)
        _checks.positive("meas_sd", self.meas_sd)
        # a study's TOML gives targets as tables (dicts) or arrays; store TargetSpecs
        if not is_sequence(self.targets):
            raise FusionInputError(f"targets must be a sequence of TargetSpec, got "
                                   f"{type(self.targets).__name__}")
        targets = tuple(_target_spec(i, tg) for i, tg in enumerate(self.targets))
        object.__setattr__(self, "targets", targets)
        _checks.nonnegative("clutter_rate", self.clutter_rate)
        _checks.probability("birth_prob", self.birth_prob)
        _checks.positive("lifetime_shape", self.lifetime_shape)
        _checks.positive("lifetime_scale", self.lifetime_scale)
        self.filter_model()  # dt, q and meas_sd give a model float64 holds
        _check_prior_ratio(self.prior_cov, self.meas_sd**2, "meas_sd^2")
        for i, tg in enumerate(self.targets):
            _check_rates(f"targets[{i}]", [tg.turn_rate, *(w[2] for w in tg.turn_windows)],
                         self.q, self.dt, self.turn_noise_sd)
        _checks.fits("n_steps, targets and clutter_rate", self._run_bytes())
        for i, tg in enumerate(self.targets):
            check_reach(f"targets[{i}]", tg.x0[:2], float(np.hypot(*tg.x0[2:])),
                        min(tg.death, self.n_steps * self.dt) - tg.birth, self.meas_sd,
                        "meas_sd")

    def _run_bytes(self) -> float:
        """About the bytes of a simulated run: the truth, each target's propagation from
        its birth, and each node's measurements (a few hundred bytes a point, in lists)."""
        T, end = self.n_steps, self.n_steps * self.dt
        propagated = sum(max(0.0, (min(tg.death, end) - tg.birth) / self.dt)
                         for tg in self.targets)
        points = len(self.p_detect) * T * (1.0 + self.clutter_rate)
        return 40.0 * (len(self.targets) * T + propagated) + 300.0 * points

    def filter_model(self) -> LinearGaussian:
        """The filters' model: constant velocity (a = 0), Qc = q I2, R = meas_sd^2 I2."""
        return turn_model(0.0, self.q, _checks.variance("meas_sd", self.meas_sd), self.dt)

    def prior(self) -> tuple[np.ndarray, np.ndarray]:
        """New-target prior (m0, P0): zero mean, prior_cov I4."""
        return np.zeros(4), self.prior_cov * np.eye(4)

    def times(self) -> np.ndarray:
        return self.dt * np.arange(1, self.n_steps + 1)


@dataclass(frozen=True, eq=False)  # == is identity, as for an Estimates
class MultiTargetData:
    """One simulated run of a multi-target scenario (Table 2, crossing targets).

    times (T,); truth (n_targets, T, 4) states, NaN where the target is not alive;
    alive (n_targets, T) bool; nodes: one NodeData per monitoring node (origins are the
    target's index or CLUTTER).
    """

    times: np.ndarray
    truth: np.ndarray
    alive: np.ndarray
    nodes: tuple[NodeData, ...]

    def states_at(self, k: int) -> np.ndarray:
        """The (m, 4) states of the targets alive at step k."""
        return self.truth[self.alive[:, k], k]

    @property
    def n_alive(self) -> np.ndarray:
        """(T,) number of alive targets at each step."""
        return self.alive.sum(axis=0)


def simulate_table2(config: Table2Config, rng: np.random.Generator) -> MultiTargetData:
    """Simulate the truth and every node's measurements for one run of Table 2.

    Each node, each step: with probability p_D one measurement of one alive target chosen
    uniformly (none if no target is alive), plus Poisson(clutter_rate) clutter points
    uniform on the region; a step's measurements are in random order.
    """
    if not isinstance(config, Table2Config):
        raise FusionInputError(f"config must be a Table2Config, got {type(config).__name__}")
    rng = _checks.generator("rng", rng)
    truth_rng, *node_rngs = _spawn(rng, 1 + len(config.p_detect))
    dt, T = config.dt, config.n_steps
    times = config.times()
    n_tg = len(config.targets)
    truth = np.full((n_tg, T, 4), np.nan)
    alive = np.zeros((n_tg, T), dtype=bool)
    grid = np.arange(1, T + 1)  # t_k / dt
    for j, tg in enumerate(config.targets):
        b, e = _grid_index(tg.birth, dt), _grid_index(tg.death, dt)
        steps = np.flatnonzero((grid > b) & (grid <= e))
        if steps.size == 0:
            continue
        _checks.fits(f"targets[{j}]: {grid[steps[-1]] - b} steps from its birth",
                     8.0 * 8 * (grid[steps[-1]] - b))
        # propagate from the birth time b dt to each alive step's time
        t_prop = dt * np.arange(b + 1, grid[steps[-1]] + 1)
        rates = _turn_rates(t_prop, tg.turn_windows, tg.turn_rate, config.turn_noise_sd,
                            truth_rng)
        X = _propagate(tg.x0, rates, dt, config.q, config.truth_process_noise, truth_rng)
        truth[j, steps] = X[grid[steps] - b - 1]
        alive[j, steps] = True

    nodes = []
    for p_d, nrng in zip(config.p_detect, node_rngs, strict=True):
        vals, steps, origins = [], [], []
        n_alive = alive.sum(axis=0)
        detected = (nrng.random(T) < p_d) & (n_alive > 0)
        for k in np.flatnonzero(detected):
            j = nrng.choice(np.flatnonzero(alive[:, k]))
            vals.append(truth[j, k, :2] + config.meas_sd * nrng.standard_normal(2))
            steps.append(k)
            origins.append(j)
        n_clutter = nrng.poisson(config.clutter_rate, T)
        c_steps = np.repeat(np.arange(T), n_clutter)
        vals.extend(_uniform_in(config.region, c_steps.size, nrng))
        steps.extend(c_steps)
        origins.extend([CLUTTER] * c_steps.size)
        vals_arr = np.asarray(vals, dtype=float).reshape(-1, 2)
        steps_arr = np.asarray(steps, dtype=int)
        origins_arr = np.asarray(origins, dtype=int)
        # random order within a step: sort by step, ties broken by a random key
        order = np.lexsort((nrng.random(steps_arr.size), steps_arr))
        nodes.append(_node_data(vals_arr[order], steps_arr[order], origins_arr[order], times))
    return MultiTargetData(times, truth, alive, tuple(nodes))


# ------------------------------------------------------------------- crossing targets


@dataclass(frozen=True)
class CrossingConfig:
    """Targets that cross, seen by many monitoring nodes (the network example).

    n_targets targets start on the circle of radius start_radius at the angles
    2 pi j / n_targets and move at `speed` towards the centre, their heading turned by
    +heading_offset or -heading_offset (alternating), so every straight path passes within
    start_radius sin(heading_offset) of the centre. Birth times (s) and turn rates (rad/s)
    are cycled over the targets; a target lives 2 start_radius / speed seconds from its
    birth (the time to cross the circle) or until the run ends, and moves with the
    coordinated-turn model of its rate, with no process noise. Node i detects each alive
    target independently with probability p_detect[i] (the usual multi-target model),
    measures its position with noise N(0, meas_sd^2 I2), and adds Poisson(clutter_rate[i])
    clutter points uniform on the region; a step's measurements come in random order.
    q is the spectral density of the filters' constant-velocity model."""

    dt: float = 0.05
    n_steps: int = 110
    q: float = 0.1
    meas_sd: float = 0.05
    region: tuple[tuple[float, float], tuple[float, float]] = ((-2.5, 2.5), (-2.5, 2.5))
    n_targets: int = 20
    start_radius: float = 2.0
    speed: float = 1.0
    heading_offset: float = 0.15
    births: tuple[float, ...] = (0.0, 0.5, 1.0, 1.5)
    turn_rates: tuple[float, ...] = (0.0, 0.0, 0.0, 0.2, 0.0, -0.2)
    p_detect: tuple[float, ...] = (0.95, 0.7, 0.85, 0.6, 0.9, 0.75, 0.98, 0.65, 0.8, 0.9,
                                   0.7, 0.85, 0.6, 0.95, 0.75, 0.8)
    clutter_rate: tuple[float, ...] = (0.2, 1.0, 0.5, 2.0, 0.1, 1.5, 0.3, 2.5, 0.5, 1.0, 0.2,
                                       3.0, 0.8, 0.4, 1.2, 0.6)

    def __post_init__(self) -> None:
        _float_fields(self)
        for name in ("dt", "q", "meas_sd", "start_radius", "speed"):
            _checks.positive(name, getattr(self, name))
        for name in ("n_steps", "n_targets"):
            _checks.positive_int(name, getattr(self, name))
        _check_region("region", self.region)
        h = _checks.finite("heading_offset", self.heading_offset)
        if not 0.0 <= h <= _PI / 2:
            raise FusionInputError(f"heading_offset must be in [0, pi/2], got {h}")
        for name, check in (("births", _checks.nonnegative), ("turn_rates", _checks.finite),
                            ("p_detect", _checks.probability),
                            ("clutter_rate", _checks.nonnegative)):
            values = _checks.finite_array(name, getattr(self, name), ndim=1)
            if values.size == 0:
                raise FusionInputError(f"{name} must not be empty")
            for i, v in enumerate(values.tolist()):
                check(f"{name}[{i}]", v)
        _check_rates("turn_rates", self.turn_rates, self.q, self.dt)
        check_reach("start_radius", [self.start_radius], self.speed,
                    2 * self.start_radius / self.speed, self.meas_sd, "meas_sd")
        if len(self.clutter_rate) != len(self.p_detect):
            raise FusionInputError(f"clutter_rate must give one rate per node "
                                   f"({len(self.p_detect)}, as p_detect), got "
                                   f"{len(self.clutter_rate)}")
        # the truth and, per node, the detections and clutter of a run
        steps, targets = wide_float(self.n_steps), wide_float(self.n_targets)
        points = steps * (len(self.p_detect) * targets + sum(self.clutter_rate))
        _checks.fits("n_steps, n_targets and clutter_rate",
                     48.0 * targets * steps + 300.0 * points)
        self.filter_model()  # dt, q and meas_sd give a model float64 holds

    def filter_model(self) -> LinearGaussian:
        """The filters' model: constant velocity (a = 0), Qc = q I2, R = meas_sd^2 I2."""
        return turn_model(0.0, self.q, _checks.variance("meas_sd", self.meas_sd), self.dt)

    def times(self) -> np.ndarray:
        return self.dt * np.arange(1, self.n_steps + 1)

    def targets(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """x0 (J, 4) at birth, births (J,), deaths (J,) in s, turn rates (J,) in rad/s."""
        j = np.arange(self.n_targets)
        angle = 2 * np.pi * j / self.n_targets
        heading = angle + np.pi + self.heading_offset * (-1.0) ** j  # inwards, turned
        x0 = np.column_stack([self.start_radius * np.cos(angle),
                              self.start_radius * np.sin(angle),
                              self.speed * np.cos(heading), self.speed * np.sin(heading)])
        births = np.resize(np.asarray(self.births, dtype=float), j.size)
        rates = np.resize(np.asarray(self.turn_rates, dtype=float), j.size)
        return x0, births, births + 2 * self.start_radius / self.speed, rates


def simulate_crossing(config: CrossingConfig, rng: np.random.Generator) -> MultiTargetData:
    """Simulate the truth and every node's measurements for one run of the crossing
    scenario (CrossingConfig); node i draws from the i-th child generator of ``rng``."""
    if not isinstance(config, CrossingConfig):
        raise FusionInputError(f"config must be a CrossingConfig, got {type(config).__name__}")
    rng = _checks.generator("rng", rng)
    truth, alive = _crossing_truth(config)
    times = config.times()
    nodes = tuple(_crossing_node(truth, alive, p, c, config, nrng, times)
                  for p, c, nrng in zip(config.p_detect, config.clutter_rate,
                                        _spawn(rng, len(config.p_detect)), strict=True))
    return MultiTargetData(times, truth, alive, nodes)


def _grid_index(t: float, dt: float) -> int:
    """round(t / dt), the step of time t, within +-2^62 (t / dt overflowed at dt = 1e-308
    and round(inf) raised OverflowError: fuzz N8; a step that far is never in a run)."""
    with np.errstate(over="ignore"):
        x = t / dt
    return round(min(max(x, -(2.0**62)), 2.0**62))


def _crossing_truth(config: CrossingConfig) -> tuple[np.ndarray, np.ndarray]:
    """truth (J, T, 4), NaN where not alive, and alive (J, T): step k holds a target born
    at b and dying at e iff b < t_k <= e (on the grid)."""
    x0, births, deaths, rates = config.targets()
    dt, T = config.dt, config.n_steps
    truth = np.full((len(x0), T, 4), np.nan)
    for j in range(len(x0)):
        b, e = _grid_index(births[j], dt), min(_grid_index(deaths[j], dt), T)
        if e > b:
            truth[j, b:e] = _propagate(x0[j], np.full(e - b, rates[j]), dt, config.q, False,
                                       None)
    return truth, ~np.isnan(truth[..., 0])


def _crossing_node(truth, alive, p_d, clutter_rate, config, rng, times) -> NodeData:
    """One node's measurements: each alive target with probability p_d, plus clutter."""
    values, steps, origins = [], [], []
    for k in range(truth.shape[1]):
        seen = np.flatnonzero(alive[:, k] & (rng.random(len(truth)) < p_d))
        y = truth[seen, k, :2] + config.meas_sd * rng.standard_normal((seen.size, 2))
        n_c = rng.poisson(clutter_rate)
        clutter = _uniform_in(config.region, n_c, rng)
        order = rng.permutation(seen.size + n_c)
        values.append(np.concatenate([y, clutter])[order])
        origins.append(np.concatenate([seen, np.full(n_c, CLUTTER)])[order])
        steps.append(np.full(seen.size + n_c, k))
    return _node_data(np.concatenate(values), np.concatenate(steps),
                      np.concatenate(origins), times)

"""N-node fusion with known truth: MBCI against BCI and the alternatives as N grows.

Static case: N nodes estimate one state (dimension n, truth 0). Node i detects with p_i
~ U[p_center -+ spread / 2]; it has missed k_i ~ Geometric(p_i) - 1 recent scans, so its
true and reported covariance is P_i = B_i growth_true^k_i (B_i a random base covariance;
growth is the paper's chi^-1 >= 1, the covariance growth over a missed scan).
Errors e_i = c + u_i share one common error c ~ N(0, C), C = rho lam I with lam the
smallest eigenvalue of all P_i, and add independent u_i ~ N(0, P_i - C): the joint
covariance S has blocks S_ij = C, S_ii = P_i (rho = 0: independent; rho = 1: the largest
common error every node can hold; no rule can remove c). A rule with gains K_i
(sum K_i = I) has fused error sum K_i e_i, true error covariance K S K^T, and reports P.
Scores over `draws` error draws: MSE, ANEES (with its chi-square band), and exactly:
tr(K S K^T) and whether P - K S K^T is PSD (consistency).

Dynamic case: N Kalman filters (trackers.kalman.KalmanFilter) track one common target
(the Table 1 model, a = 0), each detecting with its own p_i, and report every step to a
fusion centre, one fusion_opt.ProcessingNode per rule. Their errors are correlated
through the common prior and process noise; the cross-covariances follow the exact
recursion of trackers.kalman.cross_covariance_step, which the known-cross rule uses.

Scaling: solve time of one fusion against N (n = 4) and against n, per backend, with the
log-log slope; measured once after the runs (scaling.json).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
from matplotlib.patches import Patch
from matplotlib.ticker import FuncFormatter

import fusion_opt as fo
from fusion_opt.prepare import MAX_CONDITION
from fusion_opt.validation import safe_repr
from trackers import kalman, metrics
from trackers.models import turn_model

from . import config as configs
from . import plotting, stats

SCALING = "scaling.json"
MEASUREMENTS = (SCALING,)  # files `benchmark` writes; the CLI records and verifies them
NAMED = ("sweeps",)  # a --config's [sweeps] replaces the default's whole (config.load)
RULES = {
    "naive": {"method": "naive"},
    "BCI trace": {"method": "bci", "criterion": "trace"},
    "BCI logdet": {"method": "bci", "criterion": "logdet"},
    "MBCI trace": {"method": "mbci", "criterion": "trace"},
    "MBCI logdet": {"method": "mbci", "criterion": "logdet"},
    "fast CI": {"method": "fast-ci"},
    "IFCI": {"method": "ifci"},
    "known cross": {"method": "known-cross"},
}
OPTIMISED = ("bci", "mbci")


# ---------------------------------------------------------------------- configuration

def _growth(where, x):
    return configs.number(where, x, low=1, why="a covariance growth chi^-1 per missed scan")


def _log10_range(where, x):
    low, high = (configs.number(f"{where}[{i}]", v)
                 for i, v in enumerate(configs.items(where, x, length=2)))
    if high < low:
        raise configs.ConfigError(f"{where} must be [low, high] with low <= high, got "
                                  f"{safe_repr(x)}")


SCALE_LOG10 = 100  # a static case's covariances stay within 10^-100..10^100
STATIC = {  # field of [static] -> its check
    "n": lambda w, x: configs.integer(w, x, low=1),
    "N": lambda w, x: configs.integer(w, x, low=2),
    "p_center": configs.probability, "spread": lambda w, x: configs.number(w, x, low=0),
    "p_min": lambda w, x: configs.number(w, x, high=1, above=0),
    "rho": configs.probability, "growth_true": _growth, "reported_share": configs.probability,
    "growth_assumed": _growth, "max_misses": lambda w, x: configs.integer(w, x, low=0),
    "base_log10": _log10_range, "draws": lambda w, x: configs.integer(w, x, low=1),
}
DYNAMIC = {
    "N": lambda w, x: [configs.integer(f"{w}[{i}]", v, low=2)
                       for i, v in enumerate(configs.items(w, x))],
    "steps": lambda w, x: configs.integer(w, x, low=1),
    "burn_in": lambda w, x: configs.integer(w, x, low=0),
    "dt": lambda w, x: configs.number(w, x, above=0),
    "q": lambda w, x: configs.number(w, x, above=0),
    "r": lambda w, x: configs.number(w, x, above=0),
    "p_center": configs.probability, "spread": lambda w, x: configs.number(w, x, low=0),
    "p_min": lambda w, x: configs.number(w, x, high=1, above=0), "growth_assumed": _growth,
    "threshold": lambda w, x: configs.number(w, x, above=0),
}


def check(config: dict) -> None:
    """Refuse, with a ConfigError naming the field, anything in config this study cannot
    run: called on the whole merged configuration before anything runs. Every value of
    every sweep is checked as the [static] field it replaces."""
    configs.fields(config, "", ("runs", "seed", "backend", "static", "sweeps", "dynamic",
                                "scaling"))
    configs.run_fields(config)
    static = configs.table(config["static"], "static", STATIC)
    backend = configs.choice("backend", config["backend"], fo.BACKENDS)
    _static_fits("static.n, static.N and static.draws", static, backend)
    _static_scales("static", static)
    sweeps = config["sweeps"]
    if not isinstance(sweeps, dict) or "N" not in sweeps:
        raise configs.ConfigError("[sweeps] must be a table with a sweep over N (the figures "
                                  f"plot it), got {safe_repr(sweeps)}")
    nodes = [static["N"]]
    for name, spec in sweeps.items():
        nodes += _check_sweep(static, name, spec, backend)
    dyn = configs.table(config["dynamic"], "dynamic", DYNAMIC)
    if dyn["burn_in"] >= dyn["steps"]:
        raise configs.ConfigError(f"dynamic.burn_in must be below dynamic.steps "
                                  f"({dyn['steps']}), got {dyn['burn_in']}")
    for i, N in enumerate(dyn["N"]):  # before the model check, which runs every step
        _dynamic_fits(f"dynamic.N[{i}] = {N} with dynamic.steps = {dyn['steps']}", dyn, N,
                      backend)  # (10^7 steps ran it for minutes, gigabytes: fuzz N9)
    _check_dynamic_model(dyn)
    configs.backend("backend", backend, nodes=max(nodes + list(dyn["N"])))
    _check_scaling(config["scaling"])


def _check_dynamic_model(dyn: dict) -> None:
    """The dynamic case's model, run on its covariances alone (no data, a few ms): the
    step's Q must be positive definite in float64; two nodes that detect at every step (the
    best case for telling their errors apart) must each have a covariance a fusion accepts,
    and so must a node never detecting, after `steps`; and the two must give joint
    covariances that "known cross" fuses after burn_in. A run where nodes miss can still
    fail later (its message says so); these fail at every seed (fuzz H5, H8, H9)."""
    where = (f"dynamic.dt = {dyn['dt']:.3g}, dynamic.q = {dyn['q']:.3g}, dynamic.r = "
             f"{dyn['r']:.3g}")
    try:
        model = dynamic_model(dyn)
    except fo.FusionInputError as exc:
        raise configs.ConfigError(f"{where}: {exc}") from None
    try:
        np.linalg.cholesky(model.Q)
    except np.linalg.LinAlgError:
        raise configs.ConfigError(f"{where}: the step's process noise covariance Q is not "
                                  f"positive definite in float64 (its smallest entry, "
                                  f"q dt^3 / 3, is {model.Q[0, 0]:.3g})") from None
    m0, P0 = dynamic_prior(model.n)
    C, joint = np.broadcast_to(P0, (2, 2, model.n, model.n)), []
    never = P0
    for t in range(dyn["steps"]):
        C = kalman.cross_covariance_step(C, np.ones(2, dtype=bool), model)[0]
        never = kalman.predict(m0, never, model.A, model.Q)[1]
        if t >= dyn["burn_in"]:
            joint.append(C)
    configs.fusable(f"{where}, dynamic.steps = {dyn['steps']}: the covariance of a node "
                    f"detecting at every step or of one never detecting is not one a fusion "
                    f"accepts", [C[0, 0], never])
    joint = np.array(joint)
    covs = np.diagonal(joint, axis1=1, axis2=2).transpose(0, 3, 1, 2)
    try:
        fo.fuse_batch(np.zeros(covs.shape[:-1]), covs, method="known-cross", cross=joint)
    except fo.FusionInputError as exc:
        raise configs.ConfigError(
            f"{where}, dynamic.burn_in = {dyn['burn_in']}: even two nodes that detect at "
            f"every step keep linearly dependent errors (the prior they share, e.g. its "
            f"velocity, is not yet measured away): {exc}") from None


def _check_scaling(sc) -> None:
    """[scaling]: two or more distinct sizes per axis (a log-log slope needs two), each
    fusion within fusion_opt.limits for every backend."""
    configs.fields(sc, "scaling", ("N", "n", "backends", "repeats"))
    sizes = {}
    for key, low in (("N", 2), ("n", 1)):
        values = configs.items(f"scaling.{key}", sc[key])
        sizes[key] = [configs.integer(f"scaling.{key}[{i}]", v, low=low)
                      for i, v in enumerate(values)]
        if len(set(values)) < 2:
            raise configs.ConfigError(f"scaling.{key} must hold two or more distinct sizes "
                                      f"(the log-log slope is fitted to them), got "
                                      f"{safe_repr(values)}")
    for i, b in enumerate(configs.items("scaling.backends", sc["backends"])):
        configs.backend(f"scaling.backends[{i}]", b, nodes=max(sizes["N"] + [8]))
        for key, shapes in (("N", [(4, N) for N in sizes["N"]]),
                            ("n", [(n, 8) for n in sizes["n"]])):
            for j, (n, N) in enumerate(shapes):
                configs.fusion_fits(f"scaling.{key}[{j}] with {b}", n, N, b)
    configs.integer("scaling.repeats", sc["repeats"], low=1)


def _static_fits(where: str, cfg: dict, backend: str) -> None:
    """Refuse a static case (cfg a [static] table) beyond fusion_opt.limits: its arrays
    (static_scores: the joint covariance (N n, N n) about four times over, the error
    draws (draws, N + 1, n) four times, the reported covariance per draw (draws, n, n))
    and its fusions."""
    N, n, draws = cfg["N"], cfg["n"], cfg["draws"]
    configs.fits(where, 8.0 * (4 * (N * n) ** 2 + 4 * draws * (N + 1) * n + draws * n * n))
    configs.fusion_fits(where, n, N, backend)


def _static_scales(where: str, cfg: dict) -> None:
    """Refuse a static case whose covariances could leave 10^-SCALE_LOG10..10^SCALE_LOG10:
    eigenvalues 10^base_log10, grown by growth_true up to max_misses times (the case's
    products and eigendecompositions, of their squares, stay finite there; growth_true =
    1e308 or base_log10 = [-320, -310] ended runs in numpy's LinAlgError), or whose
    eigenvalues span a condition the fusion refuses (growth scales a node's eigenvalues
    alike, so its condition is at most 10^(high - low))."""
    low, high = cfg["base_log10"]
    top = high + cfg["max_misses"] * math.log10(cfg["growth_true"])
    if low < -SCALE_LOG10 or top > SCALE_LOG10:
        raise configs.ConfigError(
            f"{where}: the covariances reach 10^{low:g} to 10^{top:.4g} (base_log10, grown "
            f"by growth_true up to max_misses times), outside "
            f"10^-{SCALE_LOG10}..10^{SCALE_LOG10}")
    if high - low > math.log10(MAX_CONDITION):
        raise configs.ConfigError(
            f"{where}: base_log10 spans {high - low:g} decades, so a node's covariance has a "
            f"condition up to 10^{high - low:g}, beyond the {MAX_CONDITION:.2g} a fusion "
            f"accepts (fuzz H2: [-100, 100] failed every run)")


def _dynamic_fits(where: str, dyn: dict, N: int, backend: str) -> None:
    """Refuse a dynamic case of N nodes beyond fusion_opt.limits: the cross-covariances
    kept per step after burn-in (N, N, 4, 4), twice, and the scans (about 50 words per
    node and step), and its fusions of N estimates."""
    steps = dyn["steps"]
    configs.fits(where, 8.0 * (32 * N * N * (steps - dyn["burn_in"]) + 50 * N * steps))
    configs.fusion_fits(where, 4, N, backend)


def _check_sweep(static: dict, name: str, spec, backend: str) -> list[int]:
    """Check one sweep (either form of sweep_spec), each of its cases within
    fusion_opt.limits; returns the node counts it uses."""
    where = f"sweeps.{name}"
    if isinstance(spec, dict):
        configs.fields(spec, where, ("field", "values"), ("fixed",))
        configs.choice(f"{where}.field", spec["field"], STATIC)
        if not isinstance(spec.get("fixed", {}), dict):
            raise configs.ConfigError(f"{where}.fixed must be a table of [static] fields, got "
                                      f"{safe_repr(spec['fixed'])}")
        configs.table(static | spec.get("fixed", {}), f"{where}.fixed", STATIC)
        if spec["field"] in spec.get("fixed", {}):  # the sweep's values would replace it
            raise configs.ConfigError(f"{where}.fixed sets {safe_repr(spec['field'])}, the field "
                                      f"the sweep varies")
        where += ".values"
    elif name not in STATIC:
        raise configs.ConfigError(f"{where} sweeps no field of [static] (one of "
                                  f"{list(STATIC)}); give a table {{field, values, fixed}}"
                                  + configs.renamed_hint([name], STATIC))
    field, values, fixed = sweep_spec(name, spec)
    values = configs.items(where, values)
    if len({str(v) for v in values}) != len(values):  # its results are kept by str(value)
        raise configs.ConfigError(f"{where} lists a value more than once: {safe_repr(values)}")
    for i, v in enumerate(values):
        STATIC[field](f"{where}[{i}]", v)
        _static_fits(f"{where}[{i}] = {v}", static | fixed | {field: v}, backend)
        _static_scales(f"{where}[{i}] = {v}", static | fixed | {field: v})
    return [(static | fixed | {field: v})["N"] for v in values]


# ------------------------------------------------------------------------ static case

def detection_probabilities(cfg: dict, N: int, rng) -> np.ndarray:
    lo = max(cfg["p_min"], cfg["p_center"] - cfg["spread"] / 2)
    hi = min(1.0, cfg["p_center"] + cfg["spread"] / 2)
    return rng.uniform(lo, max(lo, hi), N)


def static_case(cfg: dict, rng) -> dict:
    """covs (N, n, n) as reported, true_covs (N, n, n), the true joint cross (N, N, n, n),
    the square roots of the common and own error covariances (n, n) and (N, n, n),
    p (N,), misses (N,). A node reports the growth of a `reported_share` of its misses
    (1: its covariance is right; 0: it reports its covariance as of its last detection)."""
    N, n, rho = cfg["N"], cfg["n"], cfg["rho"]
    p = detection_probabilities(cfg, N, rng)
    misses = np.minimum(rng.geometric(p) - 1, cfg["max_misses"])
    rot = np.linalg.qr(rng.standard_normal((N, n, n)))[0]
    eig = 10.0 ** rng.uniform(*cfg["base_log10"], size=(N, 1, n))
    base = (rot * eig) @ np.swapaxes(rot, -1, -2)
    base = 0.5 * (base + np.swapaxes(base, -1, -2))

    def grown(k):
        return base * (cfg["growth_true"] ** k)[:, None, None]

    true_covs = grown(misses)
    common = rho * np.linalg.eigvalsh(true_covs).min() * np.eye(n)
    cross = np.broadcast_to(common, (N, N, n, n)).copy()
    cross[np.arange(N), np.arange(N)] = true_covs
    return {"covs": grown(cfg["reported_share"] * misses), "true_covs": true_covs,
            "cross": cross, "common_root": np.sqrt(common),
            "own_root": _psd_sqrt(true_covs - common), "p": p, "misses": misses}


def _psd_sqrt(A: np.ndarray) -> np.ndarray:
    """Symmetric square roots of PSD matrices (..., n, n) (Cholesky fails on singular
    ones, as P_i - C is at rho = 1)."""
    lam, V = np.linalg.eigh(A)
    return (V * np.sqrt(np.maximum(lam, 0.0))[..., None, :]) @ np.swapaxes(V, -1, -2)


def draw_errors(case: dict, draws: int, rng) -> np.ndarray:
    """Node errors (draws, N, n) with the joint covariance of the case."""
    N, n = case["covs"].shape[:2]
    z = rng.standard_normal((draws, N + 1, n))
    return (np.einsum("ab,db->da", case["common_root"], z[:, 0])[:, None, :]
            + np.einsum("iab,dib->dia", case["own_root"], z[:, 1:]))


def fuse_rule(name: str, means, covs, *, p, growth, backend, cross=None, batch=False):
    """One fusion by rule `name` of RULES (MBCI with p_detect p and growth, the growth it
    assumes); with batch=True, B of them at once by `fuse_batch` (means (B, N, n), cross
    (B, N, N, n, n))."""
    spec = dict(RULES[name])
    method = spec.pop("method")
    if method == "mbci":
        spec.update(p_detect=p, growth=growth)
    if method == "known-cross":
        spec["cross"] = cross
    if method in OPTIMISED:
        spec["backend"] = backend
    return (fo.fuse_batch if batch else fo.fuse)(means, covs, method=method, **spec)


def gains(name: str, result, case: dict, growth: float) -> np.ndarray:
    """K (N, n, n) of a rule's fused estimate, from its result (independent of the rule's
    code: CI family K_i = P w_i s_i Y_i; naive K_i = P Y_i; BLUE K = P H^T S^-1)."""
    covs = case["covs"]
    N, n = covs.shape[:2]
    Ys = np.linalg.inv(covs)
    P = result.cov
    if name == "known cross":
        S = np.concatenate(np.concatenate(case["cross"], axis=1), axis=1)
        X = np.linalg.solve(S, np.tile(np.eye(n), (N, 1))).reshape(N, n, n)
        return P @ np.swapaxes(X, -1, -2)
    if name == "naive":
        return P @ Ys
    s = fo.detection_scales(case["p"], growth=growth) if name.startswith("MBCI") \
        else np.ones(N)
    return P @ (result.weights[:, None, None] * s[:, None, None] * Ys)


def static_scores(cfg: dict, rng, backend: str) -> dict:
    case = static_case(cfg, rng)
    N, n = cfg["N"], cfg["n"]
    draws = cfg["draws"]
    e = draw_errors(case, draws, rng)
    S = np.concatenate(np.concatenate(case["cross"], axis=1), axis=1)
    growth = cfg["growth_assumed"]
    out = {}
    for name in RULES:
        t0 = time.perf_counter()
        # the known-cross optimum is told the truth: the true joint covariance
        covs = case["true_covs"] if name == "known cross" else case["covs"]
        r = fuse_rule(name, np.zeros((N, n)), covs, p=case["p"], growth=growth,
                      backend=backend, cross=case["cross"])
        wall = time.perf_counter() - t0
        K = gains(name, r, case, growth)
        Kf = np.concatenate(K, axis=1)  # (n, N n)
        true_cov = Kf @ S @ Kf.T
        err = np.einsum("iab,dib->da", K, e)
        margin = np.linalg.eigvalsh(r.cov - true_cov).min() / np.linalg.norm(r.cov, 2)
        out[name] = {
            "mse": float(np.mean(np.sum(err**2, axis=1))),
            "mse_exact": float(np.trace(true_cov)),
            "anees": metrics.anees(err, np.zeros_like(err),
                                   np.broadcast_to(r.cov, (draws, n, n))),
            "consistent": float(margin >= -1e-9),
            "trace": float(np.trace(r.cov)),
            "time": wall,
        }
    return out


# ----------------------------------------------------------------------- dynamic case

def simulate_target(dcfg: dict, N: int, rng) -> dict:
    """One target seen by N nodes: truth (T, n), scans (T, N) of measurements (k, 2) with
    k = 1 where node i detected at step t and 0 where it missed, detected (T, N) and the
    detection probabilities p (N,)."""
    model = dynamic_model(dcfg)
    n, T = model.n, dcfg["steps"]
    p = detection_probabilities(dcfg, N, rng)
    m0, P0 = dynamic_prior(n)
    x = m0 + np.linalg.cholesky(P0) @ rng.standard_normal(n)
    Lq = np.linalg.cholesky(model.Q)
    truth, detected, scans = np.empty((T, n)), np.empty((T, N), dtype=bool), []
    for t in range(T):
        x = model.A @ x + Lq @ rng.standard_normal(n)
        detected[t] = rng.random(N) < p
        y = x[:2] + np.sqrt(dcfg["r"]) * rng.standard_normal((N, 2))
        truth[t] = x
        scans.append([y[i:i + 1] if detected[t, i] else y[:0] for i in range(N)])
    return {"truth": truth, "scans": scans, "detected": detected, "p": p}


def dynamic_model(dcfg: dict):
    """The nodes' model and the truth's: the Table 1 model with turn rate a = 0."""
    return turn_model(0.0, dcfg["q"], dcfg["r"], dcfg["dt"])


def dynamic_prior(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The common prior (m0 (n,), P0 (n, n)) of the truth and of every node's filter."""
    return np.array([0.0, 0.0, 1.0, 0.0]), np.eye(n)


def fusion_centre(name: str, N: int, dcfg: dict, p, backend: str) -> fo.ProcessingNode:
    """A ProcessingNode fusing the N nodes (sources 0..N-1) by rule `name` of RULES (not
    "known cross": a processing node does not know cross-covariances). One target: its
    threshold is set so far above any error that every step forms one group."""
    spec = dict(RULES[name])
    if spec["method"] == "mbci":
        spec.update(p_detect=dict(enumerate(p)), growth=dcfg["growth_assumed"])
    if spec["method"] in OPTIMISED:
        spec["backend"] = backend
    return fo.ProcessingNode(range(N), threshold=dcfg["threshold"], min_sources=N,
                             name=name, **spec)


def dynamic_scores(dcfg: dict, N: int, rng, backend: str) -> dict:
    """MSE, ANEES, mean fused trace and time per fusion (s) of every rule over the steps
    after burn_in: N trackers.kalman.KalmanFilter nodes report each step to one
    ProcessingNode per rule; "known cross" fuses with the nodes' exact joint error
    covariance from trackers.kalman.cross_covariance_step, every step in one fuse_batch."""
    sim = simulate_target(dcfg, N, rng)
    model, (m0, P0) = dynamic_model(dcfg), dynamic_prior(4)
    filters = [kalman.KalmanFilter(model, m0, P0) for _ in range(N)]
    centres = {name: fusion_centre(name, N, dcfg, sim["p"], backend)
               for name in RULES if name != "known cross"}
    C = np.broadcast_to(P0, (N, N, 4, 4)).copy()  # the prior error is common to all nodes
    fused = {name: [] for name in centres}
    wall = dict.fromkeys(centres, 0.0)
    means, cross = [], []
    for t, scans in enumerate(sim["scans"]):
        reports = {i: f.step(scan) for i, (f, scan) in enumerate(zip(filters, scans,
                                                                       strict=True))}
        C = kalman.cross_covariance_step(C, sim["detected"][t], model)[0]
        if t < dcfg["burn_in"]:
            continue
        means.append([r.means[0] for r in reports.values()])
        cross.append(C)
        for name, centre in centres.items():
            t0 = time.perf_counter()
            fused[name].append(_one_track(centre.step(reports), name, reports, dcfg))
            wall[name] += time.perf_counter() - t0
    truth, steps = sim["truth"][dcfg["burn_in"]:], len(means)
    out = {name: _dynamic_row([e.means[0] for e in est], [e.covs[0] for e in est], truth,
                              wall[name] / steps) for name, est in fused.items()}
    cross = np.array(cross)
    t0 = time.perf_counter()
    try:
        known = fo.fuse_batch(np.array(means), np.diagonal(cross, axis1=1, axis2=2).transpose(
            0, 3, 1, 2), method="known-cross", cross=cross)
    except fo.FusionInputError as exc:
        # the errors share the prior and the process noise; each detection adds a node's
        # own 2-D noise to its 4-D error: until every node has about two, the joint is
        # singular (8 nodes, quick settings: for the first 3 to 5 or more steps of a run)
        raise fo.FusionInputError(
            f"{exc} after dynamic.burn_in = {dcfg['burn_in']} steps: until every node has "
            "made about two detections of its own, the nodes' errors are linearly "
            "dependent; a longer burn-in avoids it") from None
    out["known cross"] = _dynamic_row(known.mean, known.cov, truth,
                                      (time.perf_counter() - t0) / steps)
    return out


def _one_track(fused: fo.Estimates, name: str, reports: dict, dcfg: dict) -> fo.Estimates:
    """The one track the centre `name` made of the N reports, or an error saying how far
    apart the reports were (the threshold must exceed it)."""
    if len(fused) != 1:
        xy = np.array([r.means[0][:2] for r in reports.values()])
        spread = np.max(np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)))
        raise RuntimeError(
            f"the fusion centre {safe_repr(name)} made {len(fused)} tracks of the N = {len(xy)} "
            f"estimates of the one target: their positions lie up to {spread:.3g} m apart, "
            f"beyond dynamic.threshold = {dcfg['threshold']:.3g} (the filters' errors grow "
            f"with dynamic.dt and dynamic.q: raise the threshold above them)")
    return fused


def _dynamic_row(means, covs, truth, seconds) -> dict:
    means, covs = np.asarray(means), np.asarray(covs)
    return {"mse": metrics.mse(means, truth), "anees": metrics.anees(means, truth, covs),
            "trace": float(np.mean(np.trace(covs, axis1=1, axis2=2))), "time": seconds}


# ------------------------------------------------------------------------------ runs

def run_one(config: dict, index: int, seed: np.random.SeedSequence) -> tuple[dict, None]:
    """(every static sweep point and every dynamic N for one seed, no figure data: the
    figures draw the summaries); one child seed per sweep (common random numbers across a
    sweep's values)."""
    sweeps, dyn = config["sweeps"], config["dynamic"]
    children = seed.spawn(len(sweeps) + 1)
    static = {}
    for (name, spec), ss in zip(sweeps.items(), children, strict=False):
        field, values, fixed = sweep_spec(name, spec)
        static[name] = {str(v): static_scores(config["static"] | fixed | {field: v},
                                              np.random.default_rng(ss), config["backend"])
                        for v in values}
    dyn_seeds = children[-1].spawn(len(dyn["N"]))
    dynamic = {str(N): dynamic_scores(dyn, N, np.random.default_rng(ss), config["backend"])
               for N, ss in zip(dyn["N"], dyn_seeds, strict=True)}
    return {"static": static, "dynamic": dynamic}, None


def sweep_spec(name: str, spec) -> tuple[str, list, dict]:
    """(field, values, fixed settings) of a sweep: a list of values of the field `name`,
    or a table {field, values, fixed} (a sweep of one field with others held apart)."""
    if not isinstance(spec, dict):  # a list (`check` refuses anything else)
        return name, spec, {}
    return spec["field"], spec["values"], spec.get("fixed", {})


# --------------------------------------------------------------------------- scaling

def benchmark(config: dict, out: Path, progress: bool = True) -> None:
    """Median solve time per backend against N (n = 4) and against n (N = 8), with the
    log-log slope of each; written to scaling.json (measured once, after the runs)."""
    sc = config["scaling"]
    rng = np.random.default_rng(config["seed"])
    result = {"vs_N": {}, "vs_n": {}, "repeats": sc["repeats"]}
    for backend in sc["backends"]:
        result["vs_N"][backend] = {str(N): _time_solve(backend, 4, N, sc["repeats"], rng)
                                   for N in sc["N"]}
        result["vs_n"][backend] = {str(n): _time_solve(backend, n, 8, sc["repeats"], rng)
                                   for n in sc["n"]}
        if progress:
            print(f"nnode scaling: {backend} timed", flush=True)
    (Path(out) / SCALING).write_text(json.dumps(result, indent=1))


def _time_solve(backend: str, n: int, N: int, repeats: int, rng) -> float:
    """Median wall time (s) of fo.bci (trace) on random instances, after one warm-up solve
    (so a cached program is what is timed); NaN if the backend failed on any of them."""
    times = []
    for k in range(repeats + 1):
        rot = np.linalg.qr(rng.standard_normal((N, n, n)))[0]
        covs = (rot * 10.0 ** rng.uniform(-1, 1, (N, 1, n))) @ np.swapaxes(rot, -1, -2)
        covs = 0.5 * (covs + np.swapaxes(covs, -1, -2))
        t0 = time.perf_counter()
        try:
            fo.bci(np.zeros((N, n)), covs, "trace", backend)
        except fo.FusionSolverError:
            return float("nan")
        if k:
            times.append(time.perf_counter() - t0)
    return float(np.median(times))


def slope(xs, ys) -> float | None:
    """Least-squares slope of log(y) against log(x), over the points that are not NaN (a
    solve that failed); None without two such points of distinct x."""
    x, y = np.asarray(xs, float), np.asarray(ys, float)
    ok = np.isfinite(y)
    if len(set(x[ok])) < 2:
        return None
    return float(np.polyfit(np.log(x[ok]), np.log(y[ok]), 1)[0])


def _finite(x: float) -> float | None:
    """x, or None (an empty CSV cell, "-" in a table) for the NaN of a failed solve."""
    return x if x is not None and np.isfinite(x) else None


def _cell(x: float | None, spec: str) -> str:
    return "-" if _finite(x) is None else format(x, spec)


# ---------------------------------------------------------------------------- report

def report(config: dict, results: list[dict], out: Path, figure: None) -> None:
    """nnode.md (a table per sweep, dynamic, scaling), its tables as CSV files and the
    figures (drawn from the summaries: the runs return no figure data, so figure is None)."""
    out = Path(out)
    lines = [f"# N-node fusion study ({len(results)} runs, seed {config['seed']}, backend "
             f"{config['backend']})", "", "Mean [95% interval] over runs. MSE of the fused "
             "estimate over error draws; ANEES over draws (band for the mean of chi2(n)); "
             "consistent: share of runs with P - K S K^T PSD (exact). "
             + stats.INTERVAL_NOTE, ""]
    n, draws = config["static"]["n"], config["static"]["draws"]
    band = metrics.anees_bounds(n, draws)
    for field in config["sweeps"]:
        lines += _sweep_tables(results, field, config["sweeps"][field], band)
    lines += _dynamic_table(config, results)
    lines += _scaling_table(out)
    (out / "nnode.md").write_text("\n".join(lines) + "\n")
    _csv_tables(config, results, out)
    _figures(config, results, out, band)


def _csv_tables(config, results, out: Path) -> None:
    """The tables of nnode.md as CSV, one line per (value, rule): nnode_sweep_NAME.csv and
    nnode_sweep_NAME_paired.csv per sweep, nnode_dynamic.csv, nnode_scaling.csv."""
    def cells(path, rule, keys):
        return {f"{k}_{s}": v for k in keys
                for s, v in zip(("mean", "low", "high"), _summary(results, path, rule, k),
                                strict=True)}

    for name, spec in config["sweeps"].items():
        field = sweep_spec(name, spec)[0]
        values = list(results[0]["static"][name])
        stats.write_rows(out / f"nnode_sweep_{name}.csv", [
            {field: v, "rule": rule, **cells(("static", name, v), rule,
                                             ("mse", "anees", "consistent"))}
            for v in values for rule in RULES])
        stats.write_rows(out / f"nnode_sweep_{name}_paired.csv", [
            {field: v, "criterion": crit, **_mbci_minus_bci(results, name, v, crit)}
            for v in values for crit in ("trace", "logdet")])
    stats.write_rows(out / "nnode_dynamic.csv", [
        {"N": N, "rule": rule, **cells(("dynamic", N), rule, ("mse", "anees", "time"))}
        for N in results[0]["dynamic"] for rule in RULES])
    sc = _scaling(out)
    if sc is not None:
        stats.write_rows(out / "nnode_scaling.csv", [
            {"axis": axis, "backend": b, "size": k, "median_s": _finite(t),
             "loglog_slope": slope([float(k) for k in times], list(times.values()))}
            for axis in ("vs_N", "vs_n") for b, times in sc[axis].items()
            for k, t in times.items()])


def _mbci_minus_bci(results, name, v, crit) -> dict:
    """MBCI minus BCI (MSE, criterion crit) at value v of sweep name, paired over runs."""
    return stats.paired(*([r["static"][name][v][f"{rule} {crit}"]["mse"] for r in results]
                          for rule in ("MBCI", "BCI")))


def _summary(results, path, rule, key):
    """mean_ci of results[...][path...][rule][key] over runs."""
    vals = []
    for r in results:
        node = r
        for p in path:
            node = node[p]
        vals.append(node[rule][key])
    return stats.mean_ci(vals)


def _sweep_tables(results, name, spec, band) -> list[str]:
    field, _, fixed = sweep_spec(name, spec)
    values = list(results[0]["static"][name])
    head = "| " + field + " | " + " | ".join(RULES) + " |"
    rule_line = "|---" * (len(RULES) + 1) + "|"
    held = f" (with {', '.join(f'{k} = {v}' for k, v in fixed.items())})" if fixed else ""
    lines = [f"## Static sweep over {field}{held}: MSE", "", head, rule_line]
    for v in values:
        cells = [stats.fmt(*_summary(results, ("static", name, v), r, "mse"), 3)
                 for r in RULES]
        lines.append(f"| {v} | " + " | ".join(cells) + " |")
    lines += ["", f"## Static sweep over {field}{held}: ANEES (band {band[0]:.2f}-"
              f"{band[1]:.2f}) and share consistent", "", head, rule_line]
    for v in values:
        cells = [f"{_summary(results, ('static', name, v), r, 'anees')[0]:.2f} / "
                 f"{_summary(results, ('static', name, v), r, 'consistent')[0]:.2f}"
                 for r in RULES]
        lines.append(f"| {v} | " + " | ".join(cells) + " |")
    lines += ["", f"MBCI minus BCI, paired over runs (MSE; negative: MBCI better){held}:", "",
              f"| {field} | trace: mean [95%] | share MBCI lower | logdet: mean [95%] "
              "| share MBCI lower |", "|---|---|---|---|---|"]
    for v in values:
        cells = []
        for crit in ("trace", "logdet"):
            d = _mbci_minus_bci(results, name, v, crit)
            cells += [stats.fmt(d["mean_diff"], d["low"], d["high"], 3),
                      stats.fmt_share(d)]
        lines.append(f"| {v} | " + " | ".join(cells) + " |")
    return lines + [""]


def _dynamic_table(config, results) -> list[str]:
    d = config["dynamic"]
    band = metrics.anees_bounds(4, d["steps"] - d["burn_in"])
    lines = ["## Dynamic: N Kalman filters, fusion every step", "",
             f"MSE / ANEES (band {band[0]:.2f}-{band[1]:.2f} if the steps were independent; "
             "they are not, so read it loosely) / time per fusion (ms)", "",
             "| N | " + " | ".join(RULES) + " |", "|---" * (len(RULES) + 1) + "|"]
    for N in results[0]["dynamic"]:
        cells = []
        for r in RULES:
            mse = _summary(results, ("dynamic", N), r, "mse")[0]
            anees = _summary(results, ("dynamic", N), r, "anees")[0]
            ms = 1e3 * _summary(results, ("dynamic", N), r, "time")[0]
            cells.append(f"{mse:.4f} / {anees:.2f} / {ms:.2f}")
        lines.append(f"| {N} | " + " | ".join(cells) + " |")
    return lines + [""]


def _scaling(out: Path) -> dict | None:
    path = out / SCALING
    return json.loads(path.read_text()) if path.exists() else None


def _scaling_table(out: Path) -> list[str]:
    sc = _scaling(out)
    if sc is None:
        return ["## Scaling", "", "not measured (run the study to measure it)", ""]
    lines = ["## Scaling: median time per BCI solve (ms), trace criterion ('-': the "
             "backend failed)", ""]
    for axis, label in (("vs_N", "N (n = 4)"), ("vs_n", "n (N = 8)")):
        keys = list(next(iter(sc[axis].values())))
        lines += ["| backend | " + " | ".join(f"{label.split()[0]} = {k}" for k in keys)
                  + " | log-log slope |", "|---" * (len(keys) + 2) + "|"]
        for backend, times in sc[axis].items():
            s = slope([float(k) for k in times], list(times.values()))
            cells = [_cell(1e3 * t, ".3g") for t in times.values()] + [_cell(s, ".2f")]
            lines.append(f"| {backend} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines


# a colour, marker and line per rule: rules that coincide (fast CI, IFCI and known cross
# in MSE; the BCI and MBCI pairs) stay apart by their markers and dashes
RULE_STYLE = {rule: {"color": f"C{i}", "marker": "osD^vPX*"[i], "ms": 4.5,
                     "fillstyle": "none", "ls": ("-", "--", ":", "-.")[i % 4], "lw": 1.3}
              for i, rule in enumerate(RULES)}


def _figures(config, results, out, band) -> None:
    Ns = list(results[0]["static"]["N"])
    x = [int(v) for v in Ns]
    fig, axes = plotting.panels(1, 3, width=16, height=5.6)
    mse, excess, anees = axes
    best = np.array([_summary(results, ("static", "N", v), "known cross", "mse")[0]
                     for v in Ns])
    for rule in RULES:
        for ax, key in ((mse, "mse"), (anees, "anees")):
            m = np.array([_summary(results, ("static", "N", v), rule, key) for v in Ns])
            ax.plot(x, m[:, 0], label=rule, **RULE_STYLE[rule])
            ax.fill_between(x, m[:, 1], m[:, 2], color=RULE_STYLE[rule]["color"], alpha=0.1,
                            lw=0)
            if key == "mse":
                excess.plot(x, 100 * (m[:, 0] / best - 1), **RULE_STYLE[rule])
    anees.axhspan(*band, color="black", alpha=0.12, lw=0)
    n = config["static"]["n"]
    for ax, label in ((mse, f"MSE of the fused estimate (state units², n = {n})"),
                      (anees, f"ANEES ({n} dof: {n} if consistent)")):
        plotting.log_axes(ax, x, "N (nodes)")
        ax.set_ylabel(label)
    for axis in (mse.yaxis, anees.yaxis):  # 0.6, 2, 4 rather than 6 x 10^-1, 2 x 10^0
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if
                                               f"{v:.1g}"[0] in "2346" else ""))
    plotting.log_axes(excess, x, "N (nodes)")
    excess.set_yscale("symlog", linthresh=1.0)  # 0-1% linear, logarithmic above
    excess.set_ylim(bottom=-0.2)
    excess.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    excess.set_ylabel("mean MSE above known cross's (%)")
    for ax, title in ((mse, "MSE"), (excess, "distance to the optimum, known cross "
                                            "(y linear below 1%)"), (anees, "ANEES")):
        ax.set_title(title, fontsize=10)
    bands = [Patch(color="C0", alpha=0.25, lw=0, label="shaded: 95% interval of the "
                   "mean over runs (bootstrap), in the rule's colour"),
             Patch(color="black", alpha=0.12, lw=0, label=f"grey: 95% band of the ANEES "
                   f"of a consistent estimate ({band[0]:.2f}-{band[1]:.2f})")]
    plotting.legend_below(fig, axes[0].get_lines() + bands, ncol=5)
    fig.suptitle(f"N-node static case: MSE and ANEES against N, the other fields as "
                 f"[static] ({len(results)} runs, seed {config['seed']})", fontsize=11)
    plotting.save(fig, out / "nnode_mse_anees_vs_N.png")
    sc = _scaling(out)
    if sc is not None:
        fig, axes = plotting.panels(1, 1, width=6.5, height=5.4)
        for i, (backend, times) in enumerate(sc["vs_N"].items()):
            axes[0].plot([int(k) for k in times], [1e3 * t for t in times.values()],
                         color=f"C{i}", marker="osD^v"[i % 5], fillstyle="none",
                         label=backend)
        plotting.log_axes(axes[0], [int(k) for k in next(iter(sc["vs_N"].values()))],
                          "N (nodes), n = 4")
        axes[0].set_ylabel("median wall time per solve (ms)")
        plotting.legend_below(fig, axes[0].get_lines())
        fig.suptitle(f"BCI (trace) solve time against N: median of {sc['repeats']} random "
                     f"problems per point (seed {config['seed']})", fontsize=10)
        plotting.save(fig, out / "nnode_time_vs_N.png")

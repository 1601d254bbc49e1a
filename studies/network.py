"""Network example: 16 RBMCDA monitoring nodes, 4 processing nodes in two levels, 20
crossing targets; and the throughput of one processing node.

A runnable example of the library as a user would deploy it: every monitoring node is a
`trackers.rbmcda.RBMCDA`, every processing node a `fusion_opt.ProcessingNode`, and one
`fusion_opt.Network` steps them all. The study only simulates the scenario, configures the
network and scores what comes out; association, fusion and fused ids are the library's.

Scenario: trackers.scenarios.CrossingConfig (its docstring; every number is a field of
[scenario] in studies/configs/network.toml), simulated by simulate_crossing: 20 targets
on a circle heading for its centre, so the paths cross near the middle, born in four
waves, a third turning gently; each monitoring node detects each alive target with its
own p_D (Table 2's one-measurement-per-step model would give each of 20 targets a
detection every 20 steps) and has its own clutter rate.

- Each monitoring node runs RBMCDA with the constant-velocity model (q as the truth's),
  the new-target prior N(0, diag(prior_pos_var, prior_pos_var, prior_vel_var,
  prior_vel_var)) and the settings of [tracker].
- Processing nodes, for each fusion rule of [rules] (one copy of the hierarchy per rule,
  all fed by the same trackers): first-level nodes fuse the monitoring nodes named in
  network.level1, second-level nodes fuse the first-level nodes named in network.level2.
  The default has three first-level nodes over 6 monitoring nodes each, overlapping in
  nodes 6 and 11 (as Table 2's processing nodes share nodes 3 and 5), and one
  second-level node over the three: its sources share information (the common target
  and the overlapping nodes), which CI-family rules tolerate and naive fusion counts
  twice. Association by position (network.association, network.threshold); a group of
  fewer than network.min_sources sources is dropped, and a fused id stays claimable for
  network.memory steps after its track was last reported (ProcessingNode's memory).
- MBCI: each monitoring node's p_D as its p_detect; a first-level node, as a source of the
  second level, has p_detect = 1 - prod_i (1 - p_D[i]) over its monitoring nodes (our
  assumption: the probability that at least one of them detects the target at a step),
  and growth = fusion.growth (the paper's chi^-1 = 1 + dt) at both levels.

Scores per node and rule, over the steps of one run (position = state components 0, 1):

- OSPA and GOSPA (trackers.metrics, position, cut-off c = metrics.cutoff, order
  p = metrics.order, GOSPA alpha = metrics.alpha), means over the steps;
- cardinality error: mean over the steps of |n_estimated - n_alive|;
- matching: at each step the node's estimates are assigned to the alive targets by an
  optimal assignment on position with cost min(d, c), and a pair is matched iff d < c;
- id switches per target: for each target j, the ids of the estimates matched to j at the
  steps where j is matched, in step order; its switches are the number of consecutive
  entries of that sequence that differ (steps where j is unmatched are skipped, so a
  track that drops out and comes back with its id is no switch). The score is the mean
  of the switches over the targets alive at some step (a never-matched target counts 0;
  its misses are in OSPA and GOSPA);
- ANEES: the mean over all matched (estimate, target) pairs of all steps of the full-state
  NEES (m - x)^T P^-1 (m - x), 4 degrees of freedom: about 4 for a consistent estimate
  (not divided by the dimension, as in Table 1).

Run FIGURE_RUN also returns the figure data (true paths and the estimates of the nodes in
[figure]), kept by the store beside its scores, so `report` draws without simulating.

Throughput (`benchmark`, measured once after the runs by the CLI, written to
throughput.json, which `report` reads): one ProcessingNode (benchmark.backend,
benchmark.criterion, benchmark.association) steps on synthetic reports: targets on a
square grid spaced benchmark.spacing (far beyond benchmark.threshold, so groups are the
targets), each source reporting each target with its p_D (spread evenly over
benchmark.p_detect) with a mean off by N(0, noise_sd^2) per component and a fixed random
covariance noise_sd^2 (I + G G^T), G (4, 4) standard normal, per (source, target); each
source's track id of a target is the target's index, so fused ids persist. Timed:
ProcessingNode.step alone (reports are built before the clock starts), after
benchmark.warmup untimed steps (the compiled kernels load on the first). Per-step latency
median and p90 over benchmark.steps steps; fused tracks per second = the tracks the node
output over the timed steps / their total time.

Where the time goes (timers around associate, fuse_batch and the id step inside
ProcessingNode.step, newton, at commit 80eb0aa; pyinstrument does not see the time spent
in the compiled kernels and puts it elsewhere): fuse_batch 45-63% of a step, association
16-40% (its share grows with the number of sources: the k-d tree pairs grow as the square
of the estimates per target), the fused-id bookkeeping 6-15%, the rest (checks, the
Estimates) 3-11%.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.lines import Line2D
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

import fusion_opt as fo
from fusion_opt.validation import safe_repr
from trackers import kalman, metrics, rbmcda
from trackers.scenarios import CrossingConfig, MultiTargetData, simulate_crossing

from . import config as configs
from . import plotting, stats
from .runner import FIGURE_RUN

POSITION = [0, 1]  # position components of the state [x, y, vx, vy]
COLUMNS = ("ospa", "gospa", "card_err", "id_switches", "anees")
HEADERS = ("OSPA", "GOSPA", "card. error", "id switches / target", "ANEES (4-dof)")
MONITOR = "RBMCDA"  # the rule column of a monitoring node's row
RULE_METHODS = ("bci", "mbci", "naive", "fast-ci", "ifci")  # rules fusing groups of any size
CI_FAMILY = ("bci", "mbci")
THROUGHPUT = "throughput.json"
MEASUREMENTS = (THROUGHPUT,)  # files `benchmark` writes; the CLI records and verifies them
# tables of named entries: a --config's replaces the default's whole (config.load)
NAMED = ("network.level1", "network.level2", "rules")


# ---------------------------------------------------------------------- configuration

def _positive(where, x):
    return configs.number(where, x, above=0)


def _scale(where, x):
    """A length of the synthetic scene: its squares (covariances) stay far inside float64."""
    return configs.number(where, x, low=1e-100, high=1e100, why="positions and their "
                          "covariances (its square) must stay well inside float64's range")


def _count(where, x):
    return configs.integer(where, x, low=1)


def _numbers(where, x, rule=configs.number):
    return [rule(f"{where}[{i}]", v) for i, v in enumerate(configs.items(where, x))]


TRACKER = {
    "n_particles": _count, "birth_prob": configs.probability, "clutter_prior": configs.probability,
    "lifetime_shape": _positive, "lifetime_scale": _positive, "clutter_density": _positive,
    "prior_pos_var": _positive, "prior_vel_var": _positive,
    "resample_threshold": configs.probability,
}
METRICS = {"cutoff": _positive, "order": lambda w, x: configs.number(w, x, low=1),
           "alpha": lambda w, x: configs.number(w, x, high=2, above=0)}
BENCHMARK = {
    "sources": lambda w, x: _numbers(w, x, lambda ww, v: configs.integer(ww, v, low=2)),
    "targets_at_sources": _count,
    "targets": lambda w, x: _numbers(w, x, _count),
    "sources_at_targets": lambda w, x: configs.integer(w, x, low=2),
    "methods": lambda w, x: [configs.choice(f"{w}[{i}]", v, CI_FAMILY)
                             for i, v in enumerate(configs.items(w, x))],
    "p_detect": lambda w, x: [configs.probability(f"{w}[{i}]", v)
                              for i, v in enumerate(configs.items(w, x, length=2))],
    "noise_sd": _scale, "spacing": _scale, "threshold": _positive,
    "growth": configs.growth, "warmup": _count, "steps": _count,
    "backend": lambda w, x: configs.choice(w, x, fo.BACKENDS),
    "criterion": lambda w, x: configs.choice(w, x, ("trace", "logdet")),
    "association": lambda w, x: configs.choice(w, x, ("nearest", "assignment")),
}


def check(config: dict) -> None:
    """Refuse, with a ConfigError naming the field, anything in config this study cannot
    run: called on the whole merged configuration before anything runs."""
    configs.fields(config, "", ("runs", "seed", "backend", "scenario", "tracker", "network",
                                "rules", "fusion", "metrics", "figure", "benchmark"))
    configs.run_fields(config)
    sc = scenario(config)
    tr = configs.table(config["tracker"], "tracker", TRACKER)
    if tr["birth_prob"] == 0 and tr["clutter_prior"] == 0:
        raise configs.ConfigError("tracker.birth_prob and tracker.clutter_prior must not "
                                  "both be 0: nothing could explain a measurement")
    configs.construct("tracker", monitoring_node, config, sc, 1, np.random.default_rng(0))
    _check_first_update(sc, tr)
    width = _check_network(config["network"], len(sc.p_detect))
    configs.backend("backend", config["backend"], nodes=width)
    _check_rules(config["rules"])
    fusion = configs.fields(config["fusion"], "fusion", ("growth",))
    configs.growth("fusion.growth", fusion["growth"])
    configs.table(config["metrics"], "metrics", METRICS)
    _check_figure(config)
    bm = configs.table(config["benchmark"], "benchmark", BENCHMARK)
    configs.backend("benchmark.backend", bm["backend"],
                    nodes=max(bm["sources"] + [bm["sources_at_targets"]]))
    for where, S, J in (("benchmark.sources and targets_at_sources", max(bm["sources"]),
                         bm["targets_at_sources"]),
                        ("benchmark.sources_at_targets and targets", bm["sources_at_targets"],
                         max(bm["targets"]))):
        configs.fits(where, 8.0 * 64 * S * J)  # synthetic_scene: G and covs (S, J, 4, 4)


def _check_first_update(sc: CrossingConfig, tr: dict) -> None:
    """A new track's covariance after its first measurement, from the tracker's prior and
    scenario.meas_sd, must be one the fusion accepts: positions near min(prior_pos_var,
    meas_sd^2), velocities at prior_vel_var (fuzz H7: prior_vel_var = 1e300 passed the
    check and failed every run at its first fusion)."""
    model = sc.filter_model()
    P0 = np.diag([tr["prior_pos_var"]] * 2 + [tr["prior_vel_var"]] * 2)
    P1 = kalman.update(np.zeros(4), P0, np.zeros(2), model.H, model.R)[1]
    configs.fusable(f"tracker.prior_pos_var = {tr['prior_pos_var']:.3g}, tracker.prior_vel_var"
                    f" = {tr['prior_vel_var']:.3g} with scenario.meas_sd = {sc.meas_sd:.3g}: "
                    f"a new track's covariance after its first update is not one a fusion "
                    f"accepts", [P1, P1])


def _check_network(net, monitors: int) -> int:
    """Check [network]; returns the most sources any processing node fuses."""
    configs.fields(net, "network", ("level1", "level2", "association", "threshold",
                                    "min_sources", "memory"))
    configs.integer("network.memory", net["memory"], low=1)
    configs.choice("network.association", net["association"], ("nearest", "assignment"))
    configs.number("network.threshold", net["threshold"], above=0)
    level1 = configs.sources(net["level1"], "network.level1",
                             lambda w, k: configs.integer(w, k, low=1, high=monitors))
    level2 = configs.sources(net["level2"], "network.level2",
                             lambda w, k: configs.choice(w, k, list(level1)))
    both = sorted(set(level1) & set(level2))
    if both:
        raise configs.ConfigError(f"network.level2 reuses the first-level names {both}")
    minimum = configs.fields(net["min_sources"], "network.min_sources", ("level1", "level2"))
    for level, nodes in (("level1", level1), ("level2", level2)):
        configs.integer(f"network.min_sources.{level}", minimum[level], low=1,
                        high=min(len(m) for m in nodes.values()))
    return max(len(m) for m in (*level1.values(), *level2.values()))


def _check_rules(rules) -> None:
    """[rules]: name -> {method, criterion}; criterion for the CI family only."""
    if not isinstance(rules, dict) or not rules:
        raise configs.ConfigError(f"[rules] must name at least one fusion rule, got "
                                  f"{safe_repr(rules)}")
    for name, spec in rules.items():
        where = f"rules.{name}"
        configs.fields(spec, where, ("method",), ("criterion",))
        configs.choice(f"{where}.method", spec["method"], RULE_METHODS)
        if spec["method"] in CI_FAMILY:
            configs.fields(spec, where, ("method", "criterion"))
            configs.choice(f"{where}.criterion", spec["criterion"], ("trace", "logdet"))
        elif "criterion" in spec:
            raise configs.ConfigError(f"{where}.criterion applies to methods {list(CI_FAMILY)}"
                                      f", not {safe_repr(spec['method'])}")


def _check_figure(config) -> None:
    fig = configs.fields(config["figure"], "figure", ("rule", "nodes"))
    configs.choice("figure.rule", fig["rule"], list(config["rules"]))
    names = [*config["network"]["level1"], *config["network"]["level2"]]
    for i, node in enumerate(configs.items("figure.nodes", fig["nodes"])):
        configs.choice(f"figure.nodes[{i}]", node, names)


# --------------------------------------------------------------------------- scenario

def scenario(config: dict) -> CrossingConfig:
    """The [scenario] table as trackers.scenarios.CrossingConfig (checked by it)."""
    return configs.build(CrossingConfig, config["scenario"], "scenario")


# ---------------------------------------------------------------------------- network

def monitor_name(k: int) -> str:
    return f"{MONITOR} {k}"


def build_network(config: dict, rngs) -> fo.Network:
    """RBMCDA trackers "RBMCDA k" (k = 1..len(rngs), each with its generator) and, per
    rule R of [rules], the processing nodes "R NAME" of both levels."""
    sc = scenario(config)
    trackers = {monitor_name(k): monitoring_node(config, sc, k, rng)
                for k, rng in enumerate(rngs, start=1)}
    processing = {}
    for rule, spec in config["rules"].items():
        for name, (sources, p_detect, level) in _levels(config, rule).items():
            processing[name] = fo.ProcessingNode(
                sources, **_rule_args(config, spec, p_detect), name=name,
                association=config["network"]["association"],
                threshold=config["network"]["threshold"], dims=POSITION,
                min_sources=config["network"]["min_sources"][level],
                memory=config["network"]["memory"])
    return fo.Network(trackers, processing)


def monitoring_node(config: dict, sc: CrossingConfig, k: int, rng) -> rbmcda.RBMCDA:
    """Monitoring node k: RBMCDA with the settings of [tracker] (the check makes one: it
    refuses sizes and settings before any run)."""
    tr = config["tracker"]
    P0 = np.diag([tr["prior_pos_var"]] * 2 + [tr["prior_vel_var"]] * 2)
    settings = {key: v for key, v in tr.items() if key not in ("prior_pos_var", "prior_vel_var")}
    return rbmcda.RBMCDA(sc.filter_model(), np.zeros(4), P0, rng=rng, dt=sc.dt,
                         name=monitor_name(k), **settings)


def _levels(config: dict, rule: str) -> dict:
    """{"rule NAME": (sources, {source: p_detect}, "level1" | "level2")} of one rule."""
    net, p = config["network"], config["scenario"]["p_detect"]
    p_first = {}
    nodes = {}
    for node, members in net["level1"].items():
        nodes[f"{rule} {node}"] = ([monitor_name(k) for k in members],
                                   {monitor_name(k): p[k - 1] for k in members}, "level1")
        p_first[f"{rule} {node}"] = 1 - float(np.prod([1 - p[k - 1] for k in members]))
    for node, members in net["level2"].items():
        sources = [f"{rule} {m}" for m in members]
        nodes[f"{rule} {node}"] = (sources, {s: p_first[s] for s in sources}, "level2")
    return nodes


def _rule_args(config: dict, spec: dict, p_detect: dict) -> dict:
    """ProcessingNode arguments of one rule: method, and criterion and backend for the
    CI family, p_detect and growth for MBCI."""
    args = {"method": spec["method"]}
    if spec["method"] in CI_FAMILY:
        args |= {"criterion": spec["criterion"], "backend": config["backend"]}
    if spec["method"] == "mbci":
        args |= {"p_detect": p_detect, "growth": config["fusion"]["growth"]}
    return args


def run_network(config: dict, seed: np.random.SeedSequence):
    """One run: (MultiTargetData, {node name: list over steps of Estimates})."""
    sc = scenario(config)
    sim_seed, *node_seeds = seed.spawn(1 + len(sc.p_detect))
    data = simulate_crossing(sc, np.random.default_rng(sim_seed))
    net = build_network(config, [np.random.default_rng(s) for s in node_seeds])
    scans = [{monitor_name(k): node.scans[t] for k, node in enumerate(data.nodes, start=1)}
             for t in range(sc.n_steps)]
    return data, net.run(scans, times=data.times.tolist())


# ---------------------------------------------------------------------------- scoring

def matches(series, truth: np.ndarray, alive: np.ndarray, c: float) -> list[tuple]:
    """Per step, the estimates matched to the alive targets (truth (J, T, >= 2), alive
    (J, T)) by trackers.metrics.match on position, gated at c: (estimate rows (K,),
    target indices (K,)); series holds one Estimates per step."""
    out = []
    for t, e in enumerate(series):
        on = np.flatnonzero(alive[:, t])
        rows, cols = metrics.match(e.means[:, POSITION], truth[on, t][:, POSITION], c)
        out.append((rows, on[cols]))
    return out


def matched_ids(series, pairs: list[tuple], n_targets: int) -> list[list[int]]:
    """For each of the n_targets targets, the ids of the estimates matched to it (pairs of
    `matches`), in step order."""
    ids: list[list[int]] = [[] for _ in range(n_targets)]
    for e, (rows, targets) in zip(series, pairs, strict=True):
        for i, j in zip(rows.tolist(), targets.tolist(), strict=True):
            ids[j].append(int(e.ids[i]))
    return ids


def id_switches(ids: list[list[int]], alive: np.ndarray) -> float:
    """Mean over the targets alive at some step (alive (J, T)) of trackers.metrics'
    id_switches of their matched ids (module docstring)."""
    present = np.flatnonzero(alive.any(axis=1))
    switches = metrics.id_switches([ids[j] for j in present])
    return float(switches.mean()) if present.size else 0.0


def scores(config: dict, data: MultiTargetData, series) -> dict:
    """OSPA, GOSPA, cardinality error, id switches per target and ANEES of one node's
    Estimates series (one per step) against the truth (module docstring)."""
    m = config["metrics"]
    ospa, gospa, card, est, true, covs, pairs = [], [], [], [], [], [], []
    for t, e in enumerate(series):
        on = np.flatnonzero(data.alive[:, t])
        X = data.truth[on, t][:, POSITION]
        errors = metrics.set_errors(e.means[:, POSITION], X, m["cutoff"], m["order"],
                                    m["alpha"])
        rows, targets = errors.rows, on[errors.cols]  # as `matches` gives them
        pairs.append((rows, targets))
        ospa.append(errors.ospa)
        gospa.append(errors.gospa)
        card.append(abs(len(e) - len(X)))
        est.append(e.means[rows])
        true.append(data.truth[targets, t])
        covs.append(e.covs[rows])
    nees = metrics.nees(np.concatenate(est), np.concatenate(true), np.concatenate(covs))
    ids = matched_ids(series, pairs, len(data.truth))
    return {"ospa": float(np.mean(ospa)), "gospa": float(np.mean(gospa)),
            "card_err": float(np.mean(card)), "id_switches": id_switches(ids, data.alive),
            "anees": float(np.mean(nees)) if nees.size else float("nan")}


def run_one(config: dict, index: int, seed: np.random.SeedSequence) -> tuple[dict, dict]:
    """(scores of every node, figure data or None) of one run; the figure data is run
    FIGURE_RUN's."""
    data, series = run_network(config, seed)
    result = {name: scores(config, data, s) for name, s in series.items()}
    return result, figure_data(config, data, series) if index == FIGURE_RUN else None


def figure_data(config: dict, data: MultiTargetData, series) -> dict:
    """What the figures draw of one run: the true paths (J lists of (x, y)), the number of
    targets per step, and for each node of [figure] its estimates as rows (step, id, x, y),
    its number of estimates per step and its id switches in total (summed over targets)."""
    c, fig = config["metrics"]["cutoff"], config["figure"]
    nodes = {}
    for node in fig["nodes"]:
        s = series[f"{fig['rule']} {node}"]
        ids = matched_ids(s, matches(s, data.truth, data.alive, c), len(data.truth))
        nodes[node] = {
            "rows": np.concatenate([np.column_stack([np.full(len(e), t), e.ids, e.means[:, :2]])
                                    for t, e in enumerate(s)]),
            "counts": [len(e) for e in s],
            "switches": int(metrics.id_switches(ids).sum())}
    return {"times": data.times, "n_alive": data.alive.sum(axis=0),
            "paths": [data.truth[j, data.alive[j], :2] for j in range(len(data.truth))],
            "nodes": nodes}


# ------------------------------------------------------------------------- throughput

def synthetic_reports(truth: np.ndarray, covs: np.ndarray, p: np.ndarray, noise_sd: float,
                      rng: np.random.Generator) -> dict:
    """{source s: Estimates} of one step: source s reports target j (truth (J, 4)) with
    probability p[s], mean truth[j] + N(0, noise_sd^2 I), covariance covs[s, j] (S, J, 4,
    4), track id j."""
    reports = {}
    for s in range(len(p)):
        seen = np.flatnonzero(rng.random(len(truth)) < p[s])
        means = truth[seen] + noise_sd * rng.standard_normal((seen.size, 4))
        reports[s] = fo.Estimates(means, covs[s, seen], seen)
    return reports


def synthetic_scene(bm: dict, n_sources: int, n_targets: int, rng: np.random.Generator):
    """truth (J, 4): targets at rest on a square grid spaced bm["spacing"]; covs
    (S, J, 4, 4): noise_sd^2 (I + G G^T), G standard normal; p (S,): the sources' p_D,
    evenly spread over bm["p_detect"]."""
    side = int(np.ceil(np.sqrt(n_targets)))
    j = np.arange(n_targets)
    truth = np.column_stack([bm["spacing"] * (j % side), bm["spacing"] * (j // side),
                             np.zeros((n_targets, 2))])
    G = rng.standard_normal((n_sources, n_targets, 4, 4))
    covs = bm["noise_sd"] ** 2 * (np.eye(4) + G @ G.swapaxes(-1, -2))
    return truth, covs, np.linspace(*bm["p_detect"], n_sources)


def time_node(bm: dict, method: str, n_sources: int, n_targets: int,
              rng: np.random.Generator) -> dict:
    """Per-step latency (median, p90, ms) and fused tracks per second of one
    ProcessingNode on synthetic reports (module docstring)."""
    truth, covs, p = synthetic_scene(bm, n_sources, n_targets, rng)
    extra = {"p_detect": dict(enumerate(p.tolist())), "growth": bm["growth"]} \
        if method == "mbci" else {}
    node = fo.ProcessingNode(range(n_sources), method=method, criterion=bm["criterion"],
                             backend=bm["backend"], association=bm["association"],
                             threshold=bm["threshold"], dims=POSITION, **extra)
    seconds, tracks = [], 0
    for step in range(bm["warmup"] + bm["steps"]):
        reports = synthetic_reports(truth, covs, p, bm["noise_sd"], rng)
        t0 = time.perf_counter()
        out = node.step(reports)
        elapsed = time.perf_counter() - t0
        if step >= bm["warmup"]:
            seconds.append(elapsed)
            tracks += len(out)
    ms = 1e3 * np.array(seconds)
    return {"median_ms": float(np.median(ms)), "p90_ms": float(np.quantile(ms, 0.9)),
            "tracks_per_s": tracks / float(np.sum(seconds)),
            "tracks_per_step": tracks / len(seconds)}


def benchmark(config: dict, out: Path, progress: bool = True) -> None:
    """Throughput of one processing node against the number of sources and of targets,
    per method; written to throughput.json (called by the CLI once, after the runs)."""
    bm = config["benchmark"]
    rng = np.random.default_rng(config["seed"])
    result = {"vs_sources": {}, "vs_targets": {}, "steps": bm["steps"]}
    for method in bm["methods"]:
        result["vs_sources"][method] = {
            str(S): time_node(bm, method, S, bm["targets_at_sources"], rng)
            for S in bm["sources"]}
        result["vs_targets"][method] = {
            str(J): time_node(bm, method, bm["sources_at_targets"], J, rng)
            for J in bm["targets"]}
        if progress:
            print(f"network throughput: {method} timed", flush=True)
    (Path(out) / THROUGHPUT).write_text(json.dumps(result, indent=1))


# ----------------------------------------------------------------------------- report

def table_rows(config: dict) -> list[tuple[str, str, str, str]]:
    """(row name, node, rule, level) of every node in table order: the monitoring nodes,
    then each processing node (first level, then second) with every rule."""
    net = config["network"]
    out = [(monitor_name(k), str(k), MONITOR, "monitoring")
           for k in range(1, len(config["scenario"]["p_detect"]) + 1)]
    for level in ("level1", "level2"):
        out += [(f"{rule} {node}", node, rule, level[-1])
                for node in net[level] for rule in config["rules"]]
    return out


def report(config: dict, results: list[dict], out: Path, figure: dict | None) -> None:
    """network.md, its tables as network.csv and network_throughput.csv, the figure of
    run FIGURE_RUN (if stored) and the throughput figure (if throughput.json exists)."""
    out = Path(out)
    table = table_rows(config)
    summary = stats.summarise(results, [r for r, *_ in table], COLUMNS)
    stats.write_rows(out / "network.csv", [
        {"node": node, "rule": rule, "level": level,
         **{f"{c}_{s}": v for c in COLUMNS
            for s, v in zip(("mean", "low", "high"), summary[row][c], strict=True)}}
        for row, node, rule, level in table])
    lines = _markdown(config, table, summary, len(results))
    if figure is not None:
        lines += _figure_note(config, figure)
        _tracks_figure(config, figure, out)
    throughput = _throughput(out)
    if throughput is not None:
        lines += _throughput_table(config, throughput)
        stats.write_rows(out / "network_throughput.csv", _throughput_rows(throughput))
        _throughput_figure(config, throughput, out)
    (out / "network.md").write_text("\n".join(lines) + "\n")


def _markdown(config, table, summary, runs) -> list[str]:
    m, net = config["metrics"], config["network"]
    lines = [f"# Network example ({runs} runs, seed {config['seed']}, backend "
             f"{config['backend']}, association {net['association']}, threshold "
             f"{net['threshold']})", "",
             f"Mean and 95% interval over runs. OSPA and GOSPA on position (c = {m['cutoff']}, "
             f"p = {m['order']}, GOSPA alpha = {m['alpha']}); card. error: mean |n_est - "
             "n_true|; id switches / target and ANEES (mean 4-dof NEES of the matched "
             "estimates; 4 if consistent; over the runs in which the node matched a target, "
             "- if none) as defined in studies/network.py. 95% intervals: "
             f"bootstrap percentile over the runs ({stats.RESAMPLES} seeded resamples).", "",
             "| node | rule | level | " + " | ".join(HEADERS) + " |", "|---" * 8 + "|"]
    for row, node, rule, level in table:
        cells = " | ".join(stats.fmt(*summary[row][c]) for c in COLUMNS)
        lines.append(f"| {node} | {rule} | {level} | {cells} |")
    return lines


def _figure_note(config, figure) -> list[str]:
    rule = config["figure"]["rule"]
    switches = ", ".join(f"{node}: {d['switches']}" for node, d in figure["nodes"].items())
    return ["", f"Run {FIGURE_RUN}, rule {rule}, id switches summed over the targets: "
            f"{switches}.", "", "![fused tracks](network_tracks.png)"]


def _tracks_figure(config, figure, out: Path) -> None:
    """One panel per node of [figure]: its estimates coloured by fused id over the true
    paths (black, with their starts and directions), and a last panel with the number of
    targets over time."""
    nodes, rule = figure["nodes"], config["figure"]["rule"]
    fig, axes = plotting.panels(1, len(nodes) + 1, width=5.4 * (len(nodes) + 1), height=6.0)
    cmap = colormaps["tab20"]  # 20 colours, cycled over the ids
    for ax, (node, d) in zip(axes[:-1], nodes.items(), strict=True):
        for xy in figure["paths"]:
            plotting.path(ax, xy, at=(0.3,), lw=0.8)  # before the crossings
        r = np.array(d["rows"]).reshape(-1, 4)
        ax.scatter(r[:, 2], r[:, 3], s=4, c=cmap(r[:, 1].astype(int) % cmap.N), zorder=2)
        plotting.trajectory_axes(ax, f"{rule} {node}: {len(np.unique(r[:, 1]))} fused ids, "
                                     f"{d['switches']} id switches")
    ax = axes[-1]
    ax.plot(figure["times"], figure["n_alive"], color="black", lw=2.6, alpha=0.45,
            drawstyle="steps-post", label="true number of targets")
    for i, (node, d) in enumerate(nodes.items()):
        ax.plot(figure["times"], d["counts"], drawstyle="steps-post", color=f"C{i}",
                ls=("--", ":", "-.")[i % 3], lw=1.3, label=f"estimated by {rule} {node}")
    ax.set(xlabel="time (s)", ylabel="number of targets (tracks reported)")
    ax.set_title("number of targets", fontsize=10)
    ids = Line2D([], [], ls="none", marker="o", ms=4, color=cmap(0),
                 label="fused estimates (means; colour: fused id, 20 colours cycled)")
    plotting.legend_below(fig, plotting.path_handles(lw=0.8) + [ids] + ax.get_lines(),
                          ncol=3)
    plotting.run_title(fig, f"Network example: fused tracks under {rule}", FIGURE_RUN,
                       config["seed"])
    plotting.save(fig, out / "network_tracks.png")


def _throughput(out: Path) -> dict | None:
    path = out / THROUGHPUT
    return json.loads(path.read_text()) if path.exists() else None


def _throughput_rows(tp: dict) -> list[dict]:
    return [{"sweep": sweep, "method": method, "size": size, **cell}
            for sweep in ("vs_sources", "vs_targets")
            for method, cells in tp[sweep].items() for size, cell in cells.items()]


def _throughput_table(config, tp: dict) -> list[str]:
    bm = config["benchmark"]
    lines = ["", f"## Throughput of one processing node ({tp['steps']} timed steps each)",
             "", f"ProcessingNode.step, backend {bm['backend']}, {bm['criterion']}, "
             f"association {bm['association']}, threshold {bm['threshold']}; sources at "
             f"{bm['targets_at_sources']} targets, targets at {bm['sources_at_targets']} "
             f"sources; p_D spread over {bm['p_detect']}. Latency per step in ms (median / "
             "p90); fused tracks per second = tracks output / time.", "",
             "| sweep | size | method | latency median / p90 (ms) | fused tracks / s | "
             "tracks / step |", "|---" * 6 + "|"]
    for row in _throughput_rows(tp):
        lines.append(f"| {row['sweep'][3:]} | {row['size']} | {row['method']} | "
                     f"{row['median_ms']:.3g} / {row['p90_ms']:.3g} | "
                     f"{row['tracks_per_s']:.4g} | {row['tracks_per_step']:.4g} |")
    return lines + ["", "![throughput](network_throughput.png)"]


def _throughput_figure(config, tp: dict, out: Path) -> None:
    """Latency (median solid, p90 dotted) against sources and against targets, log-log."""
    fig, axes = plotting.panels(1, 2, width=11, height=5.0)
    bm = config["benchmark"]
    for ax, sweep, label, fixed in (
            (axes[0], "vs_sources", "sources", f"{bm['targets_at_sources']} targets"),
            (axes[1], "vs_targets", "targets", f"{bm['sources_at_targets']} sources")):
        for colour, (method, cells) in zip(colormaps["tab10"].colors, tp[sweep].items(),
                                           strict=False):
            sizes = [int(s) for s in cells]
            for key, style in (("median_ms", "o-"), ("p90_ms", "x:")):
                ax.plot(sizes, [c[key] for c in cells.values()], style, color=colour,
                        label=f"{method} {key[:-3]}")
        plotting.log_axes(ax, sizes, f"number of {label}")
        ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))  # 1, 2, 5, 10, ...
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set(ylabel="latency of one step (ms)")
        ax.set_title(f"latency against the number of {label} ({fixed})", fontsize=10)
    plotting.legend_below(fig, axes[0].get_lines())
    fig.suptitle(f"One processing node: latency per step ({tp['steps']} timed steps per "
                 f"point, synthetic reports of seed {config['seed']})", fontsize=11)
    plotting.save(fig, out / "network_throughput.png")

"""Table 2: unknown number of targets; 7 RBMCDA nodes, 3 processing nodes fusing with CI
and modified CI.

Each run simulates the scenario and steps one `fusion_opt.Network` over it: an RBMCDA
tracker per monitoring node, and per processing node two `ProcessingNode`s over its
neighbours, which associate the neighbours' estimates at every step and fuse every group
of two or more with CI (BCI, trace) and with modified CI (MBCI with the group's p_D and
chi^-1 = 1 + dt); an estimate no other node shares is passed on as is. The study only
configures the network and scores what it reports.

Scores per node (DESIGN §3 leaves the paper's "sum over detected targets" open; ours):
each step, estimates are matched to the alive targets by optimal assignment on position,
gated at the cut-off c. For each target, MSE_j is the mean over its matched steps of the
full-state squared error and MNCM_j the mean spectral norm of the matched covariances; the
table's MSE and MNCM are the sums over the targets ever matched. OSPA and GOSPA (position,
cut-off c, order p, alpha = 2) and the cardinality error |n_est - n_true| are means over
the steps.

Run 0 also returns what the figures draw of it (`figure_data`), which the store keeps
beside its scores, so `report` draws the figures without simulating again.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
from matplotlib.lines import Line2D

import fusion_opt as fo
from trackers import metrics, rbmcda
from trackers.scenarios import Table2Config, simulate_table2

from . import config as configs
from . import plotting, stats
from .runner import FIGURE_RUN

POSITION = [0, 1]
# The kernel parts its runs call (`runner.run_all`): it fuses with BCI and MBCI only, so no
# rule's part ("rules", "cross", "pairs") is compiled for it.
KERNELS = ("solve", "assemble", "conic", "fuse", "network")
COLUMNS = ("mse", "mncm", "mse_pos", "mncm_pos", "ospa", "gospa", "card_err")
PAPER = {"RBMCDA 1": (0.1430, 0.0578), "RBMCDA 2": (0.4716, 0.0616),
         "RBMCDA 3": (0.1228, 0.0533), "RBMCDA 4": (0.1830, 0.0580),
         "RBMCDA 5": (0.1010, 0.0511), "RBMCDA 6": (0.1166, 0.0529),
         "RBMCDA 7": (0.1912, 0.0556), "CI 8": (0.0821, 0.0508), "CI 9": (0.0731, 0.0560),
         "CI 10": (0.0884, 0.0505), "modified CI 8": (0.0784, 0.0501),
         "modified CI 9": (0.0763, 0.0523), "modified CI 10": (0.0799, 0.0493)}


NAMED = ("network.neighbours",)  # a --config's table replaces the default's whole
SHOWN_NODE, SHOWN_PROC = 3, "9"  # the monitoring and processing node the figures show


def scenario(config: dict) -> Table2Config:
    return configs.build(Table2Config, config["scenario"], "scenario")


def check(config: dict) -> None:
    """Refuse, with a ConfigError naming the field, anything in config this study cannot
    run: called on the whole merged configuration before anything runs."""
    configs.fields(config, "", ("runs", "seed", "backend", "scenario", "network", "fusion",
                                "metrics"))
    configs.run_fields(config)
    sc = scenario(config)
    nodes = len(sc.p_detect)
    configs.construct("scenario", _monitoring, sc, [np.random.default_rng(0)])
    net = configs.fields(config["network"], "network", ("neighbours", "association", "threshold"))
    neighbours = configs.sources(  # processing node name -> its monitoring nodes
        net["neighbours"], "network.neighbours",
        lambda where, k: configs.integer(where, k, low=1, high=nodes), "monitoring node")
    configs.backend("backend", config["backend"],
                    nodes=max(len(m) for m in neighbours.values()))
    configs.choice("network.association", net["association"], ("nearest", "assignment"))
    configs.number("network.threshold", net["threshold"], above=0)
    fusion = configs.fields(config["fusion"], "fusion", ("growth",))
    configs.growth("fusion.growth", fusion["growth"])
    metric = configs.fields(config["metrics"], "metrics", ("cutoff", "order"))
    configs.number("metrics.cutoff", metric["cutoff"], above=0)
    configs.number("metrics.order", metric["order"], low=1)


def estimates(config: dict, seed: np.random.SeedSequence):
    """One run: (data, {row: list over steps of Estimates}), the rows being the monitoring
    nodes "RBMCDA k" and, per processing node p, "CI p" and "modified CI p"."""
    sc = scenario(config)
    sim_rng, *node_rngs = (np.random.default_rng(s) for s in seed.spawn(1 + len(sc.p_detect)))
    data = simulate_table2(sc, sim_rng)
    trackers = _monitoring(sc, node_rngs)
    scans = [{name: node.scans[t] for name, node in zip(trackers, data.nodes, strict=True)}
             for t in range(sc.n_steps)]
    return data, fo.Network(trackers, _processing(config, sc)).run(scans)


def _monitoring(sc: Table2Config, rngs) -> dict[str, rbmcda.RBMCDA]:
    """The monitoring nodes: an RBMCDA named "RBMCDA k" (k = 1, 2, ...) per node."""
    model, (m0, P0) = sc.filter_model(), sc.prior()
    return {f"RBMCDA {k}": rbmcda.RBMCDA(
        model, m0, P0, rng=rng, dt=sc.dt, n_particles=sc.n_particles,
        birth_prob=sc.birth_prob, lifetime_shape=sc.lifetime_shape,
        lifetime_scale=sc.lifetime_scale, clutter_prior=sc.clutter_prior,
        clutter_density=sc.clutter_density, resample_threshold=sc.resample_threshold,
        name=f"RBMCDA {k}") for k, rng in enumerate(rngs, start=1)}


def _processing(config: dict, sc: Table2Config) -> dict[str, fo.ProcessingNode]:
    """Per processing node p of network.neighbours, "CI p" (BCI, trace) and "modified CI p"
    (MBCI with each neighbour's p_D and fusion.growth), both over its neighbours."""
    net, growth = config["network"], config["fusion"]["growth"]
    nodes = {}
    for proc, members in net["neighbours"].items():
        sources = [f"RBMCDA {k}" for k in members]
        mbci = dict(p_detect={f"RBMCDA {k}": sc.p_detect[k - 1] for k in members},
                    growth=growth)
        for row, method, extra in (("CI", "bci", {}), ("modified CI", "mbci", mbci)):
            nodes[f"{row} {proc}"] = fo.ProcessingNode(
                sources, method=method, backend=config["backend"],
                association=net["association"], threshold=net["threshold"], dims=POSITION,
                name=f"{row} {proc}", **extra)
    return nodes


def run_one(config: dict, index: int, seed: np.random.SeedSequence) -> tuple[dict, dict]:
    """(scores of every node, figure data or None) of one run; the figure data is run
    FIGURE_RUN's."""
    data, est = estimates(config, seed)
    figure = figure_data(data, est) if index == FIGURE_RUN else None
    return {row: _scores(config, data, series) for row, series in est.items()}, figure


def figure_data(data, est) -> dict:
    """What the figures draw of one run: each target's path while alive, the measurements
    (target-originated and clutter apart) and RBMCDA estimates (positions) of monitoring
    node SHOWN_NODE (or the last, if there are fewer), the modified-CI estimates at
    SHOWN_PROC (if it exists), and the number of targets over time, true and estimated
    (arrays; read back from the store as lists)."""
    node = min(SHOWN_NODE, len(data.nodes))
    shown = data.nodes[node - 1]
    rows = {"RBMCDA": f"RBMCDA {node}", "fused": f"modified CI {SHOWN_PROC}"}
    rows = {key: row for key, row in rows.items() if row in est}
    return {"node": node, "proc": SHOWN_PROC, "rows": rows, "times": data.times,
            "n_alive": data.n_alive,
            "paths": [data.truth[j, data.alive[j], :2] for j in range(len(data.truth))],
            "measurements": {"target": shown.values[shown.origin >= 0],
                             "clutter": shown.values[shown.origin < 0]},
            "estimates": {key: np.concatenate([e.means[:, :2] for e in est[row]])
                          for key, row in rows.items()},
            "counts": {key: [len(e) for e in est[row]] for key, row in rows.items()}}


def _scores(config, data, series) -> dict:
    c, p = config["metrics"]["cutoff"], config["metrics"]["order"]
    per_target = {k: defaultdict(list) for k in ("mse", "mncm", "mse_pos", "mncm_pos")}
    ospa, gospa, card, matched, matched_covs = [], [], [], [], []
    for t, e in enumerate(series):
        means, covs = e.means, e.covs
        alive = np.flatnonzero(data.alive[:, t])
        truth = data.truth[alive, t]
        errors = metrics.set_errors(means[:, POSITION], truth[:, POSITION], c, p)
        ospa.append(errors.ospa)
        gospa.append(errors.gospa)
        card.append(abs(len(means) - len(alive)))
        for i, j in zip(errors.rows, errors.cols, strict=True):
            err = means[i] - truth[j]
            per_target["mse"][alive[j]].append(float(err @ err))
            per_target["mse_pos"][alive[j]].append(float(err[POSITION] @ err[POSITION]))
            matched.append(alive[j])
            matched_covs.append(covs[i])
    _spectral_norms(per_target, matched, matched_covs)
    # summed over the targets matched at least once; a node that matched none has no MSE
    # or MNCM in this run (NaN, left out of the tables' means), not a perfect 0
    scores = {key: float(sum(np.mean(v) for v in d.values())) if d else np.nan
              for key, d in per_target.items()}
    return scores | {"ospa": float(np.mean(ospa)), "gospa": float(np.mean(gospa)),
                     "card_err": float(np.mean(card))}


def _spectral_norms(per_target, targets, covs) -> None:
    """Appends to per_target["mncm"] and ["mncm_pos"] the spectral norms of covs (k, n, n),
    whole and position block, matched to targets (k,): `metrics.spectral_norms` once per
    run (numpy's norm(P, 2) matrix by matrix was a third of the scoring's time)."""
    if not targets:
        return
    P = np.stack(covs)
    for key, components in (("mncm", None), ("mncm_pos", POSITION)):
        norms = metrics.spectral_norms(P, components).tolist()
        for target, norm in zip(targets, norms, strict=True):
            per_target[key][target].append(norm)


# ------------------------------------------------------------------------------ report

def report(config: dict, results: list[dict], out: Path, figure: dict | None) -> None:
    """table2.md, its tables as table2.csv and table2_paired.csv, and the figures of run
    FIGURE_RUN from its figure data (none if that run is not stored)."""
    rows = stats.summarise(results, results[0], COLUMNS)
    paper = _paper(config)  # the paper's values, or none beside another setting
    stats.write_csv(out / "table2.csv", rows, COLUMNS, paper,
                    ("paper_mse_e-3", "paper_mncm"))
    stats.write_rows(out / "table2_paired.csv",
                     [{"node": proc, "measure": key, **p}
                      for proc, pair in _paired(config, results).items()
                      for key, p in pair.items()])
    (out / "table2.md").write_text(_markdown(config, rows, results, paper))
    if figure is not None:
        _figures(config, figure, out)


def _paired(config, results) -> dict:
    """{processing node: {"mse": ..., "mncm": ...}}: modified CI minus CI, paired."""
    return {proc: {key: stats.paired([r[f"modified CI {proc}"][key] for r in results],
                                     [r[f"CI {proc}"][key] for r in results])
                   for key in ("mse", "mncm")}
            for proc in config["network"]["neighbours"]}


def _markdown(config, rows, results, paper: dict) -> str:
    lines = [f"# Table 2 ({len(results)} runs, seed {config['seed']}, backend "
             f"{config['backend']}, association {config['network']['association']})", "",
             "Mean and 95% interval over runs; MSE and MNCM summed over the targets matched "
             "(studies/table2.py says how); the paper's MSE column is in units of 1e-3. "
             + stats.INTERVAL_NOTE, "",
             "| node | MSE | paper MSE (x1e-3) | MNCM | paper MNCM | MSE pos | MNCM pos | OSPA "
             "| GOSPA | card. error |", "|---" * 10 + "|"]
    for row, cols in rows.items():
        p_mse, p_mncm = paper.get(row, ("-", "-"))
        c = [stats.fmt(*cols[k]) for k in COLUMNS]
        lines.append(f"| {row} | {c[0]} | {p_mse} | {c[1]} | {p_mncm} | "
                     + " | ".join(c[2:]) + " |")
    lines += ["", "Paired comparison, modified CI minus CI at each processing node:", "",
              "| node | MSE difference [95%] | share MCI lower | MNCM difference [95%] |",
              "|---|---|---|---|"]
    for proc, pair in _paired(config, results).items():
        pm, pc = pair["mse"], pair["mncm"]
        lines.append(f"| {proc} | {stats.fmt(pm['mean_diff'], pm['low'], pm['high'], 3)} | "
                     f"{stats.fmt_share(pm)} | "
                     f"{stats.fmt(pc['mean_diff'], pc['low'], pc['high'], 3)} |")
    shown = [] if paper else ["", PAPER_NOTE]
    return "\n".join(lines + shown) + "\n"


PAPER_FIELDS = ("network", "fusion", "metrics")  # beside the scenario
PAPER_NOTE = ("The paper's columns are left empty: this configuration's scenario, network, "
              "growth or metrics are not the paper's.")


def _paper(config) -> dict:
    """The paper's values by row, or none when config is not the paper's setting."""
    return PAPER if configs.paper_setting("table2", config, scenario, PAPER_FIELDS) else {}


MEASURED = {"target": dict(marker="o", ms=2.2, color="tab:blue", ls="none",
                           label="target measurement"),
            "clutter": dict(marker="x", ms=3.5, color="tab:gray", ls="none", mew=0.8,
                            label="clutter")}
ESTIMATED = {"RBMCDA": dict(marker="o", ms=1.6, color="tab:red", ls="none"),
             "fused": dict(marker="o", ms=1.6, color="tab:blue", ls="none")}
COUNTS = {"RBMCDA": dict(color="tab:red", ls="--", lw=1.2),
          "fused": dict(color="tab:blue", ls=":", lw=1.6)}


def _figures(config, figure, out) -> None:
    """The paper's figures from the figure data of one run (see figure_data): node 3
    (paths, measurements, estimates, number of targets) and the fused estimates at node 9."""
    node, proc, est = figure["node"], figure["proc"], figure["estimates"]
    paths = [np.array(p).reshape(-1, 2) for p in figure["paths"]]
    fig, axes = plotting.panels(1, 3, width=16, height=5.4,
                                gridspec_kw={"width_ratios": [1, 1, 1.15]})
    for ax in axes[:2]:
        for xy in paths:
            plotting.path(ax, xy, at=(0.3,))
    for key, style in MEASURED.items():
        axes[0].plot(*np.array(figure["measurements"][key]).reshape(-1, 2).T, **style)
    plotting.trajectory_axes(axes[0], f"targets and measurements, node {node}")
    handles = plotting.path_handles() + [Line2D([], [], **s) for s in MEASURED.values()]
    if "RBMCDA" in est:
        axes[1].plot(*np.array(est["RBMCDA"]).reshape(-1, 2).T, **ESTIMATED["RBMCDA"])
        handles.append(Line2D([], [], **ESTIMATED["RBMCDA"] | {"ms": 4},
                              label=f"estimates of {figure['rows']['RBMCDA']} (means)"))
    plotting.trajectory_axes(axes[1], f"RBMCDA estimates, node {node}")
    ax = axes[2]
    ax.plot(figure["times"], figure["n_alive"], color="black", lw=2.6, alpha=0.45,
            drawstyle="steps-post", label="true number of targets")
    for key, counts in figure["counts"].items():
        ax.plot(figure["times"], counts, drawstyle="steps-post", **COUNTS[key],
                label=f"estimated by {figure['rows'][key]}")
    ax.set(xlabel="time (s)", ylabel="number of targets (tracks reported)")
    ax.set_title("number of targets", fontsize=10)
    ax.yaxis.get_major_locator().set_params(integer=True)
    plotting.legend_below(fig, handles + ax.get_lines(), ncol=4)
    plotting.run_title(fig, f"Table 2: monitoring node {node}", FIGURE_RUN, config["seed"])
    plotting.save(fig, out / f"table2_node{node}.png")
    if "fused" in est:
        fig, axes = plotting.panels(1, 1, width=6.5, height=6.6)
        for xy in paths:
            plotting.path(axes[0], xy, at=(0.3,))
        axes[0].plot(*np.array(est["fused"]).reshape(-1, 2).T, **ESTIMATED["fused"])
        plotting.trajectory_axes(axes[0])
        plotting.legend_below(fig, plotting.path_handles() + [Line2D(
            [], [], **ESTIMATED["fused"] | {"ms": 4},
            label=f"estimates of {figure['rows']['fused']} (means)")], ncol=2)
        plotting.run_title(fig, f"Table 2: modified CI\nat processing node {proc}",
                           FIGURE_RUN, config["seed"])
        plotting.save(fig, out / f"table2_node{proc}.png")

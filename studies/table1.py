"""Table 1: one target in clutter, two nodes (KF, RBPF) fused by CI and modified CI.

Each run simulates the scenario (trackers.scenarios.simulate_table1), runs the KF baseline
and the RBPF at nodes a and b, fuses the two RBPF estimates at every step with CI (trace),
modified CI (trace, p_D of each node, growth chi^-1 = 1 + dt), naive fusion and BCI (log-det), and
scores each with the full-state MSE and MNCM (the paper's columns, DESIGN §3), the position
ones, and ANEES. Run 0 also returns what the figures draw of it (`figure_data`), which the
store keeps beside its scores, so `report` draws the figures without simulating again.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.lines import Line2D

import fusion_opt as fo
from fusion_opt.validation import safe_repr
from trackers import kalman, metrics, rbpf
from trackers.scenarios import Table1Config, simulate_table1

from . import config as configs
from . import plotting, stats
from .runner import FIGURE_RUN

POSITION = [0, 1]
# The kernel parts its runs call (`runner.run_all`): naive is its only rule, ici and ei
# ("pairs") never run here.
KERNELS = ("solve", "assemble", "conic", "rules", "fuse", "network")
PAPER = {"KF a": (1.447, None), "KF b": (1.613, None), "RBPF a": (0.141, 0.0632),
         "RBPF b": (0.161, 0.0666), "CI": (0.141, 0.0613), "modified CI": (0.109, 0.0592)}
ROWS = ("KF a", "KF b", "RBPF a", "RBPF b", "CI", "modified CI", "naive", "BCI logdet")
PATH_ROWS = ("RBPF a", "RBPF b", "modified CI")
COVNORM_ROWS = ("RBPF a", "RBPF b", "CI", "modified CI", "naive", "BCI logdet")
COLUMNS = ("mse_full", "mncm_full", "mse_pos", "mncm_pos", "anees")
CHECKED = ("CI", "modified CI", "BCI logdet")  # the rules with weights, checked per run
CHECK = "check"  # a run's result key: {row: worst objective difference to the reference}


def scenario(config: dict) -> Table1Config:
    return configs.build(Table1Config, config["scenario"], "scenario")


def check(config: dict) -> None:
    """Refuse, with a ConfigError naming the field, anything in config this study cannot
    run: called on the whole merged configuration before anything runs."""
    configs.fields(config, "", ("runs", "seed", "backend", "scenario", "fusion", "check"))
    configs.run_fields(config)
    configs.backend("backend", config["backend"], nodes=2)
    sc = scenario(config)
    if len(sc.p_detect) != 2:
        raise configs.ConfigError("scenario.p_detect must hold 2 detection probabilities "
                                  f"(nodes a and b), got "
                                  f"{safe_repr(config['scenario']['p_detect'])}")
    configs.construct("scenario", _filter, sc, np.random.default_rng(0))
    check = configs.fields(config["check"], "check", ("backend", "steps"))
    configs.backend("check.backend", check["backend"], nodes=2)
    configs.integer("check.steps", check["steps"], low=0, high=sc.n_steps)  # steps of a run
    fusion = configs.fields(config["fusion"], "fusion", ("growth", "window"))
    configs.growth("fusion.growth", fusion["growth"])
    start, end = (configs.number(f"fusion.window[{i}]", t) for i, t in
                  enumerate(configs.items("fusion.window", fusion["window"], length=2)))
    if end < start:
        raise configs.ConfigError(f"fusion.window must be [start, end] with start <= end, "
                                  f"got {safe_repr(fusion['window'])}")


def estimates(config: dict, seed: np.random.SeedSequence):
    """Simulate one run; returns (data, {row: (means (T, 4), covs (T, 4, 4))}, the check of
    the fusion against the reference backend: `_fused`)."""
    sc = scenario(config)
    sim_rng, *filter_rngs = (np.random.default_rng(s) for s in seed.spawn(3))
    data = simulate_table1(sc, sim_rng)
    model, (m0, P0) = sc.filter_model(), sc.prior()
    out = {}
    for name, node, frng in zip("ab", data.nodes, filter_rngs, strict=True):
        kf = kalman.run(node.scans, model, m0, P0)
        pf = rbpf.run(node.scans, model, m0, P0, rng=frng, **_filter_settings(sc))
        out[f"KF {name}"] = (kf.means, kf.covs)
        out[f"RBPF {name}"] = (pf.means, pf.covs)
    fused, check = _fused(config, sc, out["RBPF a"], out["RBPF b"])
    return data, out | fused, check


def _filter_settings(sc: Table1Config) -> dict:
    """The RBPF's settings of [scenario]."""
    return dict(n_particles=sc.n_particles, clutter_prior=sc.clutter_prior,
                clutter_density=sc.clutter_density, resample_threshold=sc.resample_threshold)


def _filter(sc: Table1Config, rng) -> rbpf.RBPF:
    """A node's RBPF as a run makes it (the check makes one: it refuses sizes and
    settings before any run)."""
    return rbpf.RBPF(sc.filter_model(), *sc.prior(), rng=rng, **_filter_settings(sc))


def _fused(config, sc, a, b) -> tuple[dict, dict]:
    """({row: (means (T, n), covs (T, n, n))} of the fusion rules, the check of their
    weights against config["check"]["backend"] on a sample of steps)."""
    means = np.stack([a[0], b[0]], axis=1)  # (T, 2, n)
    covs = np.stack([a[1], b[1]], axis=1)  # (T, 2, n, n)
    backend = config["backend"]
    rules = {"CI": dict(method="ci", backend=backend), "naive": dict(method="naive"),
             "modified CI": dict(method="mbci", backend=backend, p_detect=list(sc.p_detect),
                                 growth=config["fusion"]["growth"]),
             "BCI logdet": dict(method="bci", backend=backend, criterion="logdet")}
    results = {row: fo.fuse_batch(means, covs, **kw) for row, kw in rules.items()}
    steps = np.unique(np.linspace(0, len(means) - 1, config["check"]["steps"]).astype(int))
    reference = {"backend": config["check"]["backend"], "polish": False}
    check = {row: _disagreement(results[row], means, covs, steps, rules[row] | reference)
             for row in CHECKED}
    return {row: (r.mean, r.cov) for row, r in results.items()}, check


def _disagreement(ours, means, covs, steps, reference: dict) -> dict:
    """Objective differences at the sampled steps, ours minus that of the reference's
    unpolished answer (relative to |f| for "trace", in nats for "logdet"): the largest in
    absolute value and the largest (<= 0 where ours is at least as good); 0.0 with no
    step."""
    if not len(steps):
        return {"abs": 0.0, "max": 0.0}
    ref = fo.fuse_batch(means[steps], covs[steps], **reference)
    diff = ours.objective[steps] - ref.objective
    if ours.criterion == "trace":
        diff = diff / np.abs(ref.objective)
    return {"abs": float(np.abs(diff).max()), "max": float(diff.max())}


def run_one(config: dict, index: int, seed: np.random.SeedSequence) -> tuple[dict, dict]:
    """(scores of every row, figure data or None) of one run (a pure function of config
    and seed); the figure data is run FIGURE_RUN's."""
    data, est, check = estimates(config, seed)
    figure = figure_data(data, est) if index == FIGURE_RUN else None
    return {**{row: _scores(*est[row], data.truth) for row in ROWS}, CHECK: check}, figure


def figure_data(data, est) -> dict:
    """What the figures draw of one run: positions of the truth, of each node's target
    measurements and clutter, of the PATH_ROWS estimates, and the covariance 2-norm of
    the COVNORM_ROWS over time (arrays; read back from the store as lists)."""
    return {"times": data.times, "truth": data.truth[:, :2],
            "nodes": [{"target": node.values[node.origin >= 0],
                       "clutter": node.values[node.origin < 0]} for node in data.nodes],
            "paths": {row: est[row][0][:, :2] for row in PATH_ROWS},
            "covnorm": {row: np.linalg.norm(est[row][1], 2, axis=(1, 2))
                        for row in COVNORM_ROWS}}


def _scores(means, covs, truth) -> dict:
    return {
        "mse_full": metrics.mse(means, truth), "mse_pos": metrics.mse(means, truth, POSITION),
        "mncm_full": metrics.mncm(covs), "mncm_pos": metrics.mncm(covs, POSITION),
        "anees": metrics.anees(means, truth, covs),
    }


# ------------------------------------------------------------------------------ report

def report(config: dict, results: list[dict], out: Path, figure: dict | None) -> None:
    """table1.md, its tables as table1.csv and table1_paired.csv, and the figures of run
    FIGURE_RUN from its figure data (none if that run is not stored)."""
    rows = stats.summarise(results, ROWS, COLUMNS)
    paper = _paper(config)  # the paper's values, or none beside another setting
    stats.write_csv(out / "table1.csv", rows, COLUMNS, paper, ("paper_mse", "paper_mncm"))
    stats.write_rows(out / "table1_paired.csv",
                     [{"measure": col, **p} for col, p in _paired(results).items()])
    (out / "table1.md").write_text(_markdown(config, rows, results, paper))
    if figure is not None:
        _figures(config, figure, out)


def _paired(results) -> dict:
    """Modified CI minus CI, paired over the runs, for the MSE and MNCM columns."""
    return {col: stats.paired([r["modified CI"][col] for r in results],
                              [r["CI"][col] for r in results]) for col in COLUMNS[:4]}


def _markdown(config, rows, results, paper: dict) -> str:
    n = len(results)
    lines = [f"# Table 1 ({n} runs, seed {config['seed']}, backend {config['backend']})", "",
             "Mean and 95% interval over runs. MSE: mean over time of the squared error norm; "
             "MNCM: mean spectral norm of the covariance; full state and position block. "
             + stats.INTERVAL_NOTE, "",
             "| row | MSE full | paper MSE | MNCM full | paper MNCM | MSE pos | MNCM pos "
             "| ANEES (4-dof) |", "|---|---|---|---|---|---|---|---|"]
    for row, cols in rows.items():
        p_mse, p_mncm = paper.get(row, (None, None))
        cells = [stats.fmt(*cols[c]) for c in COLUMNS]
        lines.append(f"| {row} | {cells[0]} | {p_mse or '-'} | {cells[1]} | {p_mncm or '-'} "
                     f"| {cells[2]} | {cells[3]} | {cells[4]} |")
    lines += ["", "Paired comparison, modified CI minus CI (negative: modified CI better):", "",
              "| measure | mean difference [95%] | share of runs where modified CI is lower |",
              "|---|---|---|"]
    for col, p in _paired(results).items():
        lines.append(f"| {col} | {stats.fmt(p['mean_diff'], p['low'], p['high'], 3)} "
                     f"| {stats.fmt_share(p)} |")
    shown = [] if paper else ["", PAPER_NOTE]
    return "\n".join(lines + ["", _check_note(config, results)] + shown) + "\n"


PAPER_FIELDS = ("fusion.growth",)  # beside the scenario
PAPER_NOTE = ("The paper's columns are left empty: this configuration's scenario or growth "
              "is not the paper's.")


def _paper(config) -> dict:
    """The paper's values by row, or none when config is not the paper's setting."""
    return PAPER if configs.paper_setting("table1", config, scenario, PAPER_FIELDS) else {}


def _check_note(config, results) -> str:
    """The worst disagreement of the fusion with the reference backend over every run."""
    check = config["check"]
    if check["steps"] == 0:
        return "The fusion was not checked against a reference backend (check.steps = 0)."
    worst = {row: [max(r[CHECK][row][k] for r in results) for k in ("abs", "max")]
             for row in CHECKED}
    return (f"Check: at {check['steps']} evenly spaced steps of every run, the rules with "
            f"weights were fused again by {safe_repr(check['backend'])} (unpolished). Objective "
            f"differences, {config['backend']} minus {check['backend']} (relative for "
            "trace, nats for log det), largest in absolute value / largest (<= 0: "
            f"{config['backend']} never worse): "
            + ", ".join(f"{row} {a:.2g} / {m:.2g}" for row, (a, m) in worst.items()) + ".")


def _figures(config, figure, out) -> None:
    """The paper's figures, from the figure data of one run (see figure_data)."""
    truth = np.array(figure["truth"]).reshape(-1, 2)
    seed, p_detect = config["seed"], config["scenario"]["p_detect"]
    _measurements_figure(truth, figure["nodes"], p_detect, seed,
                         out / "table1_measurements.png")
    _paths_figure(truth, figure["paths"], seed, out / "table1_paths.png")
    _covnorm_figure(np.array(figure["times"]), figure["covnorm"], config["fusion"]["window"],
                    seed, out / "table1_covnorm.png")


MEASURED = {"target": dict(marker="o", ms=2.5, color="tab:blue", ls="none",
                           label="target measurement"),
            "clutter": dict(marker="x", ms=3.5, color="tab:gray", ls="none", mew=0.8,
                            label="clutter")}


def _measurements_figure(truth, nodes, p_detect, seed, path) -> None:
    fig, axes = plotting.panels(1, len(nodes), width=11, height=5.2)
    for ax, node, name, p in zip(axes, nodes, "ab", p_detect, strict=True):
        for key, style in MEASURED.items():
            ax.plot(*np.array(node[key]).reshape(-1, 2).T, **style)
        plotting.path(ax, truth, lw=1.4)
        plotting.trajectory_axes(ax, f"node {name} (p_D = {p})")
    handles = plotting.path_handles(lw=1.4) + [
        Line2D([], [], **style) for style in MEASURED.values()]
    plotting.legend_below(fig, handles)
    plotting.run_title(fig, "Table 1: the target's path and each node's measurements",
                       FIGURE_RUN, seed)
    plotting.save(fig, path)


def _paths_figure(truth, paths, seed, path) -> None:
    fig, axes = plotting.panels(1, len(PATH_ROWS), width=13, height=4.9)
    for ax, row in zip(axes, PATH_ROWS, strict=True):
        plotting.path(ax, truth, color="tab:red", ls="--", lw=1.4)
        ax.plot(*np.array(paths[row]).reshape(-1, 2).T, "k-", lw=0.9)
        plotting.trajectory_axes(ax, row)
    handles = plotting.path_handles(color="tab:red", ls="--", lw=1.4) + [
        Line2D([], [], color="black", lw=0.9, label="estimate (mean)")]
    plotting.legend_below(fig, handles, ncol=3)
    plotting.run_title(fig, "Table 1: estimated paths of the RBPFs and of modified CI",
                       FIGURE_RUN, seed)
    plotting.save(fig, path)


# CI, modified CI and BCI logdet nearly coincide: CI wide underneath, the others dashed
# and dotted over it with markers, and their differences to CI in a panel of their own
COVNORM_STYLE = {
    "RBPF a": dict(color="tab:blue", lw=1.0), "RBPF b": dict(color="tab:orange", lw=1.0),
    "CI": dict(color="black", lw=2.6, alpha=0.45),
    "modified CI": dict(color="tab:red", lw=1.2, ls="--", marker="^", ms=3.5, markevery=6),
    "BCI logdet": dict(color="tab:green", lw=1.2, ls=":", marker="o", ms=3.5,
                       mfc="none", markevery=(3, 6)),
    "naive": dict(color="tab:purple", lw=1.0, ls="-."),
}


def _covnorm_figure(times, covnorm, window, seed, path) -> None:
    """The covariance 2-norm of every fused and node estimate over the window, and a panel
    per rule that nearly coincides with CI showing its difference to CI."""
    close = ("modified CI", "BCI logdet")
    fig, (ax, *diffs) = plotting.panels(1 + len(close), 1, width=8, height=8.6,
                                        gridspec_kw={"height_ratios": [2.4, 1, 1]})
    sel = (times >= window[0]) & (times <= window[1])
    title = "Table 1: 2-norm of the covariance"
    if not sel.any():  # a shortened run ends before the window: show all of it, and say so
        sel[:] = True
        title += f"\nover the whole run: no step in fusion.window {list(window)} s;"
    for row in COVNORM_ROWS:
        ax.plot(times[sel], np.array(covnorm[row])[sel], label=row, **COVNORM_STYLE[row])
    ax.set(xlabel="time (s)", ylabel="2-norm of the covariance\n(full 4x4: m², (m/s)², m²/s)")
    ci = np.array(covnorm["CI"])[sel]
    for diff, row in zip(diffs, close, strict=True):
        diff.axhline(0.0, color="black", lw=2.6, alpha=0.45)
        diff.plot(times[sel], np.array(covnorm[row])[sel] - ci, **COVNORM_STYLE[row])
        diff.set(xlabel="time (s)", ylabel=f"{row} minus CI\n(same units)")
    plotting.legend_below(fig, ax.get_lines(), ncol=3)
    plotting.run_title(fig, title, FIGURE_RUN, seed)
    plotting.save(fig, path)

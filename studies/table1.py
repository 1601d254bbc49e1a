"""Table 1: one target in clutter, two nodes (KF, RBPF) fused by CI and modified CI.

Each run simulates the scenario (trackers.scenarios.simulate_table1), runs the KF baseline
and the RBPF at nodes a and b, fuses the two RBPF estimates at every step with CI (trace),
modified CI (trace, p_D of each node, chi^-1 = 1 + dt), naive fusion and BCI (log-det), and
scores each with the full-state MSE and MNCM (the paper's columns, DESIGN §3), the position
ones, and ANEES.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import fusion_opt as fo
from trackers import kalman, metrics, rbpf
from trackers.scenarios import Table1Config, simulate_table1

from . import config as configs
from . import stats
from .plotting import new_figure, save

POSITION = [0, 1]
PAPER = {"KF a": (1.447, None), "KF b": (1.613, None), "RBPF a": (0.141, 0.0632),
         "RBPF b": (0.161, 0.0666), "CI": (0.141, 0.0613), "modified CI": (0.109, 0.0592)}
ROWS = ("KF a", "KF b", "RBPF a", "RBPF b", "CI", "modified CI", "naive", "BCI logdet")
COLUMNS = ("mse_full", "mncm_full", "mse_pos", "mncm_pos", "anees")


def scenario(config: dict) -> Table1Config:
    return configs.build(Table1Config, config["scenario"], "scenario")


def estimates(config: dict, seed: np.random.SeedSequence):
    """Simulate one run; returns (data, {row: (means (T, 4), covs (T, 4, 4))})."""
    sc = scenario(config)
    sim_rng, *filter_rngs = (np.random.default_rng(s) for s in seed.spawn(3))
    data = simulate_table1(sc, sim_rng)
    model, (m0, P0) = sc.filter_model(), sc.prior()
    out = {}
    for name, node, frng in zip("ab", data.nodes, filter_rngs, strict=True):
        kf = kalman.run(node.scans, model, m0, P0)
        pf = rbpf.run(node.scans, model, m0, P0, rng=frng, n_particles=sc.n_particles,
                      clutter_prior=sc.clutter_prior, clutter_density=sc.clutter_density,
                      resample_threshold=sc.resample_threshold)
        out[f"KF {name}"] = (kf.means, kf.covs)
        out[f"RBPF {name}"] = (pf.means, pf.covs)
    out.update(_fused(config, sc, out["RBPF a"], out["RBPF b"]))
    return data, out


def _fused(config, sc, a, b) -> dict:
    means = np.stack([a[0], b[0]], axis=1)  # (T, 2, n)
    covs = np.stack([a[1], b[1]], axis=1)  # (T, 2, n, n)
    backend = config["backend"]
    chi = 1.0 / config["fusion"]["chi_inv"]
    rules = {"CI": dict(method="ci"), "naive": dict(method="naive"),
             "modified CI": dict(method="mbci", p_detect=list(sc.p_detect), chi=chi),
             "BCI logdet": dict(method="bci", criterion="logdet")}
    return {row: _fuse_series(means, covs, backend, **kw) for row, kw in rules.items()}


def _fuse_series(means, covs, backend, method, criterion="trace", **args):
    """Fuse every step: means (T, N, n), covs (T, N, n, n) -> (T, n), (T, n, n)."""
    r = fo.fuse_batch(means, covs, method=method, criterion=criterion, backend=backend,
                      **args)
    return r.mean, r.cov


def run_one(config: dict, index: int, seed: np.random.SeedSequence) -> dict:
    """Scores of every row for one run (a pure function of config and seed)."""
    data, est = estimates(config, seed)
    return {row: _scores(*est[row], data.truth) for row in ROWS}


def _scores(means, covs, truth) -> dict:
    return {
        "mse_full": metrics.mse(means, truth), "mse_pos": metrics.mse(means, truth, POSITION),
        "mncm_full": metrics.mncm(covs), "mncm_pos": metrics.mncm(covs, POSITION),
        "anees": metrics.anees(means, truth, covs),
    }


# ------------------------------------------------------------------------------ report

def report(config: dict, results: list[dict], out: Path) -> None:
    """table1.md, table1.csv and the figures, from the stored runs."""
    rows = stats.summarise(results, ROWS, COLUMNS)
    stats.write_csv(out / "table1.csv", rows, COLUMNS, PAPER, ("paper_mse", "paper_mncm"))
    (out / "table1.md").write_text(_markdown(config, rows, results))
    _figures(config, out)


def _markdown(config, rows, results) -> str:
    n = len(results)
    lines = [f"# Table 1 ({n} runs, seed {config['seed']}, backend {config['backend']})", "",
             "Mean and 95% interval over runs. MSE: mean over time of the squared error norm; "
             "MNCM: mean spectral norm of the covariance; full state and position block.", "",
             "| row | MSE full | paper MSE | MNCM full | paper MNCM | MSE pos | MNCM pos "
             "| ANEES (4-dof) |", "|---|---|---|---|---|---|---|---|"]
    for row, cols in rows.items():
        p_mse, p_mncm = PAPER.get(row, (None, None))
        cells = [stats.fmt(*cols[c]) for c in COLUMNS]
        lines.append(f"| {row} | {cells[0]} | {p_mse or '-'} | {cells[1]} | {p_mncm or '-'} "
                     f"| {cells[2]} | {cells[3]} | {cells[4]} |")
    lines += ["", "Paired comparison, modified CI minus CI (negative: modified CI better):", "",
              "| measure | mean difference [95%] | share of runs where modified CI is lower |",
              "|---|---|---|"]
    for col in COLUMNS[:4]:
        p = stats.paired([r["modified CI"][col] for r in results],
                         [r["CI"][col] for r in results])
        lines.append(f"| {col} | {stats.fmt(p['mean_diff'], p['low'], p['high'], 3)} "
                     f"| {p['share_better']:.2f} |")
    return "\n".join(lines) + "\n"


def _figures(config, out) -> None:
    """The paper's figures, from run 0 (recomputed: it is a pure function of its seed)."""
    seed = np.random.SeedSequence(config["seed"]).spawn(1)[0]
    data, est = estimates(config, seed)
    _measurements_figure(data, out / "table1_measurements.png")
    _paths_figure(data, est, ("RBPF a", "RBPF b", "modified CI"), out / "table1_paths.png")
    _covnorm_figure(data.times, est, config["fusion"]["window"], out / "table1_covnorm.png")


def _measurements_figure(data, path) -> None:
    fig, axes = new_figure(1, len(data.nodes), width=10)
    for ax, node, name in zip(axes, data.nodes, "ab", strict=True):
        ax.plot(data.truth[:, 0], data.truth[:, 1], "k-", label="target path")
        is_c = node.origin < 0
        ax.plot(*node.values[~is_c].T, "o", ms=2, color="tab:blue", label="target meas.")
        ax.plot(*node.values[is_c].T, "x", ms=3, color="tab:pink", label="clutter")
        ax.set_title(f"node {name}")
    axes[0].legend(loc="best", fontsize=8)
    save(fig, path)


def _paths_figure(data, est, rows, path) -> None:
    fig, axes = new_figure(1, len(rows), width=12)
    for ax, row in zip(axes, rows, strict=True):
        ax.plot(data.truth[:, 0], data.truth[:, 1], "r--", label="target path")
        ax.plot(est[row][0][:, 0], est[row][0][:, 1], "k-", lw=1, label="estimate")
        ax.set_title(row)
    axes[0].legend(loc="best", fontsize=8)
    save(fig, path)


def _covnorm_figure(times, est, window, path) -> None:
    fig, axes = new_figure(1, 1, width=6)
    sel = (times >= window[0]) & (times <= window[1])
    if not sel.any():  # a shortened run ends before the window: show all of it
        sel[:] = True
    for row in ("RBPF a", "RBPF b", "CI", "modified CI", "naive", "BCI logdet"):
        axes[0].plot(times[sel], np.linalg.norm(est[row][1][sel], 2, axis=(1, 2)), label=row)
    axes[0].set_xlabel("time (s)")
    axes[0].set_ylabel("2-norm of covariance")
    axes[0].legend(fontsize=8)
    save(fig, path)

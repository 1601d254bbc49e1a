"""Table 2: unknown number of targets; 7 RBMCDA nodes, 3 processing nodes fusing with CI
and modified CI.

Each run simulates the scenario, runs RBMCDA at every monitoring node, and at each
processing node and step associates its neighbours' estimates (fusion_opt.association)
and fuses every group of two or more with CI (BCI, trace) and with modified CI (MBCI with
the group's p_D and chi^-1 = 1 + dt); an estimate no other node shares is passed on as is.

Scores per node (DESIGN §3 leaves the paper's "sum over detected targets" open; ours):
each step, estimates are matched to the alive targets by optimal assignment on position,
gated at the cut-off c. For each target, MSE_j is the mean over its matched steps of the
full-state squared error and MNCM_j the mean spectral norm of the matched covariances; the
table's MSE and MNCM are the sums over the targets ever matched. OSPA and GOSPA (position,
cut-off c, order p, alpha = 2) and the cardinality error |n_est - n_true| are means over
the steps.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

import fusion_opt as fo
from fusion_opt.association import associate
from trackers import metrics, rbmcda
from trackers.scenarios import Table2Config, simulate_table2

from . import config as configs
from . import stats
from .plotting import new_figure, save

POSITION = [0, 1]
COLUMNS = ("mse", "mncm", "mse_pos", "mncm_pos", "ospa", "gospa", "card_err")
PAPER = {"RBMCDA 1": (0.1430, 0.0578), "RBMCDA 2": (0.4716, 0.0616),
         "RBMCDA 3": (0.1228, 0.0533), "RBMCDA 4": (0.1830, 0.0580),
         "RBMCDA 5": (0.1010, 0.0511), "RBMCDA 6": (0.1166, 0.0529),
         "RBMCDA 7": (0.1912, 0.0556), "CI 8": (0.0821, 0.0508), "CI 9": (0.0731, 0.0560),
         "CI 10": (0.0884, 0.0505), "modified CI 8": (0.0784, 0.0501),
         "modified CI 9": (0.0763, 0.0523), "modified CI 10": (0.0799, 0.0493)}


def scenario(config: dict) -> Table2Config:
    return configs.build(Table2Config, config["scenario"], "scenario")


def estimates(config: dict, seed: np.random.SeedSequence):
    """One run: (data, {row: list over steps of (means (m, 4), covs (m, 4, 4))})."""
    sc = scenario(config)
    sim_rng, *node_rngs = (np.random.default_rng(s) for s in seed.spawn(1 + len(sc.p_detect)))
    data = simulate_table2(sc, sim_rng)
    model, (m0, P0) = sc.filter_model(), sc.prior()
    out = {}
    for k, (node, rng) in enumerate(zip(data.nodes, node_rngs, strict=True), start=1):
        tracks = rbmcda.run(node.scans, model, m0, P0, rng=rng, dt=sc.dt,
                            n_particles=sc.n_particles, birth_prob=sc.birth_prob,
                            lifetime_shape=sc.lifetime_shape,
                            lifetime_scale=sc.lifetime_scale,
                            clutter_prior=sc.clutter_prior,
                            clutter_density=sc.clutter_density,
                            resample_threshold=sc.resample_threshold)
        out[f"RBMCDA {k}"] = [_stack(step) for step in tracks]
    for proc, neighbours in config["network"]["neighbours"].items():
        out.update(_processing_node(config, sc, proc, neighbours, out))
    return data, out


def _stack(tracks) -> tuple[np.ndarray, np.ndarray]:
    if not tracks:
        return np.zeros((0, 4)), np.zeros((0, 4, 4))
    return np.array([t.mean for t in tracks]), np.array([t.cov for t in tracks])


def _processing_node(config, sc, proc, neighbours, out) -> dict:
    """Rows "CI proc" and "modified CI proc": per step, fused groups plus singletons."""
    net, chi = config["network"], 1.0 / config["fusion"]["chi_inv"]
    p_all = np.array(sc.p_detect)
    T = sc.n_steps
    groups = [associate([out[f"RBMCDA {k}"][t][0] for k in neighbours], net["threshold"],
                        net["association"], dims=POSITION) for t in range(T)]
    rows = {}
    for row, method in ((f"CI {proc}", "bci"), (f"modified CI {proc}", "mbci")):
        fused = _fuse_groups(groups, neighbours, out, method, p_all, chi, config["backend"])
        rows[row] = fused
    return rows


def _fuse_groups(groups, neighbours, out, method, p_all, chi, backend):
    """Fuse all groups of each size in one batch; singletons pass through."""
    steps: list[list] = [[] for _ in groups]
    by_size = defaultdict(list)  # size -> [(t, group)]
    for t, gs in enumerate(groups):
        for g in gs:
            by_size[len(g)].append((t, g))
    for size, items in by_size.items():
        means = np.array([[out[f"RBMCDA {neighbours[k]}"][t][0][i] for k, i in g]
                          for t, g in items])
        covs = np.array([[out[f"RBMCDA {neighbours[k]}"][t][1][i] for k, i in g]
                         for t, g in items])
        if size == 1:
            fused_m, fused_c = means[:, 0], covs[:, 0]
        else:
            args = {}
            if method == "mbci":
                args = dict(p_detect=np.array([[p_all[neighbours[k] - 1] for k, _ in g]
                                               for _, g in items]), chi=chi)
            r = fo.fuse_batch(means, covs, method=method, backend=backend, **args)
            fused_m, fused_c = r.mean, r.cov
        for (t, _), m, c in zip(items, fused_m, fused_c, strict=True):
            steps[t].append((m, c))
    return [(np.array([m for m, _ in s]).reshape(-1, 4), np.array([c for _, c in s])
             .reshape(-1, 4, 4)) for s in steps]


def run_one(config: dict, index: int, seed: np.random.SeedSequence) -> dict:
    data, est = estimates(config, seed)
    return {row: _scores(config, data, series) for row, series in est.items()}


def _scores(config, data, series) -> dict:
    c, p = config["metrics"]["cutoff"], config["metrics"]["order"]
    per_target = {k: defaultdict(list) for k in ("mse", "mncm", "mse_pos", "mncm_pos")}
    ospa, gospa, card = [], [], []
    for t, (means, covs) in enumerate(series):
        alive = np.flatnonzero(data.alive[:, t])
        truth = data.truth[alive, t]
        ospa.append(metrics.ospa(means[:, POSITION], truth[:, POSITION], c, p))
        gospa.append(metrics.gospa(means[:, POSITION], truth[:, POSITION], c, p))
        card.append(abs(len(means) - len(alive)))
        for i, j in _matches(means, truth, c):
            err = means[i] - truth[j]
            for key, e, P in (("mse", err, covs[i]),
                              ("mse_pos", err[POSITION], covs[i][:2, :2])):
                per_target[key][alive[j]].append(float(e @ e))
                per_target[key.replace("mse", "mncm")][alive[j]].append(
                    float(np.linalg.norm(P, 2)))
    scores = {key: float(sum(np.mean(v) for v in d.values())) for key, d in per_target.items()}
    return scores | {"ospa": float(np.mean(ospa)), "gospa": float(np.mean(gospa)),
                     "card_err": float(np.mean(card))}


def _matches(means, truth, c):
    """Optimal assignment of estimates to targets on position, pairs closer than c."""
    if len(means) == 0 or len(truth) == 0:
        return []
    D = np.linalg.norm(means[:, None, :2] - truth[None, :, :2], axis=-1)
    r, s = linear_sum_assignment(np.minimum(D, c))
    return [(i, j) for i, j in zip(r, s, strict=True) if D[i, j] < c]


# ------------------------------------------------------------------------------ report

def report(config: dict, results: list[dict], out: Path) -> None:
    rows = stats.summarise(results, results[0], COLUMNS)
    stats.write_csv(out / "table2.csv", rows, COLUMNS, PAPER, ("paper_mse_e-3", "paper_mncm"))
    (out / "table2.md").write_text(_markdown(config, rows, results))
    _figures(config, out)


def _markdown(config, rows, results) -> str:
    lines = [f"# Table 2 ({len(results)} runs, seed {config['seed']}, backend "
             f"{config['backend']}, association {config['network']['association']})", "",
             "Mean and 95% interval over runs; MSE and MNCM summed over the targets matched "
             "(studies/table2.py says how); the paper's MSE column is in units of 1e-3.", "",
             "| node | MSE | paper MSE (x1e-3) | MNCM | paper MNCM | MSE pos | MNCM pos | OSPA "
             "| GOSPA | card. error |", "|---" * 10 + "|"]
    for row, cols in rows.items():
        p_mse, p_mncm = PAPER.get(row, ("-", "-"))
        c = [stats.fmt(*cols[k]) for k in COLUMNS]
        lines.append(f"| {row} | {c[0]} | {p_mse} | {c[1]} | {p_mncm} | "
                     + " | ".join(c[2:]) + " |")
    lines += ["", "Paired comparison, modified CI minus CI at each processing node:", "",
              "| node | MSE difference [95%] | share MCI lower | MNCM difference [95%] |",
              "|---|---|---|---|"]
    for proc in config["network"]["neighbours"]:
        pm = stats.paired([r[f"modified CI {proc}"]["mse"] for r in results],
                          [r[f"CI {proc}"]["mse"] for r in results])
        pc = stats.paired([r[f"modified CI {proc}"]["mncm"] for r in results],
                          [r[f"CI {proc}"]["mncm"] for r in results])
        lines.append(f"| {proc} | {stats.fmt(pm['mean_diff'], pm['low'], pm['high'], 3)} | "
                     f"{pm['share_better']:.2f} | "
                     f"{stats.fmt(pc['mean_diff'], pc['low'], pc['high'], 3)} |")
    return "\n".join(lines) + "\n"


def _figures(config, out) -> None:
    """The paper's figures from run 0: node 3 (paths, measurements, estimates, number of
    targets) and the fused estimates at node 9."""
    seed = np.random.SeedSequence(config["seed"]).spawn(1)[0]
    data, est = estimates(config, seed)
    fig, axes = new_figure(1, 3, width=14)
    for j in range(len(data.truth)):
        for ax in axes[:2]:
            ax.plot(data.truth[j, :, 0], data.truth[j, :, 1], "k-", lw=1)
    axes[0].plot(*data.nodes[2].values.T, "x", ms=3, color="tab:red")
    axes[0].set_title("targets and measurements, node 3")
    pts = np.concatenate([m for m, _ in est["RBMCDA 3"]])
    axes[1].plot(pts[:, 0], pts[:, 1], "o", ms=1.5, color="tab:red")
    axes[1].set_title("RBMCDA estimates, node 3")
    axes[2].plot(data.times, data.n_alive, "k-", label="truth")
    for row, style in (("RBMCDA 3", "r--"), ("modified CI 9", "b:")):
        if row in est:
            axes[2].plot(data.times, [len(m) for m, _ in est[row]], style, label=row)
    axes[2].set_xlabel("time (s)")
    axes[2].set_title("number of targets")
    axes[2].legend(fontsize=8)
    save(fig, out / "table2_node3.png")
    if "modified CI 9" in est:
        fig, axes = new_figure(1, 1, width=5)
        for j in range(len(data.truth)):
            axes[0].plot(data.truth[j, :, 0], data.truth[j, :, 1], "k-", lw=1)
        pts = np.concatenate([m for m, _ in est["modified CI 9"]])
        axes[0].plot(pts[:, 0], pts[:, 1], "o", ms=1.5, color="tab:blue")
        axes[0].set_title("modified CI, processing node 9")
        save(fig, out / "table2_node9.png")

"""Figure helpers shared by the studies (matplotlib, no display needed).

Conventions of the studies' figures: every axis is labelled with its unit; trajectory
panels have equal aspect and mark where each path starts and its direction of travel; a
legend sits outside the panels (it never covers data) and names every kind of mark, bands
included; a figure drawn from one run says which run and seed in its title. Positions
are in metres and times in seconds (the paper gives no unit of length; we read it as m).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)
import numpy as np  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.ticker import NullFormatter  # noqa: E402

POSITION_LABELS = ("x (m)", "y (m)")
START = {"marker": "o", "ms": 6, "mfc": "white", "mec": "black", "mew": 1.2, "ls": "none"}


def new_figure(rows: int, cols: int, width: float = 6.0):
    """A figure and a flat list of its axes."""
    fig, axes = plt.subplots(rows, cols, figsize=(width, width / cols * rows * 0.9),
                             squeeze=False)
    return fig, list(axes.ravel())


def panels(rows: int, cols: int, width: float, height: float, **kw):
    """A figure of rows x cols panels laid out by matplotlib's constrained layout (which
    leaves room for a legend placed "outside"), and a flat list of its axes."""
    fig, axes = plt.subplots(rows, cols, figsize=(width, height), squeeze=False,
                             layout="constrained", **kw)
    return fig, list(axes.ravel())


def save(fig, path: Path) -> None:
    if fig.get_layout_engine() is None:
        fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def log_axes(ax, xs, xlabel: str) -> None:
    """Log-log axes with x ticks at the values xs, labelled plainly (no crowded minors)."""
    ax.set(xscale="log", yscale="log", xlabel=xlabel)
    ax.set_xticks(list(xs))
    ax.set_xticklabels([str(x) for x in xs])
    ax.xaxis.set_minor_formatter(NullFormatter())


def trajectory_axes(ax, title: str | None = None) -> None:
    """Equal aspect and position labels in metres."""
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(xlabel=POSITION_LABELS[0], ylabel=POSITION_LABELS[1])
    if title:
        ax.set_title(title, fontsize=10)


def path(ax, xy, color="black", arrows: int = 3, at=None, **style) -> None:
    """A path (T, 2) with a hollow circle at its start and `arrows` arrowheads along it
    (at the middles of equal shares of its length, or at the shares `at` of its length)
    showing the direction of travel."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    if not len(xy):
        return
    ax.plot(xy[:, 0], xy[:, 1], color=color, **({"lw": 1.0, "zorder": 3} | style))
    ax.plot(*xy[0], **(START | {"mec": color, "zorder": 4}))
    with np.errstate(over="ignore", invalid="ignore"):  # a path beyond 1e308 gets no arrows
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    if not 0 < arc[-1] < np.inf:
        return
    for share in (np.arange(arrows) + 0.5) / arrows if at is None else at:
        at = share * arc[-1]
        head = [np.interp(at, arc, xy[:, k]) for k in (0, 1)]
        tail = [np.interp(at - 0.02 * arc[-1], arc, xy[:, k]) for k in (0, 1)]
        ax.annotate("", xy=head, xytext=tail, zorder=4, arrowprops={
            "arrowstyle": "-|>", "color": color, "lw": 1.0, "mutation_scale": 12})


def path_handles(color="black", label="true path", **style) -> list:
    """Legend entries for `path`: the line (with an arrowhead-like marker) and the start."""
    return [Line2D([], [], color=color, marker=">", ms=5, label=f"{label} (arrows: "
                   "direction of travel)", **({"lw": 1.0} | style)),
            Line2D([], [], **(START | {"mec": color}), label="start of a path")]


def legend_below(fig, handles: list, ncol: int | None = None, **kw) -> None:
    """One legend for the whole figure, below its panels (never over data)."""
    fig.legend(handles=handles, loc="outside lower center",
               ncol=ncol or min(len(handles), 4), fontsize=8, frameon=False, **kw)


def run_title(fig, what: str, run: int, seed: int) -> None:
    """The figure's title: what it shows, of which run and root seed."""
    fig.suptitle(f"{what} (run {run}, seed {seed})", fontsize=11)

"""Figure helpers shared by the studies (matplotlib, no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)
from matplotlib.ticker import NullFormatter  # noqa: E402


def new_figure(rows: int, cols: int, width: float = 6.0):
    """A figure and a flat list of its axes."""
    fig, axes = plt.subplots(rows, cols, figsize=(width, width / cols * rows * 0.9),
                             squeeze=False)
    return fig, list(axes.ravel())


def save(fig, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def log_axes(ax, xs, xlabel: str) -> None:
    """Log-log axes with x ticks at the values xs, labelled plainly (no crowded minors)."""
    ax.set(xscale="log", yscale="log", xlabel=xlabel)
    ax.set_xticks(list(xs))
    ax.set_xticklabels([str(x) for x in xs])
    ax.xaxis.set_minor_formatter(NullFormatter())

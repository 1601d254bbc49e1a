"""Every figure a study draws (Table 1, Table 2, nnode, network; tiny runs through the
command line), as a reader needs it: each axis labelled with its unit, trajectory panels
with equal aspect and the start and direction of every path marked, one legend for the
figure outside its panels (none inside one, where it could cover data), and a title that
says which run and seed (or how many runs) it shows."""

import matplotlib.colors as mcolors
import pytest

from studies import plotting
from studies.__main__ import main

TINY = {
    "table1": 'runs = 2\nbackend = "newton"\n[scenario]\nn_steps = 40\nn_particles = 4\n'
              "[check]\nsteps = 0\n",
    "table2": 'runs = 2\nbackend = "newton"\n[scenario]\nn_steps = 40\nn_particles = 4\n',
    "nnode": "runs = 2\n[static]\ndraws = 10\n[sweeps]\nN = [2, 4]\n[dynamic]\nN = [2]\n"
             'steps = 12\nburn_in = 2\n[scaling]\nN = [2, 3]\nn = [2, 3]\nbackends = ["newton"]\n'
             "repeats = 1\n",
    "network": "runs = 2\n[scenario]\nn_steps = 10\nn_targets = 3\nbirths = [0.0]\n"
               "[tracker]\nn_particles = 3\n[benchmark]\nsources = [2]\ntargets_at_sources = 3"
               "\ntargets = [3]\nsources_at_targets = 2\nwarmup = 1\nsteps = 1\n",
}
FIGURES = {
    "table1": {"table1_measurements.png", "table1_paths.png", "table1_covnorm.png"},
    "table2": {"table2_node3.png", "table2_node9.png"},
    "nnode": {"nnode_mse_anees_vs_N.png", "nnode_time_vs_N.png"},
    "network": {"network_tracks.png", "network_throughput.png"},
}


@pytest.fixture(scope="module")
def drawn(tmp_path_factory) -> dict:
    """{study: {file name: Figure}} of a tiny run of every study."""
    out = tmp_path_factory.mktemp("figures")
    figures: dict = {}
    original = plotting.save

    def keep(fig, path):
        figures.setdefault(path.parent.name, {})[path.name] = fig
        original(fig, path)

    with pytest.MonkeyPatch.context() as m:
        m.setattr(plotting, "save", keep)
        for study, text in TINY.items():
            config = out / f"{study}.toml"
            config.write_text(text)
            assert main(["run", study, "--config", str(config), "--out", str(out), "--quiet",
                         "--workers", "1"]) == 0
    return figures


def _is_start(line) -> bool:
    return line.get_marker() == "o" and mcolors.to_rgba(line.get_markerfacecolor()) == \
        mcolors.to_rgba("white")


@pytest.mark.parametrize("study", sorted(TINY))
def test_every_figure_is_labelled_marked_and_titled(drawn, study):
    assert set(drawn[study]) == FIGURES[study]
    for name, fig in drawn[study].items():
        title = fig._suptitle.get_text() if fig._suptitle else ""
        assert "seed" in title and ("run 0" in title or "runs" in title or "steps" in title
                                    or "problems" in title), (name, title)
        assert fig.legends, f"{name}: no figure legend"
        for ax in fig.axes:
            where = f"{name}, panel {ax.get_title()!r}"
            assert ax.get_legend() is None, f"{where}: a legend inside the panel"
            xlabel, ylabel = ax.get_xlabel(), ax.get_ylabel()
            assert xlabel and ylabel, f"{where}: unlabelled axis"
            if xlabel == plotting.POSITION_LABELS[0]:  # a trajectory panel
                assert ylabel == plotting.POSITION_LABELS[1] and ax.get_aspect() == 1.0, where
                assert any(_is_start(line) for line in ax.get_lines()), f"{where}: no start"
                assert any(t.arrow_patch is not None for t in ax.texts), f"{where}: no arrow"
            else:
                assert "(" in xlabel or "N (nodes)" in xlabel or "number of" in xlabel, \
                    f"{where}: x label {xlabel!r} without a unit"


def test_coinciding_covariance_norms_stay_visible(drawn):
    """CI, modified CI and BCI logdet nearly coincide: each has its own line style or
    marker, and a panel shows their differences to CI."""
    fig = drawn["table1"]["table1_covnorm.png"]
    top, *diffs = fig.axes
    styles = {line.get_label(): (line.get_linestyle(), line.get_marker(), line.get_color())
              for line in top.get_lines()}
    assert len({styles[r] for r in ("CI", "modified CI", "BCI logdet")}) == 3
    assert [d.get_ylabel().split("\n")[0] for d in diffs] == ["modified CI minus CI",
                                                              "BCI logdet minus CI"]


def test_bands_are_in_the_legend(drawn):
    fig = drawn["nnode"]["nnode_mse_anees_vs_N.png"]
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert any("95% band of the ANEES" in t for t in labels)
    assert any("95% interval of the mean" in t for t in labels)


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")  # matplotlib's ticks
@pytest.mark.parametrize("xy, arrows", [([[1e300, 1e300], [1.5e300, 1.7e300]], 1),
                                        ([[0.0, 0.0], [1e308, 0.0], [0.0, 1.0], [1e308, 1.0]], 0)])
def test_a_path_far_out_is_drawn_and_saved(tmp_path, xy, arrows):
    """A target configured at 1e300 (fuzz H17): its path's arc length once overflowed in
    norm's squares, the arrow's position became NaN and savefig ended in matplotlib's
    StopIteration. Now the arc is summed with hypot; a path whose length exceeds the floats
    (three legs of 1e308) is drawn without arrows."""
    fig, (ax,) = plotting.panels(1, 1, width=3, height=3)
    plotting.path(ax, xy, at=(0.3,))
    assert len(ax.texts) == arrows
    plotting.save(fig, tmp_path / "far.png")
    assert (tmp_path / "far.png").stat().st_size > 0

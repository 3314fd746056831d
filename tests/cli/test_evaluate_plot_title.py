"""``evaluate --plot``: the accuracy plot's title names the take and its frame range; a long
take name (``cmu_02_05_expressions.c3d:0:900``) ran past the figure's right edge and lost the
range. The title wraps inside the figure."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402

from labeler_service.cli.evaluate import plot_accuracy_vs_downsampling  # noqa: E402


def test_a_long_take_name_stays_inside_the_figure(tmp_path, monkeypatch):
    figures = []
    monkeypatch.setattr(plt, "close", lambda fig: figures.append(fig))
    title = "knee_functional_clusters_73markers_100hz.c3d:120:900"
    curves = {"online": [(1, 0.99), (2, 0.98), (4, 0.97)]}
    plot_accuracy_vs_downsampling(curves, tmp_path / "acc.png", title=title)
    (fig,) = figures
    renderer = fig.canvas.get_renderer()
    ax = fig.axes[0]
    box = ax.title.get_window_extent(renderer)
    assert box.x0 >= 0 and box.x1 <= fig.bbox.width
    assert "".join(ax.get_title().split()).endswith("120:900")


def test_a_plot_format_matplotlib_cannot_write_is_refused_before_the_run(tmp_path, capsys):
    """``--plot out.xyz`` ran the three evaluations, then ended in matplotlib's traceback
    "ValueError: Format 'xyz' is not supported"."""
    from labeler_service.cli.main import main

    code = main(["evaluate", str(tmp_path / "missing.c3d"), "--plot", str(tmp_path / "p.xyz")])
    assert code == 2
    err = capsys.readouterr().err
    assert "p.xyz: cannot write a plot as .xyz" in err and "png" in err
    assert "missing.c3d" not in err  # said before the capture is read

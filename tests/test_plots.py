"""camrep.runtime.plots: means and bands over seeds, Gram-map ticks in the DOF's units, PNG and
PDF twins that do not change between identical calls."""

from __future__ import annotations

import numpy as np

from camrep.runtime import plots


def test_mean_and_band_over_seeds_skip_non_finite_values():
  values = np.array([[1.0, 2.0, np.nan, np.nan], [3.0, 6.0, 5.0, np.nan]])
  mean, low, high, seeds = plots.mean_and_band(values)
  assert seeds == 2
  np.testing.assert_allclose(mean, [2.0, 4.0, 5.0, np.nan])
  np.testing.assert_allclose(low, [1.0, 2.0, 5.0, np.nan])
  np.testing.assert_allclose(high, [3.0, 6.0, 5.0, np.nan])
  one = plots.mean_and_band([1.0, 2.0])
  assert one[3] == 1 and np.array_equal(one[0], one[1]) and np.array_equal(one[0], one[2])


def test_curves_figure_draws_a_band_only_for_seeds():
  x = [0.0, 0.1, 0.2]
  series = {"two seeds": np.array([[1.0, 2.0, 3.0], [3.0, 4.0, 5.0]]), "one": [1.0, np.nan, 0.0]}
  fig = plots.curves_figure(x, [plots.Panel("t", "y", series, xlabel="x")])
  (ax,) = fig.axes
  lines = ax.get_lines()
  np.testing.assert_allclose(lines[0].get_ydata(), [2.0, 3.0, 4.0])
  np.testing.assert_allclose(lines[1].get_xdata(), [0.0, 0.2])  # the NaN point left out
  assert len(ax.collections) == 1  # one band: the series with seeds
  assert [t.get_text() for t in ax.get_legend().get_texts()] == [
    "two seeds (mean of 2 seeds)",
    "one",
  ]


def test_a_legend_says_how_few_seeds_remain_where_runs_stopped():
  """Seeds that stopped before the others (their values NaN at the later points) are not
  counted in the legend's "mean of" as if they were still there."""
  x = [0.0, 1.0, 2.0]
  series = {
    "stopped": np.array([[1.0, 2.0, np.nan], [3.0, 4.0, 5.0], [2.0, np.nan, np.nan]]),
    "all": np.array([[1.0, 2.0, 3.0], [2.0, 3.0, 4.0]]),
  }
  fig = plots.curves_figure(x, [plots.Panel("t", "y", series, xlabel="x")])
  (ax,) = fig.axes
  assert [t.get_text() for t in ax.get_legend().get_texts()] == [
    "stopped (mean of the 1-3 seeds logged at each step)",
    "all (mean of 2 seeds)",
  ]
  np.testing.assert_allclose(ax.get_lines()[0].get_ydata(), [2.0, 3.0, 5.0])


def test_panels_with_the_same_series_share_one_legend_below_them():
  x = [0.0, 0.1]
  series = {"ours": [1.0, 2.0], "quat": np.array([[1.0, 1.5], [2.0, 2.5]])}
  fig = plots.curves_figure(x, [plots.Panel("a", "y", series), plots.Panel("b", "z", series)])
  assert all(ax.get_legend() is None for ax in fig.axes)  # no legend over either panel's curves
  (legend,) = fig.legends
  assert [t.get_text() for t in legend.get_texts()] == ["ours", "quat (mean of 2 seeds)"]
  # Panels with different series keep a legend each.
  other = {"mlp": [0.0, 1.0]}
  fig = plots.curves_figure(x, [plots.Panel("a", "y", series), plots.Panel("b", "z", other)])
  assert not fig.legends and all(ax.get_legend() is not None for ax in fig.axes)


def test_gram_ticks_are_in_the_dofs_units():
  k = 360
  yaw = plots.gram_axis(np.deg2rad(np.arange(k)), name="yaw", angular=True)
  fig = plots.gram_figure(np.eye(k), yaw, title="yaw")
  ax = fig.axes[0]
  labels = [t.get_text() for t in ax.get_xticklabels()]
  assert labels[:4] == ["0", "90", "180", "270"] and "degrees" in ax.get_xlabel()
  np.testing.assert_allclose(ax.get_xticks()[:2], [0.0, 90.0 * (k - 1) / 359])
  # A polar DOF's flat (x, y) grid: ticks at the start of x rows, labelled with x.
  g = np.stack(np.meshgrid(np.linspace(-1, 1, 21), np.linspace(-1, 1, 21), indexing="ij"), -1)
  xy = plots.gram_axis(g.reshape(-1, 2), name="xy", angular=False)
  ax = plots.gram_figure(np.eye(441), xy, title="xy").axes[0]
  assert ax.get_xticklabels()[0].get_text() == "x=-1" and ax.get_xticks()[1] % 21 == 0
  # A linear DOF keeps its own values.
  lin = plots.gram_axis(np.linspace(0.0, 2.0, 41), name="z", angular=False)
  labels = [
    t.get_text() for t in plots.gram_figure(np.eye(41), lin, title="z").axes[0].get_xticklabels()
  ]
  assert labels[0] == "0" and labels[-1] == "2"


def test_save_writes_png_and_pdf_twins_reproducibly(tmp_path):
  fig = plots.curves_figure([0, 1], [plots.Panel("t", "y", {"a": [0.0, 1.0]})])
  paths = plots.save(fig, str(tmp_path / "f.png"))
  assert paths == [str(tmp_path / "f.png"), str(tmp_path / "f.pdf")]
  png, pdf = (open(p, "rb").read() for p in paths)
  assert png.startswith(b"\x89PNG") and pdf.startswith(b"%PDF")
  again = plots.save(fig, str(tmp_path / "g.png"))
  assert open(again[0], "rb").read() == png and open(again[1], "rb").read() == pdf
  rgb = plots.to_rgb(fig)
  assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3


def test_nine_representations_get_nine_distinct_line_looks():
  """A Table 1 column's nine curves (and up to 40 series) never share colour, style and marker."""
  x = np.arange(3.0)
  series = {f"rep{i}": np.full(3, float(i)) for i in range(12)}
  fig = plots.curves_figure(x, [plots.Panel("t", "y", series)])
  lines = fig.axes[0].get_lines()
  looks = {(ln.get_color(), ln.get_linestyle(), ln.get_marker()) for ln in lines}
  assert len(lines) == 12 and len(looks) == 12
  assert len({ln.get_color() for ln in lines[:10]}) == 10  # tab10 before any style repeats
  assert len({tuple(plots.series_style(i).values()) for i in range(40)}) == 40


def test_a_long_title_is_wrapped_to_the_figure_width():
  """A title longer than the panels are wide is wrapped (and the figure made taller for it)."""
  title = "car: validation score = " + "a long definition of the score " * 6
  fig = plots.curves_figure([0.0, 1.0], [plots.Panel("t", "y", {"a": [1.0, 2.0]})], suptitle=title)
  lines = fig._suptitle.get_text().splitlines()
  assert len(lines) > 1 and max(map(len, lines)) <= 13 * plots.PANEL_SIZE[0]
  assert " ".join(lines) == title.strip()
  assert fig.get_size_inches()[1] > plots.PANEL_SIZE[1] + 0.2

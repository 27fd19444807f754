"""The report's figures: drawn once on a padded canvas and cropped to what is drawn, as
``savefig(bbox_inches="tight")`` would crop them."""

from __future__ import annotations

import numpy as np
import pytest

mpl = pytest.importorskip("matplotlib")
mpl.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.image import imread

from imupipe.report.exporter import DPI, PAD_IN, _new_figure, _save


def _drawn(note_x: float = 0.5):
    fig = _new_figure(plt, (7, 3.6))
    ax = fig.subplots()
    ax.plot(np.arange(50), np.sin(np.arange(50) / 5), ".", label="a")
    ax.set_xlabel("time, s")
    ax.set_ylabel("error")
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0))
    ax.text(note_x, 0.5, "note", transform=ax.transAxes)
    return fig


@pytest.mark.parametrize("note_x", [0.5, 2.5])  # 2.5 axes widths: past the padded canvas
def test_a_figure_is_cropped_as_a_tight_bounding_box_would_crop_it(tmp_path, note_x):
    fig = _drawn(note_x)
    _save(fig, tmp_path / "one.png")
    fig.savefig(tmp_path / "tight.png", format="png", dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    one, tight = imread(tmp_path / "one.png"), imread(tmp_path / "tight.png")
    assert abs(one.shape[0] - tight.shape[0]) <= 1 and abs(one.shape[1] - tight.shape[1]) <= 1
    if note_x > 1:  # wider than the canvas: savefig draws the measured box
        assert one.shape[1] > (7 + 2 * PAD_IN) * DPI
    h, w = min(one.shape[0], tight.shape[0]), min(one.shape[1], tight.shape[1])
    # the same picture: a pixel's shift at most (the crop rounds where savefig snaps)
    assert np.mean(np.abs(one[:h, :w] - tight[:h, :w]) > 0.1) < 0.05

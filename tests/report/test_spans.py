"""``shade``: the pixels and x limits of one ``axvspan`` per band."""

from __future__ import annotations

import numpy as np
import pytest

from imupipe.report.spans import shade

mpl = pytest.importorskip("matplotlib")
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402


def _pixels(draw) -> tuple[bytes, tuple[float, float]]:
    fig = Figure(figsize=(4, 3), dpi=80)
    canvas = FigureCanvasAgg(fig)
    ax = fig.subplots()
    draw(ax)
    canvas.draw()
    return bytes(canvas.buffer_rgba()), ax.get_xlim()


def test_shade_draws_the_pixels_of_axvspan():
    rng = np.random.default_rng(2)
    x0 = np.sort(rng.uniform(0, 100, 60))
    x1 = x0 + rng.uniform(0.1, 8.0, 60)  # overlapping, reaching past the data on the right
    t = np.linspace(0, 100, 500)

    def spans(ax):
        for a, b in zip(x0, x1, strict=True):
            ax.axvspan(a, b, color="r", alpha=0.2, lw=0)
        ax.plot(t, np.sin(t), lw=0.6)

    def collection(ax):
        shade(ax, x0, x1, color="r", alpha=0.2, lw=0)
        ax.plot(t, np.sin(t), lw=0.6)

    (want, want_xlim), (got, got_xlim) = _pixels(spans), _pixels(collection)
    np.testing.assert_allclose(got_xlim, want_xlim, rtol=1e-15)  # axvspan's pass through transforms
    assert got == want

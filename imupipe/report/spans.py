"""Shaded time spans in the report's figures."""

from __future__ import annotations

import numpy as np


def shade(ax, x0: np.ndarray, x1: np.ndarray, **style) -> None:
    """Bands from ``x0`` to ``x1`` (data x, (n,) each) over the axes' full height: the pixels
    of one ``ax.axvspan`` per band, in one collection (thousands of patches are slow)."""
    from matplotlib.collections import PolyCollection

    x0, x1 = np.asarray(x0, float), np.asarray(x1, float)
    if not len(x0):
        return
    bands = np.zeros((len(x0), 4, 2))  # (a, 0), (a, 1), (b, 1), (b, 0): no Python tuple per band
    bands[:, :2, 0], bands[:, 2:, 0], bands[:, 1:3, 1] = x0[:, None], x1[:, None], 1.0
    ax.add_collection(PolyCollection(bands, transform=ax.get_xaxis_transform(), **style), autolim=False)
    ax.update_datalim(np.column_stack([np.r_[x0, x1], np.zeros(2 * len(x0))]), updatey=False)
    ax.autoscale_view(scaley=False)  # x limits as axvspan sets them

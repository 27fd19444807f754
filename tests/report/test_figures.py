"""The report's figures: drawn once on a padded canvas and cropped to what is drawn, as
``savefig(bbox_inches="tight")`` would crop them; copied, not drawn, when the figure store holds
one drawn from the same values."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

pytest.importorskip("matplotlib")
from matplotlib.image import imread

from imupipe.report.exporter import DPI, PAD_IN, _new_figure, _save


def _drawn(note_x: float = 0.5):
    fig = _new_figure((7, 3.6))
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
    one, tight = imread(tmp_path / "one.png"), imread(tmp_path / "tight.png")
    assert abs(one.shape[0] - tight.shape[0]) <= 1 and abs(one.shape[1] - tight.shape[1]) <= 1
    if note_x > 1:  # wider than the canvas: savefig draws the measured box
        assert one.shape[1] > (7 + 2 * PAD_IN) * DPI
    h, w = min(one.shape[0], tight.shape[0]), min(one.shape[1], tight.shape[1])
    # the same picture: a pixel's shift at most (the crop rounds where savefig snaps)
    assert np.mean(np.abs(one[:h, :w] - tight[:h, :w]) > 0.1) < 0.05


def _tables(errors_after: float) -> dict:
    """A ``rests`` table (the positions figure) and a ``validation`` table (the turn errors)."""
    from imupipe.schemas import SCHEMA_KEY

    u = np.random.default_rng(0).normal(size=(12, 3))
    rests = pa.table({"accel_mean": pa.FixedSizeListArray.from_arrays(pa.array(u.ravel()), 3)},
                     metadata={SCHEMA_KEY: b"rests"})
    turns = pa.table({"angle_error_before_deg": np.linspace(-0.3, 0.3, 8),
                      "angle_error_after_deg": np.full(8, errors_after)},
                     metadata={SCHEMA_KEY: b"validation", b"imupipe.summary": b'{"tolerance_deg": 0.1}'})
    return {"rests.rests": rests, "validate.validation": turns}


def test_a_figure_drawn_before_from_the_same_values_is_copied_not_drawn(tmp_path, monkeypatch):
    """With a figure store (``imupipe run``'s cache), a report redrawn because one table changed
    draws only the figures that read it and copies the others; without one, every figure is drawn."""
    from imupipe.report import exporter

    drawn = []
    save = exporter._save
    monkeypatch.setattr(exporter, "_save", lambda fig, path: (drawn.append(path.name), save(fig, path)))
    context = {"session": "s", "figure_store": str(tmp_path / "store")}

    exporter.REPORT.export(_tables(0.01), context, tmp_path / "a")
    assert sorted(drawn) == ["positions.png", "turn_errors.png"]
    drawn.clear()
    exporter.REPORT.export(_tables(0.02), context, tmp_path / "b")  # the validation changed
    assert drawn == ["turn_errors.png"]
    same = [(tmp_path / d / "figures" / "positions.png").read_bytes() for d in "ab"]
    assert same[0] == same[1]
    assert (tmp_path / "a" / "figures" / "turn_errors.png").read_bytes() != \
        (tmp_path / "b" / "figures" / "turn_errors.png").read_bytes()
    drawn.clear()
    exporter.REPORT.export(_tables(0.02), {"session": "s"}, tmp_path / "c")  # no store: drawn
    assert sorted(drawn) == ["positions.png", "turn_errors.png"]
    drawn.clear()
    (tmp_path / "not_a_folder").write_text("")  # a store that cannot be read or written: drawn
    exporter.REPORT.export(_tables(0.02), {"session": "s", "figure_store": str(tmp_path / "not_a_folder")},
                           tmp_path / "d")
    assert sorted(drawn) == ["positions.png", "turn_errors.png"]
    assert (tmp_path / "d" / "report.md").is_file()


def test_each_figure_is_freed_once_saved_and_nothing_is_left_frozen(tmp_path, monkeypatch):
    """A figure is a web of reference cycles holding its raster: each is gone by the time the
    next is drawn, without waiting for the collector, and the report leaves no object frozen."""
    import gc
    import weakref

    from imupipe.report import exporter

    figures, alive_when_drawn = [], []
    drawn = exporter._drawn

    def spy(title, draw, panels):
        alive_when_drawn.append(sum(f() is not None for f in figures))
        fig = drawn(title, draw, panels)
        figures.append(weakref.ref(fig))
        return fig

    monkeypatch.setattr(exporter, "_drawn", spy)
    gc.disable()  # only the report's own collections
    try:
        exporter.REPORT.export(_tables(0.01), {"session": "s"}, tmp_path)
        assert len(figures) == 2
        assert alive_when_drawn == [0, 0]
        assert all(f() is None for f in figures)
        assert gc.get_freeze_count() == 0
    finally:
        gc.enable()


def test_a_figure_key_follows_every_value_its_drawing_holds():
    from imupipe.report.exporter import figure_key

    def key_of(value, title="t"):
        return figure_key("f", title, False, lambda ax, v=value: None)

    a, b = np.arange(5.0), np.arange(5.0)
    assert key_of(b) == key_of(a)
    b[2] = 7.0
    assert key_of(b) != key_of(a)
    assert key_of(a, "other title") != key_of(a)
    assert key_of(a.astype(np.float32)) != key_of(a)
    table = pa.table({"x": [1.0, 2.0]}, metadata={b"k": b"1"})
    assert key_of(table.replace_schema_metadata({b"k": b"2"})) != key_of(table)
    assert key_of(pa.table({"x": [1.0, 2.5]}, metadata={b"k": b"1"})) != key_of(table)
    assert key_of({"doc": [1, 2.0, "x"]}) != key_of({"doc": [1, 2, "x"]})
    assert key_of(np) is None  # a module: not digested, always drawn

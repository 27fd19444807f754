"""``report.html``: the exporter's Markdown subset rendered with its figures embedded."""

from __future__ import annotations

from imupipe.report.html import render


def test_headings_tables_lists_and_embedded_figures(tmp_path):
    (tmp_path / "figures").mkdir()
    (tmp_path / "figures" / "a.png").write_bytes(b"\x89PNG fake")
    md = ("# Report: <x>\n\n## Verdict: warn\n\n- warn: **k** `b0`\n- pass\n\n"
          "| check | status |\n|---|---|\n| chi2 | warn |\n\n![the fit](figures/a.png)\n![gone](figures/b.png)\n")
    page = render(md, tmp_path)
    assert "<title>Report: &lt;x&gt;</title>" in page and "<h2>Verdict: warn</h2>" in page
    assert "<li>warn: <b>k</b> <code>b0</code></li>" in page
    assert '<td class="warn">warn</td>' in page and "<th>status</th>" in page
    assert 'src="data:image/png;base64,iVBORyBmYWtl"' in page  # embedded
    assert 'src="figures/b.png"' in page  # a missing figure stays a link

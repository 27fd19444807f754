"""``report.html``: the report as one self-contained page (figures embedded), for a browser.

The report is written as Markdown by ``exporter.py`` in a small subset: headings, paragraphs,
bullet lists, pipe tables, images, ``**bold**`` and ``code``. This renders that subset; it is
not a general Markdown converter (none is a dependency).
"""

from __future__ import annotations

import base64
import html
import re
from pathlib import Path

STYLE = """body{font-family:system-ui,sans-serif;max-width:70em;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:.2em .5em;vertical-align:top}
th{background:#f3f3f3}img{max-width:100%}code{background:#f3f3f3;padding:0 .2em}
td.pass{color:#1a7f37}td.warn{color:#9a6700;font-weight:bold}td.fail{color:#cf222e;font-weight:bold}"""


def _inline(text: str, folder: Path) -> str:
    out = html.escape(text, quote=False)
    out = re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", out)
    return re.sub(r"`(.+?)`", r"<code>\1</code>", out)


def _image(alt: str, src: str, folder: Path) -> str:
    path = folder / src
    if path.is_file():  # embedded: the page stands alone when mailed or moved
        src = "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode()
    return f'<figure><img alt="{html.escape(alt)}" src="{src}"><figcaption>{html.escape(alt)}</figcaption></figure>'


def _row(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def render(markdown: str, folder: Path) -> str:
    """The HTML page of a report written in the exporter's Markdown subset (images under ``folder``)."""
    body: list[str] = []
    lines = markdown.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if m := re.match(r"(#{1,6}) (.*)", line):
            n = len(m.group(1))
            body.append(f"<h{n}>{_inline(m.group(2), folder)}</h{n}>")
        elif m := re.fullmatch(r"!\[(.*)\]\((.*)\)", line.strip()):
            body.append(_image(m.group(1), m.group(2), folder))
        elif line.startswith("|"):
            block = []
            while i < len(lines) and lines[i].startswith("|"):
                block.append(lines[i])
                i += 1
            head, rows = _row(block[0]), [_row(b) for b in block[2:]]
            cells = "".join(f"<th>{_inline(c, folder)}</th>" for c in head)
            table = [f"<table><tr>{cells}</tr>"]
            for r in rows:
                table.append("<tr>" + "".join(
                    f'<td class="{c}">{_inline(c, folder)}</td>' if c in ("pass", "warn", "fail")
                    else f"<td>{_inline(c, folder)}</td>" for c in r) + "</tr>")
            body.append("".join(table) + "</table>")
            continue
        elif line.startswith("- "):
            items = []
            while i < len(lines) and lines[i].startswith("- "):
                items.append(f"<li>{_inline(lines[i][2:], folder)}</li>")
                i += 1
            body.append("<ul>" + "".join(items) + "</ul>")
            continue
        elif line.strip():
            body.append(f"<p>{_inline(line, folder)}</p>")
        i += 1
    title = next((re.sub(r"^#+ ", "", x) for x in lines if x.startswith("# ")), "imupipe report")
    return (f"<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
            f"<style>{STYLE}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n")

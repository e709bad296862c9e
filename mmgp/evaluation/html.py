"""One self-contained HTML report: title, sections, key-figure tables, embedded PNGs, JSON summary.

Every command that writes plots writes a ``report.html`` beside its JSON with this builder; the
file needs nothing else (no scripts, no style sheets, no image files: the PNGs are embedded as
base64 ``data:`` addresses), so it can be mailed, attached to a ticket or opened offline.

Numbers are shown rounded (4 significant digits) and carry their exact value in a ``data-value``
attribute, so a reader sees short figures and a program can check them against the JSON::

    report = HtmlReport("mmgp train", subtitle="log.parquet")
    report.section("Key figures").key_figures({"samples": 330, "sweeps": 26})
    report.section("Plots").figure("labels.png", "torque coloured by mode")
    report.section("Summary").json(report_dict)
    report.write("out/report.html")
"""
from __future__ import annotations

import base64
import html
import json
import math
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from .._version import __version__
from ..data.outputs import atomic_write_bytes, jsonable

__all__ = ["HtmlReport", "format_value", "PNG_SIGNATURE"]

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

_STYLE = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:2em auto;max-width:1100px;
color:#222;padding:0 1em;line-height:1.45}
h1{font-size:1.6em;margin-bottom:0.1em}h2{font-size:1.25em;border-bottom:1px solid #ddd;padding-bottom:0.2em;
margin-top:1.8em}.subtitle{color:#666;margin-top:0}
table{border-collapse:collapse;margin:0.6em 0 1em 0;font-size:0.92em}
th,td{border:1px solid #ddd;padding:0.25em 0.7em;text-align:left}th{background:#f4f4f4}
td.num{text-align:right;font-variant-numeric:tabular-nums}caption{text-align:left;color:#555;padding:0.2em 0}
figure{margin:1em 0}figure img{max-width:100%;border:1px solid #eee}figcaption{color:#555;font-size:0.9em}
pre{background:#f7f7f7;padding:0.8em;overflow:auto;font-size:0.85em;max-height:40em}
.footer{color:#888;font-size:0.8em;margin-top:3em}
"""


def format_value(value: Any) -> str:
    """How a table cell shows ``value``: floats to 4 significant digits, bools as yes/no,
    None as an en dash, lists joined by commas, anything else as ``str``."""
    if value is None:
        return "\u2013"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(format_value(v) for v in value)
    return str(value)


def _cell(value: Any, tag: str = "td") -> str:
    text = html.escape(format_value(value))
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        # repr keeps every digit, so the figure shown can be checked against the JSON exactly
        return f'<{tag} class="num" data-value="{html.escape(repr(value))}">{text}</{tag}>'
    return f"<{tag}>{text}</{tag}>"


def _png_bytes(png: str | Path | bytes) -> tuple[bytes, str | None]:
    if isinstance(png, (bytes, bytearray)):
        data, name = bytes(png), None
    else:
        data, name = Path(png).read_bytes(), Path(png).name
    if not data.startswith(PNG_SIGNATURE):
        raise ValueError(f"{name or 'figure'}: not a PNG image")
    return data, name


class HtmlReport:
    """A report assembled block by block and written as one self-contained HTML file.

    ``title``: the page heading (also the window title); ``subtitle``: one line under it.
    :meth:`section` starts a section; :meth:`paragraph`, :meth:`key_figures`, :meth:`table`,
    :meth:`figure` and :meth:`json` append to the current one (a report without sections gets
    an unnamed one). Every method returns the report, so calls chain.
    """

    def __init__(self, title: str, subtitle: str | None = None):
        self.title = title
        self.subtitle = subtitle
        self._sections: list[tuple[str | None, list[str]]] = []

    def _blocks(self) -> list[str]:
        if not self._sections:
            self._sections.append((None, []))
        return self._sections[-1][1]

    def section(self, heading: str, text: str | None = None) -> "HtmlReport":
        """Start a section with ``heading`` and, optionally, a paragraph of ``text``."""
        self._sections.append((heading, []))
        return self.paragraph(text) if text else self

    def paragraph(self, text: str) -> "HtmlReport":
        """A paragraph of plain text (escaped; no markup)."""
        self._blocks().append(f"<p>{html.escape(text)}</p>")
        return self

    def key_figures(self, figures: Mapping[str, Any], caption: str | None = None) -> "HtmlReport":
        """A two-column table: one row per figure name and value."""
        return self.table(["figure", "value"], [[k, v] for k, v in figures.items()], caption=caption,
                          kind="key-figures")

    def table(self, columns: Sequence[str], rows: Iterable[Sequence[Any]], caption: str | None = None,
              kind: str = "table") -> "HtmlReport":
        """A table with a header row ``columns`` and one row per item of ``rows`` (cells are
        numbers, strings, bools, None or lists; see :func:`format_value`). ``kind`` becomes the
        table's class, so a program reading the report can find tables by kind."""
        head = "".join(f"<th>{html.escape(str(c))}</th>" for c in columns)
        body = "".join("<tr>" + "".join(_cell(v) for v in row) + "</tr>" for row in rows)
        cap = f"<caption>{html.escape(caption)}</caption>" if caption else ""
        self._blocks().append(f'<table class="{html.escape(kind)}">{cap}<thead><tr>{head}</tr></thead>'
                              f"<tbody>{body}</tbody></table>")
        return self

    def figure(self, png: str | Path | bytes, caption: str | None = None) -> "HtmlReport":
        """Embed a PNG (a file or its bytes) as a base64 ``data:`` image, with ``caption``
        (default: the file name). The ``img`` carries the file name in ``data-file``."""
        data, name = _png_bytes(png)
        caption = caption if caption is not None else name
        encoded = base64.b64encode(data).decode("ascii")
        attr = f' data-file="{html.escape(name)}"' if name else ""
        alt = html.escape(caption or "figure")
        cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
        self._blocks().append(f'<figure><img src="data:image/png;base64,{encoded}" alt="{alt}"{attr}>{cap}</figure>')
        return self

    def json(self, data: Any, name: str = "summary") -> "HtmlReport":
        """The JSON ``data`` itself, pretty-printed in a collapsed block (``id`` = ``name``), so
        the report carries every figure, not only those in its tables."""
        text = json.dumps(jsonable(data), indent=2, default=str)
        self._blocks().append(f'<details><summary>{html.escape(name)} (JSON)</summary>'
                              f'<pre class="json" id="{html.escape(name)}">{html.escape(text)}</pre></details>')
        return self

    def to_html(self) -> str:
        """The whole page as a string."""
        parts = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
                 '<meta name="viewport" content="width=device-width, initial-scale=1">',
                 f"<title>{html.escape(self.title)}</title><style>{_STYLE}</style></head><body>",
                 f"<h1>{html.escape(self.title)}</h1>"]
        if self.subtitle:
            parts.append(f'<p class="subtitle">{html.escape(self.subtitle)}</p>')
        for heading, blocks in self._sections:
            parts.append("<section>")
            if heading:
                parts.append(f"<h2>{html.escape(heading)}</h2>")
            parts.extend(blocks)
            parts.append("</section>")
        stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
        parts.append(f'<p class="footer">mmgp {html.escape(__version__)}, {stamp}</p></body></html>')
        return "\n".join(parts) + "\n"

    def write(self, path: str | Path) -> Path:
        """Write the page to ``path`` (atomically: complete or absent); returns the path."""
        path = Path(path)
        atomic_write_bytes(path, self.to_html().encode("utf-8"))
        return path

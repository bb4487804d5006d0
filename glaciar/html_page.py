"""Pieces of a self-contained HTML page: escaped text, tables that carry exact values,
embedded PNG figures, sections, and the inline style sheet (``glaciar.report`` builds the
run's page from them).

Every number in a table carries its exact value in a ``data-value`` attribute (``repr``
of the float), so that tests and scripts can read a page back; what is shown is the
value formatted.  Nothing here reads or writes files.
"""
from __future__ import annotations

import base64
import html
import math

import numpy as np

#: the page's inline style sheet (no external resource: the page is one file)
STYLE = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;max-width:1200px;
padding:0 1.2em 3em;color:#222;line-height:1.4}
h1{margin-bottom:0.2em}h2{border-bottom:2px solid #ccc;padding-bottom:0.2em;margin-top:1.8em}
nav a{margin-right:0.9em}table{border-collapse:collapse;margin:0.6em 0;font-size:0.85em}
th,td{border:1px solid #ddd;padding:0.15em 0.5em;text-align:right}th{background:#f4f4f4}
table.kv th{text-align:left}td:first-child{text-align:left}
figure{margin:1em 0}figure img{max-width:100%;height:auto;border:1px solid #eee}
dl{font-size:0.9em}dt{font-weight:600}dd{margin:0 0 0.3em 1.5em}
figcaption{font-size:0.85em;color:#555}pre{background:#f8f8f8;padding:0.8em;overflow:auto;font-size:0.8em}
.note{color:#444;font-size:0.9em}.missing{color:#8a5a00;font-weight:600}.warning{color:#b00020;font-weight:600}
details{margin:0.5em 0}summary{cursor:pointer}
"""


def esc(x) -> str:
    """``str(x)`` escaped for HTML text and attribute values."""
    return html.escape(str(x), quote=True)


def fmt(v, spec: str) -> str:
    """``v`` as shown: numbers with the format ``spec``, '—' for None and non-finite values."""
    if v is None:
        return "—"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return f"{int(v):d}"
    if isinstance(v, (float, np.floating)):
        return "—" if not math.isfinite(float(v)) else format(float(v), spec)
    return str(v)


def td(v, spec: str = ".4g") -> str:
    """A table cell showing ``v`` formatted, with its exact value in ``data-value``."""
    if isinstance(v, (bool, np.bool_)):
        exact = "true" if v else "false"
    elif isinstance(v, (int, np.integer)):
        exact = str(int(v))
    elif isinstance(v, (float, np.floating)):
        exact = repr(float(v))
    else:
        exact = str(v)
    return f'<td data-value="{esc(exact)}">{esc(fmt(v, spec))}</td>'


def table(columns, rows, *, table_id: str | None = None, formats: dict | None = None,
          headers: dict | None = None) -> str:
    """An HTML table; ``rows`` are sequences aligned with ``columns``.

    ``formats`` maps a column to its format spec (default ``.4g``), ``headers`` to the
    text shown in its header (default the column name, kept in ``data-column``).
    """
    formats = formats or {}
    headers = headers or {}
    tid = f' id="{esc(table_id)}"' if table_id else ""
    head = "".join(f'<th data-column="{esc(c)}">{esc(headers.get(c, c))}</th>' for c in columns)
    body = "".join("<tr>" + "".join(td(v, formats.get(c, ".4g")) for c, v in zip(columns, r))
                   + "</tr>" for r in rows)
    return f"<table{tid}><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def kv_table(items, table_id: str | None = None) -> str:
    """A two-column table of (key, value) pairs; the key is kept in ``data-key``."""
    tid = f' id="{esc(table_id)}"' if table_id else ""
    body = "".join(f'<tr><th data-key="{esc(k)}">{esc(k)}</th>{td(v)}</tr>' for k, v in items)
    return f"<table class=\"kv\"{tid}><tbody>{body}</tbody></table>"


def figure(fig, caption: str, fig_id: str) -> str:
    """A ``<figure>`` with the PNG embedded, shown at one PNG pixel per CSS pixel.

    The ``width``/``height`` attributes are the PNG's own (read from its IHDR chunk), so
    a figure is laid out at the size its fonts were drawn for (``plots.REPORT_DPI``) and
    only shrinks (``max-width: 100%``) on a screen narrower than the figure.
    """
    from .plots import png_bytes

    png = png_bytes(fig)
    width, height = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    b64 = base64.b64encode(png).decode("ascii")
    return (f'<figure id="{esc(fig_id)}"><img alt="{esc(caption)}" width="{width}" height="{height}" '
            f'src="data:image/png;base64,{b64}"><figcaption>{esc(caption)}</figcaption></figure>')


def note(text: str, cls: str = "note") -> str:
    """A paragraph of ``text`` (escaped) in the class ``cls`` (note, missing, warning)."""
    return f'<p class="{cls}">{esc(text)}</p>'


def section(sid: str, title: str, body: str) -> str:
    """A ``<section>`` with the id ``sid``, an ``<h2>`` title and ``body`` (HTML)."""
    return f'<section id="{esc(sid)}"><h2>{esc(title)}</h2>{body}</section>'

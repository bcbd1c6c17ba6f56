"""HTML building blocks of the report: one page shell with inline CSS and the inline table-sort script (no
external resource), tables whose cells carry their sort value, and escaping."""

from __future__ import annotations

import html
import math
from dataclasses import dataclass

CSS = """
body{font:14px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0;color:#1d232a;background:#f5f6f8}
header{background:#1d2b3a;color:#fff;padding:10px 24px}header a{color:#9cc8ff}
header h1{font-size:19px;margin:0 0 2px}header .sub{color:#b8c4d0;font-size:12px}
nav{margin-top:4px}nav a{margin-right:14px}
main{padding:14px 24px 40px}
h2{font-size:16px;margin:22px 0 8px;border-bottom:1px solid #d8dde3;padding-bottom:3px}
.cards{display:flex;flex-wrap:wrap;gap:10px}
.card{background:#fff;border:1px solid #dde2e8;border-radius:6px;padding:8px 14px;min-width:120px}
.card .v{font-size:20px;font-weight:600}.card .k{color:#5b6773;font-size:12px}
.card.bad .v{color:#c9302c}
table{border-collapse:collapse;background:#fff;font-size:13px;margin:4px 0}
th,td{border:1px solid #dde2e8;padding:3px 7px;text-align:left;vertical-align:top}
th{background:#eef1f4;position:sticky;top:0}
td.n{text-align:right;font-variant-numeric:tabular-nums}
table.sortable th{cursor:pointer;user-select:none}table.sortable th:hover{background:#dfe6ee}
th.asc::after{content:" \\25B2"}th.desc::after{content:" \\25BC"}
tr.flagged td:first-child{border-left:4px solid #f0ad4e}tr.failed td:first-child{border-left:4px solid #d9534f}
.badge{display:inline-block;border-radius:3px;padding:0 5px;margin:1px 2px 1px 0;font-size:11px;color:#fff;
background:#f0ad4e;white-space:nowrap}.badge.failed{background:#d9534f}.badge.off{background:#9aa4ae}
.muted{color:#6b7580}.mono{font-family:ui-monospace,Menlo,Consolas,monospace;font-size:12px}
.thumbs{display:flex;flex-wrap:wrap;gap:10px}
figure{margin:0;background:#fff;border:1px solid #dde2e8;border-radius:6px;padding:6px;width:220px}
figure img{width:220px;height:220px;display:block}
div.nogrid{width:208px;height:208px;padding:6px;overflow:hidden;word-break:break-all;font-size:11px;
background:#fbeaea;color:#7a2320}
figcaption{font-size:11px;margin-top:3px;word-break:break-all}
.pager a,.pager span{margin-right:8px}.pager span{font-weight:600}
div.row{display:flex;flex-wrap:wrap;gap:0 24px}img.plot{max-width:100%;background:#fff;border:1px solid #dde2e8}
.legend span{display:inline-block;margin-right:10px;font-size:12px}
.legend i{display:inline-block;width:11px;height:11px;margin-right:4px;vertical-align:-1px;border:1px solid #555}
details{margin:6px 0}pre{background:#fff;border:1px solid #dde2e8;padding:8px;overflow:auto;max-height:420px}
"""

SORT_JS = """
document.querySelectorAll('table.sortable').forEach(function(table){
  table.querySelectorAll('th').forEach(function(th, col){
    th.addEventListener('click', function(){
      var body = table.tBodies[0], rows = Array.prototype.slice.call(body.rows);
      var desc = !th.classList.contains('desc');
      table.querySelectorAll('th').forEach(function(h){h.classList.remove('asc','desc');});
      th.classList.add(desc ? 'desc' : 'asc');
      function key(row){var c = row.cells[col], v = c.getAttribute('data-v');
        if (v === null) return c.textContent.trim().toLowerCase();
        var f = parseFloat(v); return isNaN(f) ? -Infinity : f;}
      rows.sort(function(a, b){var x = key(a), y = key(b);
        var r = (x < y) ? -1 : (x > y) ? 1 : 0; return desc ? -r : r;});
      rows.forEach(function(r){body.appendChild(r);});
    });
  });
});
"""


def esc(value: object) -> str:
    """HTML-escaped text of a value."""
    return html.escape(str(value), quote=True)


def fmt(value: float | int | None, digits: int = 3) -> str:
    """A figure for a cell: '-' for missing/NaN, thousands separators for large numbers."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if isinstance(value, int) or (abs(value) >= 1000):
        return f"{value:,.0f}"
    return f"{value:.{digits}g}"


@dataclass(frozen=True)
class Cell:
    """A table cell: inner HTML (already escaped), an optional numeric sort value, and a CSS class."""

    html: str
    sort: float | None = None
    css: str = ""


def num(value: float | int | None, digits: int = 3) -> Cell:
    """A right-aligned numeric cell sorted by its value (missing values sort last)."""
    sort = float(value) if value is not None and math.isfinite(float(value)) else float("nan")
    return Cell(fmt(value, digits), sort, "n")


def text(value: object) -> Cell:
    return Cell(esc(value))


def table(headers: list[str], rows: list[tuple[str, list[Cell]]], sortable: bool = True) -> str:
    """A table; rows are (row CSS class, cells)."""
    head = "".join(f"<th>{esc(h)}</th>" for h in headers)
    body = []
    for css, cells in rows:
        tds = []
        for c in cells:
            attrs = (f' class="{c.css}"' if c.css else "") + (
                f' data-v="{c.sort if math.isfinite(c.sort) else "NaN"}"' if c.sort is not None else "")
            tds.append(f"<td{attrs}>{c.html}</td>")
        body.append(f'<tr class="{css}">' + "".join(tds) + "</tr>")
    cls = ' class="sortable"' if sortable else ""
    return f"<table{cls}><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def page(title: str, subtitle: str, nav: list[tuple[str, str]], body: str) -> str:
    """A whole page: header with title, subtitle and nav links (label, href), the body, inline CSS and JS."""
    links = "".join(f'<a href="{esc(href)}">{esc(label)}</a>' for label, href in nav)
    return (f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{esc(title)}</title>"
            f"<style>{CSS}</style></head><body><header><h1>{esc(title)}</h1><div class=\"sub\">{subtitle}</div>"
            f"<nav>{links}</nav></header><main>{body}</main><script>{SORT_JS}</script></body></html>")


def pager(current: int, total: int, href) -> str:
    """Page links 1..total; href(k) gives page k's address."""
    if total <= 1:
        return ""
    items = [f"<span>{k}</span>" if k == current else f'<a href="{esc(href(k))}">{k}</a>' for k in range(1, total + 1)]
    return f'<div class="pager">pages: {"".join(items)}</div>'

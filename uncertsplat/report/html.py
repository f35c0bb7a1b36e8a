"""Small HTML helpers: every string goes through ``esc``; the page is self-contained (inline CSS only)."""

from __future__ import annotations

import html
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

CSS = """
:root { --fg:#1d2330; --muted:#5b6475; --line:#dde2ea; --bg:#ffffff; --soft:#f5f7fa; --accent:#2457c5;
        --warn-bg:#fff8e6; --warn-line:#f0c36d; }
* { box-sizing: border-box; }
body { margin:0; font: 14px/1.5 system-ui, -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif;
       color:var(--fg); background:var(--bg); }
header { padding:20px 32px 12px; border-bottom:1px solid var(--line); background:var(--soft); }
header h1 { margin:0 0 4px; font-size:22px; }
header p { margin:0; color:var(--muted); }
nav { padding:8px 32px; border-bottom:1px solid var(--line); font-size:13px; position:sticky; top:0;
      background:rgba(255,255,255,.96); z-index:1; }
nav a { color:var(--accent); text-decoration:none; margin-right:16px; white-space:nowrap; }
main { padding:8px 32px 48px; max-width:1400px; }
section { margin-top:28px; }
h2 { font-size:18px; border-bottom:1px solid var(--line); padding-bottom:4px; margin:0 0 12px; }
h3 { font-size:15px; margin:20px 0 8px; }
h4 { font-size:13px; margin:14px 0 6px; color:var(--muted); }
table { border-collapse:collapse; margin:6px 0 12px; font-size:13px; }
th, td { border-bottom:1px solid var(--line); padding:4px 10px; text-align:right; white-space:nowrap; }
th { background:var(--soft); font-weight:600; white-space:normal; vertical-align:bottom; max-width:110px; }
th:first-child, td:first-child { text-align:left; }
td.text { text-align:left; white-space:normal; }
tr.mean td { font-weight:600; border-top:2px solid var(--line); }
.scroll { overflow-x:auto; max-width:100%; }
figure { margin:8px 0 18px; }
figure img { max-width:100%; height:auto; border:1px solid var(--line); border-radius:4px; display:block; }
figcaption { color:var(--muted); font-size:12px; margin-top:4px; max-width:1000px; }
.note { background:var(--warn-bg); border-left:4px solid var(--warn-line); padding:6px 10px; margin:8px 0;
        font-size:13px; max-width:1000px; }
.muted { color:var(--muted); }
details { margin:6px 0; }
summary { cursor:pointer; color:var(--accent); }
pre { background:var(--soft); border:1px solid var(--line); padding:8px; font-size:12px; overflow:auto;
      max-height:420px; }
dl.kv { display:grid; grid-template-columns:max-content auto; gap:2px 16px; margin:6px 0 10px; font-size:13px; }
dl.kv dt { color:var(--muted); }
dl.kv dd { margin:0; word-break:break-all; }
.legend { font-size:12px; color:var(--muted); }
"""


def esc(x: Any) -> str:
    """HTML-escape anything (quotes too, so it is safe inside attributes)."""
    return html.escape(str(x), quote=True)


def note(text: str) -> str:
    return f'<p class="note">{esc(text)}</p>'


def para(text: str, cls: str = "") -> str:
    c = f' class="{esc(cls)}"' if cls else ""
    return f"<p{c}>{esc(text)}</p>"


def figure(src: str, caption: str, alt: str) -> str:
    return (f'<figure><img src="{esc(src)}" alt="{esc(alt)}">'
            f"<figcaption>{esc(caption)}</figcaption></figure>")


def details(summary: str, body_html: str) -> str:
    return f"<details><summary>{esc(summary)}</summary>{body_html}</details>"


def pre(text: str) -> str:
    return f"<pre>{esc(text)}</pre>"


def kv(items: Iterable[tuple[str, Any]]) -> str:
    rows = "".join(f"<dt>{esc(k)}</dt><dd>{esc(v)}</dd>" for k, v in items)
    return f'<dl class="kv">{rows}</dl>'


class Cell:
    """A table cell: display text, plus (for numbers) the metric key and the exact value from the file."""

    def __init__(self, text: str, *, key: str | None = None, value: Any = None, text_cell: bool = False):
        self.text, self.key, self.value, self.text_cell = text, key, value, text_cell

    def render(self) -> str:
        attrs = []
        if self.key is not None:
            attrs.append(f'data-key="{esc(self.key)}"')
            # repr keeps every digit, so a test (or a reader) can compare with the JSON file exactly.
            attrs.append(f'data-value="{esc(repr(self.value) if isinstance(self.value, float) else self.value)}"')
        if self.text_cell:
            attrs.append('class="text"')
        a = (" " + " ".join(attrs)) if attrs else ""
        return f"<td{a}>{esc(self.text)}</td>"


def table(header: Sequence[str], rows: Sequence[tuple[str, Sequence[Cell | str]]], *, table_id: str = "",
          row_attr: str = "data-row") -> str:
    """A table; each row is (row label, cells); a row label 'mean' is styled as the summary row."""
    tid = f' id="{esc(table_id)}"' if table_id else ""
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = []
    for label, cells in rows:
        cls = ' class="mean"' if label == "mean" else ""
        tds = "".join(c.render() if isinstance(c, Cell) else f"<td>{esc(c)}</td>" for c in cells)
        body.append(f'<tr{cls} {row_attr}="{esc(label)}"><td class="text">{esc(label)}</td>{tds}</tr>')
    return f'<div class="scroll"><table{tid}><thead><tr>{head}</tr></thead><tbody>{"".join(body)}</tbody></table></div>'


GENERATOR = "uncertsplat report"
"""The page's ``<meta name="generator">``: how ``report`` knows a folder's index.html for one of its own (which it
may replace) from someone else's page (which it must not)."""


def is_report_page(path: Path) -> bool:
    """Whether ``path`` is an HTML page ``page`` wrote for a report (its generator tag, or for pages written before the
    tag their head and style sheet), judged from its first 4 KB; False when it cannot be read."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096).decode("utf-8", "replace")
    except OSError:
        return False
    if 'name="generator"' in head:  # the tag says who wrote it (a sweep's page carries its own)
        return f'<meta name="generator" content="{GENERATOR}">' in head
    # pages written before the tag (2026-11-29): their head as page() wrote it, with the report's style sheet; a
    # sweep's page of then is told by its title
    return (head.startswith("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">")
            and '<link rel="icon" href="data:,"><title>' in head and "--warn-line:" in head
            and "<title>uncertsplat sweep: " not in head)


def page(title: str, subtitle: str, nav: Sequence[tuple[str, str]], body: str, generator: str = GENERATOR) -> str:
    """A whole HTML page; ``generator`` names the command that wrote it (``is_report_page`` reads it back)."""
    links = "".join(f'<a href="#{esc(anchor)}">{esc(label)}</a>' for anchor, label in nav)
    return (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
        f'<meta name="generator" content="{esc(generator)}">'
        f'<link rel="icon" href="data:,">'
        f"<title>{esc(title)}</title><style>{CSS}</style></head><body>"
        f"<header><h1>{esc(title)}</h1><p>{esc(subtitle)}</p></header>"
        f"<nav>{links}</nav><main>{body}</main></body></html>\n"
    )

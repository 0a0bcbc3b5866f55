"""One self-contained HTML page of text, tables and inlined figures, and the matplotlib helpers that make the
figures: what `deepcharuco.cli.calibrate`'s report and the evaluation's report pages are written with.

matplotlib is imported only when a figure is drawn (`pyplot`), so the runtime needs it only for reports
(the ``eval`` extra).
"""

from __future__ import annotations

import base64
import html
import io


def image_format(data: bytes) -> str:
    """"jpeg" for JPEG bytes (the real-captures gallery: photos stay small), else "png"."""
    return "jpeg" if data[:3] == b"\xff\xd8\xff" else "png"


CSS = """body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;
color:#222;line-height:1.45}h1{margin-bottom:.2em}h2{border-bottom:1px solid #ddd;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.8em 0;font-size:.9em}th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}code{background:#f3f3f3;padding:.1em .3em}
.figures{display:flex;flex-wrap:wrap;gap:1em}.figures img{max-width:100%;border:1px solid #eee}"""


def inline(text: str) -> str:
    """Markdown's **bold** in table cells and text, escaped otherwise."""
    parts = html.escape(text).split("**")
    return "".join(f"<b>{p}</b>" if i % 2 else p for i, p in enumerate(parts))


def html_page(title: str, command: str, page_sections: list[tuple[str, str, list[list[str]] | None, list[str]]],
              figures: dict[str, bytes]) -> str:
    """A self-contained HTML page (figures inlined as PNG): a title, the command that made it, then each
    (title, text, table rows (first = header) or None, figure names) section."""
    body = [f"<h1>{html.escape(title)}</h1><p><code>{html.escape(command)}</code></p>"]
    for heading, text, rows, names in page_sections:
        body.append(f"<h2>{html.escape(heading)}</h2><p>{inline(text)}</p>")
        if rows:
            body.append("<table><tr>" + "".join(f"<th>{inline(c)}</th>" for c in rows[0]) + "</tr>")
            body += ["<tr>" + "".join(f"<td>{inline(c)}</td>" for c in r) + "</tr>" for r in rows[1:]]
            body.append("</table>")
        if names:
            body.append('<div class="figures">' + "".join(
                f'<img alt="{name}" src="data:image/{image_format(figures[name])};base64,{base64.b64encode(figures[name]).decode()}">'
                for name in names if name in figures) + "</div>")
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{CSS}</style></head><body>{''.join(body)}</body></html>")


def pyplot():
    """matplotlib's pyplot, drawing to files only (imported here: the runtime needs it only for reports)."""
    import matplotlib

    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    return plt


def png(figure) -> bytes:
    """A matplotlib figure as PNG bytes (110 dpi, tight); the figure is closed."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110, bbox_inches="tight")
    pyplot().close(figure)
    return buffer.getvalue()

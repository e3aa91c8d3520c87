"""The HTML kit of the project's self-contained pages: the run report (:mod:`passt_mav.analysis.report`)
and the paper's evaluation page (``passt-mav paper``).

A :class:`Page` collects HTML parts; figures are written as PNG files beside the page and embedded in
it as base64 (the same bytes), so the page loads nothing from outside (no scripts, no URLs).
:func:`pyplot` gives matplotlib's ``pyplot`` on the Agg backend (no display needed).
"""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path

__all__ = ["CSS", "Page", "pyplot"]

#: the pages' style sheet (one column, plain tables, figures at most the page's width)
CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;margin:2em auto;max-width:1100px;color:#222;padding:0 1em}
h1{font-size:1.6em;margin-bottom:.2em}h2{font-size:1.2em;border-bottom:1px solid #ccc;margin-top:1.8em}
table{border-collapse:collapse;margin:.6em 0}th,td{border:1px solid #ccc;padding:.25em .6em;text-align:left}
th{background:#f3f3f3;font-weight:600}td.num{text-align:right}img{max-width:100%;border:1px solid #ddd}
.missing{color:#a33;font-style:italic}.note{color:#555}.status{font-weight:600}.warn{color:#a33}
"""


def pyplot():
    """matplotlib's ``pyplot`` with the Agg backend forced (figures are only saved, never shown)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


class Page:
    """One HTML page under construction; figures go to PNG files in ``out`` (a directory).

    ``parts``: the body's HTML fragments in order; ``figures``: the PNG paths written.
    """

    def __init__(self, out: Path):
        self.out = Path(out)
        self.parts: list[str] = []
        self.figures: list[Path] = []

    def add(self, s: str) -> None:
        """Append an HTML fragment as is (the caller escapes what it took from data)."""
        self.parts.append(s)

    def h2(self, s: str) -> None:
        """A section heading (text, escaped)."""
        self.add(f"<h2>{html.escape(s)}</h2>")

    def missing(self, s: str) -> None:
        """A line saying what the page cannot show (text, escaped)."""
        self.add(f'<p class="missing">{html.escape(s)}</p>')

    def note(self, s: str) -> None:
        """A note paragraph (text, escaped)."""
        self.add(f'<p class="note">{html.escape(s)}</p>')

    def figure(self, fig, name: str, alt: str, plt) -> None:
        """Save the matplotlib figure ``fig`` as ``out/name`` (PNG, 100 dpi), close it, and embed the same
        bytes with ``alt`` as its text and caption."""
        buf = io.BytesIO()
        try:
            fig.savefig(buf, format="png", dpi=100)
        finally:
            plt.close(fig)
        data = buf.getvalue()
        path = self.out / name
        path.write_bytes(data)  # the same bytes on disk and in the page
        self.figures.append(path)
        b64 = base64.b64encode(data).decode("ascii")
        self.add(
            f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{b64}">'
            f"<figcaption>{html.escape(alt)} ({html.escape(name)})</figcaption></figure>"
        )

    def table(self, rows: list[tuple[str, str]]) -> None:
        """A two-column table: each row's key (text, escaped) and value (HTML, as given)."""
        body = "".join(f"<tr><th>{html.escape(k)}</th><td>{v}</td></tr>" for k, v in rows)
        self.add(f"<table>{body}</table>")

    def write(self, path: Path, title: str, *, css: str = "") -> Path:
        """Write the page to ``path`` (UTF-8) with ``title`` (text, escaped) and :data:`CSS` followed by
        ``css``; returns ``path``."""
        doc = (
            f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
            f"<style>{CSS}{css}</style></head><body>\n" + "\n".join(self.parts) + "\n</body></html>\n"
        )
        path = Path(path)
        path.write_text(doc, encoding="utf-8")
        return path

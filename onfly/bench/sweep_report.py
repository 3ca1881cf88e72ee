"""The picture of a sweep: one self-contained HTML page (no script, no network) with the table
and, for every metric, one scatter plot per swept key (metric against the key's value, one
dot per combination and method, the method's colour).

Plain SVG written here rather than a plotting library: the page must open offline and the
project does not depend on matplotlib.
"""

from __future__ import annotations

import html
import math
from typing import Any, Sequence

__all__ = ["sweep_html", "scatter_svg"]

_COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf")


def _num(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v) if math.isfinite(v) else None


def _ticks(lo: float, hi: float) -> list[float]:
    if hi <= lo:
        return [lo]
    return [lo + (hi - lo) * i / 4 for i in range(5)]


def scatter_svg(points: Sequence[tuple[float, float, str]], x_label: str, y_label: str, *, log_x: bool = False,
                width: int = 260, height: int = 190) -> str:
    """An SVG scatter plot of ``(x, y, colour)`` points with labelled axes."""
    pts = [(x, y, c) for x, y, c in points if x is not None and y is not None and (not log_x or x > 0)]
    ml, mr, mt, mb = 46, 10, 10, 34
    w, h = width - ml - mr, height - mt - mb
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" font-family="sans-serif" font-size="9">',
           f'<rect x="{ml}" y="{mt}" width="{w}" height="{h}" fill="#fafafa" stroke="#999"/>']
    if pts:
        fx = (lambda v: math.log10(v)) if log_x else (lambda v: v)
        xs, ys = [fx(p[0]) for p in pts], [p[1] for p in pts]
        x0, x1 = min(xs), max(xs)
        y0, y1 = min(ys), max(ys)
        if x1 == x0:
            x0, x1 = x0 - 0.5, x1 + 0.5
        if y1 == y0:
            pad = abs(y0) * 0.05 or 0.5
            y0, y1 = y0 - pad, y1 + pad
        sx = lambda v: ml + (v - x0) / (x1 - x0) * w  # noqa: E731
        sy = lambda v: mt + h - (v - y0) / (y1 - y0) * h  # noqa: E731
        for t in _ticks(x0, x1):
            lab = 10**t if log_x else t
            out.append(f'<line x1="{sx(t):.1f}" y1="{mt + h}" x2="{sx(t):.1f}" y2="{mt + h + 3}" stroke="#666"/>')
            out.append(f'<text x="{sx(t):.1f}" y="{mt + h + 12}" text-anchor="middle">{lab:.3g}</text>')
        for t in _ticks(y0, y1):
            out.append(f'<line x1="{ml - 3}" y1="{sy(t):.1f}" x2="{ml}" y2="{sy(t):.1f}" stroke="#666"/>')
            out.append(f'<text x="{ml - 5}" y="{sy(t) + 3:.1f}" text-anchor="end">{t:.3g}</text>')
        for (x, y, c), xv in zip(pts, xs):
            out.append(f'<circle cx="{sx(xv):.1f}" cy="{sy(y):.1f}" r="3.2" fill="{c}" fill-opacity="0.8"/>')
    else:
        out.append(f'<text x="{ml + w / 2}" y="{mt + h / 2}" text-anchor="middle">no values</text>')
    out.append(f'<text x="{ml + w / 2}" y="{height - 4}" text-anchor="middle">{html.escape(x_label)}{" (log)" if log_x else ""}</text>')
    out.append(f'<text x="10" y="{mt + h / 2}" text-anchor="middle" transform="rotate(-90 10 {mt + h / 2})">{html.escape(y_label)}</text>')
    out.append("</svg>")
    return "".join(out)


def sweep_html(name: str, rows: list[dict], keys: list[str], metrics: Sequence[tuple[str, str, str, float]]) -> str:
    """The sweep page: a legend, the table, and a grid of plots (rows: metrics; columns: keys).

    ``metrics`` are ``(row key, header, format, scale)`` as :data:`onfly.bench.sweep.ROW_METRICS`.
    """
    methods = sorted({r["method"] for r in rows})
    color = {m: _COLORS[i % len(_COLORS)] for i, m in enumerate(methods)}
    legend = " ".join(f'<span style="color:{color[m]}">&#9679; {html.escape(m)}</span>' for m in methods)
    head = "".join(f"<th>{html.escape(k)}</th>" for k in keys) + "<th>method</th><th>episodes</th>"
    head += "".join(f"<th>{html.escape(h)}</th>" for _, h, _, _ in metrics)
    body = []
    for r in rows:
        cells = [html.escape(f"{r[k]:.4g}" if isinstance(r[k], float) else str(r[k])) for k in keys]
        cells += [html.escape(r["method"]), str(r.get("episodes", ""))]
        for key, _, fmt, scale in metrics:
            v = _num(r.get(key))
            cells.append("n/a" if v is None else fmt.format(v * scale))
        body.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    grid = []
    for key, header, _, scale in metrics:
        cells = []
        for k in keys:
            xs = [_num(r.get(k)) for r in rows]
            log_x = all(x is not None and x > 0 for x in xs) and len({x for x in xs}) > 2 and max(xs) / min(xs) >= 20
            pts = [(_num(r.get(k)), None if _num(r.get(key)) is None else _num(r.get(key)) * scale, color[r["method"]]) for r in rows]
            cells.append(f"<td>{scatter_svg(pts, k, header, log_x=log_x)}</td>")
        grid.append("<tr>" + "".join(cells) + "</tr>")
    style = ("body{font-family:sans-serif;margin:1em} table{border-collapse:collapse} "
             "td,th{border:1px solid #ccc;padding:2px 6px;text-align:right;font-size:12px} .plots td{border:none}")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(name)}</title><style>{style}</style></head><body>"
            f"<h2>{html.escape(name)}: {len(rows)} rows</h2><p>{legend}</p>"
            f"<table><tr>{head}</tr>{''.join(body)}</table>"
            f"<h3>What the weights change (one dot per combination and method)</h3>"
            f"<table class='plots'>{''.join(grid)}</table></body></html>")

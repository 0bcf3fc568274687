"""Small SVG charts for the analysis report: lines, markers, bars, footprints; no dependencies.

A ``Chart`` maps data to pixels with "nice" axis ticks; missing values (NaN)
break lines instead of joining across gaps. Everything is returned as SVG
text to embed in HTML, so a report is one self-contained file.
"""

from __future__ import annotations

import html
import math
from typing import Sequence

import numpy as np

LEFT_COLOUR = "#d64545"    # seed 003's Figure 7: left foot red ...
RIGHT_COLOUR = "#3b6fd6"   # ... right foot blue
TRUTH_COLOUR = "#8a8a8a"
PALETTE = ("#d64545", "#3b6fd6", "#2e9d62", "#c77d16", "#8756c9", "#1f9bb0")


def nice_ticks(lo: float, hi: float, count: int = 5) -> list[float]:
    """Round tick values covering [lo, hi] (1, 2 or 5 times a power of ten apart)."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return [0.0, 1.0]
    if hi - lo < 1e-12:
        lo, hi = lo - 0.5, hi + 0.5
    raw = (hi - lo) / max(count, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw)
    start = math.floor(lo / step) * step
    ticks = []
    v = start
    while v <= hi + step * 0.5:
        ticks.append(round(v, 10))
        v += step
    return ticks


def _fmt(v: float) -> str:
    return f"{v:g}" if abs(v) >= 1e-9 else "0"


class Chart:
    """One plot area. Add series, then ``svg()``. Sizes in pixels; data in its own units."""

    def __init__(self, width: int = 760, height: int = 240, *, title: str = "",
                 x_label: str = "", y_label: str = "", equal: bool = False,
                 y_range: tuple[float, float] | None = None) -> None:
        self.width, self.height, self.title = width, height, title
        self.x_label, self.y_label, self.equal, self.y_range = x_label, y_label, equal, y_range
        self.items: list[tuple[str, dict]] = []
        self.legend: list[tuple[str, str, str]] = []   # (label, colour, kind)
        self.margin = (54, 16, 30, 40)  # left, right, top (title and legend), bottom

    # ------------------------------------------------------------ content
    def line(self, x: Sequence[float], y: Sequence[float], colour: str, *, width: float = 1.6,
             dash: str | None = None, label: str | None = None, opacity: float = 1.0) -> None:
        self.items.append(("line", dict(x=np.asarray(x, float), y=np.asarray(y, float),
                                        colour=colour, width=width, dash=dash, opacity=opacity)))
        if label:
            self.legend.append((label, colour, "line" if not dash else "dash"))

    def markers(self, x: Sequence[float], y: Sequence[float], colour: str, *, shape: str = "x",
                size: float = 5.0, label: str | None = None, texts: Sequence[str] | None = None,
                ) -> None:
        self.items.append(("markers", dict(x=np.asarray(x, float), y=np.asarray(y, float),
                                           colour=colour, shape=shape, size=size, texts=texts)))
        if label:
            self.legend.append((label, colour, shape))

    def bars(self, x: Sequence[float], y: Sequence[float], colours: Sequence[str],
             width: float = 0.8) -> None:
        self.items.append(("bars", dict(x=np.asarray(x, float), y=np.asarray(y, float),
                                        colours=list(colours), bw=width)))

    def footprints(self, x: Sequence[float], y: Sequence[float], angle: Sequence[float],
                   colours: Sequence[str], *, length: float = 0.24, width: float = 0.09,
                   outline: bool = False, texts: Sequence[str] | None = None) -> None:
        """Feet drawn to scale (metres) at (x, y), pointing along ``angle`` (radians)."""
        self.items.append(("feet", dict(x=np.asarray(x, float), y=np.asarray(y, float),
                                        a=np.asarray(angle, float), colours=list(colours),
                                        fl=length, fw=width, outline=outline, texts=texts)))

    # ------------------------------------------------------------ drawing
    def _extent(self) -> tuple[float, float, float, float]:
        xs, ys = [], []
        for kind, d in self.items:
            ok = np.isfinite(d["x"]) & np.isfinite(d["y"])
            xs.append(d["x"][ok])
            ys.append(d["y"][ok])
            if kind == "bars":
                ys.append(np.zeros(1))
                xs.append(d["x"][ok] - 0.5)
                xs.append(d["x"][ok] + 0.5)
            if kind == "feet":
                xs.append(d["x"][ok] + d["fl"])
                xs.append(d["x"][ok] - d["fl"])
                ys.append(d["y"][ok] + d["fl"])
                ys.append(d["y"][ok] - d["fl"])
        x = np.concatenate(xs) if xs else np.zeros(0)
        y = np.concatenate(ys) if ys else np.zeros(0)
        if not len(x):
            return 0.0, 1.0, 0.0, 1.0
        x0, x1 = float(x.min()), float(x.max())
        y0, y1 = (float(y.min()), float(y.max())) if self.y_range is None else self.y_range
        if y1 - y0 < 1e-9:
            y0, y1 = y0 - 1.0, y1 + 1.0
        if x1 - x0 < 1e-9:
            x0, x1 = x0 - 1.0, x1 + 1.0
        pad = 0.04 * (y1 - y0)
        return x0, x1, y0 - pad, y1 + pad

    def svg(self) -> str:
        ml, mr, mt, mb = self.margin
        w, h = self.width, self.height
        pw, ph = w - ml - mr, h - mt - mb
        x0, x1, y0, y1 = self._extent()
        if self.equal:  # same metres per pixel on both axes
            scale = min(pw / (x1 - x0), ph / (y1 - y0))
            cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
            x0, x1 = cx - pw / scale / 2, cx + pw / scale / 2
            y0, y1 = cy - ph / scale / 2, cy + ph / scale / 2
        xt, yt = nice_ticks(x0, x1, max(2, pw // 90)), nice_ticks(y0, y1, max(2, ph // 45))
        if not self.equal and self.y_range is None:
            y0, y1 = min(y0, yt[0]), max(y1, yt[-1])

        def px(v):
            return ml + (v - x0) / (x1 - x0) * pw

        def py(v):
            return mt + (y1 - v) / (y1 - y0) * ph
        out = [f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {w} {h}" width="{w}" '
               f'height="{h}" class="chart" role="img">']
        if self.title:
            out.append(f'<text x="{ml}" y="16" class="title">{html.escape(self.title)}</text>')
        out.append(f'<rect x="{ml}" y="{mt}" width="{pw}" height="{ph}" class="frame"/>')
        for v in xt:
            if x0 <= v <= x1:
                out.append(f'<line x1="{px(v):.1f}" y1="{mt}" x2="{px(v):.1f}" y2="{mt + ph}" '
                           f'class="grid"/><text x="{px(v):.1f}" y="{mt + ph + 14}" '
                           f'class="tick" text-anchor="middle">{_fmt(v)}</text>')
        for v in yt:
            if y0 <= v <= y1:
                out.append(f'<line x1="{ml}" y1="{py(v):.1f}" x2="{ml + pw}" y2="{py(v):.1f}" '
                           f'class="grid"/><text x="{ml - 6}" y="{py(v) + 4:.1f}" class="tick" '
                           f'text-anchor="end">{_fmt(v)}</text>')
        if self.x_label:
            out.append(f'<text x="{ml + pw / 2:.0f}" y="{h - 6}" class="label" '
                       f'text-anchor="middle">{html.escape(self.x_label)}</text>')
        if self.y_label:
            out.append(f'<text x="12" y="{mt + ph / 2:.0f}" class="label" text-anchor="middle" '
                       f'transform="rotate(-90 12 {mt + ph / 2:.0f})">'
                       f'{html.escape(self.y_label)}</text>')
        out.append(f'<clipPath id="c{id(self)}"><rect x="{ml}" y="{mt}" width="{pw}" '
                   f'height="{ph}"/></clipPath><g clip-path="url(#c{id(self)})">')
        for kind, d in self.items:
            out.append(getattr(self, "_draw_" + kind)(d, px, py, (x1 - x0) / pw))
        out.append("</g>")
        out.append(self._legend(ml + pw, 2))
        out.append("</svg>")
        return "".join(out)

    def _draw_line(self, d, px, py, _):
        x, y = d["x"], d["y"]
        ok = np.isfinite(x) & np.isfinite(y)
        parts, path = [], []
        for k in range(len(x)):
            if ok[k]:
                path.append(f"{'L' if path else 'M'}{px(x[k]):.1f},{py(y[k]):.1f}")
            elif path:
                parts.append("".join(path))
                path = []
        if path:
            parts.append("".join(path))
        dash = f' stroke-dasharray="{d["dash"]}"' if d["dash"] else ""
        return "".join(f'<path d="{p}" fill="none" stroke="{d["colour"]}" '
                       f'stroke-width="{d["width"]}" opacity="{d["opacity"]}"{dash}/>'
                       for p in parts)

    def _draw_markers(self, d, px, py, _):
        out = []
        s = d["size"]
        for k, (x, y) in enumerate(zip(d["x"], d["y"])):
            if not (math.isfinite(x) and math.isfinite(y)):
                continue
            X, Y = px(x), py(y)
            if d["shape"] == "x":
                out.append(f'<path d="M{X - s:.1f},{Y - s:.1f}L{X + s:.1f},{Y + s:.1f}'
                           f'M{X - s:.1f},{Y + s:.1f}L{X + s:.1f},{Y - s:.1f}" '
                           f'stroke="{d["colour"]}" stroke-width="2"/>')
            else:
                out.append(f'<circle cx="{X:.1f}" cy="{Y:.1f}" r="{s:.1f}" fill="{d["colour"]}"/>')
            if d["texts"]:
                out.append(f'<text x="{X + s + 2:.1f}" y="{Y - s:.1f}" class="note">'
                           f'{html.escape(d["texts"][k])}</text>')
        return "".join(out)

    def _draw_bars(self, d, px, py, _):
        out = []
        half = d["bw"] / 2
        for x, y, c in zip(d["x"], d["y"], d["colours"]):
            if not (math.isfinite(x) and math.isfinite(y)):
                continue
            top, bottom = py(max(y, 0.0)), py(min(y, 0.0))
            out.append(f'<rect x="{px(x - half):.1f}" y="{top:.1f}" '
                       f'width="{px(x + half) - px(x - half):.1f}" '
                       f'height="{max(bottom - top, 0.5):.1f}" fill="{c}"/>')
        return "".join(out)

    def _draw_feet(self, d, px, py, per_px):
        out = []
        rx, ry = d["fl"] / 2 / per_px, d["fw"] / 2 / per_px
        for k, (x, y, a, c) in enumerate(zip(d["x"], d["y"], d["a"], d["colours"])):
            if not (math.isfinite(x) and math.isfinite(y)):
                continue
            deg = -math.degrees(a if math.isfinite(a) else 0.0)
            style = (f'fill="none" stroke="{c}" stroke-width="1.5" stroke-dasharray="3 2"'
                     if d["outline"] else f'fill="{c}" fill-opacity="0.75"')
            out.append(f'<ellipse cx="{px(x):.1f}" cy="{py(y):.1f}" rx="{rx:.1f}" ry="{ry:.1f}" '
                       f'transform="rotate({deg:.1f} {px(x):.1f} {py(y):.1f})" {style}/>')
            if d["texts"]:
                out.append(f'<text x="{px(x):.1f}" y="{py(y) + 3:.1f}" class="foot" '
                           f'text-anchor="middle">{html.escape(d["texts"][k])}</text>')
        return "".join(out)

    def _legend(self, right: float, top: float) -> str:
        if not self.legend:
            return ""
        out = []
        x = right - 8
        for label, colour, kind in reversed(self.legend):
            width = 7 * len(label) + 26
            x -= width
            if kind in ("line", "dash"):
                dash = ' stroke-dasharray="5 3"' if kind == "dash" else ""
                sym = (f'<line x1="{x:.0f}" y1="{top + 10:.0f}" x2="{x + 16:.0f}" '
                       f'y2="{top + 10:.0f}" stroke="{colour}" stroke-width="2"{dash}/>')
            elif kind == "x":
                sym = (f'<path d="M{x + 4:.0f},{top + 6:.0f}L{x + 12:.0f},{top + 14:.0f}'
                       f'M{x + 4:.0f},{top + 14:.0f}L{x + 12:.0f},{top + 6:.0f}" '
                       f'stroke="{colour}" stroke-width="2"/>')
            else:
                sym = f'<circle cx="{x + 8:.0f}" cy="{top + 10:.0f}" r="4" fill="{colour}"/>'
            out.append(sym + f'<text x="{x + 20:.0f}" y="{top + 14:.0f}" class="legend">'
                             f'{html.escape(label)}</text>')
        return "".join(out)

"""The HTML report of ``stage analyze``: one self-contained page of charts and a few tables.

What a person looks at first: footprints seen from above (seed 003's
Figure 6), the ankles along the walk with the foot events (its Figure 7),
step by step lengths and widths, then joint angles, movement and seed 004's
KPIs. When several sensor subsets were analysed they stand side by side;
with ground truth, its steps are drawn in grey and seed 003's agreement
statistics (bias, RPC, ICC(A,1)) are tabled. The analysis itself is
embedded as JSON (``<script id="analysis">``) for machines.
"""

from __future__ import annotations

import html
import json
import math

import numpy as np

from ..joints import JOINT_INDEX as J
from .analyze import Analysis, SubsetResult
from .features import series
from .gait import PARAMETERS
from .agreement import category
from .svg import LEFT_COLOUR, PALETTE, RIGHT_COLOUR, TRUTH_COLOUR, Chart

_CSS = """
body{font:14px/1.45 system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0;color:#1d2430;
background:#f5f6f8}
header{background:#1d2430;color:#fff;padding:18px 28px}header h1{margin:0 0 4px;font-size:22px}
header p{margin:0;color:#c9d1dc}main{padding:8px 28px 40px;max-width:1600px}
section{background:#fff;border-radius:8px;padding:14px 18px;margin:16px 0;
box-shadow:0 1px 2px rgba(0,0,0,.08)}h2{font-size:17px;margin:2px 0 10px}
.cards{display:flex;flex-wrap:wrap;gap:14px}.card{border:1px solid #e2e5ea;border-radius:8px;
padding:10px 14px;min-width:250px}.card h3{margin:0 0 6px;font-size:15px}
.big{font-size:24px;font-weight:600}.muted{color:#6b7480}.row{display:flex;flex-wrap:wrap;gap:10px}
table{border-collapse:collapse;font-size:13px}td,th{padding:3px 8px;border-bottom:1px solid #eceef1;
text-align:right}th{background:#f0f2f5}td:first-child,th:first-child{text-align:left}
.excellent{color:#1b7f3b;font-weight:600}.good{color:#4d8f1f}.fair{color:#b26b00}
.poor{color:#c62828;font-weight:600}svg.chart{background:#fff}svg .frame{fill:none;stroke:#c9ced6}
svg .grid{stroke:#eef0f3}svg .tick{font-size:11px;fill:#6b7480}svg .label{font-size:12px;
fill:#3b4350}svg .title{font-size:13px;font-weight:600;fill:#1d2430}svg .legend{font-size:12px;
fill:#3b4350}svg .note{font-size:10px;fill:#3b4350}svg .foot{font-size:9px;fill:#fff;
font-weight:600}.key span{display:inline-block;width:10px;height:10px;border-radius:5px;
margin:0 4px 0 12px}footer{color:#6b7480;font-size:12px;margin-top:20px}
"""


def _cm(v) -> str:
    return "–" if v is None or not math.isfinite(v) else f"{100 * v:.1f}"


def _num(v, digits: int = 2) -> str:
    return "–" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def _walk_axis(r: SubsetResult) -> np.ndarray:
    """Unit (x, z) direction of the pelvis path (its principal horizontal axis)."""
    p = r.trajectory.joints[:, J["SpineBase"]][:, [0, 2]]
    p = p[np.isfinite(p).all(axis=1)]
    if len(p) < 3:
        return np.array([0.0, 1.0])
    c = p - p.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    axis = vt[0]
    return axis if (p[-1] - p[0]) @ axis >= 0 else -axis


def _foot_colour(side: str) -> str:
    return LEFT_COLOUR if side == "left" else RIGHT_COLOUR


def _events_chart(r: SubsetResult, truth: SubsetResult | None, axis: np.ndarray) -> str:
    tr = r.trajectory.filled(0.25).smoothed(0.05)
    c = Chart(1180, 230, title=f"{r.subset.name}: ankles along the walk, foot events (x)",
              x_label="time (s)", y_label="metres along the walk")
    for side, joint, colour in (("left", "AnkleLeft", LEFT_COLOUR),
                                ("right", "AnkleRight", RIGHT_COLOUR)):
        a = tr.joints[:, J[joint]][:, [0, 2]] @ axis
        c.line(tr.t, a, colour, label=f"{side} ankle")
        if truth is not None:
            ta = truth.trajectory.joints[:, J[joint]][:, [0, 2]] @ axis
            c.line(truth.trajectory.t, ta, colour, width=1.0, dash="4 3", opacity=0.7)
    ev = np.array([[s.t, np.array([s.x, s.z]) @ axis] for s in r.steps]) if r.steps else \
        np.zeros((0, 2))
    c.markers(ev[:, 0], ev[:, 1], "#111", label="foot event")
    return c.svg()


def _footprint_chart(results: list[SubsetResult], truth: SubsetResult | None,
                     axis: np.ndarray) -> str:
    c = Chart(1180, 150 + 70 * len(results), title="Footprints seen from above (left red, right "
              "blue; grey outlines: truth; every walk of the recording on top of each other)",
              x_label="metres along the walk",
              y_label="metres across", equal=True)
    across = np.array([axis[1], -axis[0]])     # the walker's left is up
    heading = 0.0
    for k, r in enumerate(results):
        offset = -0.6 * k
        xs = [np.array([s.x, s.z]) @ axis for s in r.steps]
        ys = [np.array([s.x, s.z]) @ across + offset for s in r.steps]
        one_walk = len({s.bout for s in r.steps}) <= 1
        c.footprints(xs, ys, [heading] * len(xs), [_foot_colour(s.side) for s in r.steps],
                     texts=[str(s.index + 1) for s in r.steps] if one_walk else None)
        c.markers([min(xs) - 0.5] if xs else [], [offset], "#1d2430", shape="dot", size=0.1,
                  texts=[r.subset.name])
        if truth is not None:
            c.footprints([np.array([s.x, s.z]) @ axis for s in truth.steps],
                         [np.array([s.x, s.z]) @ across + offset for s in truth.steps],
                         [heading] * len(truth.steps), [TRUTH_COLOUR] * len(truth.steps),
                         outline=True)
    return c.svg()


def _step_bars(results: list[SubsetResult], truth: SubsetResult | None, what: str) -> str:
    label = {"length": "step length (cm)", "width": "step width (cm)"}[what]
    c = Chart(580, 220, title=f"{label.split(' (')[0].capitalize()} step by step",
              x_label="step (in time order; each subset its own colour band)", y_label=label)
    x0 = 0
    for r in results:
        used = [s for s in r.steps if getattr(s, what) is not None]
        xs = np.arange(len(used)) + x0
        c.bars(xs, [100 * getattr(s, what) for s in used], [_foot_colour(s.side) for s in used])
        if truth is not None:
            pairs = {id(m): t for m, t in r.pairs}
            tv = [100 * getattr(pairs[id(s)], what) if id(s) in pairs and
                  getattr(pairs[id(s)], what) is not None else math.nan for s in used]
            c.markers(xs, tv, "#111", shape="dot", size=2.5)
        x0 += len(used) + 2
    if truth is not None:
        c.legend.append(("truth", "#111", "dot"))
    return c.svg()


def _angle_charts(results: list[SubsetResult], truth: SubsetResult | None) -> str:
    out = []
    for joint in ("Knee", "Hip", "Elbow", "Shoulder"):
        c = Chart(580, 200, title=f"{joint} angle", x_label="time (s)", y_label="degrees")
        for k, r in enumerate(results[:3]):
            f = series(r.trajectory.t, r.trajectory.filled(0.25).smoothed(0.05).joints)
            dash = None if k == 0 else "5 3"
            c.line(r.trajectory.t, f[f"angle_{joint}Left"], LEFT_COLOUR, dash=dash,
                   label=f"left ({r.subset.name})")
            c.line(r.trajectory.t, f[f"angle_{joint}Right"], RIGHT_COLOUR, dash=dash,
                   label=f"right ({r.subset.name})")
        if truth is not None:
            f = series(truth.trajectory.t, truth.trajectory.joints)
            c.line(truth.trajectory.t, f[f"angle_{joint}Left"], TRUTH_COLOUR, width=1.0)
            c.line(truth.trajectory.t, f[f"angle_{joint}Right"], TRUTH_COLOUR, width=1.0,
                   dash="2 2")
        out.append(c.svg())
    return "".join(out)


def _motion_chart(results: list[SubsetResult]) -> str:
    c = Chart(1180, 210, title="Centre-of-mass speed (solid) and quantity of motion: mean joint "
              "speed over the last second (dashed)", x_label="time (s)", y_label="m/s")
    for k, r in enumerate(results):
        f = series(r.trajectory.t, r.trajectory.filled(0.25).smoothed(0.1).joints)
        colour = PALETTE[k % len(PALETTE)]
        c.line(r.trajectory.t, f["com_speed_horizontal"], colour, label=r.subset.name)
        c.line(r.trajectory.t, f["quantity_of_motion"], colour, dash="5 3", width=1.2)
    return c.svg()


def _coverage_chart(results: list[SubsetResult]) -> str:
    names = ("AnkleLeft", "AnkleRight", "KneeLeft", "KneeRight", "HipLeft", "HipRight",
             "WristLeft", "WristRight", "Head")
    c = Chart(1180, 200, title="How often each joint was missing (untracked or inferred by "
              "every sensor of the subset)", x_label="joint (groups: " + ", ".join(names) + ")",
              y_label="% of samples", y_range=(0.0, 100.0))
    width = 1.0 / (len(results) + 1)
    for k, r in enumerate(results):
        miss = r.trajectory.missing()
        c.bars(np.arange(len(names)) + k * width, [100 * miss[J[n]] for n in names],
               [PALETTE[k % len(PALETTE)]] * len(names), width=width * 0.9)
        c.legend.append((r.subset.name, PALETTE[k % len(PALETTE)], "dot"))
    return c.svg()


def _card(r: SubsetResult, truth: SubsetResult | None) -> str:
    g = r.gait

    def cell(p: str, side: str) -> str:
        v = g[p][side]
        t = truth.gait[p][side]["mean"] if truth is not None else None
        scale = 1.0 if p == "step_time" else 100.0
        unit = "s" if p == "step_time" else "cm"
        text = f"{_num(v['mean'] * scale, 2 if p == 'step_time' else 1)} {unit}"
        if t is not None:
            text += f' <span class="muted">({_num(t * scale, 2 if p == "step_time" else 1)})</span>'
        return text
    rows = "".join(f"<tr><td>{p.replace('_', ' ')}</td><td>{cell(p, 'left')}</td>"
                   f"<td>{cell(p, 'right')}</td></tr>" for p in PARAMETERS)
    sensors = ", ".join(r.trajectory.meta.get("sensors", []))
    truth_speed = (f' <span class="muted">({_num(truth.gait["speed"])})</span>'
                   if truth is not None else "")
    return (f'<div class="card" data-subset="{html.escape(r.subset.name)}">'
            f'<h3>{html.escape(r.subset.name)}</h3><div class="muted">{html.escape(sensors)}</div>'
            f'<div class="row"><div><div class="big">{_num(g["speed"])}</div>m/s walking'
            f'{truth_speed}</div><div><div class="big">{_num(g["cadence"], 0)}</div>steps/min'
            f'</div><div><div class="big">{g["used"]}</div>steps used (of {g["steps"]})</div>'
            f'</div><table><tr><th></th><th>left</th><th>right</th></tr>{rows}</table></div>')


def _agreement_table(results: list[SubsetResult]) -> str:
    head = ("<tr><th>parameter</th><th>subset</th><th>n</th><th>measured</th><th>truth</th>"
            "<th>r</th><th>bias</th><th>RPC</th><th>CV %</th><th>ICC(A,1)</th></tr>")
    rows = []
    for p in PARAMETERS:
        scale, unit = (1.0, "s") if p == "step_time" else (100.0, "cm")
        for side in ("left", "right", "all"):
            for r in results:
                a = r.agreement[p][side]
                icc = a["icc"]
                rows.append(
                    f"<tr><td>{p.replace('_', ' ')} {side[0].upper() if side != 'all' else 'L+R'}"
                    f" ({unit})</td><td>{html.escape(r.subset.name)}</td><td>{a['n']}</td>"
                    f"<td>{_num(a['mean'] * scale)} ± {_num(a['sd'] * scale)}</td>"
                    f"<td>{_num(a['truth_mean'] * scale)} ± {_num(a['truth_sd'] * scale)}</td>"
                    f"<td>{_num(a['r'], 3)}</td><td>{_num(a['bias'] * scale)}</td>"
                    f"<td>{_num(a['rpc'] * scale)}</td><td>{_num(a['cv'], 1)}</td>"
                    f'<td class="{category(icc)}">{_num(icc, 3)} {category(icc)}</td></tr>')
    return f"<table>{head}{''.join(rows)}</table>"


def _kpi_tables(results: list[SubsetResult]) -> str:
    out = []
    for r in results[:3]:
        k = r.kpi
        angles = "".join(f"<tr><td>{n}</td><td>{_num(a['mean'], 0)}</td><td>{_num(a['min'], 0)}"
                         f"</td><td>{_num(a['max'], 0)}</td><td>{_num(a['range'], 0)}</td></tr>"
                         for n, a in k.get("angles", {}).items())
        joints = "".join(
            f"<tr><td>{n}</td><td>{_cm(j['amplitude_m'])}</td><td>{_num(j['speed_mean'])}</td>"
            f"<td>{_num(j['speed_p95'])}</td><td>{_num(j['fatigue_percent'], 0)}</td></tr>"
            for n, j in k.get("joints", {}).items()
            if n in ("Head", "HandLeft", "HandRight", "ElbowLeft", "ElbowRight", "KneeLeft",
                     "KneeRight", "FootLeft", "FootRight"))
        env = "".join(f"<tr><td>{n}</td><td>{_num(1000 * v, 1)}</td></tr>"
                      for n, v in k.get("envelope_m3", {}).items())
        out.append(
            f'<div class="card"><h3>{html.escape(r.subset.name)}</h3><div class="row">'
            f"<table><tr><th>angle (°)</th><th>mean</th><th>min</th><th>max</th>"
            f"<th>range</th></tr>{angles}</table>"
            f"<table><tr><th>joint</th><th>amplitude cm</th><th>mean m/s</th><th>p95 m/s</th>"
            f"<th>fatigue %</th></tr>{joints}</table>"
            f"<table><tr><th>working envelope</th><th>litres</th></tr>{env}</table>"
            f"</div></div>")
    return '<div class="cards">' + "".join(out) + "</div>"


def render(analysis: Analysis) -> str:
    """The report as one HTML document (text)."""
    results, truth = analysis.results, analysis.truth
    axis = _walk_axis(results[0])
    duration = max(r.trajectory.duration for r in results)
    sections = [
        '<section id="summary"><h2>Gait (seed 003: first step of each walk left out)</h2>'
        '<div class="cards">' + "".join(_card(r, truth) for r in results) + "</div>"
        + ('<p class="muted">In brackets: the truth.</p>' if truth is not None else "")
        + "</section>",
        '<section id="footprints"><h2>Where the feet were put</h2>'
        + _footprint_chart(results, truth, axis) + "</section>",
        '<section id="events"><h2>Foot events (seed 003, Figure 7)</h2>'
        '<p class="muted">Each ankle\'s position along the walk; an event (x) is where one foot '
        'passes the other, and marks where the standing foot was put.'
        + (" Dashed: the truth." if truth is not None else "") + "</p>"
        + "".join(_events_chart(r, truth, axis) for r in results) + "</section>",
        '<section id="steps"><h2>Step by step</h2><div class="row">'
        + _step_bars(results, truth, "length") + _step_bars(results, truth, "width")
        + "</div></section>",
    ]
    if truth is not None:
        sections.append('<section id="agreement"><h2>Agreement with the truth (seed 003\'s '
                        'statistics, paired steps)</h2>' + _agreement_table(results)
                        + '<p class="muted">RPC = 1.96 × SD of the differences; CV = SD of the '
                        "differences / mean; ICC(A,1): poor &lt; 0.4 ≤ fair &lt; 0.6 ≤ good "
                        "&lt; 0.75 ≤ excellent; n/a where the truth does not vary from step "
                        "to step (a gait set in the simulator): then RPC says it all.</p>"
                        "</section>")
    sections += [
        '<section id="angles"><h2>Joint angles</h2><div class="row">'
        + _angle_charts(results, truth) + "</div></section>",
        '<section id="motion"><h2>Movement</h2>' + _motion_chart(results) + "</section>",
        '<section id="kpi"><h2>Body KPIs (seed 004)</h2>' + _kpi_tables(results) + "</section>",
        '<section id="coverage"><h2>Sensor coverage</h2>' + _coverage_chart(results)
        + "</section>",
    ]
    data = json.dumps(analysis.as_json()).replace("</", "<\\/")
    title = f"stage analyze: {analysis.source}"
    return (f'<!doctype html><html lang="en"><head><meta charset="utf-8"><title>'
            f"{html.escape(title)}</title><style>{_CSS}</style></head><body><header>"
            f"<h1>Walk and body analysis</h1><p>{html.escape(analysis.source)} · "
            f"{duration:.1f} s · sensors {html.escape(', '.join(analysis.sensors))}</p>"
            f'<p class="key"><span style="background:{LEFT_COLOUR}"></span>left foot'
            f'<span style="background:{RIGHT_COLOUR}"></span>right foot</p></header><main>'
            + "".join(sections)
            + '<footer>Steps: seed 003 (foot events where one ankle passes the other; length '
              "and width between successive placements along and across the walk; 30 Hz, "
              "untracked and inferred joints missing). KPIs: seed 004. Made by stage analyze."
              f'</footer></main><script type="application/json" id="analysis">{data}</script>'
              "</body></html>")


def write_report(analysis: Analysis, path: str) -> None:
    """Write the report atomically, readable as any file the user makes (the umask's mode)."""
    import os
    from ..yamlio import write_atomic
    write_atomic(path, render(analysis))
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(path, 0o666 & ~mask)

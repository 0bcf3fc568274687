"""See a performance: a piano roll of what was played, drawn with matplotlib.

Above: every note as a bar at its pitch, from its onset for as long as it
sounded, coloured by its section, each phrase in its own shade and labelled
with its name and the trigger that fired it (a thin line from the firing to
the phrase's start shows a wait for the beat or for another phrase); notes
held by an ending's pedal are drawn lighter to where they stopped; cut notes
keep a dotted outline of what was scheduled (a cancelled note is only that
outline). Phrases not played are crosses at the top. Section boundaries are
vertical lines. Below: the dancer's zone occupancy, one row per zone, and
every trigger that fired.

matplotlib comes with ``pip install 'stage-kuatro[plot]'`` (and with filterpy).
"""

from __future__ import annotations

import os
from typing import Any

from ..errors import ConfigError
from .report import Performance

#: one colour per section (then again): matplotlib's tab10, which stays readable in grey
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2",
           "#7f7f7f", "#bcbd22", "#17becf")
_NAMES = ("C", "C#", "D", "Eb", "E", "F", "F#", "G", "Ab", "A", "Bb", "B")


def _pyplot() -> Any:
    try:
        import matplotlib  # noqa: PLC0415  (optional: only scores need it)
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # noqa: PLC0415
    except ImportError:
        raise ConfigError("drawing a score needs matplotlib (pip install "
                          "'stage-kuatro[plot]')") from None
    return plt


def check_score_path(path: str | os.PathLike) -> None:
    """Before a show: the folder exists, the format is one matplotlib writes, matplotlib is
    installed (one-line ConfigError otherwise)."""
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise ConfigError(f"--score {path}: folder '{folder}' does not exist")
    if os.path.splitext(str(path))[1].lower() not in (".png", ".svg", ".pdf"):
        raise ConfigError(f"--score {path}: write a .png, .svg or .pdf")
    _pyplot()


def draw_score(perf: Performance, path: str | os.PathLike, title: str = "") -> str:
    """Draw ``perf`` into the image ``path`` (PNG, SVG or PDF by its extension)."""
    check_score_path(path)
    plt = _pyplot()
    from matplotlib.patches import Rectangle  # noqa: PLC0415

    zones = sorted(perf.zones)
    fig, (roll, below) = plt.subplots(
        2, 1, figsize=(max(12.0, perf.end / 5.0), 8.5), sharex=True,
        gridspec_kw={"height_ratios": [4.0, 0.6 + 0.35 * (len(zones) + 1)]})
    colour = {s.name: PALETTE[k % len(PALETTE)] for k, s in enumerate(perf.sections)}
    pitches = [n.note for n in perf.notes] or [60]
    low, high = min(pitches) - 2, max(pitches) + 4
    for k, s in enumerate(perf.sections):
        for ax in (roll, below):
            ax.axvspan(s.start, s.end, color=colour[s.name], alpha=0.06, lw=0)
            ax.axvline(s.start, color="0.35", lw=0.8, ls="--")
        roll.text(s.start + 0.2, high - 0.5, f"{s.index + 1}. {s.name}", va="top", ha="left",
                  fontsize=9, color=colour[s.name], fontweight="bold")
    order = {pid: k for k, pid in enumerate(sorted(perf.phrases))}
    for n in perf.notes:
        phrase = perf.phrases.get(n.play, {})
        section = phrase.get("section") or getattr(perf.section_at(n.t), "name", "")
        c = colour.get(section, "0.3")
        shade = 0.95 if order.get(n.play, 0) % 2 == 0 else 0.6      # neighbours differ
        if n.sounded > 0:
            roll.add_patch(Rectangle((n.t, n.note - 0.4), n.sounded, 0.8, facecolor=c,
                                     alpha=shade, edgecolor="none"))
        if n.held > n.sounded + 1e-6:                                 # the pedal holds it
            roll.add_patch(Rectangle((n.t + n.sounded, n.note - 0.4), n.held - n.sounded, 0.8,
                                     facecolor=c, alpha=0.25, edgecolor="none"))
        if n.cut:
            roll.add_patch(Rectangle((n.t, n.note - 0.4), n.duration, 0.8, fill=False,
                                     edgecolor="#d62728", ls=":", lw=1.0))
    for pid, p in perf.phrases.items():
        mine = [n for n in perf.notes if n.play == pid]
        top = max((n.note for n in mine), default=high - 3) + 1.0
        c = colour.get(p["section"], "0.3")
        if p["t"] - p["decided"] > 0.02:                  # waited for the beat or a phrase
            roll.plot([p["decided"], p["t"]], [top, top], color=c, lw=0.8, alpha=0.8)
            roll.plot([p["decided"]], [top], marker="|", color=c, ms=6)
        roll.text(p["t"], top + 0.3, f"{p['phrase']} < {p['trigger']}", fontsize=6.5,
                  rotation=30, ha="left", va="bottom", color=c)
    for sk in perf.skipped:
        roll.plot([sk["t"]], [high - 2.0], marker="x", color="0.3", ms=6)
        roll.text(sk["t"], high - 2.6, f"{sk['phrase']}: not played", fontsize=6, rotation=30,
                  ha="left", va="top", color="0.3")
    roll.set_ylim(low, high)
    ticks = [p for p in range(low, high + 1) if p % 12 in (0, 7)]
    roll.set_yticks(ticks, [f"{_NAMES[p % 12]}{p // 12 - 1}" for p in ticks])
    roll.set_ylabel("pitch")
    roll.grid(axis="y", color="0.9", lw=0.5)
    c = perf.counts()
    roll.set_title((title + ": " if title else "") + f"{c['phrases']} phrases, {c['notes']} "
                   f"notes sounded ({c['cancelled']} cancelled, {c['shortened']} cut short), "
                   f"{perf.end:.1f} s", fontsize=10)
    for row, zone in enumerate(zones):
        for a, b in perf.zones[zone]:
            below.add_patch(Rectangle((a, row + 0.15), b - a, 0.7, facecolor="0.45",
                                      edgecolor="none"))
    trow = len(zones)
    for e in perf.triggers:
        c = colour.get(e["section"], "0.3")
        below.plot([e["t"]], [trow + 0.5], marker="v", color=c, ms=6)
        below.text(e["t"], trow + 0.95, e["trigger"], fontsize=6, rotation=45, ha="left",
                   va="bottom", color=c)
    below.set_ylim(0, trow + 2.2)
    below.set_yticks([k + 0.5 for k in range(trow + 1)], [*zones, "triggers"], fontsize=8)
    below.set_xlabel("seconds from the start")
    below.set_xlim(0, max(perf.end, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)

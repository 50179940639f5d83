"""``DIR/fleet.html``: one self-contained page (plots as PNG data URIs, inline CSS, the diagnosis
report's helpers): the changes, then per group (and channel) the trend of each quantity over time with the
history's median and scale, each bag's 95 % interval where its model's bounds give one, the flagged
bags marked and the onset drawn; the failed bags."""

from __future__ import annotations

import datetime
import html
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..diagnosis.report import CSS
from ..diagnosis.report import _img as embedded_png
from .changes import GroupChange, SeriesTest
from .table import QUANTITIES, GroupSeries, bag_date


def quantity_label(key: str, sample_rate: float) -> str:
    label, unit = QUANTITIES[key]
    if key == "time_constant" and sample_rate <= 0:
        unit = "samples"
    return f"{label} ({unit})" if unit else label


def change_line(change: GroupChange, series: GroupSeries, sample_rate: float = 0.0) -> str:
    """``robot_07/joint3: static gain -28 % from 2026-11-14, 12 bags (trend -2.1 %/day)``"""
    label = QUANTITIES[change.quantity][0]
    first = series.rows[change.first_index]
    trend = f", trend {100 * change.trend_per_day:+.1f} %/day" if np.isfinite(change.trend_per_day) else ""
    return (f"{change.group}: {label} {100 * change.size:+.0f} % from {bag_date(first)}, {change.bags} bags "
            f"(reference {change.reference:.4g}, latest {change.latest:.4g}{trend})")


def write_report(path: str | Path, series: Sequence[GroupSeries], tests: dict[str, dict[str, SeriesTest]],
                 changes: Sequence[GroupChange], rows: Sequence[dict], sample_rate: float = 0.0,
                 title: str = "hammer-ros fleet") -> None:
    Path(path).write_text(render_report(series, tests, changes, rows, sample_rate, title), encoding="utf-8")


def render_report(series: Sequence[GroupSeries], tests: dict[str, dict[str, SeriesTest]],
                  changes: Sequence[GroupChange], rows: Sequence[dict], sample_rate: float = 0.0,
                  title: str = "hammer-ros fleet") -> str:
    import matplotlib

    matplotlib.use("Agg", force=True)
    failed = [r for r in rows if r.get("error")]
    by_group = {s.key: s for s in series}
    verdict = (f"<b>{len(changes)} change(s)</b> in {len({c.group for c in changes})} of {len(series)} group(s)"
               if changes else f"<b>No change</b> in {len(series)} group(s)")
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
             f"<style>{CSS}</style></head><body>", f"<h1>{html.escape(title)}</h1>",
             f"<div class='verdict{'' if changes else ' none'}'>{verdict}; {len(rows)} bags, "
             f"{len(rows) - len(failed)} with a model, {len(failed)} failed.</div>",
             "<h2>What changed</h2>",
             "<p class='small'>Per group and quantity, a two-sided CUSUM of robust z-scores against the "
             "group's own history (median and 1.4826 MAD of its first bags and of every later bag in control; "
             "allowance 0.5, threshold 5). The onset is the first bag of the run that crossed the threshold; "
             "size: the last bags against the history's median.</p>"]
    if changes:
        parts.append("<table><tr><th>group</th><th>quantity</th><th>from</th><th>bags</th><th>size</th>"
                     "<th>trend / day</th><th>first bag</th></tr>")
        for c in changes:
            s = by_group[c.group]
            first = s.rows[c.first_index]
            parts.append(f"<tr><td>{html.escape(c.group)}</td><td>{QUANTITIES[c.quantity][0]}</td>"
                         f"<td>{html.escape(bag_date(first))}</td><td class='num'>{c.bags}</td>"
                         f"<td class='num fail'>{100 * c.size:+.1f} %</td>"
                         f"<td class='num'>{100 * c.trend_per_day:+.2f} %</td>"
                         f"<td>{html.escape(first['path'])}</td></tr>")
        parts.append("</table>")
    else:
        parts.append("<p>No quantity of any group departs from its history.</p>")
    for s in series:
        flagged = sorted({c.quantity for c in changes if c.group == s.key})
        note = f" &mdash; <span class='fail'>{', '.join(QUANTITIES[q][0] for q in flagged)}</span>" if flagged else ""
        parts.append(f"<h2>{html.escape(s.key)} ({len(s.rows)} bags){note}</h2>")
        parts.append(embedded_png(_group_figure(s, tests.get(s.key, {}), sample_rate)))
    if failed:
        channels = any("channel" in r for r in rows)
        parts.append("<h2>Failed bags</h2><table><tr><th>bag</th><th>group</th>"
                     + ("<th>channel</th>" if channels else "") + "<th>error</th></tr>")
        parts += [f"<tr><td>{html.escape(r['path'])}</td><td>{html.escape(r['group'])}</td>"
                  + (f"<td>{html.escape(str(r.get('channel')))}</td>" if channels else "")
                  + f"<td class='fail'>{html.escape(str(r['error']))}</td></tr>" for r in failed]
        parts.append("</table>")
    parts.append("</body></html>")
    return "\n".join(parts)


def _group_figure(series: GroupSeries, tests: dict[str, SeriesTest], sample_rate: float):
    import matplotlib.dates as mdates
    import matplotlib.pyplot as plt

    keys = list(QUANTITIES)
    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.0), squeeze=False)
    when = [datetime.datetime.fromtimestamp(t, tz=datetime.timezone.utc) for t in series.times]
    for ax, key in zip(axes[0], keys):
        values = series.values[key]
        test = tests.get(key)
        ax.plot(when, values, "o-", color="#1f5fa8", ms=4, lw=1, label="bags")
        sds = series.sds.get(key)
        if sds is not None and np.isfinite(sds).any():  # each bag's 95 % interval from its model's bounds
            ax.errorbar(when, values, yerr=1.96 * np.nan_to_num(sds), fmt="none", ecolor="#1f5fa8", elinewidth=1,
                        capsize=2, alpha=0.6, label="95 % interval")
        change = test.change if test else None
        if change is not None:
            idx = list(change.flagged)
            ax.plot([when[i] for i in idx], values[idx], "o", ms=8, mfc="none", mec="#b00020", mew=2,
                    label="flagged")
            ax.axhline(change.reference, color="#555", lw=1, ls="--", label="history median")
            ax.axhspan(change.reference - 2 * change.scale, change.reference + 2 * change.scale, color="#ddd",
                       alpha=0.6, lw=0)
            ax.axvline(when[change.onset], color="#b00020", lw=1, ls=":")
        elif np.isfinite(values).any():
            ax.axhline(float(np.nanmedian(values)), color="#555", lw=1, ls="--", label="median")
        ax.set_title(quantity_label(key, sample_rate), fontsize=10)
        ax.xaxis.set_major_formatter(mdates.DateFormatter("%m-%d"))
        ax.tick_params(labelsize=8)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7, loc="best")
    fig.tight_layout()
    return fig

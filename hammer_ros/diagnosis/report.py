"""``diagnose --report FILE.html``: one self-contained page (plots embedded as PNG data URIs,
inline CSS, no external resource) that a person can read without the JSON."""

from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path

import numpy as np

from .causes import EXTENSION, MEANING
from .diagnose import Diagnosis, DiagnosisRun
from .residual_tests import simultaneous_level

EXCERPT = 1500  # samples of the validation record drawn in the time plots

CSS = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; margin: 24px auto; max-width: 1100px;
       color: #222; line-height: 1.4; }
h1 { font-size: 1.5em; margin-bottom: 0.2em; }
h2 { font-size: 1.2em; margin-top: 1.6em; border-bottom: 1px solid #ccc; }
.verdict { font-size: 1.15em; padding: 10px 14px; border-radius: 6px; background: #eef5ff; border: 1px solid #b7d0f0; }
.none { background: #eefaf0; border-color: #b5dfbd; }
table { border-collapse: collapse; margin: 8px 0; font-size: 0.92em; }
td, th { border: 1px solid #ddd; padding: 3px 8px; text-align: left; }
th { background: #f4f4f4; } td.num { text-align: right; font-family: monospace; }
.fail { color: #b00020; font-weight: bold; } .pass { color: #1b7f3b; }
img { max-width: 100%; } pre { background: #f7f7f7; padding: 8px; overflow-x: auto; font-size: 0.85em; }
.small { color: #666; font-size: 0.9em; }
"""


def write_report(run: DiagnosisRun, path: str | Path, title: str = "hammer-ros diagnosis") -> None:
    Path(path).write_text(render_report(run, title), encoding="utf-8")


def render_report(run: DiagnosisRun, title: str = "hammer-ros diagnosis") -> str:
    import matplotlib

    matplotlib.use("Agg", force=True)
    d = run.diagnosis
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
             f"<style>{CSS}</style></head><body>", f"<h1>{html.escape(title)}</h1>", _verdict(run),
             "<h2>Validation: measured vs simulated</h2>",
             "<p class='small'>Free-run simulations on the validation data (the models never saw it). "
             "Bottom: the simulation errors.</p>", _img(_validation_figure(run)), _numbers(run), _chain(run),
             _not_fitted(run.diagnosis),
             "<h2>What the baseline gets wrong: the cause tests</h2>",
             "<p class='small'>Each cause leaves its own signature in the baseline's error; a test fails when "
             "the signature is significant (99 % level). Failing tests nominate causes; the extension of each "
             "nominated cause is fitted and the one with the largest validation gain is named.</p>",
             _evidence_table([t.evidence for t in run.cause_tests], [t.explained for t in run.cause_tests]),
             _img(_cause_figure(run)),
             "<h2>Residual correlation tests (Billings &amp; Voon, Billings &amp; Zhu)</h2>",
             "<p class='small'>Correlations of the validation residual with 95 % bounds from Bartlett's formula "
             "(valid for coloured signals; shaded), and the simultaneous 95 % bound over all lags (dashed).</p>",
             _img(_correlation_figure(run)),
             _evidence_table([t.evidence() for t in run.correlation_tests], None),
             "<h2>Identified maps</h2>", _img(_maps_figure(run)), _models(run),
             "<h2>The diagnosis as JSON</h2>",
             f"<pre>{html.escape(json.dumps(d.to_json(), indent=1)[:20000])}</pre>", "</body></html>"]
    return "\n".join(parts)


def _coverage(d: Diagnosis) -> str:
    """How the record was split, and which validation samples the models are judged on."""
    notes = [d.split_note] if d.split_note else []
    if d.coverage:
        notes.append(f"Input coverage: {d.coverage['judged_on']}.")
    return "".join(f"<p class='small'>{html.escape(n)}</p>" for n in notes)


def _verdict(run: DiagnosisRun) -> str:
    d = run.diagnosis
    if d.cause == "none":
        text = (f"<b>No cause found</b> (confidence {d.confidence:.2f}): {MEANING['none']}. "
                f"Baseline validation fit {d.baseline.fit_percent:.1f} %, RMS {d.baseline.rms:.4g}.")
        return f"<div class='verdict none'>{text}</div>{_coverage(d)}"
    text = (f"<b>Cause: {d.cause}</b> (confidence {d.confidence:.2f}): {html.escape(MEANING[d.cause])}.<br>"
            f"Extended model: {html.escape(d.steps[0].structure if d.steps else EXTENSION[d.cause])}.<br>"
            f"Validation RMS {d.baseline.rms:.4g} &rarr; {d.extended.rms:.4g} (gain {d.gain:.2f}), fit "
            f"{d.baseline.fit_percent:.1f} % &rarr; {d.extended.fit_percent:.1f} %.")
    if len(d.steps) > 1:
        chain = " &rarr; ".join(f"{html.escape(s.cause)} (x{s.gain:.2f})" for s in d.steps)
        text += f"<br>Compound explanation: {chain}."
    return f"<div class='verdict'>{text}</div>{_coverage(d)}"


def _chain(run: DiagnosisRun) -> str:
    """The chain of explanations: each step extends the model of the step before."""
    d = run.diagnosis
    if not d.steps:
        return ""
    body = "".join(f"<tr><td class='num'>{i}</td><td>{html.escape(s.cause)}</td><td>{html.escape(s.structure)}</td>"
                   f"<td class='num'>{s.rms:.4g}</td><td class='num'>{s.gain:.3f}</td></tr>"
                   for i, s in enumerate(d.steps, 1))
    return ("<h2>Chain of explanations</h2><p class='small'>After the named cause, the extended model's own "
            "validation residual is tested again; a further step is taken while it gains at least 5 %.</p>"
            "<table><tr><th>step</th><th>cause</th><th>structure</th><th>validation RMS</th>"
            f"<th>gain over the step before</th></tr>{body}</table>"
            f"<p class='small'>The chain stopped: {html.escape(d.chain_stopped or '')}.</p>")


def _not_fitted(d: Diagnosis) -> str:
    """The extensions tried in vain, each with its one-line reason."""
    if not d.not_fitted:
        return ""
    items = "".join(f"<li>{html.escape(c)}: {html.escape(r)}</li>" for c, r in d.not_fitted)
    return f"<p class='small'>Not fitted:</p><ul class='small'>{items}</ul>"


def _numbers(run: DiagnosisRun) -> str:
    d = run.diagnosis
    rows = [("baseline", d.baseline.structure, d.baseline.rms, d.baseline.fit_percent, 1.0)]
    for cause, gain in d.candidates:
        ext = run.extensions[cause]
        rms = d.baseline.rms / gain
        fit = 100.0 * (1.0 - (1.0 - d.baseline.fit_percent / 100.0) / gain)
        rows.append((("<b>" + cause + "</b>") if cause == d.cause else cause, ext.structure, rms, fit, gain))
    body = "".join(f"<tr><td>{c}</td><td>{html.escape(s)}</td><td class='num'>{r:.4g}</td>"
                   f"<td class='num'>{f:.2f}</td><td class='num'>{g:.3f}</td></tr>" for c, s, r, f, g in rows)
    split = run.split
    note = (f"estimation {split.n_est} samples, validation {split.v_val.size} samples "
            f"({'continuing the estimation record' if split.continuous else 'separate record, simulated from rest'})")
    return ("<table><tr><th>model</th><th>structure</th><th>validation RMS</th><th>fit %</th>"
            f"<th>gain (RMS ratio)</th></tr>{body}</table><p class='small'>{note}; a cause is named only if its "
            f"gain is at least 1.05.</p>")


def _evidence_table(evidence, explained) -> str:
    rows = []
    for i, e in enumerate(evidence):
        verdict = "<span class='pass'>pass</span>" if e.passed else "<span class='fail'>FAIL</span>"
        extra = "" if explained is None else f"<td class='num'>{100 * explained[i]:.1f} %</td><td>{e.cause}</td>"
        rows.append(f"<tr><td>{html.escape(e.test)}</td><td class='num'>{e.value:.4g}</td>"
                    f"<td class='num'>{e.bound:.4g}</td><td>{verdict}</td>{extra}</tr>")
    head = "<tr><th>test</th><th>value</th><th>bound</th><th>result</th>"
    head += "</tr>" if explained is None else "<th>residual explained</th><th>points to</th></tr>"
    return f"<table>{head}{''.join(rows)}</table>"


def _models(run: DiagnosisRun) -> str:
    d = run.diagnosis
    base = {k: v for k, v in d.to_json()["baseline"].items() if k != "nonlinearity"}
    out = [f"<p>Baseline (Hammerstein, PLLS + simulation-error refinement): "
           f"<code>{html.escape(json.dumps(_rounded(base)))}</code></p>"]
    for i, model in enumerate(run.chain.models if run.chain is not None else (), 1):
        out.append(f"<p>Step {i}, {html.escape(model.cause)} ({html.escape(model.structure)}): "
                   f"<code>{html.escape(json.dumps(_rounded(model.details)))}</code></p>")
    return "".join(out)


def _rounded(x):
    if isinstance(x, dict):
        return {k: _rounded(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_rounded(v) for v in x]
    return round(x, 5) if isinstance(x, float) else x


def _img(fig) -> str:
    import matplotlib.pyplot as plt

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    data = base64.b64encode(buffer.getvalue()).decode("ascii")
    return f"<p><img alt='plot' src='data:image/png;base64,{data}'></p>"


def _excerpt(n: int) -> slice:
    return slice(0, min(n, EXCERPT))


def _validation_figure(run: DiagnosisRun):
    import matplotlib.pyplot as plt

    s, d = run.split, run.diagnosis
    part = _excerpt(s.v_val.size)
    k = np.arange(s.v_val.size)[part] + (s.n_est if s.continuous else 0)
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(11, 5.6), sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    top.plot(k, s.y_val[part], color="black", lw=1.0, label="measured")
    top.plot(k, run.baseline_output[part], color="tab:red", lw=1.0, label=f"baseline (RMS {d.baseline.rms:.3g})")
    bottom.plot(k, (s.y_val - run.baseline_output)[part], color="tab:red", lw=0.8, label="baseline error")
    if run.extended is not None:
        out = run.extended.validation_output
        label = f"extended: {d.cause} (RMS {d.extended.rms:.3g})"
        top.plot(k, out[part], color="tab:blue", lw=1.0, ls="--", label=label)
        bottom.plot(k, (s.y_val - out)[part], color="tab:blue", lw=0.8, label="extended error")
    if s.judged is not None:  # the samples not judged: their input (or a recent one) is outside the estimation range
        for i, (first, last) in enumerate(_runs(~s.judged[part])):
            top.axvspan(k[first], k[last], color="0.85", lw=0,
                        label=None if i else "not judged: input outside the estimation range")
            bottom.axvspan(k[first], k[last], color="0.85", lw=0)
    top.set_ylabel("output")
    top.legend(loc="upper right", fontsize=8)
    bottom.set_ylabel("error")
    bottom.set_xlabel("sample")
    bottom.legend(loc="upper right", fontsize=8)
    if s.v_val.size > EXCERPT:
        top.set_title(f"first {EXCERPT} of {s.v_val.size} validation samples", fontsize=9)
    fig.tight_layout()
    return fig


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of every run of True in ``mask``."""
    edges = np.diff(np.concatenate([[0], mask.astype(int), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1))


def _correlation_figure(run: DiagnosisRun):
    import matplotlib.pyplot as plt

    tests = run.correlation_tests
    cols = 4
    rows = int(np.ceil(len(tests) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(12, 2.7 * rows))
    for ax, t in zip(axes.ravel(), tests):
        ok = t.evidence().passed
        ax.fill_between(t.lags, -t.bounds, t.bounds, color="tab:blue", alpha=0.15, lw=0)
        z = simultaneous_level(int(np.count_nonzero(~t.excluded)))
        ax.plot(t.lags, z * t.bounds / 1.96, "k--", lw=0.7)
        ax.plot(t.lags, -z * t.bounds / 1.96, "k--", lw=0.7)
        ax.vlines(t.lags, 0, t.values, color="tab:green" if ok else "tab:red", lw=1.5)
        ax.axhline(0, color="black", lw=0.5)
        ax.set_title(f"{t.name}: {'pass' if ok else 'FAIL'}", fontsize=8.5, color="black" if ok else "tab:red")
        ax.tick_params(labelsize=7)
        ax.set_xlabel("lag", fontsize=7)
    for ax in axes.ravel()[len(tests):]:
        ax.axis("off")
    fig.tight_layout()
    return fig


def _cause_figure(run: DiagnosisRun):
    import matplotlib.pyplot as plt
    from matplotlib import ticker

    fig, (bars, spectrum, windows) = plt.subplots(1, 3, figsize=(13, 3.4), gridspec_kw={"width_ratios": [1.3, 1, 1]})
    tests = run.cause_tests
    ratio = np.array([max(t.evidence.value / t.evidence.bound, 1e-3) if np.isfinite(t.evidence.bound) else 1e-3
                      for t in tests])
    colors = ["tab:red" if t.supports else "tab:green" for t in tests]
    bars.barh(np.arange(len(tests)), ratio, color=colors)
    bars.axvline(1.0, color="black", lw=1)
    bars.set_xscale("log")
    bars.xaxis.set_major_formatter(ticker.FormatStrFormatter("%g"))
    bars.xaxis.set_minor_formatter(ticker.NullFormatter())
    bars.set_yticks(np.arange(len(tests)), [t.cause for t in tests], fontsize=8)
    bars.invert_yaxis()
    bars.set_xlabel("test statistic / bound (>1: fails)", fontsize=8)
    bars.tick_params(labelsize=7)
    lines = run.lines
    spectrum.semilogy(lines.grid, np.maximum(lines.periodogram, 1e-3), color="tab:gray", lw=0.6)
    spectrum.axhline(lines.threshold, color="black", ls="--", lw=0.8, label="99 % level")
    for w in lines.frequencies:
        spectrum.axvline(w, color="tab:red", lw=1.0, alpha=0.7)
    spectrum.set_title("residual spectrum / running median (lines in red)", fontsize=8.5)
    spectrum.set_xlabel("frequency (rad/sample)", fontsize=8)
    spectrum.tick_params(labelsize=7)
    spectrum.legend(fontsize=7)
    w = run.windows
    windows.plot(w.starts, w.gain, "o-", color="tab:purple", ms=3)
    if w.change_point is not None:
        windows.axvline(w.change_point, color="tab:red", ls="--", lw=1, label="best step")
        windows.legend(fontsize=7)
    if run.split.continuous:
        windows.axvline(run.split.n_est, color="black", lw=0.8)
    windows.set_title("gain of the baseline per window", fontsize=8.5)
    windows.set_xlabel("sample (line: start of validation)", fontsize=8)
    windows.tick_params(labelsize=7)
    fig.tight_layout()
    return fig


def _maps_figure(run: DiagnosisRun):
    import matplotlib.pyplot as plt

    plots = [("baseline F (input map)", run.split.v_est, run.baseline.static)]
    extra = tuple(m for model in run.chain.models for m in model.maps) if run.chain is not None else ()
    fig, axes = plt.subplots(1, 1 + len(extra), figsize=(4.2 * (1 + len(extra)), 3.2), squeeze=False)
    title, samples, fn = plots[0]
    grid = np.linspace(float(np.min(samples)), float(np.max(samples)), 300)
    ax = axes[0, 0]
    ax.plot(grid, fn(grid), color="tab:red")
    ax.plot(run.baseline.partition, fn(run.baseline.partition), "o", color="tab:red", ms=4, label="breakpoints")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("input", fontsize=8)
    ax.legend(fontsize=7)
    for ax, m in zip(axes[0, 1:], extra):
        ax.plot(m.x, m.y, color="tab:blue")
        ax.set_title(f"extended: {m.title}", fontsize=9)
    for ax in axes.ravel():
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig

"""The session report: one self-contained HTML file from a local station's MCAP recording.

:func:`write_report` draws (matplotlib, embedded as base64 PNG; no external file or script)

* the relief and stiffness maps the palpation analysis builds from what reached the local
  station, with its findings (and the ground truth when given) marked on them;
* the trajectory coverage: samples per map cell and the probe's path over the phantom;
* the findings (position, type, size, confidence when the analysis gives one) and, with a
  ground truth, the per-tumor comparison of :func:`lab.scoring.score_findings`;
* the latency ledger: per-stage delays of every received message over time and their
  p50 / p99, for the local recording and, when given, the remote station's;
* the pins: commanded against measured height for four pins.

Ground truth is evaluation data, never written by a station: the lab passes it
(``teletouch report FILE --truth ground_truth.json``; the demo does).
"""

from __future__ import annotations

import base64
import html
import io
import json
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from lab.replay import latency_stages, summarize
from lab.scoring import score_findings
from local_site.palpation import build_maps, maps_and_findings
from local_site.recording import Recording, recording_from_mcap
from shared.errors import ConfigError, InputDataError
from shared.recording import McapRecording, RecordingFormatError, read_mcap
from shared.workspace import WorkspaceMap, load_workspace

__all__ = ["write_report"]

log = logging.getLogger(__name__)


def _plt() -> Any:
    try:
        import matplotlib
    except ImportError as err:
        raise ConfigError("teletouch report needs matplotlib: pip install "
                          "'teletouch[report]'") from err
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _png(fig: Any) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    _plt().close(fig)
    data = base64.b64encode(buf.getvalue()).decode()
    return f'<img alt="figure" src="data:image/png;base64,{data}">'


def _table(rows: list[dict[str, Any]], columns: list[str] | None = None) -> str:
    if not rows:
        return "<p><em>none</em></p>"
    cols = columns or list(rows[0])

    def cell(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.3g}"
        if isinstance(v, list | tuple):
            return ", ".join(cell(x) for x in v)
        return html.escape("n/a" if v is None else str(v))

    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{cell(r.get(c))}</td>" for c in cols) + "</tr>"
                   for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _workspace(rec: Recording) -> WorkspaceMap:
    recorded = rec.meta.get("workspace")
    return load_workspace(explicit=recorded if isinstance(recorded, dict) else None)


def _map_figures(rec: Recording, ws: WorkspaceMap, findings: list[Any],
                 truth: dict[str, Any] | None) -> list[str]:
    plt = _plt()
    maps = build_maps(rec, ws)
    extent = (maps.x_mm[0], maps.x_mm[-1], maps.y_mm[0], maps.y_mm[-1])
    out = []
    tumors = (truth or {}).get("tumors", [])
    for title, grid, cmap in (("relief (relative)", maps.relief, "viridis"),
                              ("stiffness (N/mm)", maps.stiffness_n_per_mm, "magma")):
        fig, ax = plt.subplots(figsize=(5.5, 4.5))
        im = ax.imshow(grid, origin="lower", extent=extent, cmap=cmap)
        fig.colorbar(im, ax=ax, shrink=0.8)
        for f in findings:
            ax.plot(*f.center_mm, "o", mfc="none", mec="red", ms=14, mew=2)
            ax.annotate(f"{f.kind} #{f.severity_rank}", f.center_mm, color="red",
                        xytext=(6, 6), textcoords="offset points", fontsize=8)
        for t in tumors:
            c = t.get("center_mm")
            if isinstance(c, list) and len(c) >= 2:
                ax.plot(c[0], c[1], "+", color="k", ms=14, mew=2)
        ax.set(title=f"{title}; o found" + (", + truth" if tumors else ""),
               xlabel="x (mm, phantom)", ylabel="y (mm, phantom)")
        out.append(_png(fig))
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    count = np.where(maps.relief_count > 0, maps.relief_count, np.nan).astype(float)
    im = ax.imshow(count, origin="lower", extent=extent, cmap="Blues")
    fig.colorbar(im, ax=ax, shrink=0.8, label="samples per cell")
    if rec.platform_mm.shape[0]:
        path = ws.forward_unclamped(rec.platform_mm)
        ax.plot(path[:, 0], path[:, 1], "-", color="orange", lw=0.6, alpha=0.8)
    covered = float(np.mean(maps.relief_count > 0)) * 100
    ax.set(title=f"coverage: {covered:.0f} % of the map's cells touched; path in orange",
           xlabel="x (mm, phantom)", ylabel="y (mm, phantom)",
           xlim=extent[:2], ylim=extent[2:])
    out.append(_png(fig))
    return out


def _latency_figure(mcap: McapRecording) -> tuple[str, list[dict[str, Any]]]:
    plt = _plt()
    topic = f"/{mcap.station}/latency"
    # message type -> stage (in hop order, end to end last) -> (times, delays)
    series: dict[str, dict[str, tuple[list[float], list[float]]]] = {}
    longest: dict[str, list[str]] = {}
    t0 = mcap.messages[0].t_us if mcap.messages else 0
    for m in mcap.on(topic):
        try:
            obj = m.json()
        except RecordingFormatError:  # not a JSON object: left out (counted in the summary)
            continue
        t = (m.t_us - t0) / 1e6
        per = series.setdefault(str(obj.get("type")), {})
        items, _ = latency_stages(obj)  # malformed values left out (counted in the summary)
        stages = [n for n in items if n != "end_to_end"]
        if len(stages) > len(longest.get(str(obj.get("type")), [])):
            longest[str(obj.get("type"))] = stages
        for name, v in items.items():
            if v is not None:
                ts, vs = per.setdefault(name, ([], []))
                ts.append(t)
                vs.append(float(v))
    for msg_type, per in list(series.items()):  # hop order of the longest stamp list
        ref = longest.get(msg_type, [])
        order = sorted(per, key=lambda n: (n == "end_to_end", ref.index(n) if n in ref
                                           else len(per)))
        series[msg_type] = {n: per[n] for n in order}
    rows = [{"stream": k, "stage": name, "count": len(v), "p50 ms": float(np.percentile(v, 50)),
             "p99 ms": float(np.percentile(v, 99)), "max ms": float(np.max(v))}
            for k, per in series.items() for name, (_, v) in per.items()]
    if not series:
        return f"<p>No latency stamps in {html.escape(str(mcap.path))}.</p>", rows
    fig, axes = plt.subplots(len(series), 2, figsize=(12, 3.2 * len(series)), squeeze=False,
                             gridspec_kw={"width_ratios": [3, 2]})
    for (msg_type, per), (ax, bar) in zip(series.items(), axes, strict=True):
        for name, (ts, vs) in per.items():
            ax.plot(ts, vs, "-" if name == "end_to_end" else ".",
                    color="k" if name == "end_to_end" else None,
                    lw=0.6, ms=2, label=name)
        ax.set(title=f"{mcap.station} station, received {msg_type}: delay per stage",
               xlabel="time (s)", ylabel="ms", yscale="symlog")
        ax.legend(fontsize=6, markerscale=4, loc="upper left")
        names = list(per)
        p50 = [float(np.percentile(per[n][1], 50)) for n in names]
        p99 = [float(np.percentile(per[n][1], 99)) for n in names]
        y = np.arange(len(names))
        bar.barh(y + 0.2, p99, height=0.4, label="p99", color="tab:orange")
        bar.barh(y - 0.2, p50, height=0.4, label="p50", color="tab:blue")
        bar.set_yticks(y, names, fontsize=7)
        bar.invert_yaxis()
        bar.set(xscale="symlog", xlabel="ms", title="p50 / p99 per stage (hop order)")
        bar.legend(fontsize=7)
    fig.tight_layout()
    return _png(fig), rows


def _pin_values(v: Any) -> list[float]:
    """16 pin values, or 16 NaN (no command: the safe state; or not 16 finite numbers)."""
    try:
        arr = np.asarray(v, dtype=float).ravel()
    except (TypeError, ValueError):
        arr = np.zeros(0)
    return arr.tolist() if arr.size == 16 and np.isfinite(arr).all() else [np.nan] * 16


def _pins_figure(mcap: McapRecording) -> str:
    plt = _plt()
    pins, objs = [], []
    for m in mcap.on("/local/pins"):
        try:
            objs.append(m.json())
        except RecordingFormatError:  # not a JSON object: left out (the summary counts it)
            continue
        pins.append(m)
    if not pins:
        return "<p>No pin channel in this recording.</p>"
    t0 = pins[0].t_us
    tt = np.array([(m.t_us - t0) / 1e6 for m in pins])
    cmd = np.array([_pin_values(o.get("commanded_mm")) for o in objs])
    meas = np.array([_pin_values(o.get("measured_mm")) for o in objs])
    safe = np.array([o.get("safe_reason") is not None for o in objs])
    # no sample for 2.5 sample periods: nothing is known then, no line is drawn across
    # (recordings made before the safe state was sampled have such gaps while safe)
    steps = np.diff(tt)
    period = float(np.median(steps[steps > 0])) if (steps > 0).any() else 0.0
    gaps = np.flatnonzero(steps > 2.5 * period) + 1
    t_line = np.insert(tt, gaps, np.nan)
    cmd, meas = np.insert(cmd, gaps, np.nan, axis=0), np.insert(meas, gaps, np.nan, axis=0)
    fig, axes = plt.subplots(1, 4, figsize=(12, 2.8), sharey=True)
    for ax, pin in zip(axes, (0, 5, 10, 15), strict=True):
        ax.plot(t_line, cmd[:, pin], lw=0.8, label="commanded")
        ax.plot(t_line, meas[:, pin], lw=0.8, label="measured")
        if safe.any():
            ax.fill_between(tt, 0, 1, where=safe, step="post", color="tab:red", alpha=0.15,
                            transform=ax.get_xaxis_transform(), label="safe state")
        ax.set(title=f"pin {pin}", xlabel="time (s)")
    axes[0].set_ylabel("height (mm)")
    axes[0].legend(fontsize=7)
    return (_png(fig) + f"<p>{len(gaps)} gaps with no pin sample for over 2.5 sample "
            "periods (not drawn across: unknown then); shaded red: the safe state (no "
            "command on the pins).</p>")


_CSS = ("body{font-family:sans-serif;max-width:1100px;margin:auto;padding:1em}"
        "table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;"
        "padding:2px 6px;font-size:12px;text-align:right}img{max-width:100%}"
        ".warn{color:#a00}")


def write_report(local_path: str | os.PathLike[str], out_path: str | os.PathLike[str], *,
                 truth_path: str | os.PathLike[str] | None = None,
                 remote_path: str | os.PathLike[str] | None = None) -> Path:
    """Write the HTML report of a local station's recording.

    Args:
        local_path: the local station's ``.mcap``.
        out_path: the HTML file to write.
        truth_path: the phantom's ground-truth JSON (:mod:`lab.ground_truth`), if known.
        remote_path: the remote station's ``.mcap`` of the same session, if any.

    Returns:
        ``out_path``.

    Raises:
        InputDataError: an unreadable recording or ground truth.
        ConfigError: matplotlib is missing, or the report cannot be written.
    """
    mcap = read_mcap(local_path)
    rec = recording_from_mcap(mcap)
    ws = _workspace(rec)
    truth = None
    if truth_path is not None:
        try:
            truth = json.loads(Path(truth_path).read_text())
        except (OSError, ValueError) as err:
            raise InputDataError(f"cannot read the ground truth {truth_path}: {err}") from err
        try:  # its structure, checked before anything is drawn from it
            if not isinstance(truth, dict):
                raise InputDataError("not a JSON object")
            score_findings([], truth)
        except (InputDataError, TypeError, ValueError) as err:
            raise InputDataError(f"the ground truth {truth_path} is malformed: {err}") from err
    summary = summarize(mcap)
    parts = [f"<h1>Tele-Touch session report</h1><p>{html.escape(str(mcap.path))}: "
             f"session {html.escape(str(rec.meta.get('session')))}, {summary['messages']} "
             f"messages over {summary['duration_s']:.1f} s, {rec.frames} tactile frames "
             f"accepted, {rec.platform_mm.shape[0]} platform states sent.</p>"]
    if not mcap.complete:
        why = html.escape(str(mcap.stop_reason))
        parts.append(f'<p class="warn">The recording is incomplete ({why}): the station did '
                     "not close it; shown up to its last complete chunk.</p>")
    if mcap.skipped_chunks:
        parts.append(f'<p class="warn">{mcap.skipped_chunks} corrupt chunks of the recording '
                     "were skipped: their messages are missing "
                     f"({html.escape(str(mcap.skipped_reason))}).</p>")
    counts = mcap.end.get("counts", {})
    if counts.get("write_errors") or counts.get("messages_lost"):
        parts.append(f'<p class="warn">The recorder could not write everything: '
                     f"{counts.get('write_errors')} write errors, "
                     f"{counts.get('messages_lost', 'an unknown number of')} messages lost.</p>")
    findings: list[Any] = []
    parts.append("<h2>Maps and findings</h2>")
    try:
        findings = maps_and_findings(rec, ws)[1]
        parts.extend(_map_figures(rec, ws, findings, truth))
    except InputDataError as err:
        parts.append(f'<p class="warn">No maps: {html.escape(str(err))}</p>')
    rows = []
    for i, f in enumerate(findings, 1):
        d = f.to_dict()
        rows.append({"#": i, "x mm": f.center_mm[0], "y mm": f.center_mm[1], "type": f.kind,
                     "confidence": getattr(f, "confidence", None),
                     "radius mm": d.get("equivalent_radius_mm"),
                     "severity rank": d.get("severity_rank"),
                     "stiffness N/mm": d.get("stiffness_n_per_mm")})
    parts.append("<h3>Findings</h3>" + _table(rows))
    if truth is not None:
        score = score_findings(findings, truth)
        loc = score["localization_error_mm"]
        parts.append(
            f"<h3>Against the ground truth</h3><p>{score['tumors_found']} of "
            f"{score['tumors_expected']} tumors found, {score['false_positives']} false "
            f"positives; localization error mean {loc['mean']} mm, max {loc['max']} mm; types "
            f"correct {score['types_correct']} / {score['types_total']}; severity order "
            f"Kendall tau {score['kendall_tau']}.</p>" + _table(score["matches"]))
    else:
        parts.append("<p>No ground truth given (<code>--truth</code>): findings not scored.</p>")
    parts.append("<h2>Latency ledger</h2>")
    for path in (local_path, remote_path):
        if path is None:
            continue
        one = mcap if path == local_path else read_mcap(path)
        fig_html, lat_rows = _latency_figure(one)
        parts.append(f"<h3>{html.escape(one.station)} station</h3>" + fig_html
                     + _table(lat_rows))
    parts.append("<h2>Pins</h2>" + _pins_figure(mcap))
    parts.append("<h2>Streams</h2>" + _table(
        [{"topic": k, **v} for k, v in summary["streams"].items()]))
    text = ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>Tele-Touch report"
            f"</title><style>{_CSS}</style></head><body>{''.join(parts)}</body></html>")
    out = Path(out_path)
    try:
        out.write_text(text)
    except OSError as err:
        raise ConfigError(f"cannot write the report {out}: {err}") from err
    return out

"""The plotted run report: ``report.html`` with figures of a ``vigs run`` output folder, or of several estimates
against one ground truth (``vigs eval GT EST... --html``), so a run can be looked at before its numbers are read.

Figures, each left out with a line saying why when its data is missing:

* trajectory, top view (x-y) and side view (x-z): the estimate aligned onto the ground truth and coloured by its
  translation error (several runs: one colour each), the ground truth dashed;
* ATE over time (needs ground truth);
* scale estimates, gyro and accelerometer biases and speed over time (a visual-inertial ``vigs run``:
  report.json's ``vio.scale_history`` and ``vio.keyframe_states``, velocity.txt);
* time per frame of each stage (report.json's ``timings_s`` / ``frames``);
* keyframes marked on the trajectory, with the accepted loop closures (report.json's ``loop.accepted_pairs``,
  keyframe indices) drawn as edges between keyframe positions.

A table gives each run's metrics (:func:`vigs_core.eval.evaluate_trajectory`, the numbers ``vigs eval`` prints).
An estimate's sidecars are read from its folder, the layout ``vigs run`` writes: ``keyframes.txt``,
``report.json``, ``velocity.txt``.

The figures are PNG files in ``<page stem>_figures/`` beside the page (``report_figures/`` for report.html), drawn
with matplotlib's Agg canvas (no pyplot, no display, no global backend switch). PNG files rather than inline SVG:
a trajectory coloured segment by segment is one SVG element per pose (megabytes for a long run, slow to draw in a
browser) but a PNG of tens of KiB whatever the length, and a file can be reused as it is (the README shows one).
The page refers to them by relative paths, so the output folder moves as a whole.
"""
from __future__ import annotations

import html
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence
from urllib.parse import quote

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from vigs_core.eval.association import associate
from vigs_core.eval.report import AlignedEstimate, align_estimate, evaluate_trajectory, recall_key
from vigs_core.io import read_trajectory, read_tum
from vigs_core.io.text_table import data_lines
from vigs_core.types import Trajectory

_KEYFRAME_MAX_DIFF_NS = 1_000_000   # keyframe stamps are frame stamps: paired with the trajectory within 1 ms


@dataclass
class ReportConfig:
    """Settings of the plotted report.

    Attributes:
        align: alignment of each estimate onto the ground truth before it is plotted and scored, one of
            :data:`vigs_core.eval.ALIGN_MODES` (default ``"sim3"``, as report.json's ``accuracy``).
        max_diff_s: largest stamp difference (s) paired with the ground truth (default 0.02, as ``vigs eval``).
        recall: recall thresholds (m) of the metrics table (default 0.05 and 0.10, as report.json).
        width_in: figure width in inches (default 9).
        dpi: figure resolution (default 100: a 9-inch figure is 900 pixels wide).
    """

    align: str = "sim3"
    max_diff_s: float = 0.02
    recall: tuple[float, ...] = (0.05, 0.10)
    width_in: float = 9.0
    dpi: int = 100


@dataclass
class RunOutputs:
    """One estimated trajectory and what its folder holds beside it (:func:`load_run`).

    Attributes:
        label: its name in legends and the metrics table.
        trajectory: the estimated poses.
        keyframe_t_ns: (K,) keyframe stamps (``keyframes.txt``), or None.
        report: ``report.json`` of the run (``vigs run``), or None.
        velocity: ``(t_s (N,), v (N, 3))`` body velocities in the world (``velocity.txt``), or None.
    """

    label: str
    trajectory: Trajectory
    keyframe_t_ns: np.ndarray | None = None
    report: dict | None = None
    velocity: tuple[np.ndarray, np.ndarray] | None = None


def load_run(trajectory_path: str | Path, label: str | None = None) -> RunOutputs:
    """An estimate (TUM or EuRoC CSV) with ``keyframes.txt``, ``report.json`` (or the frontend node's
    ``frontend_report.json``, which has the same ``frames``, ``timings_s`` and ``vio``) and ``velocity.txt`` from
    its folder where present; ``label`` defaults to the path."""
    path = Path(trajectory_path)
    folder = path.parent
    keyframes = folder / "keyframes.txt"
    report = folder / "report.json"
    if not report.is_file():
        report = folder / "frontend_report.json"
    velocity = None
    if _has_rows(folder / "velocity.txt"):
        rows = np.loadtxt(folder / "velocity.txt", ndmin=2)
        velocity = (rows[:, 0], rows[:, 1:4])
    return RunOutputs(label or str(path), read_trajectory(path),
                      read_tum(keyframes).t_ns if _has_rows(keyframes) else None,
                      json.loads(report.read_text()) if report.is_file() else None, velocity)


def _has_rows(path: Path) -> bool:
    """The file exists and has a data row (a run too short for a keyframe writes an empty keyframes.txt)."""
    return path.is_file() and next(data_lines(path), None) is not None


@dataclass
class _Scored:
    """A run placed for plotting: positions in the ground truth's frame when it could be aligned."""

    run: RunOutputs
    positions: np.ndarray                 # (N, 3) the whole estimate, aligned when ``pairs`` is set
    pairs: AlignedEstimate | None = None
    metrics: dict | None = None           # evaluate_trajectory's result
    why_unscored: str | None = None


def _score(run: RunOutputs, gt: Trajectory | None, cfg: ReportConfig) -> _Scored:
    if gt is None:
        return _Scored(run, run.trajectory.position, why_unscored="no ground truth")
    if not len(gt):
        return _Scored(run, run.trajectory.position, why_unscored="no ground-truth pose in the run's time span")
    try:   # the table's numbers are vigs eval's own; the pairs' errors are drawn
        metrics = evaluate_trajectory(gt, run.trajectory, cfg.align, cfg.recall, cfg.max_diff_s)
        pairs = align_estimate(gt, run.trajectory, cfg.align, cfg.max_diff_s)
    except ValueError as err:   # no overlap, too few poses, a motion that leaves the alignment undetermined
        return _Scored(run, run.trajectory.position, why_unscored=str(err))
    return _Scored(run, pairs.alignment.apply_positions(run.trajectory.position), pairs, metrics)


def _keyframe_positions(s: _Scored) -> tuple[np.ndarray, np.ndarray]:
    """Keyframe indices (into keyframes.txt) and their positions, read off the plotted trajectory."""
    i_traj, i_kf = associate(s.run.trajectory.t_ns, s.run.keyframe_t_ns, _KEYFRAME_MAX_DIFF_NS)
    order = np.argsort(i_kf)
    return i_kf[order], s.positions[i_traj[order]]


class _Page:
    """Figures and notes in page order; figures are written to ``folder`` as they come."""

    def __init__(self, folder: Path, cfg: ReportConfig) -> None:
        self.folder, self.cfg = folder, cfg
        self.items: list[tuple[str, str, str | None]] = []   # (title, caption or why left out, PNG name or None)

    def figure(self, rows: int, cols: int, height_in: float, sharex: bool = False):
        fig = Figure(figsize=(self.cfg.width_in, height_in), layout="constrained")
        FigureCanvasAgg(fig)
        return fig, fig.subplots(rows, cols, squeeze=False, sharex=sharex)

    def add(self, name: str, title: str, caption: str, fig) -> None:
        fig.savefig(self.folder / f"{name}.png", dpi=self.cfg.dpi)
        self.items.append((title, caption, f"{name}.png"))

    def omit(self, title: str, why: str) -> None:
        self.items.append((title, why, None))


def _colours(n: int) -> list:
    return [colormaps["tab10"](k % 10) for k in range(n)]


def _plot_trajectories(page: _Page, scored: list[_Scored], gt: Trajectory | None) -> None:
    drawn = [s for s in scored if len(s.positions)]
    if not drawn:
        page.omit("Trajectory", "left out: no estimate has a posed frame")
        return
    fig, axes = page.figure(1, 2, 0.5 * page.cfg.width_in)
    single = len(drawn) == 1 and drawn[0].pairs is not None and len(drawn[0].pairs.i_est) >= 2
    for ax, (a, b), view in zip(axes[0], ((0, 1), (0, 2)), ("top view", "side view")):
        if gt is not None:
            ax.plot(gt.position[:, a], gt.position[:, b], "--", color="0.3", lw=1, label="ground truth")
        for s, colour in zip(drawn, _colours(len(drawn))):
            p = s.positions
            if single:   # one run: coloured by its translation error
                q = p[s.pairs.i_est]
                ax.plot(p[:, a], p[:, b], color="0.75", lw=0.8)
                err = 0.5 * (s.pairs.errors[1:] + s.pairs.errors[:-1])
                lines = LineCollection(np.stack((q[:-1, [a, b]], q[1:, [a, b]]), axis=1), array=err,
                                       cmap="plasma", lw=2, label=s.run.label)
                ax.add_collection(lines)
            else:
                ax.plot(p[:, a], p[:, b], color=colour, lw=1.2, label=s.run.label)
            ax.plot(p[0, a], p[0, b], "o", color="k" if single else colour, ms=4)
        ax.autoscale()
        ax.set_aspect("equal", adjustable="datalim")
        ax.set(title=view, xlabel="x [m]", ylabel=("y" if b == 1 else "z") + " [m]")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize="small", loc="best")
    if single:
        fig.colorbar(lines, ax=axes[0].tolist(), label="translation error [m]", shrink=0.8)
    if gt is None:
        caption = "No ground truth: each estimate in its own world frame (z is up only once a run is metric)."
    else:
        caption = (f"Estimates aligned onto the ground truth ({page.cfg.align}); "
                   + ("coloured by the translation error of each pose." if single else "one colour per run.")
                   + " The dot marks the start.")
        caption += "".join(f" {s.run.label}: not aligned ({s.why_unscored})." for s in drawn if s.pairs is None)
    page.add("trajectory", "Trajectory", caption, fig)


def _plot_ate(page: _Page, scored: list[_Scored], t0_ns: int) -> None:
    title = "ATE over time"
    with_gt = [s for s in scored if s.pairs is not None]
    if not with_gt:
        why = {s.why_unscored for s in scored}
        page.omit(title, "left out: " + "; ".join(sorted(why)))
        return
    fig, axes = page.figure(1, 1, 0.35 * page.cfg.width_in)
    ax = axes[0, 0]
    for s, colour in zip(scored, _colours(len(scored))):
        if s.pairs is None:
            continue
        t = (s.run.trajectory.t_ns[s.pairs.i_est] - t0_ns) * 1e-9
        ax.plot(t, s.pairs.errors, color=colour, lw=1, label=f"{s.run.label} (RMSE {s.metrics['ate_rmse']:.4f} m)")
    ax.set(xlabel="time [s]", ylabel="translation error [m]")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    page.add("ate", title, f"Translation error of each pose after the {page.cfg.align} alignment.", fig)


def _plot_vio_states(page: _Page, scored: list[_Scored], t0_ns: int) -> None:
    title = "Scale, biases and speed"
    vio = [(s, (s.run.report or {}).get("vio")) for s in scored]
    vio = [(s, v, colour) for (s, v), colour in zip(vio, _colours(len(scored))) if v and "keyframe_states" in v]
    if not vio:
        page.omit(title, "left out: no visual-inertial state (report.json of a vigs run with the IMU, beside the "
                         "estimate, has vio.keyframe_states)")
        return
    fig, axes = page.figure(4, 1, 0.8 * page.cfg.width_in, sharex=True)
    axes = axes[:, 0]
    single = len(vio) == 1
    axis_colours = _colours(3)
    for s, v, colour in vio:
        prefix = "" if single else f"{s.run.label} "
        for stage, marker in (("aligned", "o"), ("joint_unaligned", "s"), ("scale_check", "^")):
            h = [e for e in v.get("scale_history", []) if e["stage"] == stage]
            if h:
                axes[0].plot([(e["t_ns"] - t0_ns) * 1e-9 for e in h], [e["scale"] for e in h], marker, ls="none",
                             color=colour, label=prefix + stage)
        states = v["keyframe_states"]
        t = (np.asarray(states["t_ns"], dtype=np.int64) - t0_ns) * 1e-9
        for ax, key in ((axes[1], "bias_gyro"), (axes[2], "bias_acc")):
            values = np.asarray(states[key], dtype=np.float64).reshape(-1, 3)
            for k, (name, style) in enumerate(zip("xyz", ("-", "--", ":"))):
                if single:
                    ax.plot(t, values[:, k], color=axis_colours[k], lw=1, label=name)
                else:   # colour: the run; line style: the axis (caption)
                    ax.plot(t, values[:, k], style, color=colour, lw=1, label=None if k else s.run.label)
        if s.run.velocity is not None:
            tv, vel = s.run.velocity
            axes[3].plot(tv - t0_ns * 1e-9, np.linalg.norm(vel, axis=1), color=colour, lw=1,
                         label=prefix + "speed")
    axes[0].set_yscale("log")
    for ax, label in zip(axes, ("scale", "gyro bias [rad/s]", "acc bias [m/s²]", "speed [m/s]")):
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if ax.has_data():
            ax.legend(fontsize="x-small", ncol=3, loc="best")
    axes[-1].set_xlabel("time [s]")
    caption = ("Scale: the vision-to-metric factor at each alignment (aligned), the joint stage's estimate, and the "
               "IMU's check of the metric map (scale_check, 1 = held). Biases at each keyframe; speed of every "
               "frame (velocity.txt, none before the IMU is initialised).")
    if not single:
        caption += " Biases: solid x, dashed y, dotted z."
    page.add("vio_states", title, caption, fig)


def _plot_stage_times(page: _Page, scored: list[_Scored]) -> None:
    title = "Time per frame by stage"
    timed = [(s, colour) for s, colour in zip(scored, _colours(len(scored)))
             if (s.run.report or {}).get("timings_s") and (s.run.report or {}).get("frames")]
    if not timed:
        page.omit(title, "left out: no report.json of a vigs run beside the estimate (timings_s, frames)")
        return
    stages = list(dict.fromkeys(k for s, _ in timed for k in s.run.report["timings_s"]))
    fig, axes = page.figure(1, 1, 1.2 + 0.3 * len(stages))
    ax = axes[0, 0]
    height = 0.8 / len(timed)
    y = np.arange(len(stages))
    for k, (s, colour) in enumerate(timed):
        r = s.run.report
        ms = [1e3 * r["timings_s"].get(stage, 0.0) / r["frames"] for stage in stages]
        ax.barh(y + (k - (len(timed) - 1) / 2) * height, ms, height, color=colour,
                label=f"{s.run.label} ({r['frames']} frames, {r.get('frames_per_s')} frames/s)")
    ax.set_yticks(y, stages)
    ax.invert_yaxis()
    ax.set_xlabel("ms per frame")
    ax.grid(alpha=0.3, axis="x")
    ax.legend(fontsize="small")
    page.add("stage_times", title, "Seconds spent in each stage over the run divided by the frames processed. "
             "input_reader_thread runs on its own thread, beside the others; input_wait is the time tracking "
             "waited for it.", fig)


def _plot_keyframes(page: _Page, scored: list[_Scored]) -> None:
    title = "Keyframes and loop closures"
    with_kf = [(s, colour) for s, colour in zip(scored, _colours(len(scored)))
               if s.run.keyframe_t_ns is not None and len(s.positions)]
    if not with_kf:
        page.omit(title, "left out: no keyframes.txt beside the estimate")
        return
    fig, axes = page.figure(1, 1, 0.5 * page.cfg.width_in)
    ax = axes[0, 0]
    notes = []
    for s, colour in with_kf:
        index, p = _keyframe_positions(s)
        at = dict(zip(index.tolist(), p))
        ax.plot(s.positions[:, 0], s.positions[:, 1], color=colour, lw=0.8, alpha=0.5)
        ax.plot(p[:, 0], p[:, 1], "o", color=colour, ms=3.5, label=f"{s.run.label}: {len(p)} keyframes")
        if len(with_kf) == 1:
            for k in range(0, len(p), max(1, len(p) // 15)):
                ax.annotate(str(index[k]), p[k, :2], fontsize=7, xytext=(3, 3), textcoords="offset points")
        loop = (s.run.report or {}).get("loop")
        if loop is None:
            notes.append(f"{s.run.label}: no loop closure report")
            continue
        pairs = [(a, b) for a, b in loop.get("accepted_pairs", []) if a in at and b in at]
        for a, b in pairs:
            ax.plot([at[a][0], at[b][0]], [at[a][1], at[b][1]], "-", color="red", lw=1.5)
            ax.annotate(f"{a}-{b}", 0.5 * (at[a][:2] + at[b][:2]), fontsize=7, color="red")
        notes.append(f"{s.run.label}: {len(pairs)} loop closures accepted")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(xlabel="x [m]", ylabel="y [m]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    caption = ("Top view; keyframes at their final poses (numbers: keyframe index, the row of keyframes.txt), "
               "accepted loop closures as red edges. " + "; ".join(notes) + ".")
    page.add("keyframes", title, caption, fig)


def _metrics_table(scored: list[_Scored], cfg: ReportConfig) -> str:
    columns = ["run", "frames", "keyframes", "frames/s", "loops", "ATE RMSE [m]", "ATE mean [m]", "ATE max [m]",
               "scale", *(recall_key(t) for t in cfg.recall), "matched / est"]
    rows = []
    for s in scored:
        r, m = s.run.report or {}, s.metrics or {}
        kf = len(s.run.keyframe_t_ns) if s.run.keyframe_t_ns is not None else None
        cells = [s.run.label, r.get("frames", len(s.run.trajectory)), kf, r.get("frames_per_s"),
                 (r.get("loop") or {}).get("loops_found"),
                 *(m.get(k) for k in ("ate_rmse", "ate_mean", "ate_max", "scale")),
                 *(m.get(recall_key(t)) for t in cfg.recall),
                 f"{m['n_matched']} / {m['n_est']}" if m else None]
        rows.append("<tr>" + "".join(f"<td>{_cell(c)}</td>" for c in cells) + "</tr>")
    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    return f"<table>\n<tr>{head}</tr>\n" + "\n".join(rows) + "\n</table>"


def _cell(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return html.escape(str(value))


def _run_notes(scored: list[_Scored]) -> list[str]:
    notes = []
    for s in scored:
        r = s.run.report or {}
        if r.get("partial"):
            notes.append(f"{s.run.label}: a checkpoint of a run still going or killed (report.json partial)")
        if r.get("interrupted"):
            notes.append(f"{s.run.label}: interrupted ({r['interrupted']}) after {r.get('frames')} frames: "
                         "the figures show what was computed")
        if r.get("error"):
            notes.append(f"{s.run.label}: the run ended with an error: {r['error']}")
        if s.metrics is None and s.why_unscored != "no ground truth":
            notes.append(f"{s.run.label}: not scored: {s.why_unscored}")
    return notes


def write_report(runs: Sequence[RunOutputs], html_path: str | Path, groundtruth: Trajectory | None = None,
                 config: ReportConfig | None = None, title: str = "VIGS run report") -> Path:
    """Write the page ``html_path`` and its figures (``<stem>_figures/*.png``, stale PNGs there removed) for
    ``runs`` against ``groundtruth`` (None: the figures that need it are left out, saying so).

    Returns:
        The page's path.
    """
    cfg = config or ReportConfig()
    html_path = Path(html_path)
    folder = html_path.with_name(f"{html_path.stem}_figures")
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("*.png"):
        old.unlink()
    scored = [_score(run, groundtruth, cfg) for run in runs]
    starts = [int(s.run.trajectory.t_ns[0]) for s in scored if len(s.run.trajectory)]
    t0_ns = int(groundtruth.t_ns[0]) if groundtruth is not None and len(groundtruth) else min(starts, default=0)
    page = _Page(folder, cfg)
    _plot_trajectories(page, scored, groundtruth)
    _plot_ate(page, scored, t0_ns)
    _plot_keyframes(page, scored)
    _plot_vio_states(page, scored, t0_ns)
    _plot_stage_times(page, scored)

    body = [f"<h1>{html.escape(title)}</h1>"]
    body += [f'<p class="note">{html.escape(n)}</p>' for n in _run_notes(scored)]
    body += ["<h2>Metrics</h2>", _metrics_table(scored, cfg)]
    if groundtruth is None:
        body.append('<p class="note">No ground truth: no accuracy, and the figures that need it are left out.</p>')
    for item_title, text, png in page.items:
        body.append(f"<h2>{html.escape(item_title)}</h2>")
        if png is None:
            body.append(f'<p class="omitted">{html.escape(item_title)}: {html.escape(text)}</p>')
        else:
            src = quote(f"{folder.name}/{png}")
            body.append(f'<figure><img src="{html.escape(src)}" alt="{html.escape(item_title)}">'
                        f"<figcaption>{html.escape(text)}</figcaption></figure>")
    page_text = (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{html.escape(title)}</title>\n<style>\n"
        "body { font-family: sans-serif; margin: 2em auto; max-width: 960px; padding: 0 1em; }\n"
        "table { border-collapse: collapse; font-size: 0.85em; display: block; overflow-x: auto; }\n"
        "th, td { border: 1px solid #ccc; padding: 2px 8px; text-align: right; }\n"
        "td:first-child { text-align: left; }\n"
        "img { max-width: 100%; }\nfigcaption { color: #444; font-size: 0.9em; }\n"
        ".omitted { color: #a33; }\n.note { color: #555; }\n"
        "</style>\n</head>\n<body>\n" + "\n".join(body) + "\n</body>\n</html>\n")
    tmp = html_path.with_name(html_path.name + ".tmp")
    tmp.write_text(page_text, encoding="utf-8")
    os.replace(tmp, html_path)
    return html_path


def write_run_report(out_dir: str | Path, groundtruth: Trajectory | None = None,
                     trajectory: str = "trajectory.txt", config: ReportConfig | None = None) -> Path:
    """``report.html`` of a ``vigs run`` output folder, beside its report.json.

    Args:
        out_dir: the run's output folder.
        groundtruth: the reference the run was scored against (``vigs run`` passes the ground truth at the frame
            times, in the frame of ``trajectory``), or None.
        trajectory: the estimate to plot: ``trajectory.txt`` (body poses) or ``trajectory_cam.txt`` (camera
            poses, what a run that is not metric is scored on).
        config: plot settings (defaults: those of report.json's ``accuracy``).
    """
    out = Path(out_dir)
    run = load_run(out / trajectory)
    run.label = (run.report or {}).get("sequence") or out.name
    return write_report([run], out / "report.html", groundtruth, config, title=f"vigs run {run.label}")

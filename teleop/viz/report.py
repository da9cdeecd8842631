"""A report for people who read rather than click: the paper's figures from a recording.

``teleop report out.rrd`` reads the ``.rrd`` back (teleop.viz.rrd, no viewer) and writes PNG
figures and a short markdown summary into ``<recording stem>_report/`` next to it:

- path following (paper experiment 1): Fig. 7 stroboscopic arm, Fig. 8 desired vs
  actual tool path per axis, Fig. 9 distance to the path;
- teleoperation (experiment 2): Fig. 7 (the arm along the task), Fig. 12 operator
  reference vs actual tool velocity, Fig. 13 control error, the feedback forces, the
  passivity observer's energy;
- both: loop rates and per-hop latency.

Only figures whose data the recording holds are drawn. A recording of several robots
gets a report per robot, in ``<stem>_report/<robot id>/``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only, never a window

import matplotlib.pyplot as plt  # noqa: E402  (after the backend choice)
import numpy as np  # noqa: E402

from teleop.bus.messages import Stage  # noqa: E402
from teleop.core import markdown  # noqa: E402
from teleop.core.criteria import judge_summary  # noqa: E402
from teleop.core.rundir import REPORT_SUMMARY_FILE, RUN_SUMMARY_FILE, report_dir  # noqa: E402
from teleop.core.summary import RunSummary, read_run_summary  # noqa: E402
from teleop.viz import entities as r  # noqa: E402
from teleop.viz import rrd  # noqa: E402
from teleop.viz.scene3d import ENTITY_GHOSTS, GHOST_SKELETON  # noqa: E402

DPI = 130  # PNG resolution (dots per inch)
FIG_SIZE_WIDE_IN = (8.0, 4.0)  # one time-series panel (inches)
FIG_SIZE_AXES_IN = (8.0, 6.5)  # three stacked per-axis panels
FIG_SIZE_TIMING_IN = (10.0, 7.5)  # rates over hops, with room for the hop names
FIG_SIZE_3D_IN = (9.0, 6.5)
# Path error is measured after the arm has converged (the run's settle time, default 10 s).
DEFAULT_SETTLE_S = 10.0
M_TO_MM = 1e3
DESIRED_STYLE = {"color": "tab:red", "linestyle": "--", "linewidth": 1.4}
ACTUAL_STYLE = {"color": "tab:blue", "linewidth": 1.0}
AXIS_COLORS = {"x": "tab:red", "y": "tab:green", "z": "tab:blue"}
FORCE_COLORS = {name: tuple(c / 255 for c in rgb) for name, rgb in r.FORCE_ARROW_COLORS.items()}
# The workspace wall's force is the device's own (device frame, no world arrow): a colour
# of its own here, apart from the arm's limits' grey.
FORCE_COLORS["workspace"] = (0.15, 0.65, 0.75)
LATENCY_PERCENTILES = (50.0, 99.0)
FIG7_MAX_POSES = 8  # ghost poses drawn in the stroboscopic figure (more would clutter it)
# A ghost pose is drawn only if its tool tip is this far from every pose drawn before
# (m): an arm that waits (dwell, lockstep pauses) would stack identical poses.
FIG7_MIN_TIP_SPACING_M = 0.04


@dataclass
class Report:
    """What :func:`write_reports` produced for one robot: the directory, the figures,
    the summary."""

    out_dir: Path
    figures: list[Path] = field(default_factory=list)
    summary: Path | None = None
    metrics: dict[str, Any] = field(default_factory=dict)


def default_out_dir(rrd_path: Path) -> Path:
    """``<dir>/<stem>_report`` next to the recording (teleop.core.rundir.report_dir)."""
    return report_dir(rrd_path)


def _save(fig: plt.Figure, path: Path, report: Report) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    report.figures.append(path)


def _start_s(series: Mapping[str, rrd.Series]) -> float:
    """First sim time of the run (s): figures start at 0 s like the paper's."""
    starts = [s.t_ns[0] for s in series.values() if s.t_ns.size]
    return min(starts) * 1e-9 if starts else 0.0


def _per_axis_figure(
    sim: Mapping[str, rrd.Series],
    report: Report,
    t0: float,
    reference: tuple[str, str],
    actual: tuple[str, str],
    ylabel: str,
    title: str,
    file_name: str,
) -> None:
    """Reference vs actual, one panel per world axis (Figs. 8 and 12).

    ``reference`` and ``actual`` are (entity base, legend label with ``{axis}``);
    ``ylabel`` has ``{axis}`` too.
    """
    fig, axes = plt.subplots(3, 1, sharex=True, figsize=FIG_SIZE_AXES_IN)
    for ax, axis in zip(axes, r.AXES, strict=True):
        for (base, label), style in ((reference, DESIRED_STYLE), (actual, ACTUAL_STYLE)):
            series = sim[r.axis_entity(base, axis)]
            ax.plot(series.t_s - t0, series.values, label=label.format(axis=axis), **style)
        ax.set_ylabel(ylabel.format(axis=axis))
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    axes[0].set_title(title)
    axes[-1].set_xlabel("time (s)")
    _save(fig, report.out_dir / file_name, report)


def _fig_paths_xyz(sim: Mapping[str, rrd.Series], report: Report, t0: float) -> None:
    """Fig. 8: desired vs actual tool position, one panel per axis."""
    _per_axis_figure(
        sim, report, t0,
        (r.ENTITY_DESIRED_P, "desired {axis}_d"), (r.ENTITY_TOOL_P, "actual {axis}"),
        "{axis} (m)", "Fig. 8: desired and actual tool path, world frame",
        "fig8_desired_vs_actual_path.png",
    )  # fmt: skip


def _fig_path_error(
    sim: Mapping[str, rrd.Series], report: Report, t0: float, settle_s: float
) -> None:
    """Fig. 9: distance from the tool to the closest point of the path."""
    error = sim[r.ENTITY_PATH_ERROR]
    t = error.t_s - t0
    fig, ax = plt.subplots(figsize=FIG_SIZE_WIDE_IN)
    ax.plot(t, error.values * M_TO_MM, color="tab:blue", linewidth=1.0, label="|h~| (mm)")
    ax.axvline(settle_s, color="0.5", linestyle=":", label=f"settle time {settle_s:g} s")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("path error (mm)")
    ax.set_title("Fig. 9: distance from the tool to the desired path")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    settled = error.values[t >= settle_s]
    if settled.size:
        # The converged error is tiny next to the start-up transient: show it in an inset.
        inset = ax.inset_axes((0.45, 0.35, 0.5, 0.4))
        inset.plot(t[t >= settle_s], settled * M_TO_MM, color="tab:blue", linewidth=0.8)
        inset.set_title("after settling", fontsize=8)
        inset.tick_params(labelsize=7)
        inset.grid(True, alpha=0.3)
        report.metrics["path_error_rms_mm"] = float(np.sqrt(np.mean(settled**2)) * M_TO_MM)
        report.metrics["path_error_max_mm"] = float(settled.max() * M_TO_MM)
    _save(fig, report.out_dir / "fig9_path_error.png", report)


def _fig_velocity(sim: Mapping[str, rrd.Series], report: Report, t0: float) -> None:
    """Fig. 12: the operator's reference velocity vs the actual tool velocity, per axis."""
    _per_axis_figure(
        sim, report, t0,
        (r.ENTITY_TELEOP_V_REF, "reference v_{axis},ref"),
        (r.ENTITY_TELEOP_V_TOOL, "actual v_{axis}"),
        "v_{axis} (m/s)", "Fig. 12: operator reference vs actual tool velocity, world frame",
        "fig12_reference_vs_actual_velocity.png",
    )  # fmt: skip


def _fig_control_error(sim: Mapping[str, rrd.Series], report: Report, t0: float) -> None:
    """Fig. 13: control error v_ref - v_tool per axis, converging to zero."""
    fig, ax = plt.subplots(figsize=FIG_SIZE_WIDE_IN)
    squares = []
    for axis in r.AXES:
        error = sim[r.axis_entity(r.ENTITY_TELEOP_V_ERROR, axis)]
        ax.plot(
            error.t_s - t0,
            error.values,
            color=AXIS_COLORS[axis],
            linewidth=0.9,
            label=f"v~_{axis}",
        )
        squares.append(error.values**2)
    ax.axhline(0.0, color="0.3", linewidth=0.6)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("control error (m/s)")
    ax.set_title("Fig. 13: control error v_ref - v (tool velocity), world frame")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    n = min(len(s) for s in squares)
    report.metrics["status_velocity_error_rms_m_s"] = float(
        np.sqrt(np.mean(np.sum([s[:n] for s in squares], axis=0)))
    )
    _save(fig, report.out_dir / "fig13_control_error.png", report)


def _fig_forces(sim: Mapping[str, rrd.Series], report: Report, t0: float) -> None:
    """The feedback force components the operator felt, as norms."""
    fig, ax = plt.subplots(figsize=FIG_SIZE_WIDE_IN)
    for component in r.FEEDBACK_COMPONENTS:
        entity = r.norm_entity(component)
        if entity not in sim:
            continue
        series = sim[entity]
        color = FORCE_COLORS.get(component, (0.5, 0.5, 0.5))
        label = "device (total rendered)" if component == "device" else component
        ax.plot(series.t_s - t0, series.values, color=color, linewidth=1.0, label=label)
        report.metrics[f"max_{component}_feedback_force_n"] = float(series.values.max())
    ax.set_xlabel("time (s)")
    ax.set_ylabel("|F| (N)")
    ax.set_title("Force feedback: components and the force rendered on the device")
    ax.grid(True, alpha=0.3)
    # Beside the panel: inside it the legend covers the held weight's level.
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    _save(fig, report.out_dir / "fig_feedback_forces.png", report)


def _fig_passivity(sim: Mapping[str, rrd.Series], report: Report, t0: float) -> None:
    """The passivity observer's energy over the run (below zero: the force gave the hand
    energy out) and what the stabiliser dissipated (teleop.devices.haptic.passivity)."""
    observed = sim[r.ENTITY_PASSIVITY_OBSERVED]
    fig, ax = plt.subplots(figsize=FIG_SIZE_WIDE_IN)
    ax.plot(observed.t_s - t0, observed.values * 1e3, color="tab:blue", linewidth=1.0,
            label="observed energy W (mJ)")  # fmt: skip
    if r.ENTITY_PASSIVITY_DISSIPATED in sim:
        dissipated = sim[r.ENTITY_PASSIVITY_DISSIPATED]
        ax.plot(dissipated.t_s - t0, dissipated.values * 1e3, color="tab:orange",
                linewidth=1.0, label="dissipated by the stabiliser (mJ)")  # fmt: skip
    ax.axhline(0.0, color="black", linewidth=0.6)
    report.metrics["passivity_observer_min_j"] = min(0.0, float(observed.values.min()))  # W(0) = 0
    ax.set_xlabel("time (s)")
    ax.set_ylabel("energy (mJ)")
    ax.set_title("Passivity of the force channel at the handle (W >= 0: passive)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    _save(fig, report.out_dir / "fig_passivity.png", report)


def _fig_timing(rec: rrd.Recording, report: Report) -> None:
    """Loop rates over the run and the latency of each hop (box plot, ms)."""
    source = rec.scalars(r.TIMELINE_SOURCE)
    rates = {e: s for e, s in source.items() if e.startswith(r.ENTITY_RATES + "/")}
    hops: dict[str, np.ndarray] = {}
    for entity in sorted(rec.entities):
        if entity.startswith(r.ENTITY_LATENCY + "/"):
            _, values, names = rec.multi_series(entity, r.TIMELINE_SOURCE)
            for j, name in enumerate(names):
                column = values[:, j]
                column = column[~np.isnan(column)]
                # A record carries the stamps of the records it answers, so the same hop
                # shows in several streams (the same loops): each hop once, from the
                # stream that saw it most often.
                if column.size > hops.get(name, np.empty(0)).size:
                    hops[name] = column
    if not rates and not hops:
        return
    fig, (ax_rate, ax_hop) = plt.subplots(2, 1, figsize=FIG_SIZE_TIMING_IN)
    t0 = min((s.t_ns[0] for s in rates.values()), default=0) * 1e-9
    for entity, series in sorted(rates.items()):
        # A rate is logged when its window closes and holds over the window before it:
        # steps, not slopes (a recorder that stalled shows one long flat window).
        ax_rate.plot(
            series.t_s - t0,
            series.values,
            drawstyle="steps-pre",
            marker=".",
            markersize=3,
            linewidth=0.9,
            label=entity.split("/")[-1],
        )
    ax_rate.set_yscale("log")
    ax_rate.set_xlabel("wall time (s)")
    ax_rate.set_ylabel("rate (Hz)")
    ax_rate.set_title("Loop rates (records per second of the producer's clock)")
    ax_rate.grid(True, which="both", alpha=0.3)
    # Beside the axes, not over them: the rates span the whole plot.
    ax_rate.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    latency: dict[str, dict[str, float]] = {}
    # In the loop's order (the first stage's index), the first hop at the top.
    names = sorted(hops, key=_hop_order, reverse=True)
    if names:
        data = [hops[n] for n in names]
        ax_hop.boxplot(data, orientation="horizontal", showfliers=False, whis=(1, 99))
        ax_hop.set_yticks(range(1, len(names) + 1), [_hop_label(n) for n in names], fontsize=8)
        ax_hop.set_xlabel("latency (ms), whiskers at p1 and p99")
        ax_hop.set_title("Latency per hop (header trace stamps)")
        ax_hop.grid(True, axis="x", alpha=0.3)
        for name, values in zip(names, data, strict=True):
            p50, p99 = np.percentile(values, LATENCY_PERCENTILES)
            latency[name] = {
                "p50_ms": float(p50),
                "p99_ms": float(p99),
                "samples": int(values.size),
            }
    report.metrics["latency"] = latency
    report.metrics["rates_hz_median"] = {
        e.split("/")[-1]: float(np.median(s.values)) for e, s in sorted(rates.items())
    }
    _save(fig, report.out_dir / "fig_timing.png", report)


def _hop_order(hop: str) -> tuple[int, int]:
    """Sort key of a hop named ``<STAGE>_to_<STAGE>`` (teleop.bus.messages.Stage)."""
    first, _, last = hop.partition("_to_")
    return (Stage[first].value if first in Stage.__members__ else len(Stage),
            Stage[last].value if last in Stage.__members__ else len(Stage))  # fmt: skip


def _hop_label(hop: str) -> str:
    """``HAPTIC_SAMPLE_to_CONTROLLER_RX`` -> ``haptic sample -> controller rx``."""
    first, _, last = hop.partition("_to_")
    return f"{first.replace('_', ' ').lower()} -> {last.replace('_', ' ').lower()}"


def _first_strip(value: Any) -> np.ndarray | None:
    """The first line strip of a LineStrips3D:strips cell, as (N, 3)."""
    while isinstance(value, list) and value and isinstance(value[0], list):
        if value and value[0] and not isinstance(value[0][0], list):
            return np.asarray(value, dtype=float)
        value = value[0]
    return None


def _equal_axes(ax: Any, points: np.ndarray) -> None:
    """Same scale on x, y and z (a circle looks like a circle), around ``points`` (N, 3)."""
    low, high = points.min(axis=0), points.max(axis=0)
    centre, half = 0.5 * (low + high), 0.5 * float((high - low).max())
    for set_lim, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
        set_lim(c - half, c + half)
    ax.set_box_aspect((1.0, 1.0, 1.0))


def _spread_poses(poses: Sequence[tuple[float, np.ndarray]]) -> list[int]:
    """Indices of at most FIG7_MAX_POSES poses, spread over the run, each with its tool
    tip (the strip's last point) at least FIG7_MIN_TIP_SPACING_M from those before."""
    candidates = np.unique(np.linspace(0, len(poses) - 1, 4 * FIG7_MAX_POSES).round())
    picked: list[int] = []
    for index in candidates.astype(int):
        tip = poses[index][1][-1]
        if all(np.linalg.norm(tip - poses[j][1][-1]) >= FIG7_MIN_TIP_SPACING_M for j in picked):
            picked.append(int(index))
    if len(picked) > FIG7_MAX_POSES:
        keep = np.unique(np.linspace(0, len(picked) - 1, FIG7_MAX_POSES).round()).astype(int)
        picked = [picked[k] for k in keep]
    return picked


def _fig_stroboscopic(rec: rrd.Recording, report: Report) -> None:
    """Fig. 7: ghost poses of the arm (links through the joints), the tool's path and the
    desired path; at most FIG7_MAX_POSES poses, evenly spread over the run."""
    entities = sorted(e for e in rec.entities if e.startswith(ENTITY_GHOSTS + "/"))
    skeletons = [e for e in entities if e.endswith("/" + GHOST_SKELETON)]
    if not skeletons:
        return
    data = rec.lists(skeletons)
    poses: list[tuple[float, np.ndarray]] = []
    for entity in skeletons:
        strip = _first_strip(data[entity].get("LineStrips3D:strips", []))
        times = data[entity].get(r.TIMELINE_SIM) or [0]
        if strip is not None:
            poses.append((times[0] * 1e-9, strip))
    picked = _spread_poses(poses)
    fig = plt.figure(figsize=FIG_SIZE_3D_IN)
    ax = fig.add_subplot(projection="3d")
    # Orthographic: links of equal length look equal wherever they are in the box.
    ax.set_proj_type("ortho")
    shades = np.linspace(0.75, 0.05, len(picked))
    drawn = []
    for shade, index in zip(shades, picked, strict=True):
        t_s, strip = poses[index]
        # Times in the legend, not beside the poses: labels at the tool tips collide.
        label = f"arm at {t_s:.1f} s"
        ax.plot(*strip.T, color=str(shade), linewidth=2.5, marker="o", markersize=3, label=label)
        drawn.append(strip)
    desired = rec.column(r.ENTITY_DESIRED_PATH, "LineStrips3D:strips")
    strip = _first_strip(desired.get(r.ENTITY_DESIRED_PATH, []))
    if strip is not None:
        ax.plot(*strip.T, label="desired path", **DESIRED_STYLE)
        drawn.append(strip)
    tool = rec.column(r.ENTITY_TOOL, "Transform3D:translation")
    points = [row[0] for row in tool.get(r.ENTITY_TOOL, []) if row]
    if points:
        tool_p = np.asarray(points, dtype=float)
        ax.plot(*tool_p.T, label="tool path", **ACTUAL_STYLE)
        drawn.append(tool_p)
    ax.scatter([0.0], [0.0], [0.0], color="k", marker="s", s=30, label="arm base")
    _equal_axes(ax, np.vstack([*drawn, np.zeros((1, 3))]))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_title(f"Fig. 7: stroboscopic motion of the arm ({len(picked)} poses, light = early)")
    ax.view_init(elev=22.0, azim=-65.0)
    ax.legend(loc="center left", bbox_to_anchor=(1.02, 0.5), fontsize=8)
    report.metrics["ghost_poses"] = len(poses)
    _save(fig, report.out_dir / "fig7_stroboscopic.png", report)


def _events(rec: rrd.Recording) -> list[str]:
    """Every event-log line (run events and the recorder's), in sim-time order."""
    rows: list[tuple[int, str]] = []
    data = rec.lists((r.ENTITY_EVENTS, r.ENTITY_RECORDER_EVENTS))
    for cols in data.values():
        times = cols.get(r.TIMELINE_SIM, [])
        for t, text in zip(times, cols.get("TextLog:text", []), strict=False):
            rows.append((t or 0, text[0] if isinstance(text, list) else str(text)))
    return [f"{t * 1e-9:8.3f} s  {text}" for t, text in sorted(rows)]


def _stats(rec: rrd.Recording) -> dict[str, Any]:
    docs = rec.column(r.ENTITY_STATS, "TextDocument:text").get(r.ENTITY_STATS, [])
    for doc in docs:
        text = doc[0] if isinstance(doc, list) else doc
        try:
            return dict(json.loads(text))
        except (TypeError, ValueError):
            continue
    return {}


def _segments_text(rec: rrd.Recording) -> list[str]:
    """report.md's section on a recording written in several segments (a recorder that
    restarted): each file, the sim time it covers, and where the record has a gap."""
    if len(rec.segments) < 2:
        return []
    lines = ["## Recording segments (the recorder restarted)", ""]
    for segment in rec.segments:
        span = "no timed data"
        if segment.sim_start_ns is not None and segment.sim_end_ns is not None:
            span = f"sim {segment.sim_start_ns * 1e-9:.3f} s to {segment.sim_end_ns * 1e-9:.3f} s"
        lines.append(f"- {segment.path.name}: {span}")
    for gap in rec.gaps():
        lines.append(
            f"- **gap**: nothing recorded from sim {gap.start_ns * 1e-9:.3f} s to "
            f"{gap.end_ns * 1e-9:.3f} s ({(gap.end_ns - gap.start_ns) * 1e-9:.3f} s, "
            f"after {gap.after.name})"
        )
    return [*lines, ""]


def _summary_text(
    title: str, report: Report, events: Sequence[str], stats: dict, segments: Sequence[str] = ()
) -> str:
    m = report.metrics
    lines = [f"# Run report: {title}", "", *segments]
    if "path_error_rms_mm" in m:
        lines += [
            "## Path following (paper experiment 1)",
            "",
            f"- path error after settling: rms {m['path_error_rms_mm']:.4f} mm, "
            f"max {m['path_error_max_mm']:.4f} mm",
            "",
        ]
    if "status_velocity_error_rms_m_s" in m:
        # Named apart from the run summary's figures: these come from the recording (the
        # controller's 100 Hz status, the forces fed back), not the services' own counts
        # (velocity_tracking_rms_m_s: every 1 kHz cycle; max_contact_force_n: the plant's
        # contact force on the gripper).
        lines += [
            "## Teleoperation (paper experiment 2)",
            "",
            "- status_velocity_error_rms_m_s (v_ref - v in the recorded 100 Hz status, "
            f"whole recording): {m['status_velocity_error_rms_m_s']:.4f} m/s",
        ]
        for component in r.FEEDBACK_COMPONENTS:
            key = f"max_{component}_feedback_force_n"
            if key in m:
                lines.append(f"- {key} (fed back to the operator): {m[key]:.3f} N")
        if "passivity_observer_min_j" in m:
            lines.append(
                "- passivity_observer_min_j (below zero: the force gave energy out): "
                f"{m['passivity_observer_min_j'] * 1e3:.3f} mJ"
            )
        lines.append("")
    if m.get("latency"):
        hops = [
            (hop, f"{v['p50_ms']:.3f}", f"{v['p99_ms']:.3f}", v["samples"])
            for hop, v in m["latency"].items()
        ]
        lines += ["## Latency per hop", ""]
        lines += [*markdown.table(("hop", "p50 (ms)", "p99 (ms)", "samples"), hops, "lrrr"), ""]
    if m.get("rates_hz_median"):
        rates = ", ".join(f"{k} {v:.0f} Hz" for k, v in m["rates_hz_median"].items())
        lines += ["## Loop rates (median)", "", rates, ""]
    if stats:
        lines += [
            "## Recorder",
            "",
            f"- samples logged: {sum(stats.get('samples_logged', {}).values())}, "
            f"dropped (decode) {stats.get('decode_drops', 0)}, "
            f"overflow {sum(stats.get('overflow_drops', {}).values())}, "
            f"Rerun errors {stats.get('rerun_errors', 0)}",
            f"- recorder CPU share: {stats.get('cpu_share', 0.0):.3f} of one core",
            "",
        ]
    lines += ["## Figures", ""]
    lines += [f"![{p.stem}]({p.name})" for p in report.figures]
    lines += ["", "## Events (sim time)", "", "```", *events, "```", ""]
    return "\n".join(lines)


def verdict_text(run_summary: RunSummary) -> list[str]:
    """The report's verdict section: the run's summary judged again by the one verdict
    (teleop.core.criteria.judge_summary, as ``teleop run`` and ``teleop sweep`` judge)."""
    verdict = judge_summary(run_summary)
    lines = [
        "## Verdict",
        "",
        f"- task: {'success' if verdict.success else 'failed'} "
        f"({run_summary.scenario}, judged by teleop.core.criteria)",
        "",
        *markdown.table(
            ("criterion", "status", "detail"),
            [(c.name, c.status, c.detail) for c in verdict.criteria],
        ),
    ]
    lines += ["", *[f"- problem: {problem}" for problem in verdict.problems]]
    return [*lines, ""] if verdict.problems else lines


def write_reports(
    rrd_path: str | Path,
    out_dir: str | Path | None = None,
    settle_s: float = DEFAULT_SETTLE_S,
    run_summary: RunSummary | Mapping[str, object] | None = None,
) -> list[Report]:
    """Read ``rrd_path`` back and write the figures and ``report.md`` of each robot it
    holds: into ``out_dir`` (default: ``<stem>_report/`` beside it) for one robot, into
    ``out_dir/<robot id>/`` each for several. With ``run_summary`` (the run's summary:
    its record, or the JSON a run just made; default: the ``summary.json`` beside the
    recording, if any) each report opens with its robot's verdict. SummaryError if that
    file is no run summary of this version."""
    path = Path(rrd_path)
    if not path.is_file():
        raise FileNotFoundError(f"no recording {path}")
    beside = path.parent / RUN_SUMMARY_FILE
    if run_summary is None and beside.exists():
        run_summary = read_run_summary(beside)
    elif run_summary is not None and not isinstance(run_summary, RunSummary):
        run_summary = RunSummary.from_json(run_summary)
    out = Path(out_dir) if out_dir is not None else default_out_dir(path)
    rec = rrd.Recording(path)
    roots = rec.robots or [""]
    reports = []
    for root in roots:
        section = run_summary
        if root and run_summary is not None and root in (run_summary.robots or {}):
            section = run_summary.section(root)
        own_out = out / root if root else out
        reports.append(_write_report(path, rec.under(root), own_out, settle_s, section, root))
    return reports


def _write_report(
    path: Path,
    rec: rrd.Recording,
    out_dir: Path,
    settle_s: float,
    run_summary: RunSummary | None,
    robot: str,
) -> Report:
    """One robot's report (``rec`` that robot's entities) into ``out_dir``."""
    report = Report(out_dir)
    report.out_dir.mkdir(parents=True, exist_ok=True)
    sim = rec.scalars(r.TIMELINE_SIM)
    t0 = _start_s(sim)
    _fig_stroboscopic(rec, report)
    path_entities = [r.ENTITY_PATH_ERROR, *(r.axis_entity(r.ENTITY_TOOL_P, a) for a in r.AXES)]
    if all(e in sim for e in path_entities):
        _fig_paths_xyz(sim, report, t0)
        _fig_path_error(sim, report, t0, settle_s)
    teleop = [
        r.axis_entity(b, a)
        for b in (r.ENTITY_TELEOP_V_REF, r.ENTITY_TELEOP_V_ERROR)
        for a in r.AXES
    ]
    if all(e in sim for e in teleop):
        _fig_velocity(sim, report, t0)
        _fig_control_error(sim, report, t0)
    if r.norm_entity("device") in sim:
        _fig_forces(sim, report, t0)
    if r.ENTITY_PASSIVITY_OBSERVED in sim:
        _fig_passivity(sim, report, t0)
    _fig_timing(rec, report)
    verdict = verdict_text(run_summary) if run_summary is not None else []
    title = f"{path.name}, robot {robot}" if robot else path.name
    summary = _summary_text(
        title, report, _events(rec), _stats(rec), [*verdict, *_segments_text(rec)]
    )
    report.summary = report.out_dir / REPORT_SUMMARY_FILE
    report.summary.write_text(summary)
    return report

"""The files of a run directory, named in one place.

Every service writes into the run directory it is given (``--run-dir``); the launcher,
the report and the latency tools read from it. Their names live here so that a writer
and its readers cannot disagree.
"""

from __future__ import annotations

from pathlib import Path

# Every service's summary, written atomically when it closes (teleop.bus.service), read
# and merged by the launcher (teleop.run.stack).
SUMMARY_SUFFIX = ".summary.json"
# While it runs, each process of a service also writes its summary so far every few
# seconds to a file of its own, ``<service>.<pid>.incarnation.json``: a process killed
# with SIGKILL writes no summary at close, and its counts would be lost with it. The
# next summary written at close takes them in (and removes the file).
INCARNATION_SUFFIX = ".incarnation.json"
# The recorder's Rerun recording when recorder.rrd_path is empty.
RECORDING_FILE = "recording.rrd"
# A restarted recorder never overwrites: it writes the next segment (segment_path), and
# this ledger in the run directory lists the run's segments and its Rerun recording id.
RECORDER_SEGMENTS_FILE = "recorder.segments.json"
# The plant's checkpoint and per-step progress mark (teleop.sim.checkpoint):
# ``<plant>.checkpoint`` (checkpoint_path); a restarted plant resumes from it, so a new
# run must not find the previous run's.
CHECKPOINT_SUFFIX = ".checkpoint"
# supervisord's own files (teleop.run.supervise): its config, control socket, pid file,
# log, console output (config errors), and the directory of the programs' logs.
SUPERVISOR_CONF_FILE = "supervisord.conf"
SUPERVISOR_SOCKET_FILE = "supervisor.sock"
SUPERVISOR_PID_FILE = "supervisord.pid"
SUPERVISOR_LOG_FILE = "supervisord.log"
SUPERVISOR_CONSOLE_FILE = "supervisord.console.log"
# The command line of each program the launcher runs in its terminal instead of under
# supervisord (a person's keyboard operator): ``<name>.json``, an argv list.
FOREGROUND_DIR = "foreground"
LOG_DIR = "logs"  # one ``<program>.log`` per supervised program (program_log_path)
# The run's credentials (teleop.bus.access): mode 0700, its files 0600.
AUTH_DIR = "auth"
# The log of the web viewer that `teleop run --web` serves.
WEB_VIEWER_LOG_FILE = "web-viewer.log"
# The Rerun recording of `teleop latency`'s figures (in its run directory).
LATENCY_RECORDING_FILE = "latency.rrd"
# A run's whole summary (`teleop run`, unless --summary-json says elsewhere; the sweep's
# tasks), which `teleop report` reads beside the recording for the run's verdict.
RUN_SUMMARY_FILE = "summary.json"
# `teleop report` (teleop.viz.report) and `teleop run --report`: the figures and the
# summary go into ``<recording stem>_report/`` next to the recording.
REPORT_DIR_SUFFIX = "_report"
REPORT_SUMMARY_FILE = "report.md"

# Raw latency files the haptic service writes at exit (read by ``teleop latency``):
# one trace row (N_STAGES stamps) per rendered feedback, one (seq, sample ns) per sample.
HAPTIC_TRACE_FILE = "haptic.trace.npy"
HAPTIC_SAMPLES_FILE = "haptic.samples.npy"
# HAPTIC_SAMPLE stamps of the handle samples a service shed on purpose (behind
# schedule): one column, ``<service>.shed.npy``.
SHED_FILE_SUFFIX = ".shed.npy"


# What a run leaves in its directory (besides supervisord's socket and config, which the
# next start rewrites), removed before the next run there so that nothing stale (a summary
# saying success, a log of another run) survives a run that fails: clear_run_results.
_RUN_RESULT_GLOBS = (
    f"*{SUMMARY_SUFFIX}",
    f"*{INCARNATION_SUFFIX}",
    f"*{SHED_FILE_SUFFIX}",
    "*.status",
    HAPTIC_TRACE_FILE,
    HAPTIC_SAMPLES_FILE,
    RECORDING_FILE,
    "recording.*.rrd",  # its later segments (segment_path)
    RECORDER_SEGMENTS_FILE,
    f"*{CHECKPOINT_SUFFIX}",
    SUPERVISOR_LOG_FILE,
    SUPERVISOR_CONSOLE_FILE,
    WEB_VIEWER_LOG_FILE,
    f"{LOG_DIR}/*.log",
    f"{FOREGROUND_DIR}/*.json",
)


def clear_run_results(run_dir: Path) -> list[Path]:
    """Remove the previous run's results from ``run_dir`` (summaries, logs, recording,
    its report); the files removed. Call only when no stack runs there."""
    run_dir = Path(run_dir)
    removed = [path for pattern in _RUN_RESULT_GLOBS for path in run_dir.glob(pattern)]
    for path in removed:
        path.unlink(missing_ok=True)
    report = report_dir(run_dir / RECORDING_FILE)
    if report.is_dir():  # its files, and each robot's of a run of several
        for path in sorted(report.rglob("*")):
            if path.is_file():
                path.unlink()
                removed.append(path)
    return removed


def segment_path(rrd_path: Path, index: int) -> Path:
    """Segment ``index`` of the recording ``rrd_path``: the path itself for the first
    (0), ``<stem>.<index>.rrd`` beside it for those of restarted recorders."""
    rrd_path = Path(rrd_path)
    if index == 0:
        return rrd_path
    return rrd_path.with_name(f"{rrd_path.stem}.{index}{rrd_path.suffix}")


def segment_paths(rrd_path: Path) -> list[Path]:
    """The segments of the recording ``rrd_path`` on disk, in order: the newest run of
    consecutive ones (the oldest may have been deleted: ``recorder.keep_mb``)."""
    rrd_path = Path(rrd_path)
    indexes = {0} if rrd_path.is_file() else set()
    for path in rrd_path.parent.glob(f"{rrd_path.stem}.*{rrd_path.suffix}"):
        index = path.name[len(rrd_path.stem) + 1 : -len(rrd_path.suffix)]
        if index.isdigit() and int(index) > 0:
            indexes.add(int(index))
    run: list[int] = []
    for index in sorted(indexes, reverse=True):
        if run and index != run[-1] - 1:
            break
        run.append(index)
    return [segment_path(rrd_path, index) for index in reversed(run)]


def checkpoint_path(run_dir: Path, plant: str) -> Path:
    """Where the plant process ``plant`` (``plant``, or one robot's ``plant-<robot>``)
    keeps its checkpoint."""
    return Path(run_dir) / f"{plant}{CHECKPOINT_SUFFIX}"


def shed_path(run_dir: Path, service: str) -> Path:
    """Where ``service`` writes the stamps of the samples it shed."""
    return Path(run_dir) / f"{service}{SHED_FILE_SUFFIX}"


def summary_path(run_dir: Path, service: str) -> Path:
    """Where ``service`` writes its summary when it closes."""
    return Path(run_dir) / f"{service}{SUMMARY_SUFFIX}"


def incarnation_path(run_dir: Path, service: str, pid: int) -> Path:
    """Where process ``pid`` of ``service`` writes its summary so far while it runs."""
    return Path(run_dir) / f"{service}.{pid}{INCARNATION_SUFFIX}"


def incarnation_paths(run_dir: Path, service: str) -> list[Path]:
    """Every process's running summary of ``service`` in ``run_dir``, oldest write first."""
    written: list[tuple[int, Path]] = []
    for path in Path(run_dir).glob(f"{service}.*{INCARNATION_SUFFIX}"):
        if not path.name[len(service) + 1 : -len(INCARNATION_SUFFIX)].isdigit():
            continue
        try:
            written.append((path.stat().st_mtime_ns, path))
        except FileNotFoundError:  # taken in and removed meanwhile
            continue
    return [path for _, path in sorted(written)]


def program_log_path(run_dir: Path, program: str) -> Path:
    """Where supervisord writes the output of ``program`` (a service or an idle poller)."""
    return Path(run_dir) / LOG_DIR / f"{program}.log"


def report_dir(rrd_path: Path) -> Path:
    """The directory of the report of the recording ``rrd_path`` (next to it)."""
    rrd_path = Path(rrd_path)
    return rrd_path.parent / f"{rrd_path.stem}{REPORT_DIR_SUFFIX}"


def idle_poll_status_path(run_dir: Path, cpu: int) -> Path:
    """Where the idle poller of ``cpu`` writes its status ('polling' or why not)."""
    return Path(run_dir) / f"idle_poll_cpu{cpu}.status"

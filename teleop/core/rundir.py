"""The files of a run directory, named in one place.

Every service writes into the run directory it is given (``--run-dir``); the launcher,
the report and the latency tools read from it. Their names live here so that a writer
and its readers cannot disagree.
"""

from __future__ import annotations

from pathlib import Path

# Raw latency files the haptic service writes at exit (read by ``teleop latency``):
# one trace row (N_STAGES stamps) per rendered feedback, one (seq, sample ns) per sample.
HAPTIC_TRACE_FILE = "haptic.trace.npy"
HAPTIC_SAMPLES_FILE = "haptic.samples.npy"
# HAPTIC_SAMPLE stamps of the handle samples a service shed on purpose (behind
# schedule): one column, ``<service>.shed.npy``.
SHED_FILE_SUFFIX = ".shed.npy"


def shed_path(run_dir: Path, service: str) -> Path:
    """Where ``service`` writes the stamps of the samples it shed."""
    return Path(run_dir) / f"{service}{SHED_FILE_SUFFIX}"

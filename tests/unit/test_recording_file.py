"""The recording's file in segments (teleop.viz.recording_file), without a bus."""

from __future__ import annotations

import os

import numpy as np
import rerun as rr

from teleop.core.config import load_config
from teleop.core.rundir import segment_paths
from teleop.viz.blueprint import build_blueprint
from teleop.viz.recording_file import BlueprintSender, RecordingFile, claim_segment
from teleop.viz.rrd import Recording
from tests.rerun_check import rerun_verify_problems

ROTATIONS = 12


def native_threads() -> int:
    return len(os.listdir("/proc/self/task"))


def test_segments_each_get_the_blueprint_and_leave_no_thread_behind(tmp_path):
    """Every segment opens alone with the blueprint, and passes Rerun's check; closing one
    leaves no Rerun stream or thread behind (Rerun's own send_blueprint leaves two
    threads per call)."""
    config = load_config(None, [])
    rrd = tmp_path / "recording.rrd"
    ledger = tmp_path / "segments.json"
    file = RecordingFile(config, claim_segment(rrd, ledger))
    file.open()
    file.log("world", (rr.ViewCoordinates.RIGHT_HAND_Z_UP,), static=True)  # in every segment
    threads_after_first = native_threads()
    for _ in range(ROTATIONS):
        file.rotate(claim_segment(rrd, ledger, after=file.segment))
    file.close()
    assert not file._blueprint.fell_back
    assert native_threads() <= threads_after_first + 2, (threads_after_first, native_threads())
    assert rerun_verify_problems(rrd) == []
    segments = sorted(tmp_path.glob("recording*.rrd"))
    assert len(segments) == ROTATIONS + 1
    assert all(Recording(p, one_segment=True).has_blueprint for p in segments)


def test_the_sender_keeps_one_blueprint_stream(tmp_path):
    sender = BlueprintSender(build_blueprint(load_config(None, [])))
    rec = rr.RecordingStream("t", recording_id="r")
    rec.set_sinks(rr.FileSink(str(tmp_path / "a.rrd"), write_footer=True))
    sender.send(rec)
    before = native_threads()
    for _ in range(ROTATIONS):
        sender.send(rec)
    rec.flush(timeout_sec=10)
    assert native_threads() == before


def test_past_keep_mb_the_oldest_segments_go_and_the_newest_stay_whole(tmp_path):
    config = load_config(None, ["recorder.segment_mb=0.1", "recorder.keep_mb=0.5"])
    rrd = tmp_path / "recording.rrd"
    ledger = tmp_path / "segments.json"
    file = RecordingFile(config, claim_segment(rrd, ledger))
    file.open()
    file.log("world", (rr.ViewCoordinates.RIGHT_HAND_Z_UP,), static=True)  # in every segment
    points = np.random.default_rng(0).random((10_000, 3))
    for k in range(ROTATIONS):
        file.log(f"world/cloud{k}", (rr.Points3D(points),), static=False)
        file.current.flush(timeout_sec=10)
        file.rotate(claim_segment(rrd, ledger, after=file.segment))
    file.close()
    kept = segment_paths(rrd)
    assert file.segments_deleted > 0 and not rrd.exists()  # the first one went
    assert kept[-1] == file.rrd_path and len(kept) == ROTATIONS + 1 - file.segments_deleted
    assert sum(p.stat().st_size for p in kept) <= (0.5 + 0.2) * 1e6
    assert all(Recording(p, one_segment=True).has_blueprint for p in kept)


def test_segment_paths_are_the_newest_consecutive_run(tmp_path):
    rrd = tmp_path / "r.rrd"
    for name in ("r.rrd", "r.2.rrd", "r.4.rrd", "r.5.rrd", "r.x.rrd", "other.6.rrd"):
        (tmp_path / name).write_bytes(b"x")
    assert segment_paths(rrd) == [tmp_path / "r.4.rrd", tmp_path / "r.5.rrd"]
    (tmp_path / "r.4.rrd").unlink()
    (tmp_path / "r.5.rrd").unlink()
    assert segment_paths(rrd) == [tmp_path / "r.2.rrd"]
    assert segment_paths(tmp_path / "none.rrd") == []

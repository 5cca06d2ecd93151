"""Recording format (crash safety, frames), `ddvs record` over Zenoh killed mid-run, analysis and `ddvs plot`."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import free_port

from clients.analysis import images_to_convergence, summarize
from clients.plot import plot_recording
from clients.recording import RecordingWriter, load_recording, read_stream
from ddvs_service.lie import pose, so3_exp
from ddvs_service.protocol import (
    Counters,
    GroundTruth,
    Header,
    Keys,
    Latency,
    SessionConfig,
    Status,
    Time,
    TwistStamped,
    declare_publisher,
    dump,
    encode_twist_stamped,
    open_session,
)

ROOT = Path(__file__).resolve().parents[1]


def _status(seq: int, state: str, norm: float, stamp_ns: int) -> Status:
    return Status(robot="r", state=state, frame_stamp_ns=stamp_ns, seq=seq, error=[norm, 0, 0, 0, 0, 0],
                  error_norm=norm, iterations=3, residual_rms=1.0, inlier_ratio=1.0, twist=[0.1 * norm] * 6,
                  latency_ms=Latency(decode=0.1, registration=seq % 7, control=0.2, publish=0.1, total=seq % 7 + 1),
                  counters=Counters(frames=seq, dropped=0, rejected=0))


def test_writer_and_reader_round_trip_with_frames(tmp_path):
    writer = RecordingWriter(tmp_path / "run", {"note": "x"})
    for i in range(3):
        writer.write("twist", {"recv_ns": i, "stamp_ns": i, "frame_id": "camera", "twist": [i, 0, 0, 0, 0, 0]})
    frame = np.random.default_rng(0).integers(0, 256, (24, 32), dtype=np.uint8)
    writer.write_frame(frame, {"recv_ns": 5, "stamp_ns": 5, "encoding": "mono8"})
    writer.close()
    rec = load_recording(tmp_path / "run")
    assert rec.meta["format"] == "ddvs-recording" and rec.meta["note"] == "x"
    assert [r["twist"][0] for r in rec["twist"]] == [0, 1, 2]
    np.testing.assert_array_equal(rec.frame(0), frame)
    assert rec["status"] == []
    with pytest.raises(FileExistsError, match="not empty"):
        RecordingWriter(tmp_path / "run", {})


def test_torn_last_line_is_skipped_and_a_torn_middle_line_is_an_error(tmp_path):
    path = tmp_path / "s.jsonl"
    path.write_text('{"a": 1}\n{"a": 2}\n{"a": 3, "b"')
    assert read_stream(path) == [{"a": 1}, {"a": 2}]
    path.write_text('{"a": 1}\n{"a": \n{"a": 3}\n')
    with pytest.raises(ValueError, match="line 2"):
        read_stream(path)


def test_killed_recorder_leaves_every_complete_record_readable(tmp_path):
    port = free_port()
    keys = Keys("ddvs", "rectest")
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "ddvs.cli", "record", str(out), "--robot", keys.robot,
           "--listen", f"tcp/127.0.0.1:{port}", "--meta", "stop_threshold=0.001"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    sent = []
    try:
        with open_session(SessionConfig(connect=[f"tcp/127.0.0.1:{port}"])) as session:
            status_pub = declare_publisher(session, keys, "servo_status")
            twist_pub = declare_publisher(session, keys, "servo_twist")
            deadline = time.monotonic() + 20
            while not (out / "meta.json").exists() and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(1.0)  # the recorder's subscriptions reach this session
            for seq in range(200):
                status = _status(seq, "SERVOING", 1.0 / (seq + 1), seq)
                status_pub.put(dump(status))
                twist_pub.put(encode_twist_stamped(TwistStamped(Header(Time.from_ns(seq), "camera"),
                                                                [seq, 0, 0], [0, 0, 0])))
                sent.append(status)
                time.sleep(0.002)
            time.sleep(0.5)
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    rec = load_recording(out)
    assert rec.meta["stop_threshold"] == 0.001
    got = [r["msg"] for r in rec["status"]]
    assert len(got) >= 190, f"only {len(got)} of 200 status records"
    by_seq = {s.seq: json.loads(dump(s)) for s in sent}
    assert all(m == by_seq[m["seq"]] for m in got)
    assert [r["twist"][0] for r in rec["twist"]] == sorted(r["twist"][0] for r in rec["twist"])


def _synthetic_run(directory: Path, converge_at: int) -> None:
    """A run whose camera approaches the reference pose exponentially and converges at image `converge_at`."""
    T_world_ref = pose(so3_exp([0.1, 0.0, 0.0]), [0.5, 0.1, 0.4])
    writer = RecordingWriter(directory, {"reference_pose": T_world_ref.reshape(-1).tolist(), "stop_threshold": 1e-3})
    for k in range(3):
        writer.write("status", {"recv_ns": k, "msg": json.loads(dump(_status(k, "READY", 0.0, k)))})
    for i in range(converge_at + 5):
        decay = np.exp(-0.05 * i)
        state = "SERVOING" if i < converge_at else "CONVERGED"
        writer.write("status", {"recv_ns": i, "msg": json.loads(dump(_status(i + 3, state, decay, 1000 + i)))})
        T_ref_cam = pose(so3_exp([0.0, 0.0, 0.2 * decay]), [0.1 * decay, 0.0, 0.0])
        truth = GroundTruth(stamp_ns=1000 + i, camera_pose=(T_world_ref @ T_ref_cam).reshape(-1).tolist())
        writer.write("ground_truth", {"recv_ns": i, "msg": json.loads(dump(truth))})
    writer.close()


def test_summary_counts_images_and_measures_the_pose_error(tmp_path):
    _synthetic_run(tmp_path / "run", converge_at=120)
    summary = summarize(load_recording(tmp_path / "run"))
    assert summary.images_to_convergence == 120
    assert summary.frames == 125 and summary.final_state == "CONVERGED"
    assert summary.initial_translation_error_mm == pytest.approx(100.0)
    assert summary.initial_rotation_error_deg == pytest.approx(np.rad2deg(0.2))
    assert summary.final_translation_error_mm == pytest.approx(100.0 * np.exp(-0.05 * 124))
    assert summary.latency_median_ms["control"] == pytest.approx(0.2)
    assert images_to_convergence(["SERVOING"] * 4) is None


def test_plot_writes_the_paper_figure_types(tmp_path):
    _synthetic_run(tmp_path / "run", converge_at=60)
    files = plot_recording(load_recording(tmp_path / "run"), tmp_path / "plots", "synthetic")
    assert sorted(p.name for p in files) == ["error_norm.png", "pose_error.png", "trajectory.png", "velocities.png"]
    assert all(p.stat().st_size > 10_000 for p in files)

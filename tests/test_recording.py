"""The JSON Lines recording format (old recordings: torn lines, frames), bags and JSON Lines loaded alike, analysis
and `ddvs plot` of both."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from clients.analysis import images_to_convergence, summarize
from clients.bag import BagWriter
from clients.channels import run_channels, topic_name
from clients.plot import plot_recording
from clients.recording import RECORDED_KEYS, RecordingWriter, load_recording, read_stream
from ddvs_service.lie import pose, so3_exp
from ddvs_service.protocol import Counters, GroundTruth, Keys, Latency, Status, dump


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


def _synthetic_run(directory: Path, converge_at: int, bag: bool = False) -> None:
    """A run whose camera approaches the reference pose exponentially and converges at image `converge_at`, as a
    JSON Lines recording or (`bag`) as a bag of `ddvs record`."""
    T_world_ref = pose(so3_exp([0.1, 0.0, 0.0]), [0.5, 0.1, 0.4])
    meta = {"reference_pose": T_world_ref.reshape(-1).tolist(), "stop_threshold": 1e-3}
    messages: list[tuple[str, int, bytes]] = [("status", k, dump(_status(k, "READY", 0.0, k))) for k in range(3)]
    for i in range(converge_at + 5):
        decay = np.exp(-0.05 * i)
        state = "SERVOING" if i < converge_at else "CONVERGED"
        messages.append(("status", i, dump(_status(i + 3, state, decay, 1000 + i))))
        T_ref_cam = pose(so3_exp([0.0, 0.0, 0.2 * decay]), [0.1 * decay, 0.0, 0.0])
        truth = GroundTruth(stamp_ns=1000 + i, camera_pose=(T_world_ref @ T_ref_cam).reshape(-1).tolist())
        messages.append(("ground_truth", i, dump(truth)))
    if bag:
        keys = Keys()
        writer = BagWriter(directory, run_channels(keys), {"prefix": keys.prefix, "robot": keys.robot, **meta})
        for stream, t, payload in messages:
            writer.write(topic_name(keys, RECORDED_KEYS[stream]), payload, t, t)
    else:
        writer = RecordingWriter(directory, meta)
        for stream, t, payload in messages:
            writer.write(stream, {"recv_ns": t, "msg": json.loads(payload)})
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


@pytest.mark.parametrize("bag", [False, True], ids=["json-lines", "bag"])
def test_plot_writes_the_paper_figure_types(tmp_path, bag):
    _synthetic_run(tmp_path / "run", converge_at=60, bag=bag)
    recording = load_recording(tmp_path / "run")
    files = plot_recording(recording, tmp_path / "plots", "synthetic")
    assert sorted(p.name for p in files) == ["error_norm.png", "pose_error.png", "trajectory.png", "velocities.png"]
    assert all(p.stat().st_size > 10_000 for p in files)
    assert summarize(recording).images_to_convergence == 60


def test_a_bag_and_json_lines_of_the_same_run_load_the_same_records(tmp_path):
    _synthetic_run(tmp_path / "jsonl", converge_at=40)
    _synthetic_run(tmp_path / "bag", converge_at=40, bag=True)
    jsonl, bag = load_recording(tmp_path / "jsonl"), load_recording(tmp_path / "bag")
    assert bag.meta["format"] == "rosbag2" and bag.meta["stop_threshold"] == jsonl.meta["stop_threshold"]
    for stream in ("status", "ground_truth"):
        assert bag[stream] == jsonl[stream]
    assert summarize(bag) == summarize(jsonl)

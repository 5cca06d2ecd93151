"""`ddvs camera`: calibration files (camera_calibration's YAML, as the ROS documentation specifies it, round-trips
into the published CameraInfo), and a video file the test writes (MJPG/avi) published over Zenoh at the requested
rate, raw or rectified with the calibration's distortion, as bgr8 or mono8, as Image or CompressedImage."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import free_port

from clients.camera import load_calibration
from ddvs_service.grey import decode_compressed
from ddvs_service.protocol import (
    Keys,
    SessionConfig,
    decode_camera_info,
    decode_compressed_image,
    decode_image,
    open_session,
)

ROOT = Path(__file__).resolve().parents[1]
KEYS = Keys("ddvs", "camtest")
K = np.array([[90.0, 0.0, 31.5], [0.0, 92.0, 23.5], [0.0, 0.0, 1.0]])
D = np.array([-0.2, 0.05, 0.001, -0.002, 0.0])
W, H = 64, 48


def _write_calibration_yaml(path: Path) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", W)
    fs.write("image_height", H)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", D.reshape(1, 5))
    fs.release()


def _write_video(path: Path, frames: int = 10) -> np.ndarray:
    """An MJPG avi of identical frames (a smooth pattern); returns the first frame as OpenCV decodes it."""
    yy, xx = np.mgrid[0:H, 0:W]
    pattern = (127 + 100 * np.sin(xx / 5.0) * np.cos(yy / 7.0)).astype(np.uint8)
    bgr = cv2.merge([pattern, np.flipud(pattern), 255 - pattern])
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (W, H))
    assert writer.isOpened()
    for _ in range(frames):
        writer.write(bgr)
    writer.release()
    capture = cv2.VideoCapture(str(path))
    ok, decoded = capture.read()
    capture.release()
    assert ok
    return decoded


def test_calibration_files_opencv_yaml_and_plain_json(tmp_path):
    _write_calibration_yaml(tmp_path / "cal.yaml")
    cal = load_calibration(tmp_path / "cal.yaml")
    np.testing.assert_allclose(cal.K, K)
    np.testing.assert_allclose(cal.D, D)
    assert (cal.width, cal.height, cal.distorted) == (W, H, True)
    (tmp_path / "cal.json").write_text(json.dumps({"K": K.tolist(), "width": W, "height": H}))
    plain = load_calibration(tmp_path / "cal.json")
    assert not plain.distorted and np.allclose(plain.K, K)
    (tmp_path / "bad.json").write_text(json.dumps({"K": [[1, 0, 0], [1, 1, 0], [0, 0, 1]], "width": W, "height": H}))
    with pytest.raises(ValueError, match="upper triangular"):
        load_calibration(tmp_path / "bad.json")
    (tmp_path / "none.json").write_text(json.dumps({"width": W, "height": H}))
    with pytest.raises(ValueError, match="camera_matrix"):
        load_calibration(tmp_path / "none.json")


def _publish(tmp_path: Path, key: str, *options: str) -> tuple[list[bytes], list[bytes], subprocess.CompletedProcess]:
    """Run `ddvs camera clip.avi --fps 20 --loop --frames 40 *options`; the payloads received on `key` and on
    camera/info."""
    port = free_port()
    images: list[bytes] = []
    infos: list[bytes] = []
    with open_session(SessionConfig(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        session.declare_subscriber(key, lambda s: images.append(s.payload.to_bytes()))
        session.declare_subscriber(KEYS.camera_info, lambda s: infos.append(s.payload.to_bytes()))
        cmd = [sys.executable, "-m", "ddvs.cli", "camera", str(tmp_path / "clip.avi"), "--fps", "20", "--loop",
               "--frames", "40", "--robot", KEYS.robot, "--connect", f"tcp/127.0.0.1:{port}", *options]
        result = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=60)
        time.sleep(0.3)
    assert result.returncode == 0, result.stdout + result.stderr
    assert len(images) >= 25, f"received {len(images)} of 40 frames"
    return images, infos, result


@pytest.mark.parametrize("encoding", ["bgr8", "mono8"])
def test_video_file_is_published_rectified_at_the_requested_rate(tmp_path, encoding):
    """`--publish rect`: image_rect, rectified to P (here [K | 0]), the CameraInfo keeping d, as image_proc does."""
    _write_calibration_yaml(tmp_path / "cal.yaml")
    decoded = _write_video(tmp_path / "clip.avi")
    maps = cv2.initUndistortRectifyMap(K, D, np.eye(3), K, (W, H), cv2.CV_32FC1)
    source = decoded if encoding == "bgr8" else cv2.cvtColor(decoded, cv2.COLOR_BGR2GRAY)
    expected = cv2.remap(source, *maps, cv2.INTER_LINEAR)
    images, infos, _ = _publish(tmp_path, KEYS.key("camera_image_rect"), "--calibration", str(tmp_path / "cal.yaml"),
                                "--encoding", encoding, "--publish", "rect")
    msgs = [decode_image(b) for b in images]
    assert all(m.encoding == encoding and (m.width, m.height) == (W, H) for m in msgs)
    assert np.abs(msgs[-1].array.astype(int) - expected.astype(int)).max() <= 1
    stamps = np.array([m.header.stamp.to_ns() for m in msgs]) * 1e-9
    rate = (len(stamps) - 1) / (stamps[-1] - stamps[0])
    assert rate == pytest.approx(20.0, rel=0.1)
    info = decode_camera_info(infos[-1])
    np.testing.assert_allclose(info.k.reshape(3, 3), K)
    np.testing.assert_allclose(info.d, D)  # kept, as ROS does: the image_rect's camera is P
    np.testing.assert_allclose(info.p.reshape(3, 4)[:, :3], K)
    assert info.rectified_intrinsics().fx == 90.0


# camera_calibration's YAML, as its documentation and camera_info_manager's parser (camera_calibration_parsers)
# specify it: the keys, `{rows, cols, data}` matrices, flow-style lists, no %YAML directive.
ROS_CALIBRATION = """image_width: {w}
image_height: {h}
camera_name: {name}
camera_matrix:
  rows: 3
  cols: 3
  data: [{k}]
distortion_model: {model}
distortion_coefficients:
  rows: 1
  cols: {n}
  data: [{d}]
rectification_matrix:
  rows: 3
  cols: 3
  data: [{r}]
projection_matrix:
  rows: 3
  cols: 4
  data: [{p}]
"""


def _numbers(values: np.ndarray) -> str:
    return ", ".join(f"{v:.6f}" for v in np.asarray(values).reshape(-1))


@pytest.mark.parametrize("model", ["plumb_bob", "equidistant"])
def test_a_camera_calibration_yaml_round_trips_into_the_published_camera_info(tmp_path, model):
    """The file camera_calibration writes, read by `ddvs camera --calibration`, comes back as the CameraInfo it
    publishes with every raw frame (default `--publish raw`: the frames as read, the service rectifies them)."""
    d = np.array([-0.2, 0.05, 0.001, -0.002, 0.0]) if model == "plumb_bob" else np.array([0.03, -0.01, 0.002, 0.0])
    R = np.array([[0.999, -0.02, 0.01], [0.02, 0.999, 0.0], [-0.01, 0.0, 1.0]])
    P = np.array([[80.0, 0.0, 30.5, 0.0], [0.0, 81.0, 22.5, 0.0], [0.0, 0.0, 1.0, 0.0]])
    (tmp_path / "cal.yaml").write_text(ROS_CALIBRATION.format(w=W, h=H, name="wrist_cam", k=_numbers(K), model=model,
                                                              n=d.size, d=_numbers(d), r=_numbers(R), p=_numbers(P)))
    decoded = _write_video(tmp_path / "clip.avi")
    images, infos, _ = _publish(tmp_path, KEYS.camera_image, "--calibration", str(tmp_path / "cal.yaml"))
    info = decode_camera_info(infos[-1])
    assert (info.width, info.height, info.distortion_model) == (W, H, model)
    np.testing.assert_allclose(info.k.reshape(3, 3), K, atol=1e-6)
    np.testing.assert_allclose(info.d, d, atol=1e-6)
    np.testing.assert_allclose(info.r.reshape(3, 3), R, atol=1e-6)
    np.testing.assert_allclose(info.p.reshape(3, 4), P, atol=1e-6)
    raw = decode_image(images[-1])
    grey = cv2.cvtColor(decoded, cv2.COLOR_BGR2GRAY)
    assert raw.encoding == "mono8" and np.abs(raw.array.astype(int) - grey.astype(int)).max() <= 1  # as read


def test_compressed_frames_go_to_the_image_transport_topic(tmp_path):
    """`--compress jpeg`: sensor_msgs/CompressedImage on camera/image/compressed, decoding to the frame read."""
    decoded = _write_video(tmp_path / "clip.avi")
    images, _, _ = _publish(tmp_path, KEYS.key("camera_image_compressed"), "--focal", "90", "--compress", "jpeg",
                            "--jpeg-quality", "95")
    msg = decode_compressed_image(images[-1])
    assert msg.format == "jpeg"
    grey = decode_compressed(msg, 1 << 20).astype(float)
    assert np.abs(grey - cv2.cvtColor(decoded, cv2.COLOR_BGR2GRAY)).mean() < 3.0

"""`ddvs camera`: calibration files, and a video file the test writes (MJPG/avi) published over Zenoh at the
requested rate, rectified with the calibration's distortion, as bgr8 or mono8."""

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
from ddvs_service.protocol import Keys, SessionConfig, decode_camera_info, decode_image, open_session

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


@pytest.mark.parametrize("encoding", ["bgr8", "mono8"])
def test_video_file_is_published_rectified_at_the_requested_rate(tmp_path, encoding):
    _write_calibration_yaml(tmp_path / "cal.yaml")
    decoded = _write_video(tmp_path / "clip.avi")
    maps = cv2.initUndistortRectifyMap(K, D, None, K, (W, H), cv2.CV_16SC2)
    source = decoded if encoding == "bgr8" else cv2.cvtColor(decoded, cv2.COLOR_BGR2GRAY)
    expected = cv2.remap(source, *maps, cv2.INTER_LINEAR)
    port = free_port()
    images, infos = [], []
    with open_session(SessionConfig(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        session.declare_subscriber(KEYS.camera_image, lambda s: images.append(s.payload.to_bytes()))
        session.declare_subscriber(KEYS.camera_info, lambda s: infos.append(s.payload.to_bytes()))
        cmd = [sys.executable, "-m", "ddvs.cli", "camera", str(tmp_path / "clip.avi"), "--calibration",
               str(tmp_path / "cal.yaml"), "--fps", "20", "--loop", "--frames", "40", "--encoding", encoding,
               "--robot", KEYS.robot, "--connect", f"tcp/127.0.0.1:{port}"]
        result = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=60)
        time.sleep(0.3)
    assert result.returncode == 0, result.stdout + result.stderr
    assert len(images) >= 25, f"received {len(images)} of 40 frames"
    msgs = [decode_image(b) for b in images]
    assert all(m.encoding == encoding and (m.width, m.height) == (W, H) for m in msgs)
    assert np.abs(msgs[-1].array.astype(int) - expected.astype(int)).max() <= 1
    stamps = np.array([m.header.stamp.to_ns() for m in msgs]) * 1e-9
    rate = (len(stamps) - 1) / (stamps[-1] - stamps[0])
    assert rate == pytest.approx(20.0, rel=0.1)
    info = decode_camera_info(infos[-1])
    np.testing.assert_allclose(info.k.reshape(3, 3), K)
    assert np.all(info.d == 0.0)  # rectified: the service's pinhole model applies
    assert info.to_intrinsics().fx == 90.0

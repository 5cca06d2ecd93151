"""Closed loops through real cameras' image pipelines: `ddvs serve` in a subprocess servoes a free-flying camera
(`sim.freeflyer`) whose frames reach it as a calibrated ROS camera sends them — `image_raw` through a plumb_bob lens
(k1 = −0.3, k2 = 0.1), a rational_polynomial or a fisheye lens with the calibrated CameraInfo, `image_rect` with the
CameraInfo's `d` kept and its P set, JPEG q80 `CompressedImage` frames — and each converges to the pose the
undistorted plant reaches from the same start, within 1 mm and 0.1°; its first twist (the intrinsics and the
rectification at work) is the undistorted plant's within 10 %. The reference published on `servo/reference` carries
the camera's header, and a raw reference upload is rectified as the live frames are."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import free_port
from test_service_node import Operator, Service, answered_frames

from ddvs_service.camera import Intrinsics
from ddvs_service.lie import pose, pose_inv, so3_exp, so3_log
from ddvs_service.protocol import (
    CameraInfo,
    CompressedImage,
    Header,
    LatestSubscriber,
    Time,
    decode_image,
    encode_camera_info,
    encode_compressed_image,
    encode_image,
    image_from_array,
)
from ddvs_service.service.config import ServiceConfig

INTR = Intrinsics(300.0, 300.0, 159.5, 119.5, 320, 240)
RECT = Intrinsics(260.0, 262.0, 158.0, 121.0, 320, 240)  # image_rect: the P of a camera whose raw K is INTR
DT = 0.1  # s: the camera moves by twist × DT between frames
T_REF = pose(so3_exp([np.pi, 0.0, 0.0]), [0.0, 0.0, 0.5])  # 0.5 m above the plane z = 0, looking down
T_START = T_REF @ pose(so3_exp([0.01, -0.015, 0.025]), [0.01, -0.008, 0.005])
LENSES = {"plumb_bob": (-0.3, 0.1, 0.0, 0.0, 0.0), "equidistant": (0.05, -0.02, 0.0, 0.0),
          "rational_polynomial": (-0.25, 0.08, 0.001, -0.001, 0.0, 0.02, 0.0, 0.0)}
FRAME_ID = "camera_optical_frame"


def _texture() -> np.ndarray:
    noise = cv2.GaussianBlur(np.random.default_rng(18).random((512, 512)).astype(np.float32), (0, 0), 3.0)
    return (40.0 + 175.0 * (noise - noise.min()) / (noise.max() - noise.min())).astype(np.float32)


class Camera:
    """The plant's camera: what it sends for the flyer's current view, as `kind` says — `pinhole` (image_raw of an
    undistorted camera), `plumb_bob` / `equidistant` (image_raw through that lens), `rect` (image_rect at P = RECT,
    the raw camera's K and d in the info), `jpeg` (the pinhole image as a JPEG q80 CompressedImage)."""

    def __init__(self, kind: str) -> None:
        from sim.lens import DistortedLens
        from sim.surfaces import Plane

        self.kind = kind
        self.plane = Plane(pose(np.eye(3), [0.0, 0.0, 0.0]), (1.5, 1.5))
        self.texture = _texture()
        self.lens = DistortedLens(INTR, kind, LENSES[kind]) if kind in LENSES else None
        header = Header(Time(0, 0), FRAME_ID)
        if self.lens is not None:
            self.info = self.lens.camera_info(header)
        elif kind == "rect":
            self.info = DistortedLens(INTR, "plumb_bob", LENSES["plumb_bob"]).camera_info(header)
            self.info.p = np.hstack([RECT.K, np.zeros((3, 1))]).reshape(-1)
        else:
            self.info = CameraInfo.from_intrinsics(INTR, header)

    @property
    def row(self) -> str:
        return {"rect": "camera_image_rect", "jpeg": "camera_image_compressed"}.get(self.kind, "camera_image")

    def settings(self) -> dict[str, str]:
        return {"images": "rect" if self.kind == "rect" else "raw",
                "transport": "compressed" if self.kind == "jpeg" else "raw"}

    def frame(self, T_world_cam: np.ndarray, header: Header) -> bytes:
        from sim.freeflyer import render_view

        def render(intrinsics: Intrinsics) -> np.ndarray:
            return render_view(self.plane, self.texture, intrinsics, T_world_cam)[0]

        image = self.lens.raw(render) if self.lens is not None else render(RECT if self.kind == "rect" else INTR)
        pixels = np.clip(np.rint(image), 0, 255).astype(np.uint8)
        if self.kind == "jpeg":
            data = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, 80])[1].tobytes()
            return encode_compressed_image(CompressedImage(header, "jpeg", data))
        return encode_image(image_from_array(pixels, "mono8", header))


class Plant(Operator):
    """The test's side: the camera's publishers (its image row and camera_info), the operator's commands."""

    def __init__(self, port: int, camera: Camera) -> None:
        super().__init__(port)
        self.frames.undeclare()
        self.frames = answered_frames(self.session, self.keys.key(camera.row))
        self.info = self.session.declare_publisher(self.keys.key("camera_info"))
        self.reference = LatestSubscriber(self.session, self.keys.key("servo_reference"))
        self.camera = camera

    def publish(self, T_world_cam: np.ndarray, stamp_ns: int) -> np.ndarray:
        """Send the view from `T_world_cam` stamped `stamp_ns`; the twist it was answered with."""
        header = Header(Time.from_ns(stamp_ns), FRAME_ID)
        self.camera.info.header = header
        self.info.put(encode_camera_info(self.camera.info))
        self.frames.put(self.camera.frame(T_world_cam, header))
        deadline = time.monotonic() + 60.0
        while stamp_ns not in self.twist_stamps:
            assert time.monotonic() < deadline, f"no twist for the frame stamped {stamp_ns}"
            time.sleep(0.002)
        return self.twists[self.twist_stamps.index(stamp_ns)]

    def close(self) -> None:
        self.info.undeclare()
        self.reference.close()
        super().close()


def _servo(kind: str, tmp_path: Path) -> tuple[np.ndarray, list[np.ndarray], Header]:
    """Run the loop for `kind` from T_START: the final camera pose, the twists, the published reference's header."""
    from sim.freeflyer import FreeFlyer

    port = free_port()
    camera = Camera(kind)
    config = ServiceConfig.model_validate({
        "robot": "t0", "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"]},
        "state_dir": str(tmp_path / kind), "camera": camera.settings(),
        "registration": {"template_size": [120, 90]},
        "control": {"gains": 2.0, "max_linear": 0.5, "max_angular": 1.0},
    })
    (tmp_path / kind).mkdir()
    service = Service(config, tmp_path / kind, "--fresh")
    plant = Plant(port, camera)
    flyer = FreeFlyer(camera.plane, INTR, T_REF, T_START, DT)
    twists: list[np.ndarray] = []
    try:
        service.wait_ready(plant)
        assert plant.command(op="set_reference", source="next_frame").ok
        reference_stamp = 1_000_000_000
        plant.publish(T_REF, reference_stamp)
        assert plant.command(op="start").ok
        sample = plant.reference.recv(10.0)
        assert sample is not None, "no reference on servo/reference"
        reference = decode_image(sample.payload.to_bytes())
        for k in range(200):
            twist = plant.publish(flyer.T_world_cam, 2_000_000_000 + k * 100_000_000)
            twists.append(twist)
            flyer.move(twist)
            if k > 10 and not np.any(twist) and plant.statuses[-1]["state"] == "CONVERGED":
                break
        assert plant.statuses[-1]["state"] == "CONVERGED", [s["state"] for s in plant.statuses[-5:]]
    finally:
        code, stderr = service.stop()
        plant.close()
        print(stderr[-3000:])
    assert code == 0
    assert reference.header == Header(Time.from_ns(reference_stamp), FRAME_ID)
    return flyer.T_world_cam, twists, reference.header


@pytest.mark.slow
def test_distorted_rectified_and_compressed_cameras_converge_where_the_undistorted_one_does(tmp_path: Path) -> None:
    goal, twists, _ = _servo("pinhole", tmp_path)
    print(f"pinhole: {len(twists)} frames, first twist {np.round(twists[0], 4).tolist()}")
    for kind in ("plumb_bob", "equidistant", "rational_polynomial", "rect", "jpeg"):
        T, kind_twists, _ = _servo(kind, tmp_path)
        E = pose_inv(goal) @ T
        dist_mm = 1e3 * float(np.linalg.norm(E[:3, 3]))
        angle_deg = float(np.degrees(np.linalg.norm(so3_log(E[:3, :3]))))
        first = float(np.linalg.norm(kind_twists[0] - twists[0]) / np.linalg.norm(twists[0]))
        print(f"{kind}: {len(kind_twists)} frames, {dist_mm:.3f} mm and {angle_deg:.4f}° from the undistorted "
              f"plant's final pose; first twist differs by {100 * first:.1f} %")
        assert dist_mm < 1.0 and angle_deg < 0.1, kind
        assert first < 0.1, kind


def test_the_reference_carries_the_cameras_header_whatever_the_frames_encoding(tmp_path: Path) -> None:
    """`servo/reference` is the frame's own header (frame_id, stamp) and its grey levels as registered, for a bgr8
    frame (mono8, its BT.601 grey) and a mono16 one (32FC1, grey levels 0–255); before, only mono8 frames were
    published, under frame_id "camera" and the publish time."""
    from test_service_node import running_service, scene, service_config

    port = free_port()
    grey = scene()
    bgr = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    frames = {"bgr8": (bgr, "mono8", grey), "mono16": (grey.astype(np.uint16) * 257, "32FC1", grey)}
    with (running_service(service_config(port, tmp_path / "state"), tmp_path, port) as (_, op),
          LatestSubscriber(op.session, op.keys.key("servo_reference")) as references):
        for k, (encoding, (pixels, published, expected)) in enumerate(frames.items()):
            header = Header(Time(1_700_000_000 + k, 250_000_000), "wrist_camera_optical")
            assert op.command(op="set_reference", source="next_frame").ok
            op.send_raw(encode_image(image_from_array(pixels, encoding, header)))
            sample = references.recv(10.0)
            assert sample is not None, f"no reference published for a {encoding} frame"
            reference = decode_image(sample.payload.to_bytes())
            assert (reference.header, reference.encoding) == (header, published), encoding
            np.testing.assert_allclose(reference.array, expected, atol=0.5)


def test_an_uploaded_raw_frame_is_rectified_like_the_live_frames(tmp_path: Path) -> None:
    """With a plumb_bob camera on image_raw, a reference uploaded as a raw frame (saved from the camera) becomes the
    rectified frame, the one `next_frame` would give, and is published so."""
    from test_service_loop import upload_command

    from ddvs_service.rectification import camera_geometry

    port = free_port()
    camera = Camera("plumb_bob")
    config = ServiceConfig.model_validate({
        "robot": "t0", "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"]},
        "state_dir": str(tmp_path / "state"), "registration": {"template_size": [120, 90]}})
    service = Service(config, tmp_path, "--fresh")
    plant = Plant(port, camera)
    try:
        service.wait_ready(plant)
        assert plant.command(op="set_reference", source="next_frame").ok
        plant.publish(T_REF, 1_000_000_000)  # the camera info and a frame: the rectification is known
        assert plant.reference.recv(10.0) is not None
        raw = decode_image(camera.frame(T_START, Header(Time(2, 0), FRAME_ID))).array
        assert plant.command(**upload_command(raw)).ok
        sample = plant.reference.recv(10.0)
        assert sample is not None, "no reference published for the upload"
        reference = decode_image(sample.payload.to_bytes())
    finally:
        code, stderr = service.stop()
        plant.close()
        print(stderr[-3000:])
    assert code == 0
    rectifier = camera_geometry(camera.info, rectified=False).rectifier
    assert rectifier is not None
    assert reference.header.frame_id == FRAME_ID
    assert float(np.abs(reference.array.astype(float) - rectifier(raw).astype(float)).mean()) < 0.5
    assert float(np.abs(reference.array.astype(float) - raw.astype(float)).mean()) > 5.0

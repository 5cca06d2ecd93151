"""One numbered message of every key a servo run publishes (payloads as the nodes publish them), shared by the
recording and live-view tests."""

from __future__ import annotations

import numpy as np

from ddvs_service.protocol import (
    CameraInfo,
    CompressedImage,
    Counters,
    GroundTruth,
    Header,
    JointState,
    Latency,
    Status,
    Time,
    TwistStamped,
    dump,
    encode_camera_info,
    encode_compressed_image,
    encode_image,
    encode_joint_state,
    encode_twist_stamped,
    image_from_array,
)


def status(seq: int) -> Status:
    return Status(robot="r", state="SERVOING", frame_stamp_ns=seq, seq=seq, error=[1.0 / (seq + 1), 0, 0, 0, 0, 0],
                  error_norm=1.0 / (seq + 1), iterations=2, residual_rms=1.5, inlier_ratio=0.9, twist=[0.01] * 6,
                  latency_ms=Latency(decode=0.1, registration=1.0, control=0.1, publish=0.1, total=1.3),
                  counters=Counters(frames=seq, dropped=0, rejected=0))


def frame(seq: int) -> np.ndarray:
    return ((np.arange(48 * 64).reshape(48, 64) + seq) % 256).astype(np.uint8)


def png(seq: int) -> bytes:
    """`frame(seq)` as a PNG file."""
    import cv2

    return cv2.imencode(".png", frame(seq))[1].tobytes()


def run_payloads(seq: int) -> dict[str, bytes]:
    """One payload of every recorded key, numbered `seq` (header stamps 1 s + `seq` ns, ground truth `seq` ns); the
    camera's frames on each of its rows (raw, rectified, and both as PNG CompressedImage)."""
    header = Header(Time.from_ns(1_000_000_000 + seq), "camera")
    compressed = encode_compressed_image(CompressedImage(header, "png", png(seq)))
    return {
        "camera_image": encode_image(image_from_array(frame(seq), "mono8", header)),
        "camera_image_rect": encode_image(image_from_array(frame(seq), "mono8", header)),
        "camera_image_compressed": compressed,
        "camera_image_rect_compressed": compressed,
        "camera_info": encode_camera_info(CameraInfo(header, 48, 64, k=[50, 0, 31.5, 0, 50, 23.5, 0, 0, 1])),
        "servo_twist": encode_twist_stamped(TwistStamped(header, [seq, 0, 0], [0, 0, 0.1])),
        "arm_joint_states": encode_joint_state(JointState(Header(header.stamp, "base"), ["j1", "j2"], [seq, 1.0],
                                                          [0.0, 0.0])),
        "servo_status": dump(status(seq)),
        "arm_ground_truth": dump(GroundTruth(stamp_ns=seq, camera_pose=np.eye(4).reshape(-1).tolist())),
    }

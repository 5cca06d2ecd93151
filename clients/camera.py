"""`ddvs camera`: publish frames from a webcam or a video file (OpenCV `VideoCapture`) with their camera info, as a
ROS camera driver (`--publish raw`) or a driver followed by image_proc (`--publish rect`) does (docs/cameras.md).

Keys: with `--publish raw` (default) `camera/image` (ROS `image_raw`): the frames as read; with `--publish rect`
`camera/image_rect` (ROS `image_rect`): the frames rectified to the calibration's P (`ddvs_service.rectification`,
the maps the service would use). `--compress jpeg|png` publishes `sensor_msgs/CompressedImage` on the image
topic's `/compressed` row instead (image_transport's name). Either way `camera/info` (ROS `camera_info`) carries the
calibration with every frame, K and d of the raw image, R and P, as camera_info_manager publishes it; everything is
stamped with the wall-clock time at which the frame was read (ns since the Unix epoch). Encodings mono8 or bgr8.

Calibration (`--calibration FILE`): the YAML that ROS's `camera_calibration` writes and `camera_info_manager` reads
(`image_width`, `image_height`, `camera_name`, `camera_matrix`, `distortion_model`, `distortion_coefficients`,
`rectification_matrix`, `projection_matrix`, matrices as `{rows, cols, data}`), any OpenCV FileStorage file
(YAML/XML/JSON) or a plain JSON object with the same keys; also accepted: `K` for the camera matrix,
`dist_coeffs` or `D` for the coefficients, `width`/`height` for the size. Without a model the coefficients are
plumb_bob; without R, the identity; without P, [K | 0]. Pixels follow OpenCV (0-based pixel centres). Without a
calibration file, `--focal F` describes the paper's coarse calibration: fx = fy = F, principal point at the image
centre, no distortion.

Rate: a video file is replayed at `--fps`, or at the rate stored in the file (30 Hz when it has none); a device is
read as fast as it delivers frames, or throttled to `--fps`.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    import zenoh

    from ddvs_service.protocol import CameraInfo, Header, Keys

log = logging.getLogger(__name__)
ENCODINGS = ("mono8", "bgr8")
PUBLISH = ("raw", "rect")
CAMERA_FRAME_ID = "camera"
DEFAULT_FILE_FPS = 30.0


@dataclass(frozen=True)
class Calibration:
    """Camera matrix `K` (3×3, pixels), distortion coefficients `D` of `model` (plumb_bob: k1 k2 p1 p2 [k3];
    rational_polynomial: 8; equidistant: k1 k2 k3 k4), image size, rectification `R` (3×3) and projection `P`
    (3×4, pixels: the rectified image's camera), as in `sensor_msgs/CameraInfo`."""

    K: NDArray[np.float64]
    D: NDArray[np.float64]
    width: int
    height: int
    model: str = "plumb_bob"
    R: NDArray[np.float64] = field(default_factory=lambda: np.eye(3))
    P: NDArray[np.float64] | None = None  # None: [K | 0]

    def __post_init__(self) -> None:
        if self.K.shape != (3, 3) or self.K[2, 2] != 1.0 or self.K[1, 0] != 0.0 or self.K[2, 0] != 0.0:
            raise ValueError(f"camera matrix must be 3×3 upper triangular with K[2,2] = 1, got {self.K.tolist()}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}×{self.height}")
        if self.R.shape != (3, 3) or (self.P is not None and self.P.shape != (3, 4)):
            raise ValueError(f"rectification matrix must be 3×3 and projection matrix 3×4, got {self.R.shape} and "
                             f"{None if self.P is None else self.P.shape}")

    @property
    def distorted(self) -> bool:
        return bool(np.any(self.D != 0.0))

    def camera_info(self, header: Header) -> CameraInfo:
        """The `sensor_msgs/CameraInfo` of this calibration (what camera_info_manager publishes from the file)."""
        from ddvs_service.protocol import CameraInfo

        P = np.hstack([self.K, np.zeros((3, 1))]) if self.P is None else self.P
        return CameraInfo(header=header, height=self.height, width=self.width, distortion_model=self.model,
                          d=self.D, k=self.K.reshape(-1), r=self.R.reshape(-1), p=P.reshape(-1))


def _first(mapping: dict, names: tuple[str, ...], path: Path, required: bool = True):
    for name in names:
        if name in mapping:
            return mapping[name]
    if required:
        raise ValueError(f"calibration {path} has none of the keys {names}")
    return None


def _as_matrix(value, what: str, path: Path) -> NDArray[np.float64]:
    if isinstance(value, dict):  # {rows, cols, data} (ROS YAML, OpenCV JSON)
        value = value.get("data")
    if value is None:
        raise ValueError(f"calibration {path}: {what} has no data")
    return np.asarray(value, dtype=np.float64)


def _read_filestorage(path: Path) -> dict:
    """The top-level entries of an OpenCV FileStorage file as Python values (matrices as arrays)."""
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise ValueError(f"OpenCV cannot read the calibration file {path}")
    try:
        entries: dict[str, object] = {}
        root = fs.root()
        for key in root.keys():  # noqa: SIM118 (a cv2.FileNode is not iterable)
            node = root.getNode(key)
            if node.isInt() or node.isReal():
                entries[key] = node.real()
            elif node.isString():
                entries[key] = node.string()
            elif node.isMap() and not node.getNode("data").empty() and node.getNode("dt").empty():
                data = node.getNode("data")
                entries[key] = {"data": [data.at(i).real() for i in range(data.size())]}
            elif node.isSeq():
                entries[key] = [node.at(i).real() for i in range(node.size())]
            else:
                entries[key] = node.mat()
        return entries
    finally:
        fs.release()


def load_calibration(path: str | Path) -> Calibration:
    """Read a calibration file (see the module docstring for the accepted layouts)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"calibration file {path} does not exist")
    entries: dict
    try:
        entries = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        entries = _read_filestorage(path)
    if not isinstance(entries, dict):
        raise ValueError(f"calibration {path} is not an object of named entries")
    K = _as_matrix(_first(entries, ("camera_matrix", "K"), path), "camera matrix", path).reshape(3, 3)
    D_value = _first(entries, ("distortion_coefficients", "dist_coeffs", "D"), path, required=False)
    D = np.zeros(5) if D_value is None else _as_matrix(D_value, "distortion", path).reshape(-1)
    width = int(_first(entries, ("image_width", "width"), path))
    height = int(_first(entries, ("image_height", "height"), path))
    model = str(_first(entries, ("distortion_model",), path, required=False) or "plumb_bob")
    R_value = _first(entries, ("rectification_matrix", "R"), path, required=False)
    R = np.eye(3) if R_value is None else _as_matrix(R_value, "rectification matrix", path).reshape(3, 3)
    P_value = _first(entries, ("projection_matrix", "P"), path, required=False)
    P = None if P_value is None else _as_matrix(P_value, "projection matrix", path).reshape(3, 4)
    return Calibration(K, D, width, height, model, R, P)


class CameraPublisher:
    """Publishes frames (grey or BGR uint8, the calibration's size) with their camera info on `session`: raw
    (`publish` "raw") or rectified to the calibration's P (`publish` "rect"), as `sensor_msgs/Image` or, with
    `compress` "jpeg"/"png", as `sensor_msgs/CompressedImage`."""

    def __init__(self, session: zenoh.Session, keys: Keys, calibration: Calibration, encoding: str = "mono8",
                 publish: str = "raw", frame_id: str = CAMERA_FRAME_ID, compress: str | None = None,
                 jpeg_quality: int = 90) -> None:
        from ddvs_service.protocol import Header, Time
        from ddvs_service.protocol.endpoints import Endpoints
        from ddvs_service.protocol.ros_graph import CAMERA_NODE
        from ddvs_service.rectification import camera_geometry

        if encoding not in ENCODINGS:
            raise ValueError(f"encoding {encoding!r} not supported; expected one of {ENCODINGS}")
        if publish not in PUBLISH:
            raise ValueError(f"publish {publish!r}: expected one of {PUBLISH}")
        self.calibration, self.encoding, self.frame_id = calibration, encoding, frame_id
        self.compress, self.jpeg_quality = compress, jpeg_quality
        info = calibration.camera_info(Header(Time(0, 0), frame_id))
        self._rectifier = camera_geometry(info, rectified=False).rectifier if publish == "rect" else None
        row = "camera_image" if publish == "raw" else "camera_image_rect"
        self._endpoints = Endpoints(session, keys, CAMERA_NODE)  # graph tokens and attachments in ROS 2 mode
        self._image = self._endpoints.publisher(row if compress is None else f"{row}_compressed")
        self._info = self._endpoints.publisher("camera_info")
        self.published = 0

    def close(self) -> None:
        self._endpoints.close()

    def publish(self, frame: NDArray[np.uint8], stamp_ns: int) -> None:
        """Convert (grey/BGR), rectify when needed, and publish `frame` with camera info stamped `stamp_ns`."""
        import cv2

        from clients.compressed_image import compress_image
        from ddvs_service.protocol import Header, Time, encode_camera_info, encode_image, image_from_array

        cal = self.calibration
        if frame.shape[:2] != (cal.height, cal.width):
            raise ValueError(f"frame is {frame.shape[1]}×{frame.shape[0]}; the calibration is for "
                             f"{cal.width}×{cal.height}")
        if self.encoding == "mono8" and frame.ndim == 3:
            frame = np.asarray(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), np.uint8)
        elif self.encoding == "bgr8" and frame.ndim == 2:
            frame = np.asarray(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR), np.uint8)
        if self._rectifier is not None:
            frame = self._rectifier(frame)
        header = Header(Time.from_ns(stamp_ns), self.frame_id)
        self._info.put(encode_camera_info(cal.camera_info(header)))
        image = image_from_array(np.ascontiguousarray(frame), self.encoding, header)
        self._image.put(encode_image(image) if self.compress is None else
                        compress_image(image, self.compress, self.jpeg_quality))
        self.published += 1


def stream(capture, publisher: CameraPublisher, fps: float | None, stop: threading.Event,
           max_frames: int | None = None, loop: bool = False) -> int:
    """Read frames from an opened `cv2.VideoCapture` and publish them, paced at `fps` (None: as fast as the source
    delivers), until the source ends (or forever with `loop`, rewinding a file), `stop` is set or `max_frames`
    were published. Returns the number of frames published."""
    import cv2

    period = 0.0 if fps is None else 1.0 / fps
    start = time.monotonic()
    count = 0
    while not stop.is_set() and (max_frames is None or count < max_frames):
        ok, frame = capture.read()
        if not ok:
            if loop and capture.set(cv2.CAP_PROP_POS_FRAMES, 0):
                ok, frame = capture.read()
            if not ok:
                break
        if period:
            wait = start + count * period - time.monotonic()
            if wait > 0 and stop.wait(wait):
                break
        publisher.publish(frame, time.time_ns())
        count += 1
    return count


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ddvs_service.protocol import add_zenoh_arguments
    from ddvs_service.protocol.ros_cli import add_ros_arguments

    parser.add_argument("source", help="webcam device index (e.g. 0) or video file path")
    calibration = parser.add_mutually_exclusive_group(required=True)
    calibration.add_argument("--calibration", type=Path, help="calibration file (OpenCV YAML/XML/JSON or JSON)")
    calibration.add_argument("--focal", type=float,
                             help="coarse calibration: fx = fy = FOCAL px, principal point at the image centre")
    parser.add_argument("--fps", type=float, default=None, help="publishing rate (default: the source's)")
    parser.add_argument("--encoding", choices=ENCODINGS, default="mono8", help="published encoding (default mono8)")
    parser.add_argument("--publish", choices=PUBLISH, default="raw",
                        help="raw: frames as read on camera/image (ROS image_raw), the service rectifies them; rect: "
                             "rectified to the calibration's P on camera/image_rect (ROS image_rect) (default raw)")
    parser.add_argument("--compress", choices=("jpeg", "png"), default=None,
                        help="publish sensor_msgs/CompressedImage on the image topic's /compressed instead")
    parser.add_argument("--jpeg-quality", type=int, default=90, help="JPEG quality 1-100 with --compress jpeg")
    parser.add_argument("--frame-id", default=CAMERA_FRAME_ID,
                        help="header.frame_id: the camera's optical frame in the robot's TF tree, which the servo's "
                             f"twist is expressed in (MoveIt Servo needs it there; default {CAMERA_FRAME_ID!r})")
    parser.add_argument("--loop", action="store_true", help="replay a video file from the start when it ends")
    parser.add_argument("--frames", type=int, default=None, help="stop after this many frames")
    parser.add_argument("--prefix", default="ddvs", help="key prefix (default ddvs)")
    parser.add_argument("--robot", default="robot0", help="robot name in the keys (default robot0)")
    add_zenoh_arguments(parser)
    add_ros_arguments(parser)


def _open_capture(source: str):
    import cv2

    capture = cv2.VideoCapture(int(source)) if source.isdigit() else cv2.VideoCapture(source)
    if not capture.isOpened():
        raise SystemExit(f"ddvs camera: cannot open {'device' if source.isdigit() else 'video file'} {source!r}")
    return capture


def run(args: argparse.Namespace) -> int:
    import signal

    import cv2

    from ddvs_service.logs import setup_logging
    from ddvs_service.protocol import Keys, open_session, session_config_from_args
    from ddvs_service.protocol.ros_cli import ros_settings_from_args

    setup_logging("INFO")
    capture = _open_capture(args.source)
    if args.calibration is not None:
        calibration = load_calibration(args.calibration)
    else:
        w, h = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        K = np.array([[args.focal, 0.0, (w - 1) / 2.0], [0.0, args.focal, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
        calibration = Calibration(K, np.zeros(5), w, h)
    fps = args.fps
    if fps is None and not args.source.isdigit():
        fps = capture.get(cv2.CAP_PROP_FPS) or DEFAULT_FILE_FPS
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with open_session(session_config_from_args(args)) as session:
        keys = Keys(args.prefix, args.robot, ros_settings_from_args(args))
        publisher = CameraPublisher(session, keys, calibration, args.encoding, args.publish, args.frame_id,
                                    args.compress, args.jpeg_quality)
        try:
            count = stream(capture, publisher, fps, stop, args.frames, args.loop)
        finally:
            publisher.close()
            capture.release()
    log.info("published %d frames", count)
    return 0

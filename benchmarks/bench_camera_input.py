"""Cost per frame of what a real camera's frames need before registration: rectification of raw frames (plumb_bob
and fisheye maps, `ddvs_service.rectification`), JPEG and PNG decoding of CompressedImage frames and the grey
conversion of driver encodings (`ddvs_service.grey`), at 320×240 and 640×480 (docs/cameras.md).

Each figure is the median of `--repeats` timed calls (ms) and its ratio to a baseline measured in the same run on
frames of the same size: one frame tracked by the planar tracker (`registration.tracker.Tracker.track`, the
service's default 200×150 template and engine settings, frames alternating 0.5 px either side of the reference),
the work every frame pays anyway, so a ratio is the share a stage adds to a frame's registration. The rectification
is also timed with OpenCV's 16-bit fixed-point maps (`CV_16SC2`, 1/32 px interpolation positions) beside the
float32 maps the service uses. The load average is printed with the figures: they are noisy on a shared host.

    .venv/bin/python benchmarks/bench_camera_input.py [--repeats 200]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_global_init import median_ms  # noqa: E402 - after the path set-up
from ddvs_service.camera import Intrinsics  # noqa: E402
from ddvs_service.grey import decode_frame  # noqa: E402
from ddvs_service.protocol import (  # noqa: E402
    CompressedImage,
    Header,
    Time,
    encode_compressed_image,
    encode_image,
    image_from_array,
)
from ddvs_service.rectification import camera_geometry  # noqa: E402
from sim.lens import DistortedLens  # noqa: E402
from sim.textures import texture_path  # noqa: E402

SIZES = ((320, 240), (640, 480))
LENSES = {"plumb_bob": (-0.3, 0.1, 0.0, 0.0, 0.0), "equidistant": (0.05, -0.02, 0.0, 0.0)}
HEADER = Header(Time(1, 0), "camera")


def frame_of_size(width: int, height: int) -> np.ndarray:
    """The boat poster as a BGR frame of `width`×`height` (textured everywhere, as a camera sees it)."""
    image = cv2.imread(str(texture_path("boat")), cv2.IMREAD_COLOR)
    return np.asarray(cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA), np.uint8)


def tracked_frame_ms(grey: np.ndarray, repeats: int) -> float:
    """Median time of one `Tracker.track` call on frames 0.5 px either side of the reference (ms)."""
    from ddvs_service.registration.config import RegistrationConfig
    from ddvs_service.registration.tracker import Tracker

    height, width = grey.shape
    roi = ((width - 200) // 2, (height - 150) // 2, 200, 150)
    reference = grey.astype(np.float32)
    frames = [np.asarray(cv2.warpAffine(reference, np.array([[1.0, 0.0, dx], [0.0, 1.0, 0.0]]), (width, height),
                                        flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT), np.float32)
              for dx in (-0.5, 0.5)]
    tracker = Tracker.prepare(reference, roi, RegistrationConfig())
    calls = iter(range(10**9))
    return median_ms(lambda: tracker.track(frames[next(calls) % 2]), repeats)


def measure(width: int, height: int, repeats: int) -> list[tuple[str, float]]:
    """(stage, ms) of every stage at one size; the first row is the baseline."""
    bgr = frame_of_size(width, height)
    grey = np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), np.uint8)
    rows = [("baseline: one tracked frame (200×150 template)", tracked_frame_ms(grey, max(repeats // 4, 10))),
            ("mono8 frame to float32", median_ms(lambda: grey.astype(np.float32), repeats))]
    intrinsics = Intrinsics.centred(0.9 * width, width, height)
    for model, d in LENSES.items():
        info = DistortedLens(intrinsics, model, d).camera_info(HEADER)
        rectifier = camera_geometry(info, rectified=False).rectifier
        assert rectifier is not None
        rows.append((f"rectify {model}, float maps (the service's)", median_ms(lambda r=rectifier: r(grey), repeats)))
        fixed = cv2.convertMaps(rectifier.map_x, rectifier.map_y, cv2.CV_16SC2)
        rows.append((f"rectify {model}, fixed-point maps",
                     median_ms(lambda m=fixed: cv2.remap(grey, m[0], m[1], cv2.INTER_LINEAR), repeats)))
        rows.append((f"maps of {model} (once per camera info)",
                     median_ms(lambda i=info: camera_geometry(i, rectified=False), max(repeats // 20, 3))))
    payloads = {
        "decode mono8 Image": (encode_image(image_from_array(grey, "mono8", HEADER)), False),
        "decode bgr8 Image to grey": (encode_image(image_from_array(bgr, "bgr8", HEADER)), False),
        "decode bayer_rggb8 Image to grey": (encode_image(image_from_array(grey, "bayer_rggb8", HEADER)), False),
        "decode yuv422 Image to grey": (encode_image(image_from_array(np.dstack([grey, grey]), "yuv422", HEADER)),
                                        False),
    }
    for name, params, fmt in (("JPEG q80 grey", [cv2.IMWRITE_JPEG_QUALITY, 80], ".jpg"),
                              ("JPEG q80 colour", [cv2.IMWRITE_JPEG_QUALITY, 80], ".jpg"),
                              ("PNG grey", [cv2.IMWRITE_PNG_COMPRESSION, 3], ".png")):
        source = bgr if "colour" in name else grey
        data = cv2.imencode(fmt, source, params)[1].tobytes()
        codec = "jpeg" if fmt == ".jpg" else "png"
        payloads[f"decode {name} CompressedImage ({len(data) // 1024} KiB)"] = (
            encode_compressed_image(CompressedImage(HEADER, codec, data)), True)
    for name, (payload, compressed) in payloads.items():
        rows.append((name, median_ms(lambda p=payload, c=compressed: decode_frame(p, c, 64 << 20), repeats)))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=200, help="timed calls per figure (default 200)")
    args = parser.parse_args()
    print(f"OpenCV {cv2.__version__}, {cv2.getNumThreads()} threads; load average {os.getloadavg()} "
          f"(1, 5, 15 min) on {os.cpu_count()} CPUs")
    for width, height in SIZES:
        rows = measure(width, height, args.repeats)
        baseline = rows[0][1]
        print(f"\n{width}×{height}: median of {args.repeats} calls")
        print("| stage | ms | × baseline |\n|---|---|---|")
        for name, ms in rows:
            print(f"| {name} | {ms:.3f} | {ms / baseline:.3f} |")
    print(f"\nload average after: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

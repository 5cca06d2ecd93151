"""`ddvs register REF CUR`: planar direct registration of two image files; prints one JSON line.

Output keys: `H` (3×3, reference → current pixels, 0-based pixel centres, H[2,2] = 1), `G`, `S`, `beta`,
`iterations` (per level, coarse → fine), `residual_rms`, `inlier_ratio`, `scale`, `converged`, `reason`, `wall_ms`
(the registration itself, excluding image loading). Exit status 0 when converged, 1 when not, 2 on bad input.
"""

from __future__ import annotations

import argparse
import json
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("reference", help="reference image file (colour is converted to grey)")
    parser.add_argument("current", help="current image file, same size as the reference")
    parser.add_argument("--roi", nargs=4, type=int, metavar=("X", "Y", "W", "H"), help="ROI in reference pixels")
    parser.add_argument("--init", metavar="H_FILE", help="initial homography: 3×3 text file (numpy.loadtxt)")
    parser.add_argument("--levels", type=int, help="pyramid levels at most (default: as many as the ROI size allows)")
    parser.add_argument("--gain-grid", default="1x1", metavar="RxC", help="gain grid rows x cols (default 1x1)")
    parser.add_argument("--robust", choices=("huber", "tukey", "none"), default="huber", help="M-estimator")


def _grid(text: str) -> tuple[int, int]:
    rows, sep, cols = text.lower().partition("x")
    if not sep or not rows.isdigit() or not cols.isdigit():
        raise ValueError(f"--gain-grid must look like RxC (e.g. 2x3), got {text!r}")
    return int(rows), int(cols)


def run(args: argparse.Namespace) -> int:
    import time

    import cv2
    import numpy as np

    from ddvs_service.registration.config import RegistrationConfig
    from ddvs_service.registration.images import to_grey
    from ddvs_service.registration.planar import register

    try:
        images = []
        for path in (args.reference, args.current):
            img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
            if img is None:
                raise ValueError(f"cannot read image {path!r}")
            images.append(to_grey(img))
        G0 = None if args.init is None else np.loadtxt(args.init).reshape(3, 3)
        levels = {} if args.levels is None else {"levels": args.levels}
        config = RegistrationConfig(**levels, gain_grid=_grid(args.gain_grid), robust=args.robust)
        start = time.perf_counter()
        result = register(images[0], images[1], roi=None if args.roi is None else tuple(args.roi), G0=G0,
                          config=config)
        wall_ms = (time.perf_counter() - start) * 1e3
    except (ValueError, OSError) as exc:
        print(json.dumps({"error": str(exc)}))
        return 2
    print(json.dumps({**result.to_json_dict(), "wall_ms": round(wall_ms, 3)}))
    sys.stdout.flush()
    return 0 if result.converged else 1

"""Real image pairs with ground-truth homographies (Oxford affine sequences), and the corner error used to judge a
registration against them.

Images come from `evaluation/data/` (the pairs shipped with the repository, see its README) or, for the others, from
the full datasets (`evaluation.datasets`, `DDVS_DATASETS`). Image k of sequence `seq` is compared with image 1;
`H1tokp` maps image-1 pixels to image-k pixels (0-based pixel centres).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ddvs_service.registration.images import to_grey
from evaluation.datasets import MISSING, datasets_dir

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
Roi = tuple[int, int, int, int]

SHIPPED_DIR = Path(__file__).resolve().parent / "data"
SHIPPED_PAIRS = (("boat", 2), ("bikes", 4), ("bikes", 6), ("leuven", 6))
PAIRS = (("boat", 2), *(("bikes", k) for k in range(2, 7)), *(("leuven", k) for k in range(2, 7)))  # the benchmark's
ROI_SIZES = ((200, 150), (400, 300))  # central ROIs of image 1 (w, h) on which pairs are judged
CAMERA_GAMMA = 2.2  # an sRGB-like response; the sequences' true responses are not published
# One gain and Huber's bounded weight: the engine settings with which the registrations from identity of the tests
# and benchmarks are measured. The schema's defaults (3×3 gains, Tukey) are the servo's; from identity over a large
# motion a single gain and Huber's weight keep the basin wider.
ONE_GAIN_HUBER: dict[str, Any] = {"gain_grid": (1, 1), "robust": "huber"}


def pair_file(seq: str, name: str) -> Path | None:
    """`evaluation/data/<seq>/<name>` if shipped, else `$DDVS_DATASETS/oxford/<seq>/<name>` if it exists, else None."""
    shipped = SHIPPED_DIR / seq / name
    if shipped.is_file():
        return shipped
    root = datasets_dir()
    full = None if root is None else root / "oxford" / seq / name
    return full if full is not None and full.is_file() else None


def is_available(seq: str, k: int) -> bool:
    """Whether both images and the ground truth of the pair 1→k of `seq` can be read here."""
    return all(pair_file(seq, name) is not None for name in ("img1.png", f"img{k}.png", f"H1to{k}p"))


def _required(seq: str, name: str) -> Path:
    path = pair_file(seq, name)
    if path is None:
        raise FileNotFoundError(f"{seq}/{name} is neither shipped in {SHIPPED_DIR} nor found: {MISSING}")
    return path


def load(seq: str, k: int) -> F32:
    """Image k of `seq` as grey float32 levels 0–255 (colour converted with ITU-R BT.601, `images.to_grey`)."""
    path = _required(seq, f"img{k}.png")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"{path} could not be read as an image")
    return to_grey(image)


def ground_truth(seq: str, k: int) -> F64:
    """Ground-truth homography image 1 → image k of `seq`, normalised to H[2,2] = 1."""
    H = np.loadtxt(_required(seq, f"H1to{k}p"))
    return H / H[2, 2]


def corner_error(H_true: F64, H_est: F64, roi: Roi) -> float:
    """Largest distance (pixels of image k) between the ROI `(x, y, w, h)`'s corner pixel centres mapped by the two
    homographies."""
    x, y, w, h = roi
    c = np.array([[x, x + w - 1, x + w - 1, x], [y, y, y + h - 1, y + h - 1], [1, 1, 1, 1]], dtype=float)
    a, b = H_true @ c, H_est @ c
    return float(np.max(np.linalg.norm(a[:2] / a[2] - b[:2] / b[2], axis=0)))


def centred_roi(shape: tuple[int, ...], w: int, h: int) -> Roi:
    """The w×h ROI `(x, y, w, h)` centred in an image of `shape` (rows, columns, ...)."""
    return ((shape[1] - w) // 2, (shape[0] - h) // 2, w, h)

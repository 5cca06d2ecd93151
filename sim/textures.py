"""Textures of the simulated targets: the grey images shipped in `sim/textures/` (source and licence in its README),
by name, or any image file by path."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

TEXTURE_DIR = Path(__file__).resolve().parent / "textures"
TEXTURES = ("graf", "boat", "wall", "notredame")


def texture_path(name_or_path: str) -> Path:
    """The file of a shipped texture (`TEXTURES`), or `name_or_path` itself when it is an existing file."""
    if name_or_path in TEXTURES:
        return TEXTURE_DIR / f"{name_or_path}.png"
    path = Path(name_or_path)
    if not path.is_file():
        raise FileNotFoundError(f"texture {name_or_path!r} is neither a shipped texture {TEXTURES} nor an image file")
    return path


def load_texture(name_or_path: str, blur_sigma: float = 0.0) -> NDArray[np.float32]:
    """Grey float32 texture (levels 0–255, read with `cv2.IMREAD_GRAYSCALE`), blurred by a Gaussian of `blur_sigma`
    texels when positive (to limit aliasing when rendered smaller)."""
    path = texture_path(name_or_path)
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ValueError(f"cannot read the texture image {str(path)!r}; expected a grey or colour image file")
    texture = image.astype(np.float32)
    return np.asarray(cv2.GaussianBlur(texture, (0, 0), blur_sigma), dtype=np.float32) if blur_sigma > 0 else texture

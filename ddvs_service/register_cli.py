"""`ddvs register REF CUR`: planar direct registration of two image files; prints one JSON line.

Output keys: `H` (3×3, reference → current pixels, 0-based pixel centres, H[2,2] = 1), `G`, `S`, `beta`,
`iterations` (per level, coarse → fine), `residual_rms`, `inlier_ratio`, `scale`, `converged`, `reason`, `wall_ms`
(the registration itself, excluding image loading). Exit status 0 when converged, 1 when not, 2 on bad input.

`--model general` registers the non-planar model (2) `p ∝ G p* + ρ*(p*) e` instead
(`registration.general_register.register_general`: ρ* estimated with several epipole starts); its extra keys:
`e` (epipole, pixels, same scale as `G`), `rho_coeffs`, `rho_degree`, `rho_std`, `parallax_px`, `margin`, `flags`.

`--gamma G` registers irradiance `255 (I / 255)^G` (the camera's response; `RegistrationConfig.gamma`);
`--defocus R` blurs the reference's irradiance by a uniform disk of radius R pixels (`RegistrationConfig.defocus_px`),
`--defocus search` estimates R (`registration.defocus.register_defocus`, planar model only) and adds `defocus_px`
and `defocus_trials` (`[radius, relative residual, converged]` per run) to the output.

The engine settings default to the configuration schema's (`RegistrationConfig`: the servo's 3×3 gains and Tukey);
from identity over a large motion a single gain with Huber's weight (`--gain-grid 1x1 --robust huber`) keeps the
basin wider.

`--init global` starts from the global initialiser (`registration.global_init`: any in-plane rotation, scale
0.6–1.6, the ROI anywhere in the image) instead of a homography file; its summary is added under `global_init`.
When it reports LOST nothing is refined: the output is `{"global_init": ..., "converged": false, "reason": ...}`
and the exit status 1.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the modules themselves are imported by `run`, so that `ddvs --help` stays light
    from numpy.typing import NDArray

    from ddvs_service.registration.general_result import GeneralResult
    from ddvs_service.registration.result import RegistrationResult


ONE_SHOT_ITERATIONS = 100  # per level; `RegistrationConfig.max_iterations` bounds a stream's frame instead


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ddvs_service.registration.config import RegistrationConfig  # the schema's defaults (pydantic, no Taichi)
    from ddvs_service.registration.general_config import GeneralConfig

    engine, general = RegistrationConfig(), GeneralConfig()
    parser.add_argument("reference", help="reference image file (colour is converted to grey)")
    parser.add_argument("current", help="current image file, same size as the reference")
    parser.add_argument("--roi", nargs=4, type=int, metavar=("X", "Y", "W", "H"), help="ROI in reference pixels")
    parser.add_argument("--init", metavar="H_FILE", help="initial homography: 3×3 text file (numpy.loadtxt), "
                        "or 'global' for the global initialiser")
    parser.add_argument("--levels", type=int, default=engine.levels,
                        help="pyramid levels at most (default: %(default)s, as many as the ROI size allows)")
    parser.add_argument("--gain-grid", default="{}x{}".format(*engine.gain_grid), metavar="RxC",
                        help="gain grid rows x cols (default %(default)s; from identity over a large motion, 1x1 "
                             "with --robust huber keeps the basin wider, or start with --init global)")
    parser.add_argument("--robust", choices=("huber", "tukey", "none"), default=engine.robust,
                        help="M-estimator (default %(default)s)")
    parser.add_argument("--max-iterations", type=int, default=ONE_SHOT_ITERATIONS, metavar="N",
                        help="Gauss-Newton iterations per pyramid level at most (default %(default)s: from identity, "
                             "Tukey's reweighting with a re-estimated scale contracts slowly at full resolution, "
                             "where a stream's warm-started frames need few)")
    parser.add_argument("--gamma", type=float, default=engine.gamma,
                        help="camera response exponent: register irradiance 255 (I/255)^GAMMA (default %(default)s)")
    parser.add_argument("--defocus", default="0", metavar="R|search",
                        help="relative defocus of the current image: disk radius in pixels applied to the "
                             "reference, or 'search' to estimate it (planar model; default 0)")
    parser.add_argument("--model", choices=("planar", "general"), default="planar",
                        help="planar homography (default) or the general model with epipole and parallax field")
    parser.add_argument("--rho-degree", type=int, choices=(2, 3), default=general.rho_degree,
                        help="general model: degree of the parallax basis (2 biquadratic, 3 bicubic; default "
                             "%(default)s)")
    parser.add_argument("--interpolation", choices=("bspline", "keys"), default=general.interpolation,
                        help="general model: sampling of the current image at full resolution, the interpolating "
                             "cubic B-spline or Keys' cubic convolution (GeneralConfig.interpolation; default "
                             "%(default)s)")


def _grid(text: str) -> tuple[int, int]:
    rows, sep, cols = text.lower().partition("x")
    if not sep or not rows.isdigit() or not cols.isdigit():
        raise ValueError(f"--gain-grid must look like RxC (e.g. 2x3), got {text!r}")
    return int(rows), int(cols)


def _defocus(text: str) -> float | None:
    """`--defocus`: a radius in pixels, or None for 'search'."""
    if text == "search":
        return None
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"--defocus must be a radius in pixels or 'search', got {text!r}") from None


def run(args: argparse.Namespace) -> int:
    import math
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
        start = time.perf_counter()  # the registration's wall time includes a global initialisation
        extra: dict[str, object] = {}
        G0: NDArray[np.float64] | None
        if args.init == "global":
            from ddvs_service.registration.global_init import register_global

            h, w = images[0].shape
            found = register_global(images[0], images[1], (0, 0, w, h) if args.roi is None else tuple(args.roi))
            extra["global_init"] = found.to_json_dict()
            if found.G is None:
                print(json.dumps({**extra, "converged": False, "reason": found.reason}))
                return 1
            G0 = found.G
        else:
            G0 = None if args.init is None else np.loadtxt(args.init).reshape(3, 3)
        defocus = _defocus(args.defocus)
        config = RegistrationConfig(levels=args.levels, max_iterations=args.max_iterations,
                                    gain_grid=_grid(args.gain_grid), robust=args.robust, gamma=args.gamma,
                                    defocus_px=0.0 if defocus is None else defocus)
        roi = None if args.roi is None else tuple(args.roi)
        if defocus is None and args.model == "general":
            raise ValueError("--defocus search estimates the defocus with the planar model; give a radius with "
                             "--model general")
        result: RegistrationResult | GeneralResult
        if defocus is None:
            from ddvs_service.registration.defocus import register_defocus

            fit = register_defocus(images[0], images[1], roi=roi, G0=G0, config=config)
            result = fit.result
            extra["defocus_px"] = fit.defocus_px
            extra["defocus_trials"] = [[r, s if math.isfinite(s) else None, c] for r, s, c in fit.trials]
        elif args.model == "general":
            from ddvs_service.registration.general_config import GeneralConfig
            from ddvs_service.registration.general_register import register_general

            result = register_general(images[0], images[1], roi=roi, G0=G0,
                                      config=GeneralConfig(base=config, rho_degree=args.rho_degree,
                                                          interpolation=args.interpolation))
        else:
            result = register(images[0], images[1], roi=roi, G0=G0, config=config)
        wall_ms = (time.perf_counter() - start) * 1e3
    except (ValueError, OSError) as exc:
        print(json.dumps({"error": str(exc)}))
        return 2
    print(json.dumps({**result.to_json_dict(), **extra, "wall_ms": round(wall_ms, 3)}))
    sys.stdout.flush()
    return 0 if result.converged else 1

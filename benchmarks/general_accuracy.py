"""Accuracy of the general registration along the paper's synthetic trajectory (saddle, 200×150 ROI), measured as
`tests/test_general_registration.py::test_paper_trajectory_from_a_cold_start` does (cold start on image 0, then
the same images tracked), for several ways of forming the frames: the warp's RMS error against the true warp over
the ROI (px), the error of the control error (16) from the estimate, absolute and relative to the criterion's
tolerance max(1 % of its norm, 1e-4), and the shape error of the estimated ρ* (`evaluation.general_accuracy`).

Renders: `point` (`sim.freeflyer.render_view`: one ray per pixel centre), `box:K` (`render_camera` with K×K rays per
pixel averaged, no optical blur), `camera:S` (`render_camera`, 4×4 rays per pixel, Gaussian optical blur of S px)
and `texture:S` (as `box:4`, the texture blurred by a Gaussian of S texels: a blur carried by the surface, the same
in every frame once warped, where the optical blur of `camera:S` is the same in every *image* and so differs between
two frames by the warp's local distortion); a `/bspline` suffix registers with `GeneralConfig(interpolation="bspline")`
(Keys by default).

Run: `.venv/bin/python benchmarks/general_accuracy.py [--renders point box:4/bspline camera:0.7/bspline] [--json]`
"""

from __future__ import annotations

import argparse
import json

from ddvs_service.registration.general_config import GeneralConfig
from evaluation.general_accuracy import measure, renderer
from sim.textures import load_texture


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--renders", nargs="+", default=["point", "camera:0.7", "camera:0.7/bspline"])
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    texture = load_texture("graf")
    report = {}
    for spec in args.renders:
        interpolation = "bspline" if spec.endswith("/bspline") else "keys"
        rows = report[spec] = measure(renderer(spec, texture), GeneralConfig(interpolation=interpolation)).rows
        worst = max(rows, key=lambda r: r["relative"])
        early = max(r["relative"] for r in rows if r["image"] <= 180)
        late = [r for r in rows if r["image"] >= 380]
        print(f"{spec:>18}: all converged {all(r['converged'] for r in rows)}; warp error ≤ "
              f"{max(r['warp_px'] for r in rows):.4f} px; |Δε̄|/tol ≤ {early:.2f} (images ≤ 180), "
              f"≤ {worst['relative']:.2f} overall (image {worst['image']}, {worst['error']:.1e} absolute), "
              f"≤ {max(r['relative'] for r in late):.2f} from image 380 (≤ {max(r['error'] for r in late):.1e} "
              f"absolute, warp ≤ {max(r['warp_px'] for r in late):.4f} px); ρ* shape error "
              f"{min(r['rho_shape'] for r in rows):.2%}–{max(r['rho_shape'] for r in rows):.2%}", flush=True)
    if args.json:
        print(json.dumps(report))


if __name__ == "__main__":
    main()

"""Accuracy of the general registration along the paper's synthetic trajectory (saddle, 200×150 ROI), for several
ways of forming the frames: per render, the warp's RMS error, the control error's error relative to its tolerance and
the ρ* shape error, as `evaluation.general_accuracy.measure` computes them (its docstring defines the render specs).

Run: `.venv/bin/python benchmarks/general_accuracy.py [--renders point box:4/bspline camera:0.7/bspline] [--json]`
"""

from __future__ import annotations

import argparse
import json

from ddvs_service.registration.config import RegistrationConfig
from ddvs_service.registration.general_config import GeneralConfig
from evaluation.general_accuracy import measure, renderer
from evaluation.pairs import ONE_GAIN_HUBER
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
        rows = report[spec] = measure(renderer(spec, texture), GeneralConfig(
            base=RegistrationConfig(**ONE_GAIN_HUBER), interpolation=interpolation)).rows
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

"""Compile time of the planar step against the gain grid (issue 21): first launch of `kernels.planar_step` in a fresh
process, cold (Taichi's offline cache at an empty directory) and warm (the same directory again), and the median
launch afterwards.

Each measurement runs in its own process (`--grid R C`); the cache directory is chosen through Taichi's
`TI_OFFLINE_CACHE_FILE_PATH`. The first launch of any kernel in a process also pays Taichi's runtime start, so what
grows with the grid is the difference to the 1×1 row.

    .venv/bin/python benchmarks/bench_compile.py [--grids 1x1 2x2 3x3 4x4] [--markdown]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.rows import print_rows  # noqa: E402


def first_launch(rows: int, cols: int) -> dict[str, float]:
    """This process: time the first `planar_step` launch on a 200×150 ROI, then the median of 50 more."""
    import cv2
    import numpy as np

    from kernels import planar_step as ps
    from kernels.backend import init
    from sim.textures import load_texture

    init()
    ref = cv2.GaussianBlur(load_texture("boat"), (0, 0), 1.0).astype(np.float32)
    G = np.array([[1.01, 0.02, 3.3], [-0.015, 0.99, -2.7], [1e-5, -2e-5, 1.0]])
    cur = cv2.warpPerspective(ref, G, (ref.shape[1], ref.shape[0])) * 0.9 + 7.0
    u0, v0, u1, v1 = 300, 250, 499, 399
    params = np.zeros(ps.PARAMS_GAINS + rows * cols, dtype=np.float32)
    params[ps.PARAMS_G:ps.PARAMS_G + 9] = G.reshape(9)
    params[ps.PARAMS_NORM:ps.PARAMS_NORM + 3] = (0.5 * (u0 + u1), 0.5 * (v0 + v1), 0.5 * (u1 - u0))
    params[ps.PARAMS_ROI:ps.PARAMS_ROI + 4] = (u0, v0, u1, v1)
    params[ps.PARAMS_SPAN:ps.PARAMS_SPAN + 4] = (u0, v0, u1, v1)
    params[ps.PARAMS_SIGMA], params[ps.PARAMS_ROBUST], params[ps.PARAMS_BANDS] = 4.0, 1, 8
    params[ps.PARAMS_GAINS:] = 1.0
    work = np.zeros(ps.work_size(ps.n_params(rows, cols)), dtype=np.float32)
    t0 = time.perf_counter()
    ps.planar_step(ref, cur, params, work, rows, cols)
    first = time.perf_counter() - t0
    launches = []
    for _ in range(50):
        t0 = time.perf_counter()
        ps.planar_step(ref, cur, params, work, rows, cols)
        launches.append(time.perf_counter() - t0)
    return {"first_s": round(first, 2), "launch_ms": round(1e3 * float(np.median(launches)), 3)}


def measure(rows: int, cols: int) -> dict[str, object]:
    """Cold then warm, each in a fresh process, sharing one new cache directory."""
    out: dict[str, object] = {"grid": f"{rows}×{cols}"}
    with tempfile.TemporaryDirectory(prefix="ddvs-ticache-") as cache:
        env = {**os.environ, "TI_OFFLINE_CACHE_FILE_PATH": cache}
        for kind in ("cold", "warm"):
            run = subprocess.run([sys.executable, __file__, "--grid", str(rows), str(cols)], env=env, check=True,
                                 capture_output=True, text=True)
            out[kind] = json.loads(run.stdout.strip().splitlines()[-1])
    out["load_average"] = round(os.getloadavg()[0], 2)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", type=int, nargs=2, metavar=("ROWS", "COLS"), help=argparse.SUPPRESS)
    parser.add_argument("--grids", nargs="+", default=["1x1", "2x2", "3x3", "4x4"])
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    if args.grid:
        print(json.dumps(first_launch(*args.grid)))
        return
    rows = [measure(*(int(n) for n in grid.split("x"))) for grid in args.grids]
    print_rows(rows, args.markdown,
               ["gain grid", "first launch, cold cache", "first launch, warm cache", "launch afterwards", "load"],
               lambda r: [r["grid"], f"{r['cold']['first_s']:.1f} s", f"{r['warm']['first_s']:.1f} s",
                          f"{r['warm']['launch_ms']:.2f} ms", f"{r['load_average']:.2f}"])


if __name__ == "__main__":
    main()

"""Compile time of the frame-path kernels against the gain grid (issue 21): first launch in a fresh process, cold
(Taichi's offline cache at an empty directory) and warm (the same directory again), and the median launch afterwards.

- `planar`: `kernels.planar_step` (the planar model's step).
- `general`: the four `kernels.general_step` launches of the general model's frame path (ρ* columns or not × Keys
  or B-spline sampling), degree `--degree` of ρ*; the times are their sum. The sampling is a run-time argument, so
  the ρ* columns alone specialise: the first launch of each pair compiles, the second runs compiled code (a
  `--general-module` whose sampling is a template argument compiles all four).
Each launch runs under `kernels.backend.compile_settings` (Taichi's settings the registrations compile them with);
a `--general-module FILE` under its own `compile_settings` if it has one, else with Taichi's defaults.

Each measurement runs in its own process; the cache directory is chosen through Taichi's
`TI_OFFLINE_CACHE_FILE_PATH`, so nobody else's cache is touched. Besides wall time each row gives the process CPU
time of the first launches (all threads; Taichi compiles on the launching thread): on a shared host the wall time
grows with the load, the CPU time much less. The first launch of any kernel in a process also pays Taichi's
runtime start (≈ 0.1 s).

    .venv/bin/python benchmarks/bench_compile.py [--paths planar general] [--grids 1x1 2x2 3x3 4x4 1x4 4x1]
        [--degree 2] [--general-module FILE] [--markdown]

`--general-module FILE` measures another version of `kernels/general_step.py` (e.g. `git show
REV:kernels/general_step.py > /tmp/general_step_before.py`) in place of this tree's, for before/after rows in one
run; the `general` rows then name the file. `--compare FILE` instead runs this tree's `general_step` and FILE's in
one process on the same inputs: how far their normal equations differ and their launch times, interleaved.

    .venv/bin/python benchmarks/bench_compile.py --compare FILE [--grids …] [--degree 3] [--reps 200] [--markdown]
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.rows import print_rows  # noqa: E402

MODULE_ENV = "DDVS_BENCH_GENERAL_MODULE"  # the child's `--general-module`

ROI = (300, 250, 499, 399)  # u0, v0, u1, v1: 200×150
H_TRUE = ((1.01, 0.02, 3.3), (-0.015, 0.99, -2.7), (1e-5, -2e-5, 1.0))


def _images():
    import cv2
    import numpy as np

    from sim.textures import load_texture

    ref = cv2.GaussianBlur(load_texture("boat"), (0, 0), 1.0).astype(np.float32)
    cur = cv2.warpPerspective(ref, np.array(H_TRUE), (ref.shape[1], ref.shape[0])) * 0.9 + 7.0
    return ref, cur.astype(np.float32)


def planar_launches(rows: int, cols: int, degree: int) -> dict[str, Callable[[], None]]:
    """`planar_step` on a 200×150 ROI of a warped boat pair (`degree` unused)."""
    import numpy as np

    from kernels import planar_step as ps
    from kernels.backend import compile_settings

    ref, cur = _images()
    u0, v0, u1, v1 = ROI
    params = np.zeros(ps.PARAMS_GAINS + rows * cols, dtype=np.float32)
    params[ps.PARAMS_G:ps.PARAMS_G + 9] = np.array(H_TRUE).reshape(9)
    params[ps.PARAMS_NORM:ps.PARAMS_NORM + 3] = (0.5 * (u0 + u1), 0.5 * (v0 + v1), 0.5 * (u1 - u0))
    params[ps.PARAMS_ROI:ps.PARAMS_ROI + 4] = ROI
    params[ps.PARAMS_SPAN:ps.PARAMS_SPAN + 4] = ROI
    params[ps.PARAMS_SIGMA], params[ps.PARAMS_ROBUST], params[ps.PARAMS_BANDS] = 4.0, 1, 8
    params[ps.PARAMS_GAINS:] = 1.0
    work = np.zeros(ps.work_size(ps.n_params(rows, cols)), dtype=np.float32)

    def launch() -> None:
        with compile_settings():
            ps.planar_step(ref[None], cur[None], params[None], work[None], rows, cols)  # a stack of one robot
    return {"planar_step": launch}


def general_launches(rows: int, cols: int, degree: int) -> dict[str, Callable[[], None]]:
    """The four `general_step` launches of the general frame path on the same pair, ρ* of `degree` non-zero; the
    last one is the tracking launch (no ρ* columns, B-spline sampling)."""
    cases = general_cases(_general_module(os.environ.get(MODULE_ENV)), rows, cols, degree)
    return {name: launch for name, (launch, _sums, _n) in cases.items()}


Case = tuple[Callable[[], None], Any, int]  # (launch, the sums it writes, number of columns)


def general_cases(gs: ModuleType, rows: int, cols: int, degree: int) -> dict[str, Case]:
    """`general_launches` of the module `gs`, each with the float32 array its launch writes the normal equations
    to and its number of columns `n`: the packed `JᵀWJ` upper triangle, `JᵀWr` and statistics (`gs.n_acc(n)`)."""
    import numpy as np

    from ddvs_service.registration.general_basis import ParallaxBasis

    ref, cur = _images()
    u0, v0, u1, v1 = ROI
    basis = ParallaxBasis.over((u0, v0, u1 - u0 + 1, v1 - v0 + 1), degree)
    params = np.zeros(gs.params_size(basis.size), dtype=np.float32)
    params[gs.PARAMS_G:gs.PARAMS_G + 9] = np.array(H_TRUE).reshape(9)
    params[gs.PARAMS_E:gs.PARAMS_E + 3] = (0.3, -0.2, 0.001)
    params[gs.PARAMS_NORM:gs.PARAMS_NORM + 3] = (0.5 * (u0 + u1), 0.5 * (v0 + v1), 0.5 * (u1 - u0))
    params[gs.PARAMS_BNORM:gs.PARAMS_BNORM + 3] = (*basis.centre, basis.half_size)
    params[gs.PARAMS_ROI:gs.PARAMS_ROI + 4] = ROI
    params[gs.PARAMS_DOMAIN:gs.PARAMS_DOMAIN + 4] = (-1e9, -1e9, 1e9, 1e9)
    params[gs.PARAMS_SPAN:gs.PARAMS_SPAN + 4] = ROI
    params[gs.PARAMS_SIGMA], params[gs.PARAMS_ROBUST], params[gs.PARAMS_BANDS] = 4.0, 1, 8
    params[gs.PARAMS_GAINS:gs.PARAMS_GAINS + rows * cols] = 1.0
    n_mono = (degree + 1) ** 2
    params[gs.PARAMS_RHO:gs.PARAMS_RHO + n_mono] = basis.monomial_coefficients(np.full(basis.size, 0.3))
    for i, row in enumerate(basis.B):
        params[gs.PARAMS_BASIS + i * gs.MAX_MONOMIALS:gs.PARAMS_BASIS + i * gs.MAX_MONOMIALS + n_mono] = row
    cases: dict[str, Case] = {}
    for with_rho, spline in ((True, False), (True, True), (False, False), (False, True)):
        n = gs.n_columns(basis.size, with_rho, rows, cols)
        work = np.zeros(gs.work_size(n), dtype=np.float32)
        name = f"general_step rho={int(with_rho)} spline={int(spline)}"
        cases[name] = (functools.partial(_launch_general, gs, ref, cur, params, work, degree, basis.size, with_rho,
                                         rows, cols, spline), work[:gs.n_acc(n)], n)
    return cases


def _launch_general(gs: ModuleType, *args: object) -> None:
    """`gs.general_step(*args)` under `kernels.backend.compile_settings` (what the registration compiles it with);
    another file's module (`--general-module`) under its own `compile_settings`, or plainly where it has none."""
    from kernels import general_step
    from kernels.backend import compile_settings

    settings: Callable[[], contextlib.AbstractContextManager[None]] = compile_settings
    if gs is not general_step:
        settings = getattr(gs, "compile_settings", contextlib.nullcontext)
    with settings():
        gs.general_step(*args)


def _general_module(path: str | None):
    """`kernels.general_step`, or the module at `path` (`--general-module`)."""
    if not path:
        from kernels import general_step

        return general_step
    spec = importlib.util.spec_from_file_location("general_step_measured", path)
    if spec is None or spec.loader is None:
        raise SystemExit(f"--general-module: cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


PATHS = {"planar": planar_launches, "general": general_launches}


def compare(before: str, rows: int, cols: int, degree: int, reps: int) -> list[dict[str, object]]:
    """This process: this tree's `general_step` and the module at `before`, each specialisation compiled once (each
    under its own module's settings), then `reps` launches of both in turn. Per specialisation: how far the normal
    equations differ (`JᵀWJ` entries over `sqrt(H_ii H_jj)`, `JᵀWr` over its largest entry) and the median launch
    times."""
    import numpy as np

    from kernels import general_step
    from kernels.backend import init

    init()
    after = general_cases(general_step, rows, cols, degree)
    old = general_cases(_general_module(before), rows, cols, degree)
    out = []
    for name, (launch, sums, n) in after.items():
        launch_old, sums_old, _n = old[name]
        launch_old()
        launch()
        nt = n * (n + 1) // 2
        upper = np.triu_indices(n)
        scale = np.sqrt(np.abs(np.diag(_unpacked(sums_old[:nt], n))))
        hess = float(np.max(np.abs(sums[:nt] - sums_old[:nt]) / np.maximum(np.outer(scale, scale)[upper], 1e-30)))
        grad_old = sums_old[nt:nt + n]
        grad = float(np.max(np.abs(sums[nt:nt + n] - grad_old)) / max(float(np.max(np.abs(grad_old))), 1e-30))
        times: dict[str, list[float]] = {"before": [], "after": []}
        for _ in range(reps):
            for key, run in (("before", launch_old), ("after", launch)):
                t0 = time.perf_counter()
                run()
                times[key].append(time.perf_counter() - t0)
        ms_old, ms_new = (1e3 * float(np.median(times[k])) for k in ("before", "after"))
        out.append({"grid": f"{rows}×{cols}", "degree": degree, "kernel": name, "hess": hess, "grad": grad,
                    "before_ms": ms_old, "after_ms": ms_new, "load_average": round(os.getloadavg()[0], 2)})
    return out


def _unpacked(triangle: Any, n: int) -> Any:
    """The symmetric `n × n` matrix whose row-major upper triangle is `triangle`."""
    import numpy as np

    full = np.zeros((n, n))
    full[np.triu_indices(n)] = triangle
    return full + np.triu(full, 1).T


def first_launches(path: str, rows: int, cols: int, degree: int) -> dict[str, object]:
    """This process: wall and CPU time of each kernel's first launch, then the median of 50 more of the last."""
    import numpy as np

    from kernels.backend import init

    init()
    launches = PATHS[path](rows, cols, degree)
    per_kernel = {}
    for name, launch in launches.items():
        t0, c0 = time.perf_counter(), time.process_time()
        launch()
        per_kernel[name] = (round(time.perf_counter() - t0, 2), round(time.process_time() - c0, 2))
    last = list(launches.values())[-1]
    times = []
    for _ in range(50):
        t0 = time.perf_counter()
        last()
        times.append(time.perf_counter() - t0)
    return {"first_s": round(sum(w for w, _ in per_kernel.values()), 2),
            "first_cpu_s": round(sum(c for _, c in per_kernel.values()), 2),
            "per_kernel": per_kernel, "launch_ms": round(1e3 * float(np.median(times)), 3)}


def measure(path: str, rows: int, cols: int, degree: int, module: str | None = None) -> dict[str, object]:
    """Cold then warm, each in a fresh process, sharing one new cache directory."""
    out: dict[str, object] = {"path": path, "grid": f"{rows}×{cols}", "degree": degree if path == "general" else None,
                              "module": module if path == "general" else None}
    with tempfile.TemporaryDirectory(prefix="ddvs-ticache-") as cache:
        env = {**os.environ, "TI_OFFLINE_CACHE_FILE_PATH": cache, MODULE_ENV: module or ""}
        for kind in ("cold", "warm"):
            run = subprocess.run([sys.executable, __file__, "--child", path, str(rows), str(cols), str(degree)],
                                 env=env, check=True, capture_output=True, text=True)
            out[kind] = json.loads(run.stdout.strip().splitlines()[-1])
    out["load_average"] = round(os.getloadavg()[0], 2)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--child", nargs=4, metavar=("PATH", "ROWS", "COLS", "DEGREE"), help=argparse.SUPPRESS)
    parser.add_argument("--paths", nargs="+", choices=sorted(PATHS), default=["planar", "general"])
    parser.add_argument("--grids", nargs="+", default=["1x1", "2x2", "3x3", "4x4", "1x4", "4x1"])
    parser.add_argument("--degree", type=int, default=2, choices=[2, 3], help="degree of ρ* (general path)")
    parser.add_argument("--general-module", metavar="FILE", help="another general_step module to measure")
    parser.add_argument("--compare", metavar="FILE", help="this tree's general_step against FILE's, in one process")
    parser.add_argument("--reps", type=int, default=200, help="interleaved launches of each (--compare)")
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    if args.child:
        path, rows, cols, degree = args.child
        print(json.dumps(first_launches(path, int(rows), int(cols), int(degree))))
        return
    grids = [tuple(int(n) for n in grid.split("x")) for grid in args.grids]
    if args.compare:
        compared = [r for grid_rows, grid_cols in grids
                    for r in compare(args.compare, grid_rows, grid_cols, args.degree, args.reps)]
        print_rows(compared, args.markdown,
                   ["gain grid", "ρ* degree", "kernel", "JᵀWJ difference", "JᵀWr difference",
                    "launch before / after", "ratio", "load"],
                   lambda r: [r["grid"], str(r["degree"]), r["kernel"], f"{r['hess']:.1e}", f"{r['grad']:.1e}",
                              f"{r['before_ms']:.3f} / {r['after_ms']:.3f} ms",
                              f"{r['after_ms'] / r['before_ms']:.2f}", f"{r['load_average']:.2f}"])
        return
    rows = [measure(path, grid_rows, grid_cols, args.degree, args.general_module) for path in args.paths
            for grid_rows, grid_cols in grids]
    print_rows(rows, args.markdown,
               ["path", "gain grid", "first launches, cold cache: wall / CPU", "each kernel, cold: CPU",
                "first launches, warm cache: wall / CPU", "launch afterwards", "load"],
               lambda r: [r["path"] + (f" (ρ* degree {r['degree']})" if r["degree"] else "")
                          + (f" [{Path(r['module']).name}]" if r["module"] else ""), r["grid"],
                          f"{r['cold']['first_s']:.1f} s / {r['cold']['first_cpu_s']:.1f} s",
                          " / ".join(f"{cpu:.1f}" for _, cpu in r["cold"]["per_kernel"].values()) + " s",
                          f"{r['warm']['first_s']:.1f} s / {r['warm']['first_cpu_s']:.1f} s",
                          f"{r['warm']['launch_ms']:.2f} ms", f"{r['load_average']:.2f}"])


if __name__ == "__main__":
    main()

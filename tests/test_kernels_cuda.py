"""The registration kernels on CUDA (issue 21): a planar and a general registration of the same rendered pair run in
a process started with `DDVS_TAICHI_ARCH=cuda` (what `ddvs serve --arch cuda` selects) and in one on the CPU, and
their warps agree. Taichi picks its backend once per process, hence the subprocesses; without a CUDA device Taichi
falls back to the CPU and the test skips."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]

# Renders the paper's saddle (reference at the identity, current after a small motion), registers the planar model
# (`register`) and the general one (`register_general`, ρ* estimated) over a 200×150 ROI, and prints the backend and
# both warps at a 5×4 grid of ROI points (full-resolution pixels) as JSON.
SCRIPT = """
import json
import cv2
import numpy as np
from ddvs_service.camera import Intrinsics
from ddvs_service.lie import pose, so3_exp
from ddvs_service.registration.general_register import register_general
from ddvs_service.registration.planar import register
from kernels.backend import init
from sim.freeflyer import render_view
from sim.surfaces import paper_saddle
from sim.textures import texture_path

arch = init()
intr = Intrinsics.centred(500.0, 550, 418)
roi = (175, 134, 200, 150)
texture = cv2.imread(str(texture_path("graf")), cv2.IMREAD_GRAYSCALE).astype(np.float32)
motion = pose(so3_exp(0.02 * np.array([-0.1, -0.31, 1.04])), 0.02 * np.array([0.17, -0.11, 0.01]))
reference = render_view(paper_saddle(), texture, intr, np.eye(4))[0]
current = render_view(paper_saddle(), texture, intr, motion)[0]
u, v = np.meshgrid(np.linspace(175, 374, 5), np.linspace(134, 283, 4))
points = np.c_[u.ravel(), v.ravel()]
planar = register(reference, current, roi=roi)
general = register_general(reference, current, roi=roi, G0=planar.G)
homogeneous = np.c_[points, np.ones(len(points))] @ planar.G.T
print(json.dumps({"arch": arch, "planar_converged": bool(planar.converged),
                  "general_converged": bool(general.converged),
                  "planar": (homogeneous[:, :2] / homogeneous[:, 2:]).tolist(),
                  "general": general.warp(points).tolist()}))
"""


def run(arch: str, code: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "DDVS_TAICHI_ARCH": arch}
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=900)


@pytest.fixture(scope="module")
def cuda() -> None:
    probe = run("cuda", "from kernels.backend import init; print(init())")
    if probe.returncode != 0 or probe.stdout.strip().splitlines()[-1:] != ["cuda"]:
        pytest.skip("no CUDA device: Taichi falls back to the CPU here, nothing to compare")


@pytest.mark.slow
def test_registration_on_cuda_matches_the_cpu(cuda: None) -> None:
    results = {}
    for arch in ("cuda", "cpu"):
        done = run(arch, SCRIPT)
        assert done.returncode == 0, done.stderr[-3000:]
        results[arch] = json.loads(done.stdout.strip().splitlines()[-1])
    assert results["cuda"]["arch"] == "cuda" and results["cpu"]["arch"] == "cpu"
    for model in ("planar", "general"):
        assert results["cuda"][f"{model}_converged"] and results["cpu"][f"{model}_converged"], model
        # float32 sums in another order (GPU threads, no AVX lanes): the same optimum to well under a pixel
        np.testing.assert_allclose(results["cuda"][model], results["cpu"][model], atol=0.02, err_msg=model)

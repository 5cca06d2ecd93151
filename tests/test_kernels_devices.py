"""The kernels on Taichi's GPU backends (docs/gpu.md): Vulkan — on a machine without a GPU through lavapipe, Mesa's
CPU driver, which `scripts/setup.sh` installs — and CUDA. Taichi picks its backend once per process, so each check
runs subprocesses with `DDVS_TAICHI_ARCH` set and compares the device's answers with the CPU's:
- the kernel tests themselves (`KERNEL_TESTS`, those not marked slow) on the device;
- planar and general registration of a rendered pair (warps within 0.02 px of the CPU's) and planar registration of
  every shipped real pair (`evaluation/data`, both ROI sizes: corners within 0.05 px of the CPU's);
- the free-flyer's closed loop on rendered frames (`tests/test_general_registration.py`) on the device;
- one `ddvs serve --arch DEVICE` exchange: the state machine and latency checks, the status naming the backend.

A backend Taichi cannot start here is skipped, unless it is required: listed in `DDVS_REQUIRE_DEVICES`
(comma-separated; `make test` sets `vulkan`, `benchmarks/device_check.py` the device it checks) or, for Vulkan, with
the `CI` environment variable set. A required backend that is missing fails the test instead.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import free_port
from test_service_node import converge, past_lost, running_service, scene, service_config, shifted, state_of

from evaluation.pairs import ROI_SIZES, centred_roi, corner_error, is_available

ROOT = Path(__file__).resolve().parents[1]
DEVICES = ("vulkan", "cuda")
KERNEL_TESTS = ("test_kernels_planar_step.py", "test_kernels_launch.py", "test_bspline.py", "test_image_formation.py",
                "test_spline_window.py", "test_freeflyer.py", "test_coarse_search.py", "test_global_init.py",
                "test_residual.py", "test_general_registration.py", "test_lockstep.py")
SHIPPED_PAIRS = (("bikes", 4), ("bikes", 6), ("boat", 2), ("leuven", 6))

pytestmark = [pytest.mark.device, pytest.mark.slow]  # minutes: make test runs them, make test-fast does not

# Renders the paper's saddle (reference at the identity, current after a small motion), registers the planar model
# (`register`) and the general one (`register_general`, ρ* estimated) over a 200×150 ROI, and prints the backend,
# both warps and the true one (ray-cast in float64) at a 5×4 grid of ROI points (full-resolution pixels) as JSON.
RENDERED_PAIR = """
import json
import cv2
import numpy as np
from ddvs_service.camera import Intrinsics
from ddvs_service.lie import pose, pose_inv, so3_exp
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
rays = np.c_[(points - [intr.cx, intr.cy]) / [intr.fx, intr.fy], np.ones(len(points))]
seen = (pose_inv(motion) @ np.c_[rays * paper_saddle().intersect(np.eye(4), rays)[:, None], np.ones(len(rays))].T)[:3]
truth = np.c_[intr.fx * seen[0] / seen[2] + intr.cx, intr.fy * seen[1] / seen[2] + intr.cy]
print(json.dumps({"arch": arch, "planar_converged": bool(planar.converged),
                  "general_converged": bool(general.converged),
                  "planar": (homogeneous[:, :2] / homogeneous[:, 2:]).tolist(),
                  "general": general.warp(points).tolist(), "truth": truth.tolist()}))
"""

# Registers every pair of `pairs` (JSON list of [seq, k, [x, y, w, h]]) from the identity and prints the backend and
# each estimated homography H (image 1 → image k) as JSON.
REAL_PAIRS = """
import json
import sys
from ddvs_service.registration.planar import register
from evaluation.pairs import load
from kernels.backend import init

arch = init()
results = []
for seq, k, roi in json.loads(sys.argv[1]):
    result = register(load(seq, 1), load(seq, k), roi=tuple(roi))
    results.append({"converged": bool(result.converged), "H": result.H.tolist()})
print(json.dumps({"arch": arch, "results": results}))
"""


def required(device: str) -> bool:
    """Whether a missing `device` fails the tests rather than skipping them (module docstring)."""
    listed = os.environ.get("DDVS_REQUIRE_DEVICES", "").replace(" ", "").split(",")
    return device in listed or (device == "vulkan" and bool(os.environ.get("CI")))


def run(arch: str, *args: str, timeout: float = 900) -> subprocess.CompletedProcess[str]:
    """`python *args` in the repository with Taichi on `arch`."""
    env = {**os.environ, "DDVS_TAICHI_ARCH": arch}
    return subprocess.run([sys.executable, *args], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=timeout)


def last_json(done: subprocess.CompletedProcess[str]) -> dict:
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module", params=DEVICES)
def device(request: pytest.FixtureRequest) -> str:
    """A backend Taichi starts here, by name; skipped or failed otherwise (module docstring)."""
    name = str(request.param)
    probe = run(name, "-c", "from kernels.backend import init; print(init())")
    if probe.returncode != 0 or probe.stdout.strip().splitlines()[-1:] != [name]:
        reason = (probe.stderr.strip().splitlines() or ["no message"])[-1][-300:]
        message = f"Taichi cannot start {name!r} here (it fell back to the CPU): {reason}"
        if required(name):
            pytest.fail(f"{message}; required by DDVS_REQUIRE_DEVICES or CI (scripts/setup.sh installs lavapipe)")
        pytest.skip(message)
    return name


def test_the_kernel_tests_pass_on_the_device(device: str) -> None:
    done = run(device, "-m", "pytest", "-q", "-m", "not slow", "-p", "no:cacheprovider",
               *(f"tests/{name}" for name in KERNEL_TESTS))
    assert done.returncode == 0, done.stdout[-6000:]
    assert " passed" in done.stdout.splitlines()[-1] and "failed" not in done.stdout.splitlines()[-1]


def test_registration_of_a_rendered_pair_matches_the_cpu(device: str) -> None:
    """The planar warp within 0.02 px of the CPU's: float32 sums in another order (device threads, no CPU vector
    lanes). The general warp within 0.1 px of the CPU's and of the truth: ρ* estimated from this one pair leaves a
    shallow valley of the cost, along which the last Gauss–Newton steps stop where that rounding takes them (lavapipe:
    0.06 px apart, the CPU 0.07 px and Vulkan 0.01 px from the truth)."""
    results = {arch: last_json(run(arch, "-c", RENDERED_PAIR)) for arch in (device, "cpu")}
    assert results[device]["arch"] == device and results["cpu"]["arch"] == "cpu"
    for model, bound in (("planar", 0.02), ("general", 0.1)):
        assert results[device][f"{model}_converged"] and results["cpu"][f"{model}_converged"], model
        np.testing.assert_allclose(results[device][model], results["cpu"][model], atol=bound, err_msg=model)
    for arch in (device, "cpu"):
        gap = np.linalg.norm(np.subtract(results[arch]["general"], results[arch]["truth"]), axis=1)
        assert np.max(gap) < 0.1, (arch, gap)


def test_the_shipped_real_pairs_register_as_on_the_cpu(device: str) -> None:
    import cv2

    cases = []
    for seq, k in SHIPPED_PAIRS:
        assert is_available(seq, k), f"shipped pair {seq} 1→{k} missing from evaluation/data"
        shape = cv2.imread(str(ROOT / "evaluation" / "data" / seq / "img1.png"), cv2.IMREAD_GRAYSCALE).shape
        cases += [(seq, k, centred_roi(shape, *size)) for size in ROI_SIZES]
    pairs = json.dumps(cases)
    results = {arch: last_json(run(arch, "-c", REAL_PAIRS, pairs)) for arch in (device, "cpu")}
    assert results[device]["arch"] == device
    for (seq, k, roi), on_device, on_cpu in zip(cases, results[device]["results"], results["cpu"]["results"],
                                                strict=True):
        assert on_device["converged"] == on_cpu["converged"], (seq, k, roi)
        gap = corner_error(np.array(on_cpu["H"]), np.array(on_device["H"]), roi)
        assert gap <= 0.05, f"{seq} 1→{k} ROI {roi}: corners {gap:.4f} px from the CPU's"


def test_the_free_flyer_closed_loop_runs_on_the_device(device: str) -> None:
    done = run(device, "-m", "pytest", "-q", "-p", "no:cacheprovider",
               "tests/test_general_registration.py::test_closed_loop_on_rendered_images_follows_the_exact_loop")
    assert done.returncode == 0 and "1 passed" in done.stdout, done.stdout[-6000:]


def test_serve_on_the_device(device: str, tmp_path: Path) -> None:
    """`ddvs serve --arch DEVICE`: reference, servo, convergence, a jump re-acquired, the latency breakdown, and the
    status naming the backend."""
    port = free_port()
    config = service_config(port, tmp_path / "state")
    img = scene()
    with running_service(config, tmp_path, port, "--arch", device) as (_, op):
        assert op.command(op="set_reference", source="next_frame").ok
        assert op.send(img)["state"] == "READY"
        assert op.command(op="start").ok
        status = op.send(shifted(img, 2.0, -1.5))
        assert status["state"] == "SERVOING" and status["backend"] == device, status
        assert np.linalg.norm(op.twists[-1]) > 0
        assert converge(op, img)["state"] == "CONVERGED"
        status, _ = past_lost(op, shifted(img, 6.0, -4.0, 3.0))  # a jump: LOST, re-acquired on the device
        assert status["state"] == "SERVOING", status
        latency = status["latency_ms"]
        assert set(latency) == {"decode", "registration", "control", "publish", "total", "cpu"}
        assert 0 < latency["registration"] <= latency["total"], latency
        assert op.command(op="stop").ok and state_of(op) == "STOPPED"

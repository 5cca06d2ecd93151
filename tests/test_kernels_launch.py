"""kernels.launch.Prepared: a prepared relaunch computes what a plain call does, on the buffers' current contents."""

import numpy as np
import pytest
import taichi as ti

from kernels.backend import init
from kernels.launch import Prepared

init()


@ti.kernel
def _scaled_sum(src: ti.types.ndarray(dtype=ti.f32, ndim=2), factor: ti.f32,
                out: ti.types.ndarray(dtype=ti.f32, ndim=1), power: ti.template()):
    """`out[r] = factor · Σ_c src[r, c]^power`."""
    for r in range(src.shape[0]):
        total = 0.0
        for c in range(src.shape[1]):
            total += src[r, c] ** power
        out[r] = factor * total


def test_prepared_launch_matches_a_plain_call_and_sees_new_contents() -> None:
    rng = np.random.default_rng(3)
    src = rng.uniform(0.0, 2.0, size=(37, 53)).astype(np.float32)
    out = np.zeros(37, dtype=np.float32)
    plain = np.zeros(37, dtype=np.float32)
    launch = Prepared(_scaled_sum, src, 1.5, out, 2)
    for _ in range(3):
        src[...] = rng.uniform(0.0, 2.0, size=src.shape)  # same buffer, new contents
        out[...] = -1.0
        launch()
        _scaled_sum(src, 1.5, plain, 2)
        np.testing.assert_allclose(out, plain, rtol=1e-6)
        np.testing.assert_allclose(out, 1.5 * (src.astype(np.float64) ** 2).sum(axis=1), rtol=1e-5)


def test_prepared_launch_refuses_non_contiguous_arrays_and_unknown_arguments() -> None:
    src = np.zeros((8, 16), dtype=np.float32)[:, ::2]
    with pytest.raises(ValueError, match="C-contiguous"):
        Prepared(_scaled_sum, src, 1.0, np.zeros(8, dtype=np.float32), 1)
    with pytest.raises(TypeError, match="numpy arrays and scalars"):
        Prepared(_scaled_sum, np.zeros((8, 8), dtype=np.float32), "two", np.zeros(8, dtype=np.float32), 1)


@ti.kernel
def _uses_an_undefined_name(out: ti.types.ndarray(dtype=ti.f32, ndim=1)):
    for i in range(out.shape[0]):
        out[i] = not_defined_anywhere  # noqa: F821 - the compile error under test


def test_compile_errors_still_name_the_file_line_and_source() -> None:
    """kernels.backend replaces Taichi's source-position formatter; a compile error must still say where."""
    with pytest.raises(Exception, match=r"(?s)test_kernels_launch\.py\", line \d+, in _uses_an_undefined_name.*"
                                        r"not_defined_anywhere"):
        _uses_an_undefined_name(np.zeros(4, dtype=np.float32))

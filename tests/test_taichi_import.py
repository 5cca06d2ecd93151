"""`kernels.taichi_import`: Taichi's decorators tell methods from functions as before, with the quick line reader.
(No `from __future__ import annotations`: Taichi reads the kernels' annotations as objects.)"""

import inspect
import sys

import numpy as np
import taichi as ti
from taichi.lang import kernel_impl

from kernels.backend import init
from kernels.taichi_import import _current_line


def test_current_line_is_what_inspect_reads() -> None:
    frame = sys._getframe()
    quick, slow = _current_line(frame), inspect.getframeinfo(frame)
    assert (quick.filename, quick.lineno, quick.function, quick.code_context) == \
        (slow.filename, slow.lineno, slow.function, slow.code_context)
    assert kernel_impl.inspect.getframeinfo is _current_line  # Taichi's decorators use it
    assert inspect.getframeinfo is not _current_line  # nobody else does


@ti.data_oriented
class Scaler:
    def __init__(self, factor: float) -> None:
        self.factor = factor

    @ti.kernel
    def scale(self, x: ti.types.ndarray(dtype=ti.f32, ndim=1)):  # type: ignore[valid-type]
        for i in x:
            x[i] *= self.factor


@ti.kernel
def add_one(x: ti.types.ndarray(dtype=ti.f32, ndim=1)):  # type: ignore[valid-type]
    for i in x:
        x[i] += 1.0


def test_decorators_tell_methods_from_functions() -> None:
    init()
    assert Scaler.scale._is_classkernel and not add_one._is_classkernel
    x = np.arange(4, dtype=np.float32)
    Scaler(3.0).scale(x)
    add_one(x)
    np.testing.assert_array_equal(x, [1.0, 4.0, 7.0, 10.0])

"""Prepared kernel launches: bind a Taichi kernel to fixed numpy buffers once, then relaunch it cheaply.

A plain call of a `@ti.kernel` re-walks its arguments in Python on every launch (type checks, pointer extraction,
a new launch context): most of the cost of launching a kernel with a few ndarray arguments, and several times that
of a prepared relaunch (figures: docs/performance.md; PLATFORM-NOTES: the launch cost grows with every ndarray
argument). An iterative solver launches the same kernel on the same buffers many times with only
their *contents* changing (parameters in, sums out), so `Prepared` builds the launch context once and replays it.

Contract: the numpy arrays given to `Prepared` must stay C-contiguous, keep their shape and stay alive (the object
holds references to them); their contents may change between launches, and the kernel sees the current contents.
Template arguments are compile-time constants fixed at preparation. On a non-CPU backend external arrays are copied
to and from the device by the regular launch path, so there `Prepared` falls back to a plain call per launch.
Each launch is a checkpoint of `kernels.exclusive.GATE` (a background holder hands the lock to a waiting frame there).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import taichi as ti
from taichi.lang import impl
from taichi.types import template

from kernels.exclusive import GATE


class Prepared:
    """`kernel(*args)` bound once; `launch()` runs it again on the same buffers (module docstring)."""

    def __init__(self, kernel: Callable[..., Any], *args: Any) -> None:
        self._args = args  # keeps the buffers alive
        primal = kernel._primal  # type: ignore[attr-defined]  # taichi.lang.kernel_impl.Kernel
        bound = [(value, argument.name) for value, argument in zip(args, primal.arguments, strict=True)
                 if not isinstance(argument.annotation, template)]
        for value, name in bound:  # the same contract on every backend
            if isinstance(value, np.ndarray):
                if not value.flags.c_contiguous:
                    raise ValueError(f"argument {name!r}: a prepared launch needs C-contiguous arrays")
            elif not isinstance(value, bool | int | float | np.integer | np.floating):
                raise TypeError(f"argument {name!r}: a prepared launch takes numpy arrays and scalars, "
                                f"got {type(value).__name__}")
        self._launch: Callable[[], None] = lambda: kernel(*args)  # the plain call: non-CPU backends keep it
        if impl.current_cfg().arch != ti.cpu:
            return
        t_kernel = primal.compiled_kernels[primal.ensure_compiled(*args)]
        context = t_kernel.make_launch_context()
        for slot, (value, _name) in enumerate(bound):
            if isinstance(value, np.ndarray):
                context.set_arg_external_array_with_shape((slot,), int(value.ctypes.data), value.nbytes,
                                                          value.shape, 0)
            elif isinstance(value, bool | int | np.integer):
                context.set_arg_int((slot,), int(value))
            else:
                context.set_arg_float((slot,), float(value))
        prog = impl.get_runtime().prog
        compiled = prog.compile_kernel(prog.config(), prog.get_device_caps(), t_kernel)
        self._launch = lambda: prog.launch_kernel(compiled, context)  # the closure keeps the context alive

    def __call__(self) -> None:
        """Launch the kernel on the bound buffers' current contents."""
        GATE.checkpoint()
        self._launch()

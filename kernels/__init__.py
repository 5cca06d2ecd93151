"""Taichi kernels: every per-pixel computation of ddvs. numpy arrays in, numpy arrays out; no I/O.

Taichi is imported here, before any kernel module: `taichi_import` makes its decorators cheaper to apply."""

from kernels.taichi_import import import_taichi

import_taichi()

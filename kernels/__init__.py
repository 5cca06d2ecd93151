"""Taichi kernels: every per-pixel computation of ddvs. numpy arrays in, numpy arrays out; no I/O."""

"""Imports Taichi with its decorators' one slow step replaced (this package's `__init__` calls `import_taichi`).

Taichi's `@ti.func` and `@ti.kernel` ask whether they decorate a method (`kernel_impl._inside_class`) by reading the
current source line of a caller's frame with `inspect.getframeinfo`, whose `inspect.getmodule` walks every loaded
module on each call, once per decorator on the service's import path (Taichi's own and this package's; the cost is
in docs/performance.md, Start-up). `_current_line` reads the same line from `linecache` (the line, or None where
there is no source, such as importlib's frames: the same answers as `inspect.getframeinfo`, tested).
"""

from __future__ import annotations

import inspect
import linecache
import types
from types import FrameType


def _current_line(frame: FrameType, context: int = 1) -> inspect.Traceback:
    """`inspect.getframeinfo(frame)` as Taichi uses it (one line of context): file, line, function, current line."""
    if context != 1:
        raise ValueError(f"one line of context only, got {context}")
    code = frame.f_code
    line = linecache.getline(code.co_filename, frame.f_lineno, frame.f_globals)
    return inspect.Traceback(code.co_filename, frame.f_lineno, code.co_name, [line] if line else None, 0)


def import_taichi() -> None:
    """Import Taichi with `_current_line` as `inspect.getframeinfo` while its own modules are decorated, then give
    Taichi's decorator module an `inspect` of its own with `_current_line` for every later decorator."""
    slow = inspect.getframeinfo
    inspect.getframeinfo = _current_line  # type: ignore[assignment]
    try:
        from taichi.lang import kernel_impl
    finally:
        inspect.getframeinfo = slow
    quick = types.ModuleType(inspect.__name__, inspect.__doc__)
    quick.__dict__.update(inspect.__dict__)
    quick.getframeinfo = _current_line  # type: ignore[attr-defined]
    kernel_impl.inspect = quick

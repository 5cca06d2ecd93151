"""Chooses the Taichi backend once per process.

`init()` is idempotent: the first call picks the architecture (`cpu` by default, or `cuda` / `vulkan` / `gpu` when
asked, or the `DDVS_TAICHI_ARCH` environment variable; `ddvs serve --arch`); later calls return the architecture in
use and refuse a conflicting request, because Taichi cannot switch backend without invalidating every allocated
field. Taichi falls back to the CPU when the requested device is absent (it warns); `init` returns the architecture
Taichi actually runs on (`cpu` then), so a caller can tell, or, with `fallback=False`, refuses the fallback
(`BackendUnavailable`). Every kernel of this package runs on every backend from one source (docs/gpu.md: what
Taichi's SPIR-V path for Vulkan cannot take, and how far each backend's sums differ from the CPU's).
"""

from __future__ import annotations

import ast
import functools
import os
import textwrap
from collections.abc import Iterator
from contextlib import contextmanager
from types import SimpleNamespace

import taichi as ti
from taichi.lang import impl, kernel_impl
from taichi.lang.ast.ast_transformer_utils import ASTTransformerContext

from kernels.exclusive import GATE

_ARCHS = {"cpu": ti.cpu, "cuda": ti.cuda, "vulkan": ti.vulkan, "gpu": ti.gpu}
_chosen: str | None = None  # the backend Taichi runs on
_requested: str | None = None  # what the first call asked for


class BackendUnavailable(RuntimeError):
    """Taichi could not start the requested backend here (no such device or driver) and no fallback was allowed."""


def init(arch: str | None = None, fallback: bool = True) -> str:
    """Initialise Taichi on `arch` ('cpu', 'cuda', 'vulkan' or 'gpu'; default `$DDVS_TAICHI_ARCH`, else 'cpu') once;
    return the architecture in use ('cpu', 'cuda', 'vulkan', …: Taichi's name of the backend it started, which
    differs from `arch` after a fallback). With `fallback=False` a start on another backend than the one asked for
    ('gpu': any but the CPU) is undone and raises `BackendUnavailable`."""
    global _chosen, _requested
    requested = arch or os.environ.get("DDVS_TAICHI_ARCH", "cpu")
    if requested not in _ARCHS:
        raise ValueError(f"unknown Taichi backend {requested!r}; expected one of {sorted(_ARCHS)}")
    if _chosen is not None:
        if arch is not None and arch not in (_chosen, _requested):
            raise RuntimeError(f"Taichi already initialised on {_chosen!r}; cannot switch to {arch!r} in this process")
        return _chosen
    _brief_source_positions()
    _source_read_once()
    os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")  # no daily request to Taichi's server from a servo
    ti.init(
        arch=_ARCHS[requested],
        default_fp=ti.f32,
        offline_cache=True,
        log_level=ti.WARN,
        debug=False,
    )
    started = impl.current_cfg().arch
    running = "cpu" if started == ti.cpu else started.name  # `ti.cpu` is the host's (x64, arm64)
    if not fallback and not satisfies(requested, running):
        ti.reset()
        raise BackendUnavailable(f"Taichi cannot start the {requested!r} backend here (it fell back to {running!r}): "
                                 f"expected a {requested} device and its driver")
    _requested, _chosen = requested, running
    return _chosen


def satisfies(requested: str, running: str) -> bool:
    """Whether Taichi running on `running` is what `requested` asked for ('gpu': any backend but the CPU)."""
    return running != "cpu" if requested == "gpu" else running == requested


def current() -> str:
    """The backend Taichi runs on ('cpu', 'vulkan', 'cuda', …), or '' before `init`."""
    return _chosen or ""


def finish() -> None:
    """End this process's Taichi program, which writes what the process compiled to Taichi's offline cache: Taichi
    writes it only when its program is finalised, otherwise as the interpreter exits, and only if the program
    object is destroyed then — never once `gc.freeze()` has moved it out of the collector's reach, as `ddvs serve`
    does with its start-up objects. For the end of a process: every thread that launches kernels must be done or
    stopped, so this takes `kernels.exclusive.GATE` for good first (a background search waits at its next
    checkpoint until the process exits); no kernel runs afterwards."""
    global _chosen, _requested
    if _chosen is None:
        return
    GATE.close()
    ti.reset()
    _chosen = _requested = None


def _source_position(self: ASTTransformerContext, node: ast.stmt | ast.expr) -> str:
    """`File "…", line N, in kernel:` and the source line: what Taichi prints for a compile error at `node`."""
    return (f'File "{self.file}", line {node.lineno + self.lineno_offset}, in {self.func.func.__name__}:\n'
            f"{self.src[node.lineno - 1]}\n")


def _brief_source_positions() -> None:
    """Taichi's front end formats a source position (TextWrapper with a ^^^ marker) for *every* AST node it
    visits, errors or not; on this project's unrolled kernels that is about half of the Python-side compile time,
    paid on every first launch even with the offline cache warm (planar_step: measured with cProfile). Replace the
    formatter by one that names the same file, line and function and quotes the line, without the marker."""
    ASTTransformerContext.get_pos_info = _source_position


def _source_read_once() -> None:
    """Taichi's front end reads a function's source (`inspect.getsourcelines`: the whole file tokenised to find the
    block) each time it builds the function's tree, which is once per kernel and once per `ti.func` call site with
    its own template arguments: about a fifth of the front end's time at a start with the offline cache warm
    (docs/performance.md, Start-up). The source of a loaded module does not change, so read it once per function
    (Taichi copies the lines it is given and parses a fresh tree from them every time). At each build Taichi also
    re-wraps every line (`textwrap.fill`) and dedents the block (`textwrap.dedent`) before it parses it: pure
    functions of the same lines, cached as well (its module uses `textwrap` for nothing else)."""
    kernel_impl.getsourcelines = functools.cache(kernel_impl.getsourcelines)
    kernel_impl.textwrap = SimpleNamespace(fill=functools.cache(textwrap.fill), dedent=functools.cache(textwrap.dedent))


@contextmanager
def compile_settings(advanced: bool = False) -> Iterator[None]:
    """Taichi's settings for compiling the unrolled accumulating kernels (`planar_step`, `general_step`, the global
    initialiser's `screen_step`), restored on exit: its CFG optimisation (store-to-load forwarding, dead stores) and
    its advanced optimisations (constant folding, algebraic simplification, common subexpressions, loop-invariant
    code motion) off, LLVM's own passes doing that work instead. On those kernels' unrolled accumulations Taichi's
    passes were most of a cold compile, growing with the gain grid (docs/performance.md, Compile time); without them
    a cold compile takes much less CPU time, with the same sums up to float32 rounding and the same launch and
    warm-cache times within the noise.
    `advanced`: keep the advanced optimisations on, the CFG optimisation alone off (the B-spline prefilter: the
    same coefficients and launch time with a fifth less CPU time cold; without Taichi's loop-invariant code motion
    its launches took a third longer, LLVM not telling its loads and stores through one array apart).
    Enclose whatever compiles a specialisation: its first plain call, or the construction of a
    `kernels.launch.Prepared` for it (on the CPU; another backend compiles at the first launch, with Taichi's
    defaults). Taichi's offline cache keys on these settings, so a kernel compiled outside keeps an entry of its own.
    The settings are process-wide: like any Taichi work this runs on one thread at a time (`kernels.exclusive.GATE`,
    which hands over only at a checkpoint, and none lies in here), so no other kernel compiles under them."""
    config = impl.current_cfg()
    saved = config.cfg_optimization, config.advanced_optimization
    config.cfg_optimization = False
    config.advanced_optimization = advanced
    try:
        yield
    finally:
        config.cfg_optimization, config.advanced_optimization = saved

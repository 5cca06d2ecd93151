"""Per-kernel breakdown of `ddvs serve --config FILE --warmup-only`: for each Taichi kernel specialisation
the warm-up compiles, the process CPU time of its Python front end (`Kernel.materialize`: AST walk, IR built), of
`compile_kernel` (with the offline cache cold: Taichi's IR passes and LLVM's optimisation, then the cache entry;
warm: the cache load) and of its first launch (machine code generated from the LLVM IR), in that process.

Run it with the offline cache at an empty directory for a cold compile, the same directory again for a warm one:

    d=$(mktemp -d); TI_OFFLINE_CACHE_FILE_PATH=$d .venv/bin/python benchmarks/warmup_kernels.py \
        configs/serve/ur5_saddle.json

Prints one line per specialisation (`name#n`: Taichi's n-th instance of the kernel) and the totals; the process
CPU time includes the imports, `ti.init` and the warm-up's own Python and numpy work. The timers wrap Taichi's
`Kernel.materialize` and its C++ program's `compile_kernel` and `launch_kernel` in this process only, so the
warm-up runs here whole: `--warmup-only` compiles a general configuration's engine step kernels in a second process
beside it (`service.startup.start_general_steps`), which this breakdown does not fork.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from taichi._lib import core as ti_core  # noqa: E402
from taichi.lang import kernel_impl  # noqa: E402

FRONT: dict[str, float] = defaultdict(float)  # specialisation → CPU seconds
COMPILE: dict[str, float] = defaultdict(float)
LAUNCH: dict[str, float] = defaultdict(float)
_names: dict[int, str] = {}  # id of Taichi's C++ kernel, then of its compiled data → specialisation


def _timed_materialize(original: Callable[..., Any]) -> Callable[..., Any]:
    def materialize(self: Any, key: Any = None, args: Any = None, arg_features: Any = None) -> Any:
        if key is not None and key in self.compiled_kernels:
            return original(self, key, args, arg_features)
        t0 = time.process_time()
        result = original(self, key, args, arg_features)
        key = key if key is not None else (self.func, 0, self.autodiff_mode)
        name = f"{self.func.__name__}#{key[1]}"
        FRONT[name] += time.process_time() - t0
        _names[id(self.compiled_kernels[key])] = name
        return result
    return materialize


def _timed_compile(original: Callable[..., Any]) -> Callable[..., Any]:
    def compile_kernel(self: Any, config: Any, caps: Any, kernel: Any) -> Any:
        t0 = time.process_time()
        compiled = original(self, config, caps, kernel)
        name = _names.get(id(kernel), "?")
        if id(compiled) not in _names:  # the first compile of this specialisation; later calls hit Taichi's cache
            COMPILE[name] += time.process_time() - t0
            _names[id(compiled)] = name
        return compiled
    return compile_kernel


def _timed_launch(original: Callable[..., Any]) -> Callable[..., Any]:
    launched: set[int] = set()

    def launch_kernel(self: Any, compiled: Any, context: Any) -> Any:
        if id(compiled) in launched:
            return original(self, compiled, context)
        t0 = time.process_time()
        result = original(self, compiled, context)
        launched.add(id(compiled))
        LAUNCH[_names.get(id(compiled), "?")] += time.process_time() - t0
        return result
    return launch_kernel


def main() -> None:
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    kernel_impl.Kernel.materialize = _timed_materialize(kernel_impl.Kernel.materialize)
    program = ti_core.Program
    program.compile_kernel = _timed_compile(program.compile_kernel)
    program.launch_kernel = _timed_launch(program.launch_kernel)
    from ddvs_service.service import serve_cli, startup

    startup.start_general_steps = lambda *_: None  # every kernel in this process (module docstring)
    parser = argparse.ArgumentParser(prog="ddvs serve")
    serve_cli.add_arguments(parser)
    code = serve_cli.run(parser.parse_args(["--config", sys.argv[1], "--warmup-only"]))
    if code:
        raise SystemExit(f"ddvs serve --warmup-only exited {code}")
    names = sorted(set(FRONT) | set(COMPILE), key=lambda n: -(FRONT[n] + COMPILE[n] + LAUNCH[n]))
    print(f"{'specialisation':28s} {'front end':>9s} {'compile':>8s} {'1st launch':>10s}  (s CPU)")
    for name in names:
        print(f"{name:28s} {FRONT[name]:9.3f} {COMPILE[name]:8.3f} {LAUNCH[name]:10.3f}")
    print(f"{'all':28s} {sum(FRONT.values()):9.3f} {sum(COMPILE.values()):8.3f} {sum(LAUNCH.values()):10.3f}")
    print(f"process CPU {time.process_time():.2f} s")


if __name__ == "__main__":
    main()

"""The layers point one way (docs/ARCHITECTURE.md): every import of every module — at the top or inside a function —
read from the source with `ast`, checked against the package order, and no import cycle between files."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# package -> the packages it may import (besides itself and third-party code)
ALLOWED: dict[str, set[str]] = {
    "kernels": set(),
    "ddvs_service": {"kernels"},
    "sim": {"kernels", "ddvs_service"},
    "clients": {"kernels", "ddvs_service"},
    "orchestration": {"kernels", "ddvs_service", "sim", "clients"},
    "evaluation": {"kernels", "ddvs_service", "sim", "orchestration"},
    "ddvs": set(),  # subcommand modules are named in a table and imported only when their subcommand runs
    "benchmarks": {"kernels", "ddvs_service", "sim", "clients", "orchestration", "evaluation"},
    "tests": {"kernels", "ddvs_service", "sim", "clients", "orchestration", "evaluation", "ddvs"},
}


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> set[str]:
    """Every module named by an import statement of `path` (absolute imports; the project uses no relative ones)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def project_graph() -> dict[str, set[str]]:
    """Module → the project modules it imports (a `from package import name` counts as the submodule when it is
    one, else as the package)."""
    files = [p for package in ALLOWED for p in (ROOT / package).rglob("*.py")]
    modules = {module_name(p): p for p in files}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        graph[name] = {target for target in imports(path) if target in modules and target != name}
    return graph


def test_packages_import_only_the_layers_below():
    wrong = sorted(
        f"{source} imports {target}"
        for source, targets in project_graph().items()
        for target in targets
        if (a := source.split(".")[0]) != (b := target.split(".")[0]) and b not in ALLOWED[a]
    )
    assert not wrong, "imports against the layering:\n" + "\n".join(wrong)


def test_no_import_cycle_between_modules():
    graph = project_graph()
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    cycles: list[list[str]] = []

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append([*path[path.index(nxt):], nxt])
            elif nxt not in state:
                visit(nxt, [*path, nxt])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    assert not cycles, "import cycles:\n" + "\n".join(" → ".join(c) for c in cycles)


def test_help_imports_neither_the_renderer_nor_taichi():
    """`ddvs --help` stays light: it imports no subcommand, so neither SAPIEN, Taichi, Zenoh nor OpenCV."""
    code = (
        "import sys\n"
        "from ddvs.cli import build_parser\n"
        "build_parser().format_help()\n"
        "print(sorted(m for m in ('sapien', 'taichi', 'zenoh', 'cv2', 'pinocchio') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr

"""The Python API reference (`docs/reference/api/*.md`) from the docstrings of the core package `ddvs_service`.

Read statically with `ast` (nothing is imported: no Taichi start-up, and it builds offline in a second): for each
module, its docstring, then each public class (its docstring, its public methods) and each public function, with
the signature as written in the source. One page per sub-package.
"""

from __future__ import annotations

import ast
from pathlib import Path

from scripts.docsgen.markdown import GENERATED, ROOT

PACKAGE = "ddvs_service"


def pages(root: Path = ROOT) -> dict[str, list[Path]]:
    """Page name → the modules it documents: `ddvs_service` (top-level modules), then one page per sub-package."""
    base = root / PACKAGE
    out: dict[str, list[Path]] = {PACKAGE: sorted(p for p in base.glob("*.py"))}
    for sub in sorted(d for d in base.iterdir() if (d / "__init__.py").exists()):
        out[f"{PACKAGE}.{sub.name}"] = sorted(sub.glob("*.py"))
    return out


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def signature(node: ast.FunctionDef | ast.AsyncFunctionDef) -> str:
    """`name(args) -> returns` as written in the source (annotations included, `self` dropped)."""
    args = node.args
    if args.args and args.args[0].arg in ("self", "cls"):
        args = ast.arguments(posonlyargs=args.posonlyargs, args=args.args[1:], vararg=args.vararg,
                             kwonlyargs=args.kwonlyargs, kw_defaults=args.kw_defaults, kwarg=args.kwarg,
                             defaults=args.defaults[-len(args.args) + 1:] if len(args.defaults) >= len(args.args)
                             else args.defaults)
    returns = f" -> {ast.unparse(node.returns)}" if node.returns else ""
    return f"{node.name}({ast.unparse(args)}){returns}"


def _public(name: str) -> bool:
    return not name.startswith("_")


def markdown_text(docstring: str) -> str:
    """A docstring as Markdown: `<` outside code spans and indented code blocks escaped, so that `<prefix>/<robot>`
    reads as written instead of vanishing as an HTML tag."""
    out = []
    in_code = False  # inside a `code span`, which may run over several lines
    for line in docstring.splitlines():
        if not in_code and line.startswith("    "):
            out.append(line)  # an indented code block
            continue
        parts = line.split("`")
        for i in range(len(parts)):
            if not in_code:
                parts[i] = parts[i].replace("<", "&lt;")
            if i < len(parts) - 1:
                in_code = not in_code
        out.append("`".join(parts))
    return "\n".join(out)


def _doc(node: ast.AST) -> str:
    text = ast.get_docstring(node)  # type: ignore[arg-type]
    return f"{markdown_text(text.strip())}\n" if text else ""


def _function(node: ast.FunctionDef | ast.AsyncFunctionDef, level: int, owner: str = "") -> str:
    decorators = {ast.unparse(d) for d in node.decorator_list}
    kind = "property" if "property" in decorators else "classmethod" if "classmethod" in decorators else ""
    head = f"{'#' * level} `{owner}{node.name}`" + (f" <small>{kind}</small>" if kind else "") + "\n"
    return "\n".join([head, f"```python\n{signature(node)}\n```\n", _doc(node)])


def _class(node: ast.ClassDef, level: int) -> str:
    bases = ", ".join(ast.unparse(b) for b in node.bases)
    out = [f"{'#' * level} `{node.name}`\n", f"```python\nclass {node.name}({bases})\n```\n", _doc(node)]
    for item in node.body:
        if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)) and _public(item.name) and ast.get_docstring(item):
            out.append(_function(item, level + 1, f"{node.name}."))
    return "\n".join(out)


def render_module(path: Path, root: Path = ROOT) -> str:
    """One module's section: its docstring, its public classes and functions in source order."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = [f"## `{module_name(path, root)}`\n", _doc(tree)]
    for node in tree.body:
        if isinstance(node, ast.ClassDef) and _public(node.name):
            out.append(_class(node, 3))
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and _public(node.name):
            out.append(_function(node, 3))
    return "\n".join(out)


def render(name: str, modules: list[Path], root: Path = ROOT) -> str:
    """One page: the modules of a package, each with its public names."""
    package_init = root / Path(*name.split(".")) / "__init__.py"
    intro = _doc(ast.parse(package_init.read_text(encoding="utf-8"))) if package_init.exists() else ""
    return "\n".join([
        GENERATED.format(source=f"the docstrings of {name}"),
        f"# `{name}`\n",
        intro,
        *(render_module(p, root) for p in modules if p.name != "__init__.py"),
    ])

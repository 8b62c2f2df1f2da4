#!/usr/bin/env python3
"""Lint: febed's modules import downwards only, and no chain of imports leads back to where it started.

Usage:
    python tools/check_layers.py [-v] [ROOT]

ROOT is the folder that holds the `febed` package (default: the repository root, the parent of `tools/`).
Every import of a febed module counts, at the top of a module or inside a function (only those under
`if TYPE_CHECKING:` do not: they never run). The rules:

1. Layers. Every module belongs to one layer of LAYERS below, listed from the top down. A module may import
   modules of its own layer and of the layers further down. Layers on the same level (runs and post; dem, gas
   and coupling) are independent: neither imports the other. A module that matches no layer is an error too.
2. No import cycles: no module reaches itself through the imports of the modules it imports.
3. An import inside a function is for a heavy dependency (HEAVY: DOLFINx, PETSc, Numba, Matplotlib, ...) that the
   module would otherwise load when it is imported. One that loads nothing the module does not load already
   belongs at the top of the module: it is printed as a note, which does not change the exit status.

Each violation is printed as `file:line: febed.X imports febed.Y (why)`; the exit status is 1 if there is any,
else 0 (2 if ROOT holds no febed package). `-v` also lists every import inside a function with what it avoids.
"""

from __future__ import annotations

import ast
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# (level, {layer: module prefixes}), from the top down. A prefix names a module or a package with everything
# in it; "febed" alone is the package's own __init__ (its public names are imported by name on first use).
LAYERS = (
    ("command line", {"cli": ("febed.cli", "febed.post.cli", "febed.post.__main__")}),
    ("studies", {"study": ("febed.study",)}),
    ("runs and post-processing", {
        "runs": ("febed.runs", "febed.restart", "febed.preflight"),
        "post": ("febed.post",),
    }),
    ("the coupled model", {"model": ("febed.solver", "febed.bed", "febed.coarse", "febed.case")}),
    ("MPI particles", {"parallel": ("febed.parallel",)}),
    ("physics", {"dem": ("febed.dem",), "gas": ("febed.gas",), "coupling": ("febed.coupling",)}),
    ("base", {"base": ("febed.io", "febed.meshing", "febed.schema", "febed.registry", "febed.kernel_cache",
                       "febed.kernel_records", "febed")}),
)  # fmt: skip

# Third-party packages worth importing inside a function when the module does not load them otherwise: slow
# to import, or with a side effect (mpi4py starts MPI). The post-processing starts without any of them, and
# `febed params` or `febed status` without the DOLFINx and Numba ones.
HEAVY = frozenset({
    "dolfinx", "basix", "ufl", "petsc4py", "mpi4py", "numba", "llvmlite", "scipy", "matplotlib", "gmsh", "h5py",
})  # fmt: skip


@dataclass(frozen=True)
class Import:
    """One import statement's febed target: who imports what, where, and whether inside a function."""

    source: str
    target: str
    line: int
    in_function: bool
    missing: str = ""  # the module named, if there is no such module (`target` is then its nearest package)


@dataclass
class Module:
    """A febed module: its file, its febed imports and the third-party packages it imports at the top."""

    name: str
    path: Path
    is_package: bool
    imports: list[Import]
    top_packages: set[str]


def module_name(package_dir: Path, path: Path) -> tuple[str, bool]:
    """Dotted name of a file under the febed package folder, and whether it is a package's __init__."""
    parts = list(path.relative_to(package_dir.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        return ".".join(parts[:-1]), True
    return ".".join(parts), False


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _absolute(name: str, is_package: bool, node: ast.ImportFrom) -> str:
    """The absolute module an `from X import ...` names (resolving relative imports)."""
    if not node.level:
        return node.module or ""
    base = name.split(".") if is_package else name.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def parse_module(name: str, path: Path, is_package: bool, known: set[str]) -> Module:
    """Read one module's imports: febed targets (resolved to modules in `known`) and top-level packages."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    imports: list[Import] = []
    packages: set[str] = set()

    def resolve(dotted: str) -> str:
        while dotted not in known and "." in dotted:
            dotted = dotted.rsplit(".", 1)[0]
        return dotted

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child.test):
                for other in child.orelse:
                    visit(other, in_function)
                continue
            inside = in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
            if isinstance(child, ast.Import):
                names = [a.name for a in child.names]
            elif isinstance(child, ast.ImportFrom):
                base = _absolute(name, is_package, child)
                if base.split(".")[0] == "febed":  # `from febed.x import y`: the module febed.x.y, or a name of febed.x
                    names = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in child.names]
                else:
                    names = [base] if base and not child.level else []
            else:
                visit(child, inside)
                continue
            for dotted in names:
                if dotted.split(".")[0] == "febed":
                    target = resolve(dotted)
                    missing = "" if target == dotted else dotted
                    imports.append(Import(name, target, child.lineno, in_function, missing))
                elif not in_function:
                    packages.add(dotted.split(".")[0])

    visit(tree, False)
    return Module(name, path, is_package, imports, packages)


def load_tree(root: Path) -> dict[str, Module]:
    """Every module of the febed package under `root`, by dotted name."""
    package_dir = root / "febed"
    files = sorted(p for p in package_dir.rglob("*.py") if "__pycache__" not in p.parts)
    names = {p: module_name(package_dir, p) for p in files}
    known = {n for n, _ in names.values()}
    return {n: parse_module(n, p, pkg, known) for p, (n, pkg) in names.items()}


def layer_of(name: str) -> tuple[int, str] | None:
    """(level, from 0 at the top; layer name) of a module, by its longest matching prefix; None if none."""
    best = None
    for level, (_, layers) in enumerate(LAYERS):
        for layer, prefixes in layers.items():
            for p in prefixes:
                if name == p or (p != "febed" and name.startswith(p + ".")):
                    if best is None or len(p) > best[0]:
                        best = (len(p), level, layer)
    return None if best is None else (best[1], best[2])


def _parents(name: str) -> list[str]:
    """The packages whose __init__ runs before a module: febed, febed.dem for febed.dem.solver."""
    parts = name.split(".")
    return [".".join(parts[:k]) for k in range(1, len(parts))]


def loads(modules: dict[str, Module]) -> dict[str, set[str]]:
    """Third-party top-level packages importing each module loads (its top-level imports, transitively)."""
    memo: dict[str, set[str]] = {}

    def visit(name: str, seen: set[str]) -> set[str]:
        if name in memo:
            return memo[name]
        if name in seen or name not in modules:
            return set()
        seen = seen | {name}
        m = modules[name]
        out = set(m.top_packages)
        for dep in [*_parents(name), *(i.target for i in m.imports if not i.in_function)]:
            out |= visit(dep, seen)
        memo[name] = out
        return out

    return {name: visit(name, set()) for name in modules}


def cycles(modules: dict[str, Module]) -> list[list[str]]:
    """The strongly connected components of more than one module (or a module importing itself), sorted."""
    graph = {n: sorted({i.target for i in m.imports if i.target in modules}) for n, m in modules.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def connect(v: str) -> None:  # Tarjan's algorithm, iterative over each node's successors
        work = [(v, iter(graph[v]))]
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        while work:
            node, succ = work[-1]
            for w in succ:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(graph[w])))
                    break
                if w in on_stack:
                    low[node] = min(low[node], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == node:
                            break
                    if len(comp) > 1 or node in graph[node]:
                        found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return sorted(found)


def _path_back(modules: dict[str, Module], start: str, goal: str, within: set[str]) -> list[str]:
    """A shortest import chain start -> ... -> goal inside the modules `within` (breadth first)."""
    prev = {start: None}
    queue = [start]
    for node in queue:
        if node == goal:
            break
        for i in modules[node].imports:
            if i.target in within and i.target not in prev:
                prev[i.target] = node
                queue.append(i.target)
    chain, node = [], goal
    while node is not None:
        chain.append(node)
        node = prev[node]
    return chain[::-1]


def check(root: Path, verbose: bool = False) -> tuple[list[str], list[str]]:
    """(violations, notes) of the febed package under `root`, each a printable line."""
    modules = load_tree(root)
    heavy = {n: p & HEAVY for n, p in loads(modules).items()}

    def shown(path: Path) -> str:
        try:
            return str(path.resolve().relative_to(Path.cwd()))
        except ValueError:
            return str(path)

    errors: list[tuple[str, int, str]] = []
    notes: list[tuple[str, int, str]] = []
    for name, m in sorted(modules.items()):
        where = layer_of(name)
        if where is None:
            errors.append((shown(m.path), 1, f"{name} is in no layer: add it to LAYERS in tools/check_layers.py"))
            continue
        for i in m.imports:
            if i.missing:
                errors.append((shown(m.path), i.line, f"{name} imports {i.missing}, which does not exist"))
                continue
            there = layer_of(i.target)
            if there is None or i.target == name:
                continue
            (level, layer), (t_level, t_layer) = where, there
            if t_level < level:
                why = f"layer {t_layer} above layer {layer}"
            elif t_level == level and t_layer != layer:
                why = f"layer {t_layer} beside layer {layer}: neither imports the other"
            else:
                why = None
            if why:
                errors.append((shown(m.path), i.line, f"{name} imports {i.target} ({why})"))
        for i in m.imports:
            if not i.in_function or i.missing:
                continue
            loaded = heavy.get(i.target, set()).union(*(heavy.get(q, set()) for q in _parents(i.target)))
            avoided = loaded - heavy[name]
            if not avoided:
                notes.append((
                    shown(m.path), i.line,
                    f"note: {name} imports {i.target} inside a function, which loads nothing {name} does not load "
                    "already: import it at the top",
                ))  # fmt: skip
            elif verbose:
                notes.append((
                    shown(m.path), i.line,
                    f"{name} imports {i.target} inside a function: avoids {', '.join(sorted(avoided))}",
                ))  # fmt: skip
    for comp in cycles(modules):
        members = set(comp)
        for name in comp:
            for i in modules[name].imports:
                if i.target in members:
                    chain = _path_back(modules, i.target, name, members)
                    text = " -> ".join([name, *chain])
                    errors.append((shown(modules[name].path), i.line, f"{name} imports {i.target} (cycle: {text})"))
    order = sorted(set(errors))
    return [f"{f}:{n}: {t}" for f, n, t in order], [f"{f}:{n}: {t}" for f, n, t in sorted(set(notes))]


def main(argv: list[str] | None = None) -> int:
    """Check the package under the given root (or the repository's) and report; returns the exit status."""
    args = sys.argv[1:] if argv is None else argv
    if any(a in ("-h", "--help") for a in args):
        print(__doc__)
        return 0
    verbose = "-v" in args
    rest = [a for a in args if a != "-v"]
    root = Path(rest[0]) if rest else ROOT
    if not (root / "febed" / "__init__.py").is_file():
        print(f"check_layers: {root} holds no febed package (febed/__init__.py)", file=sys.stderr)
        return 2
    errors, notes = check(root, verbose)
    for line in [*errors, *notes]:
        print(line)
    if errors:
        print(
            f"check_layers: {len(errors)} import(s) against febed's layers (see tools/check_layers.py and the "
            "Layers section of CONTRIBUTING.md)",
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

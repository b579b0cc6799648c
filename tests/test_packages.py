"""The house plan (issue 19): ilt/ is its packages, in pipeline order, each importing
only the packages below it, each with a face (its ``__init__``) that resolves, and the
tests in one folder per package."""

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

from tests import ROOT

PACKAGE = ROOT / "ilt"

#: the packages from the bottom up; a package imports only those of a lower rank
LAYERS = [
    ["io"],
    ["parallel"],
    ["transport", "sim"],
    ["capture"],
    ["hdr"],
    ["spots"],
    ["isf"],
    ["decompose", "refine", "separate"],
    ["report", "evaluate"],
    ["workspace"],
    ["cli"],
]
RANK = {name: rank for rank, names in enumerate(LAYERS) for name in names}


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, ast.Module]:
    return {module_name(p): ast.parse(p.read_text()) for p in sorted(PACKAGE.rglob("*.py"))}


def is_package(name: str) -> bool:
    return (ROOT / name.replace(".", "/") / "__init__.py").exists()


def imports(name: str, tree: ast.Module) -> set[str]:
    """The ilt modules ``name`` imports, at module level or inside functions."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                here = name.split(".") if is_package(name) else name.split(".")[:-1]
                base = ".".join(here[: len(here) - node.level + 1] + ([base] if base else []))
            if base.startswith("ilt"):
                out.add(base)
                out.update(f"{base}.{a.name}" for a in node.names)   # a submodule imported by name
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("ilt"))
    return out


def test_nothing_but_packages_at_the_top_of_ilt():
    loose = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert loose == ["__init__.py", "__main__.py"]
    packages = sorted(p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists())
    assert packages == sorted(RANK)


def test_every_import_points_down_the_layers():
    found = modules()
    upward = []
    for name, tree in found.items():
        own = name.split(".")[1] if name.count(".") else None
        for target in imports(name, tree):
            other = target.split(".")[1] if target.count(".") else None
            if target not in found or other not in RANK:
                continue
            if own in RANK and other != own and RANK[other] >= RANK[own]:
                upward.append(f"{name} -> {target}")
    assert upward == []


def test_no_import_circle():
    found = modules()
    graph = {name: {t for t in imports(name, tree) if t in found and t != name} for name, tree in found.items()}
    # a package's __init__ is its lazy face: it imports nothing, so edges into it are dropped
    faces = {name for name, tree in found.items() if not imports(name, tree) and name in graph}
    graph = {name: targets - faces for name, targets in graph.items()}
    index, low, stack, on_stack, circles = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                circles.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    assert circles == []


def test_each_name_is_imported_from_where_it_is_defined():
    """A module's import names the module that defines what it takes (or a package's
    face): no name is passed on through a module that only imports it."""
    found = modules()

    def defined(tree):
        names = set()
        for node in tree.body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                names.add(node.name)
            elif isinstance(node, (ast.Assign, ast.AnnAssign)):
                for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                    names.update(n.id for n in ast.walk(target) if isinstance(n, ast.Name))
        return names

    faces = {name for name in found if is_package(name)}
    passed_on = []
    for path in [*PACKAGE.rglob("*.py"), *(ROOT / "tests").rglob("*.py"), *(ROOT / "benchmarks").glob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module in found \
                    and node.module not in faces:
                own = defined(found[node.module])
                passed_on += [f"{path.relative_to(ROOT)}: {node.module}.{a.name}" for a in node.names
                              if a.name not in own and f"{node.module}.{a.name}" not in found]
    assert passed_on == []


@pytest.mark.parametrize("package", sorted(RANK))
def test_each_face_resolves(package):
    face = importlib.import_module(f"ilt.{package}")
    for name in getattr(face, "__all__", []):
        assert getattr(face, name) is not None, f"ilt.{package}.{name}"


def test_a_face_imports_nothing_until_used():
    """``import ilt.io`` (or any face) loads none of its modules: the CLI, the pool's
    workers and a capture script pay only for what they use."""
    code = ("import sys, ilt.io, ilt.transport, ilt.hdr, ilt.isf, ilt.parallel\n"
            "print(sorted(m for m in sys.modules if m.startswith('ilt.') and m.count('.') > 1))\n"
            "print(sorted(m for m in ('cv2', 'OpenImageIO', 'rawpy', 'dask', 'distributed', 'scipy') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split("\n")[:2] == ["[]", "[]"]


def test_tests_mirror_the_packages():
    folders = sorted(p.name for p in (ROOT / "tests").iterdir() if p.is_dir() and (p / "__init__.py").exists())
    assert set(folders) <= set(RANK)
    assert all(p.name.startswith("test_") for folder in folders for p in (ROOT / "tests" / folder).glob("*.py")
               if p.name != "__init__.py")

"""The house rules of docs/ARCHITECTURE.md: stage packages, no import circles, private modules kept
private, imports pointing down the pipeline only, a light command line, callable verbs."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from importlib import import_module
from pathlib import Path

import pytest

import keyshape

PACKAGE = Path(keyshape.__file__).parent
CORE = {"exceptions", "defaults", "containers", "schemes", "mesh"}

# folder -> the folders (besides CORE) it may import: docs/ARCHITECTURE.md, "Who may import whom"
ALLOWED = {
    "exceptions": set(), "defaults": set(), "containers": set(), "schemes": set(), "mesh": set(),
    "datasets": set(),
    "decompose": set(), "alignment": set(),
    "metrics": {"decompose"},
    "keyshapes": {"decompose", "metrics"},
    "io": set(),
    "capture": {"io"},
    "render": {"io", "capture"},
    "targets": {"alignment", "io", "capture", "render"},
    "report": {"alignment", "metrics", "io", "capture", "render"},
    "app": {"capture", "alignment", "keyshapes", "decompose", "targets", "io", "render", "report", "metrics"},
    "live": {"capture", "alignment", "keyshapes", "decompose", "targets", "io", "render", "report", "metrics", "app"},
}


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    return ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    return {id(n) for node in ast.walk(tree) if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
            for child in node.body for n in ast.walk(child)}


def _imports(path: Path, modules: set[str]) -> set[str]:
    """Modules of keyshape that ``path`` imports, anywhere in the file (inside functions too)."""
    name, is_init = _module_name(path), path.name == "__init__.py"
    tree = ast.parse(path.read_text())
    skip = _type_checking_nodes(tree)
    found = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.ImportFrom):
            base = name.split(".") if is_init else name.split(".")[:-1]
            module = (".".join(base[: len(base) - (node.level - 1)] + ([node.module] if node.module else []))
                      if node.level else (node.module or ""))
            found.update(f"{module}.{a.name}" if f"{module}.{a.name}" in modules else module for a in node.names)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return {m for m in found if m in modules and m != name}


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    paths = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    return {name: _imports(path, set(paths)) for name, path in paths.items()}


def _is_init(module: str) -> bool:
    return (PACKAGE.parent.joinpath(*module.split(".")) / "__init__.py").exists()


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components (Tarjan) with more than one module that is not a package's ``__init__``."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if sum(not _is_init(m) for m in component) > 1:
                out.append(sorted(component))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in graph:
        if v not in index:
            visit(v)
    return out


def _folder(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def test_the_folder_list_reads_as_the_pipeline():
    loose = sorted(p.name for p in PACKAGE.glob("*.py") if p.name not in ("__init__.py", "__main__.py"))
    stages = {"capture", "alignment", "keyshapes", "decompose", "targets", "io", "render", "report", "app", "cli"}
    packages = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()}
    assert len(loose) <= 12, loose
    assert stages <= packages


def test_no_import_circle(graph):
    assert _circles(graph) == []


def test_the_circle_finder_finds_a_circle():
    assert _circles({"keyshape.a": {"keyshape.b"}, "keyshape.b": {"keyshape.a"}}) == [["keyshape.a", "keyshape.b"]]


def test_modules_import_their_siblings_not_their_own_package(graph):
    """A module importing its own package's ``__init__`` (which imports it back) is a hidden circle.

    (The root's ``__init__`` imports only the core types, so ``from .. import __version__`` is fine.)
    """
    offenders = [(m, t) for m, targets in graph.items() if not _is_init(m)
                 for t in targets if _is_init(t) and m.startswith(t + ".") and t != "keyshape"]
    assert offenders == []


def test_private_modules_are_imported_only_inside_their_package(graph):
    offenders = []
    for module, targets in graph.items():
        for target in targets:
            parts = target.split(".")
            private = next((i for i, p in enumerate(parts) if p.startswith("_") and not p.startswith("__")), None)
            if private is None:
                continue
            owner = ".".join(parts[:private])
            if not (module == owner or module.startswith(owner + ".")):
                offenders.append((module, target))
    assert offenders == []


def test_imports_point_down_the_pipeline(graph):
    offenders = []
    for module, targets in graph.items():
        folder = _folder(module)
        if folder not in ALLOWED:  # the root, __main__, cli and viewer may import anything
            continue
        for target in targets:
            other = _folder(target)
            if other and other != folder and other not in CORE | ALLOWED[folder]:
                offenders.append((module, target))
    assert offenders == []


def test_every_folder_has_a_rule():
    packages = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()}
    folders = {p.stem for p in PACKAGE.glob("*.py")} | packages
    assert folders - set(ALLOWED) == {"__init__", "__main__", "cli", "viewer"}


def test_the_verbs_are_functions():
    verbs = ("track", "align", "find_keyshapes", "solve_weights", "retarget", "propose_targets", "export")
    assert [callable(getattr(keyshape, verb)) for verb in verbs] == [True] * 7
    alignment, targets = import_module("keyshape.alignment"), import_module("keyshape.targets")
    # importing the stage packages does not shadow the verbs
    assert keyshape.align is alignment.align
    assert keyshape.retarget is targets.retarget


@pytest.mark.parametrize("argv", [["--help"], ["run", "--help"], ["track", "--help"]])
def test_help_imports_no_verb_stack(argv):
    """Building the parser for help imports none of the heavy dependencies nor any stage."""
    code = ("import json, sys\nfrom keyshape.cli import main\n"
            f"try:\n    main({argv!r})\nexcept SystemExit:\n    pass\n"
            "print(json.dumps(sorted(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    loaded = set(json.loads(out.splitlines()[-1]))
    heavy = {"scipy", "numba", "mediapipe", "av", "matplotlib", "pygltflib", "PIL", "moderngl",
             "keyshape.app", "keyshape.capture", "keyshape.decompose", "keyshape.io", "keyshape.targets"}
    assert loaded & heavy == set()
    assert "keyshape.cli.run" in loaded if argv[0] == "run" else "keyshape.cli.run" not in loaded

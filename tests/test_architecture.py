"""The package layout holds: imports run one way between the layers, no module imports
itself in a circle, and the server does not load the simulator.

Layers, lowest first: ``app.core`` (the vision library), ``app.sim`` (the simulator),
``app.learning`` (classifier training and adaptation), ``app.services``, ``app.routers``,
``app.main``. A module may import its own layer and the layers below it, never above.
"""

from __future__ import annotations

import ast
import functools
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
APP = ROOT / "app"

#: Layer of each top-level part of the package, lowest first. Modules of ``app`` that are
#: not listed (settings, logs, db, models, schemas, deps, middleware) sit between the
#: services and the library: they may import the library, never services or routers.
LAYERS: dict[str, int] = {
    "app.core": 0,
    "app.sim": 1,
    "app.learning": 2,
    "app.settings": 3,
    "app.logs": 3,
    "app.db": 3,
    "app.models": 3,
    "app.schemas": 3,
    "app.services": 4,
    "app.client": 4,  # a client of the API: its message models, never the services
    "app.local_server": 4,  # starts `fidotrack serve` as a process of its own, never imports it
    "app.deps": 5,
    "app.middleware": 5,
    "app.routers": 6,
    "app.cli": 7,
    "app.demo": 7,
    "app.main": 7,
}

#: Outside packages the vision library must never use: it is numpy/OpenCV/SciPy only.
CORE_FORBIDDEN = ("fastapi", "starlette", "sqlalchemy", "alembic", "pydantic", "uvicorn", "httpx", "skimage")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(APP.rglob("*.py"))}


def _imports(name: str, path: Path) -> set[str]:
    """Modules of ``app`` (and outside packages) that `path` imports anywhere in it, also
    inside functions: ``from pkg import mod`` counts as ``pkg.mod`` when that is a module
    of the package, else as ``pkg``."""
    modules = _module_names()
    tree = ast.parse(path.read_text(), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{anchor}.{base}" if base else anchor
            for alias in node.names:
                found.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base)
    return found


@functools.cache
def _module_names() -> frozenset[str]:
    return frozenset(_modules())


def _layer(module: str) -> int | None:
    for prefix, layer in sorted(LAYERS.items(), key=lambda kv: -len(kv[0])):
        if module == prefix or module.startswith(prefix + "."):
            return layer
    return None


def test_imports_never_point_to_a_higher_layer() -> None:
    upward = []
    for name, path in _modules().items():
        own = _layer(name)
        if own is None:
            continue
        for imported in _imports(name, path):
            layer = _layer(imported)
            if layer is not None and layer > own:
                upward.append(f"{name} imports {imported}")
    assert not upward, "\n".join(sorted(upward))


def test_the_vision_library_uses_no_web_database_or_simulator_code() -> None:
    bad = []
    for name, path in _modules().items():
        if not name.startswith("app.core"):
            continue
        for imported in _imports(name, path):
            if imported.split(".")[0] in CORE_FORBIDDEN:
                bad.append(f"{name} imports {imported}")
    assert not bad, "\n".join(sorted(bad))


def test_inside_a_package_modules_import_each_other_directly() -> None:
    """A module never imports its own package's ``__init__`` (the public face is for
    other packages): that would tie the module to every sibling the package exports."""
    bad = []
    for name, path in _modules().items():
        ancestors = {name.rsplit(".", k)[0] for k in range(1, name.count(".") + 1)} - {"app"}
        if path.name == "__init__.py":
            ancestors.add(name)
        bad += [f"{name} imports {i}" for i in _imports(name, path) & ancestors if i != name or path.name != "__init__.py"]
    assert not bad, "\n".join(sorted(bad))


def test_no_import_cycles_between_modules() -> None:
    modules = _modules()
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        imported = {m for m in _imports(name, path) if m in modules and m != name}
        if path.name == "__init__.py":  # a package declaring its public names: not a dependency of them
            imported = {m for m in imported if not m.startswith(name + ".")}
        graph[name] = imported
    cycles = [c for c in _strongly_connected(graph) if len(c) > 1]
    assert not cycles, "\n".join(" <-> ".join(sorted(c)) for c in cycles)


def _strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components of `graph`."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(v: str) -> None:
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
            while (w := stack.pop()) != v:
                on_stack.discard(w)
                component.append(w)
            on_stack.discard(v)
            components.append([*component, v])

    for v in graph:
        if v not in index:
            visit(v)
    return components


@pytest.mark.parametrize("entry", [
    "import app.main",
    "import app.cli; app.cli.build_parser()",  # what `fidotrack serve` loads before it serves
    "import app.services.classifiers, app.learning.adapt",  # the classifier job
    "import app.services.surveys",  # the survey job
])
def test_the_server_does_not_load_the_simulator(entry: str) -> None:
    """The service and its jobs work without the simulator's dependencies installed:
    they load no module of ``app.sim``."""
    code = f"import sys; {entry}; print(sorted(m for m in sys.modules if m.startswith(('app.sim', 'skimage'))))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]", out.stdout


def test_every_json_body_is_parsed_off_the_event_loop() -> None:
    # FastAPI parses and validates a body on the event loop, where a large one holds up
    # every other client; JsonBodyRoute does it in a worker thread.
    from fastapi.routing import APIRoute

    from app.main import create_app
    from app.routers.json_bodies import JsonBodyRoute

    def flattened(routes: list) -> list:  # included routers are nested
        return [leaf for r in routes
                for leaf in (flattened(r.original_router.routes) if hasattr(r, "original_router") else [r])]

    routes = [r for r in flattened(create_app().routes) if isinstance(r, APIRoute) and r.body_field is not None]
    assert len(routes) >= 5
    assert [r.path for r in routes if not isinstance(r, JsonBodyRoute)] == []


def _requirement_names(requirements: list[str]) -> set[str]:
    import re

    names = set()
    for requirement in requirements:
        if ";" in requirement and "extra ==" in requirement:
            continue  # an optional extra of that package
        names.add(re.split(r"[\s\[<>=!~;(]", requirement, maxsplit=1)[0].lower().replace("_", "-"))
    return names


def test_what_the_package_imports_is_installed_by_its_dependencies() -> None:
    # `pip install .` (no extras) must give every outside module the package imports,
    # except the simulator's (the `sim` extra): a dependency met only by the test extra
    # works in the tests and fails for users.
    import importlib.metadata as metadata
    import tomllib

    declared = _requirement_names(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"])
    installed, todo = set(), list(declared)
    while todo:  # the declared dependencies and what they require in turn
        name = todo.pop()
        if name in installed:
            continue
        installed.add(name)
        try:
            todo += sorted(_requirement_names(metadata.requires(name) or []))
        except metadata.PackageNotFoundError:
            pass
    distributions = metadata.packages_distributions()
    missing = {}
    for name, path in _modules().items():
        if name.startswith("app.sim"):
            continue
        for imported in _imports(name, path):
            top = imported.split(".")[0]
            if top == "app" or top in sys.stdlib_module_names or top == "__future__":
                continue
            providers = {d.lower().replace("_", "-") for d in distributions.get(top, [top])}
            if not providers & installed:
                missing.setdefault(top, []).append(name)
    assert not missing, f"imported but not installed by `pip install .`: {missing}"

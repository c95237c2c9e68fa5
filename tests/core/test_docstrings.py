"""The vision library documents itself as scikit-image does: every public function and
method of ``app.core`` has a numpydoc docstring with ``Parameters`` when it takes any and
``Returns`` (or ``Yields``) when it gives something back, and every package declares its
public names in ``__all__``."""

from __future__ import annotations

import ast
import importlib
import importlib.util
from pathlib import Path

import pytest

CORE = Path(__file__).resolve().parents[2] / "app" / "core"
#: Modules named with a leading underscore (numba kernels, a package's private helpers) are private.
PUBLIC_MODULES = sorted(p for p in CORE.rglob("*.py") if not p.name.startswith("_") or p.name == "__init__.py")


def _returns_something(fn: ast.FunctionDef) -> bool:
    return fn.returns is not None and not (isinstance(fn.returns, ast.Constant) and fn.returns.value is None)


def _is_property(fn: ast.FunctionDef) -> bool:
    names = {"property", "cached_property"}
    return any((isinstance(d, ast.Name) and d.id in names) or (isinstance(d, ast.Attribute) and d.attr in names)
               for d in fn.decorator_list)


def _public_functions(tree: ast.Module) -> list[tuple[str, ast.FunctionDef]]:
    found = [(node.name, node) for node in tree.body if isinstance(node, ast.FunctionDef)]
    for cls in (n for n in tree.body if isinstance(n, ast.ClassDef) and not n.name.startswith("_")):
        found += [(f"{cls.name}.{n.name}", n) for n in cls.body
                  if isinstance(n, ast.FunctionDef) and not n.name.startswith("__")]
    return [(name, fn) for name, fn in found if not name.rpartition(".")[2].startswith("_")]


@pytest.mark.parametrize("path", PUBLIC_MODULES, ids=lambda p: str(p.relative_to(CORE)))
def test_public_functions_carry_numpydoc_sections(path: Path) -> None:
    missing = []
    for name, fn in _public_functions(ast.parse(path.read_text())):
        doc = ast.get_docstring(fn) or ""
        takes = [a.arg for a in fn.args.args + fn.args.kwonlyargs if a.arg not in ("self", "cls")]
        if not doc:
            missing.append(f"{name}: no docstring")
            continue
        if takes and "Parameters\n" not in doc:
            missing.append(f"{name}: no Parameters")
        if _returns_something(fn) and not _is_property(fn) and "Returns\n" not in doc and "Yields\n" not in doc:
            missing.append(f"{name}: no Returns")
    assert not missing, "\n".join(missing)


PACKAGES = sorted(p.parent for p in CORE.rglob("__init__.py"))


@pytest.mark.parametrize("package", PACKAGES, ids=lambda p: str(p.relative_to(CORE.parent)))
def test_packages_declare_their_public_names(package: Path) -> None:
    """Each package's ``__init__`` declares ``__all__``, and every name in it exists."""
    name = ".".join(package.relative_to(CORE.parents[1]).parts)
    module = importlib.import_module(name)
    assert hasattr(module, "__all__"), f"{name} declares no __all__"
    absent = [n for n in module.__all__ if not hasattr(module, n) and importlib.util.find_spec(f"{name}.{n}") is None]
    assert not absent, f"{name}.__all__ names what it does not have: {absent}"

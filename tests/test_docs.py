"""The docs: their generated parts match the code, every relative link in README.md and
docs/ points at a file (and a heading) that exists, every page the code cites exists, and
the architecture page's package map names every module of the package."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]

#: An inline markdown link's target: [text](target).
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.DOTALL | re.MULTILINE)
CODE_SPAN = re.compile(r"`[^`\n]*`")
HEADING = re.compile(r"^#{1,6}\s+(.+?)\s*$", re.MULTILINE)


def _generator() -> ModuleType:
    spec = importlib.util.spec_from_file_location("gen_docs", ROOT / "scripts" / "gen_docs.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _slug(heading: str) -> str:
    """The anchor a heading gets on GitHub: lower case, punctuation dropped, spaces to '-'."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    return {_slug(h) for h in HEADING.findall(FENCE.sub("", page.read_text(encoding="utf-8")))}


def _links(page: Path) -> list[str]:
    text = CODE_SPAN.sub("", FENCE.sub("", page.read_text(encoding="utf-8")))
    return LINK.findall(text)


def test_generated_docs_match_the_code() -> None:
    stale = _generator().stale_pages()
    assert not stale, f"out of date: {stale}; run .venv/bin/python scripts/gen_docs.py"


def test_generated_blocks_are_on_their_pages() -> None:
    generator = _generator()
    for page in generator.PAGES:
        assert generator.BLOCK.search((ROOT / page).read_text(encoding="utf-8")), f"{page} has no generated block"


def test_relative_links_point_at_files_and_headings() -> None:
    broken = []
    for page in PAGES:
        for target in _links(page):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
                continue
            path_part, _, fragment = target.partition("#")
            linked = (page.parent / path_part).resolve() if path_part else page
            if not linked.exists():
                broken.append(f"{page.relative_to(ROOT)}: {target} (no such file)")
            elif fragment and linked.suffix == ".md" and fragment not in _anchors(linked):
                broken.append(f"{page.relative_to(ROOT)}: {target} (no such heading)")
    assert not broken, "\n".join(broken)


def test_pages_the_code_cites_exist() -> None:
    cited = {
        (module.relative_to(ROOT).as_posix(), page)
        for folder in ("app", "bench", "scripts", "tests")
        for module in sorted((ROOT / folder).rglob("*.py"))
        for page in re.findall(r"\bdocs/[\w/.-]+\.md", module.read_text(encoding="utf-8"))
    }
    missing = sorted(f"{module}: {page}" for module, page in cited if not (ROOT / page).exists())
    assert not missing, "\n".join(missing)


def test_the_package_map_names_every_module() -> None:
    named: set[str] = set()
    for line in (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8").splitlines():
        files = re.findall(r"`([\w/.]+\.py)`", line)
        paths = [f for f in files if "/" in f]
        named.update(paths)
        # A row may name more modules of the same folder by their file names alone.
        for folder in {p.rpartition("/")[0] for p in paths}:
            named.update(f"{folder}/{f}" for f in files if "/" not in f)
    modules = [m.relative_to(ROOT).as_posix() for m in sorted((ROOT / "app").rglob("*.py")) if m.name != "__init__.py"]
    missing = [m for m in modules if m not in named]
    assert not missing, f"docs/architecture.md does not name: {missing}"
    gone = sorted(n for n in named if n.startswith("app/") and n not in modules)
    assert not gone, f"docs/architecture.md names modules that do not exist: {gone}"


def test_every_documented_field_says_what_it_is() -> None:
    """Each setting and each field of the documented messages carries a description, so
    that the generated tables have no blank cells for clients to guess at."""
    generator = _generator()
    blank = []
    for page in generator.PAGES:
        for match in generator.BLOCK.finditer((ROOT / page).read_text(encoding="utf-8")):
            cls = generator._resolve(match["target"])
            for name, field in cls.model_fields.items():
                if not (field.description or "").strip():
                    blank.append(f"{cls.__name__}.{name}")
    assert not blank, f"fields without a description: {blank}"

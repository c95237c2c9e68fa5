"""Regenerate the generated parts of the docs from the code.

A page holds generated blocks between two comment lines::

    <!-- generated: settings app.settings:Settings -->
    ...
    <!-- end generated -->

The first line names what the block shows: ``settings MODULE:CLASS`` is the table of a
pydantic-settings class (environment variable, type, default, description of every
field); ``model MODULE:CLASS`` is the table of a pydantic model's fields (JSON name,
type, default, description), from its JSON schema. Everything outside the blocks is
written by hand and left alone.

Run: ``.venv/bin/python scripts/gen_docs.py`` rewrites the blocks of every page in
`PAGES`; ``--check`` changes nothing and exits with status 1 when a page is out of date.
"""

from __future__ import annotations

import argparse
import importlib
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pydantic import BaseModel
from pydantic_settings import BaseSettings

ROOT = Path(__file__).resolve().parents[1]
#: The pages with generated blocks, relative to the repository root.
PAGES: tuple[str, ...] = ("docs/configuration.md", "docs/protocol.md")

BLOCK = re.compile(
    r"(?P<start><!-- generated: (?P<kind>[a-z]+) (?P<target>[\w.]+:\w+) -->\n)"
    r"(?P<body>.*?)"
    r"(?P<end><!-- end generated -->)",
    re.DOTALL,
)
_CHOICES = re.compile(r"^\^\(([\w|]+)\)\$$")


def _resolve(target: str) -> type:
    module, _, name = target.partition(":")
    found = getattr(importlib.import_module(module), name, None)
    if not isinstance(found, type):
        raise TypeError(f"{target} is not a class")
    return found


def _cell(text: str) -> str:
    """Text fit for one markdown table cell: one line, pipes escaped."""
    return " ".join(text.split()).replace("|", "\\|")


def _json(value: Any) -> str:
    return f"`{json.dumps(value)}`"


def _number(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else f"{value:g}"


def _bounds(schema: dict[str, Any]) -> str:
    """Numeric and length bounds of a schema, as ", 1..65535", ", > 0, <= 20000" (or "")."""
    low = schema.get("minimum", schema.get("minItems", schema.get("minLength")))
    high = schema.get("maximum", schema.get("maxItems", schema.get("maxLength")))
    if low is not None and high is not None:
        return f", {_number(low)}..{_number(high)}"
    parts = []
    if "exclusiveMinimum" in schema:
        parts.append(f"> {_number(schema['exclusiveMinimum'])}")
    elif low is not None:
        parts.append(f">= {_number(low)}")
    if high is not None:
        parts.append(f"<= {_number(high)}")
    return "".join(f", {p}" for p in parts)


def _plural(phrase: str) -> str:
    if phrase.startswith("list of "):
        return "lists of " + phrase[len("list of "):]
    if phrase in ("integer", "number", "string", "boolean", "object"):
        return phrase + "s"
    return phrase


def schema_type(schema: dict[str, Any], linked: frozenset[str] = frozenset()) -> str:
    """A short, readable type of a JSON schema (pydantic's): ``integer, 1..65535``,
    ``list of 3 numbers``, ``CameraModel or null``, ```"hello"```. Models named in
    `linked` link to their section of the page (a heading with the model's name)."""
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        return f"[`{name}`](#{name.lower()})" if name in linked else f"`{name}`"
    if "const" in schema:
        return _json(schema["const"])
    if "enum" in schema:
        return " or ".join(_json(v) for v in schema["enum"])
    if "anyOf" in schema:
        return " or ".join(schema_type(part, linked) for part in schema["anyOf"])
    kind = schema.get("type")
    if kind == "array":
        inner = _plural(schema_type(schema["items"], linked)) if "items" in schema else "values"
        n_min, n_max = schema.get("minItems"), schema.get("maxItems")
        if n_min is not None and n_min == n_max:
            return f"list of {n_min} {inner}"
        return f"list of {inner}" + _bounds({k: v for k, v in schema.items() if k in ("minItems", "maxItems")})
    if kind == "object":
        extra = schema.get("additionalProperties")
        return f"object of {_plural(schema_type(extra, linked))}" if isinstance(extra, dict) else "object"
    if kind == "string":
        if schema.get("format") == "path":
            return "path"
        choices = _CHOICES.match(schema.get("pattern", ""))
        if choices:
            return " or ".join(f"`{c}`" for c in choices.group(1).split("|"))
        return "string" + _bounds(schema)
    if kind in ("integer", "number"):
        return str(kind) + _bounds(schema)
    if kind is None:
        return "any"
    return str(kind)


def _default(value: Any) -> str:
    """A setting's default, as its environment variable would spell it."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, Path):
        return f"`{value.as_posix()}`"
    if isinstance(value, int) and value >= 1024 * 1024 and value % (1024 * 1024) == 0:
        return f"`{value}` ({value // (1024 * 1024)} MiB)"
    return f"`{value}`"


def settings_table(cls: type, linked: frozenset[str] = frozenset()) -> str:
    """Every field of a settings class: its environment variable, type, default and
    description."""
    if not issubclass(cls, BaseSettings):
        raise TypeError(f"{cls.__name__} is not a pydantic-settings class")
    prefix = str(cls.model_config.get("env_prefix", ""))
    properties = cls.model_json_schema()["properties"]
    lines = ["| variable | type | default | description |", "|---|---|---|---|"]
    for name, field in cls.model_fields.items():
        description = field.description or ""
        lines.append(f"| `{(prefix + name).upper()}` | {_cell(schema_type(properties[name], linked))} | "
                     f"{_cell(_default(field.default))} | {_cell(description)} |")
    return "\n".join(lines)


def model_table(cls: type, linked: frozenset[str] = frozenset()) -> str:
    """A pydantic model's description and its JSON fields."""
    if not issubclass(cls, BaseModel):
        raise TypeError(f"{cls.__name__} is not a pydantic model")
    schema = cls.model_json_schema(by_alias=True)
    required = set(schema.get("required", []))
    lines = []
    if cls.__doc__ and cls.__doc__.strip():
        lines += [" ".join(cls.__doc__.strip().split("\n\n")[0].split()), ""]
    lines += ["| field | type | default | description |", "|---|---|---|---|"]
    for name, prop in schema.get("properties", {}).items():
        default = "required" if name in required else _json(prop.get("default"))
        lines.append(f"| `{name}` | {_cell(schema_type(prop, linked))} | {_cell(default)} | "
                     f"{_cell(prop.get('description', ''))} |")
    return "\n".join(lines)


RENDERERS: dict[str, Callable[[type, frozenset[str]], str]] = {"settings": settings_table, "model": model_table}


def render_page(text: str) -> str:
    """The page `text` with every generated block rendered afresh from the code. A type
    that has its own model block on the page links to it."""
    linked = frozenset(m["target"].rpartition(":")[2] for m in BLOCK.finditer(text) if m["kind"] == "model")

    def block(match: re.Match[str]) -> str:
        renderer = RENDERERS.get(match["kind"])
        if renderer is None:
            raise ValueError(f"unknown generated block kind {match['kind']!r}; known: {', '.join(RENDERERS)}")
        return f"{match['start']}\n{renderer(_resolve(match['target']), linked)}\n\n{match['end']}"

    return BLOCK.sub(block, text)


def stale_pages(root: Path = ROOT) -> list[str]:
    """The pages of `PAGES` whose generated blocks differ from what the code gives."""
    stale = []
    for page in PAGES:
        text = (root / page).read_text(encoding="utf-8")
        if render_page(text) != text:
            stale.append(page)
    return stale


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="change nothing; exit 1 if a page is out of date")
    args = parser.parse_args(argv)
    if args.check:
        stale = stale_pages()
        for page in stale:
            print(f"{page} is out of date: run scripts/gen_docs.py", file=sys.stderr)
        return 1 if stale else 0
    for page in PAGES:
        path = ROOT / page
        text = path.read_text(encoding="utf-8")
        rendered = render_page(text)
        if rendered != text:
            path.write_text(rendered, encoding="utf-8")
            print(f"wrote {page}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    raise SystemExit(main())

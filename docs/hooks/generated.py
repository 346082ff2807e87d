"""mkdocs hook: pages generated from the code at build time, so they cannot drift from it.

- ``<!-- generated:config-reference -->`` in a page becomes the configuration reference: every section of
  ``apf_companion.config.ServiceConfig`` with each key's type, default, allowed range and meaning. Types and
  defaults come from the dataclass fields, meanings from the docstrings' ``Attributes:`` sections, ranges from the
  validation calls (``_check_range``, ``_check_id``, ``_fail``) in each ``__post_init__``.
- ``<!-- generated:import-graph -->`` becomes the table of which part of the code imports which (read with ``ast``
  from the sources, the same way ``tests/test_architecture.py`` checks the arrows).

Registered in ``mkdocs.yml`` (``hooks:``); ``tests/test_docs.py`` calls the renderers directly.
"""

from __future__ import annotations

import ast
import dataclasses
import enum
import importlib
import inspect
import math
import re
import textwrap
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
CONFIG_MARKER = "<!-- generated:config-reference -->"
IMPORTS_MARKER = "<!-- generated:import-graph -->"

# ServiceConfig fields that are not TOML keys (set by the loader).
_NOT_TOML_KEYS = frozenset({"base_dir"})
# Validation helpers of apf_companion/config.py whose calls spell out a key's allowed values.
_RANGE_HELPERS = frozenset({"_check_range", "_check_id", "_fail"})


# --------------------------------------------------------------------------------------------- configuration


def parse_attributes(cls: type[Any]) -> dict[str, str]:
    """The ``Attributes:`` section of a Google-style class docstring: {field name: description}.

    An entry may name several fields (``north_m, east_m, down_m: ...``); continuation lines are joined.
    """
    doc = inspect.getdoc(cls) or ""
    lines = doc.splitlines()
    try:
        start = next(i for i, line in enumerate(lines) if line.strip() == "Attributes:")
    except StopIteration:
        return {}
    entries: dict[str, str] = {}
    names: list[str] = []
    for line in lines[start + 1 :]:
        if line and not line.startswith(" "):
            break  # the next section
        entry = re.match(r"^ {4}([A-Za-z_][\w, ]*):\s*(.*)$", line)
        if entry:
            names = [n.strip() for n in entry.group(1).split(",")]
            for name in names:
                entries[name] = entry.group(2).strip()
        elif line.strip() and names:
            for name in names:
                entries[name] = f"{entries[name]} {line.strip()}"
    return entries


def _summary(cls: type[Any]) -> str:
    doc = inspect.getdoc(cls) or ""
    first = doc.split("\n\n", 1)[0].replace("\n", " ").strip()
    first = re.sub(r"^``\[[\w.]+\]``( \(.*?\))?:\s*", "", first)  # the heading already names the table
    return first[:1].upper() + first[1:]


def _number(value: float) -> str:
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return f"{value:g}" if isinstance(value, float) else str(value)


def _eval(node: ast.expr, namespace: dict[str, Any]) -> Any:
    """Evaluate a literal or an expression over module constants (f-strings included); raise if it needs more."""
    return eval(compile(ast.Expression(node), "<config>", "eval"), dict(namespace))


def _range_text(helper: str, args: list[Any], keywords: dict[str, Any]) -> str:
    if helper == "_check_range":
        lo, hi = args[2], args[3]
        left = "(" if keywords.get("lo_open") else "["
        right = ")" if keywords.get("hi_open") else "]"
        return f"{left}{_number(lo)}, {_number(hi)}{right}"
    if helper == "_check_id":
        lo = args[2] if len(args) > 2 else keywords.get("lo", 1)
        hi = args[3] if len(args) > 3 else keywords.get("hi", 255)
        return f"integer in [{lo}, {hi}]"
    return str(args[1])  # _fail(key, allowed, value)


def validation_rules(cls: type[Any]) -> list[tuple[str, str]]:
    """(key, allowed) for every validation call in ``cls.__post_init__`` that can be read without running it."""
    post_init = getattr(cls, "__post_init__", None)
    if post_init is None:
        return []
    module = importlib.import_module(cls.__module__)
    namespace = vars(module)
    tree = ast.parse(textwrap.dedent(inspect.getsource(post_init)))
    rules: list[tuple[str, str]] = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in _RANGE_HELPERS):
            continue
        try:
            # _fail(key, allowed, value); _check_range/_check_id(key, value, lo, hi): skip the value (the instance).
            skip = 2 if node.func.id == "_fail" else 1
            args: list[Any] = []
            for a in node.args:  # a range may be a module constant spread in: _check_range(key, v, *RANGE)
                if isinstance(a, ast.Starred):
                    args.extend(_eval(a.value, namespace))
                else:
                    args.append(None if len(args) == skip else _eval(a, namespace))
            keywords = {k.arg: _eval(k.value, namespace) for k in node.keywords if k.arg}
        except Exception:  # the call uses a loop variable or the instance: not a static rule
            continue
        if args and isinstance(args[0], str):
            rules.append((args[0], _range_text(node.func.id, args, keywords)))
    return rules


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, enum.Enum):
        return _toml_value(value.value)
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, float):
        return _number(value)
    if isinstance(value, tuple | list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, Mapping):
        return "{}" if not value else "{" + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + "}"
    if value is None:
        return "(unset)"
    return str(value)


def _default(f: dataclasses.Field[Any]) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def _type_text(annotation: Any) -> str:
    text = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", repr(annotation))
    return text.replace("|", "\\|")  # a bar inside a table cell


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def config_sections() -> Iterator[tuple[str, type[Any]]]:
    """("", ServiceConfig) for the top-level keys, then (section name, section class) in declaration order."""
    from apf_companion.config import ServiceConfig

    yield "", ServiceConfig
    defaults = ServiceConfig()
    for f in dataclasses.fields(ServiceConfig):
        value = getattr(defaults, f.name)
        if dataclasses.is_dataclass(value):
            yield f.name, type(value)


def config_keys() -> list[str]:
    """Every TOML key the configuration accepts, dotted (``cycle.rate_hz``), in page order."""
    keys: list[str] = []
    for section, cls in config_sections():
        defaults = cls()
        for f in dataclasses.fields(cls):
            if section == "" and (f.name in _NOT_TOML_KEYS or dataclasses.is_dataclass(getattr(defaults, f.name))):
                continue
            keys.append(f"{section}.{f.name}" if section else f.name)
    return keys


def render_config_reference() -> str:
    """The configuration reference in Markdown: one table per section."""
    out: list[str] = []
    for section, cls in config_sections():
        defaults = cls()
        meanings = parse_attributes(cls)
        rules = validation_rules(cls)
        title = f"`[{section}]`" if section else "Top-level keys"
        out += [f"### {title}", "", _summary(cls), ""]
        out += ["| Key | Type | Default | Allowed | Meaning |", "|---|---|---|---|---|"]
        prefix = f"{section}." if section else ""
        used: set[str] = set()
        for f in dataclasses.fields(cls):
            value = getattr(defaults, f.name)
            if section == "" and (f.name in _NOT_TOML_KEYS or dataclasses.is_dataclass(value)):
                continue
            key = prefix + f.name
            allowed = [text for k, text in rules if k in (key, key + "[]")]
            used.update(k for k, _ in rules if k in (key, key + "[]"))
            if isinstance(value, enum.Enum):
                allowed = allowed or [", ".join(_toml_value(m) for m in type(value))]
            row = (
                f"`{key}`",
                f"`{_type_text(f.type)}`",
                f"`{_cell(_toml_value(_default(f)))}`",
                _cell("; ".join(allowed)),
                _cell(meanings.get(f.name, "")),
            )
            out.append("| " + " | ".join(row) + " |")
        cross = [(k, text) for k, text in rules if k not in used]
        if cross:
            out += ["", "Rules across keys:", ""]
            out += [f"- `{k}` must be {text}." for k, text in cross]
        out.append("")
    return "\n".join(out)


# ----------------------------------------------------------------------------------------------- import graph


def _part(module: str) -> str | None:
    """The architecture part a module belongs to: a subpackage, or a top-level module of a package."""
    parts = module.split(".")
    if parts[0] not in ("apf_companion", "sim") or len(parts) < 2:
        return parts[0] if parts[0] in ("apf_companion", "sim") else None
    return ".".join(parts[:2])


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def import_graph() -> dict[str, set[str]]:
    """{part: parts it imports}, over apf_companion/ and sim/ (absolute and relative imports)."""
    graph: dict[str, set[str]] = {}
    for package in ("apf_companion", "sim"):
        for path in sorted((ROOT / package).rglob("*.py")):
            name = _module_name(path)
            source = _part(name)
            if source is None:
                continue
            graph.setdefault(source, set())
            is_pkg = path.name == "__init__.py"
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                targets: list[str] = []
                if isinstance(node, ast.Import):
                    targets = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom):
                    if node.level:
                        base = name.split(".")[: len(name.split(".")) - node.level + (1 if is_pkg else 0)]
                        mod = ".".join(base + ([node.module] if node.module else []))
                        targets = [mod] if node.module else [f"{mod}.{a.name}" for a in node.names]
                    elif node.module:
                        targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
                for target in targets:
                    part = _part(target)
                    if part and part != source and _is_module(part):
                        graph[source].add(part)
    return graph


def _is_module(part: str) -> bool:
    path = ROOT.joinpath(*part.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def render_import_graph() -> str:
    """The import graph as a Markdown table, one row per part, in package order."""
    graph = import_graph()
    out = ["| Part | Imports (inside the repository) |", "|---|---|"]
    for part in sorted(graph, key=lambda p: (not p.startswith("apf_companion"), p)):
        if part in ("apf_companion", "sim") or part.endswith("__main__"):
            continue
        targets = ", ".join(f"`{t}`" for t in sorted(graph[part])) or "(nothing)"
        out.append(f"| `{part}` | {targets} |")
    return "\n".join(out) + "\n"


# ------------------------------------------------------------------------------------------------ mkdocs hook


def on_page_markdown(markdown: str, **_: Any) -> str:
    """Replace the markers with the generated Markdown."""
    if CONFIG_MARKER in markdown:
        markdown = markdown.replace(CONFIG_MARKER, render_config_reference())
    if IMPORTS_MARKER in markdown:
        markdown = markdown.replace(IMPORTS_MARKER, render_import_graph())
    return markdown

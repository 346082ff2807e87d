"""The documentation holds together: links resolve, and the generated configuration reference is complete.

mkdocs checks the links between pages of the site (``mkdocs build --strict`` in CI) but not README.md, nor links
from the site to files outside it; these tests check both without building the site.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import re
from pathlib import Path
from types import ModuleType

import pytest

from apf_companion.config import ServiceConfig

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
MARKDOWN = [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]

# [text](target) and ![alt](target), with an optional "title"; <...> autolinks are not relative.
_LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_FENCE = re.compile(r"^(```|~~~).*?^\1", re.MULTILINE | re.DOTALL)
_CODE_SPAN = re.compile(r"(`+)(?:(?!\1).)+?\1", re.DOTALL)


def relative_links(path: Path) -> list[str]:
    """The relative link targets of a Markdown file, outside code blocks and code spans."""
    text = _CODE_SPAN.sub("", _FENCE.sub("", path.read_text(encoding="utf-8")))
    targets = [m.group(1) for m in _LINK.finditer(text)]
    return [t for t in targets if not re.match(r"^[a-z][a-z0-9+.-]*:", t, re.IGNORECASE) and not t.startswith("#")]


def load_hook() -> ModuleType:
    spec = importlib.util.spec_from_file_location("docs_hooks_generated", DOCS / "hooks" / "generated.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_link_pattern_finds_links_and_skips_code(tmp_path: Path) -> None:
    sample = tmp_path / "sample.md"
    sample.write_text(
        "[a](x.md) ![b](figures/y.png) [c](https://e.org) [d](#anchor) `[e](not-a-link.md)`\n```\n[f](no.md)\n```\n",
        encoding="utf-8",
    )
    assert relative_links(sample) == ["x.md", "figures/y.png"]


@pytest.mark.parametrize("path", MARKDOWN, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_point_to_existing_files(path: Path) -> None:
    missing = []
    for target in relative_links(path):
        file_part = target.split("#", 1)[0]
        if not (path.parent / file_part).resolve().exists():
            missing.append(target)
    assert not missing, f"{path.relative_to(ROOT)} links to missing files: {missing}"


def test_readme_is_short_and_starts_with_the_two_commands() -> None:
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) < 200
    first_block = lines[lines.index("```sh") + 1 : lines.index("```sh") + 3]
    assert [line.split()[:2] for line in first_block] == [["./dev", "fly"], ["./dev", "test"]]


def config_sections() -> dict[str, type[object]]:
    defaults = ServiceConfig()
    return {
        f.name: type(getattr(defaults, f.name))
        for f in dataclasses.fields(ServiceConfig)
        if dataclasses.is_dataclass(getattr(defaults, f.name))
    }


def test_the_configuration_page_includes_the_generated_reference() -> None:
    hook = load_hook()
    assert hook.CONFIG_MARKER in (DOCS / "configuration.md").read_text(encoding="utf-8")


def test_the_generated_reference_lists_every_key_of_every_section() -> None:
    page = load_hook().render_config_reference()
    sections = config_sections()
    assert {"link", "autopilot", "planner", "cycle", "sensors", "zenoh", "status"} <= set(sections)
    for section, cls in sections.items():
        assert f"### `[{section}]`" in page
        for f in dataclasses.fields(cls):  # type: ignore[arg-type]
            assert f"| `{section}.{f.name}` |" in page, f"{section}.{f.name} missing from the configuration page"
    for top in ("dry_run", "exit_when_done", "max_flight_s", "max_link_lost_s"):
        assert f"| `{top}` |" in page


def row(page: str, key: str) -> list[str]:
    line = next(line for line in page.splitlines() if line.startswith(f"| `{key}` |"))
    return [cell.strip() for cell in re.split(r"(?<!\\)\|", line)[1:-1]]


def test_the_generated_reference_reads_defaults_ranges_and_meanings_from_the_code() -> None:
    page = load_hook().render_config_reference()
    _key, type_, default, allowed, meaning = row(page, "link.heartbeat_timeout_s")
    assert (type_, default, allowed) == ("`float`", "`3`", "[0.5, 60]")
    assert "LINK_LOST" in meaning
    assert row(page, "autopilot.offboard_prestream_s")[3] == "(1, 10]"  # open lower end
    assert row(page, "link.component_id")[3].startswith("integer in [1, 255]")
    assert row(page, "autopilot.profile")[2] == '`"ardupilot"`'  # an enum default shown as its TOML value
    assert row(page, "goal.east_m")[4] == row(page, "goal.north_m")[4] != ""  # one docstring entry, two keys


def test_the_import_graph_shows_the_service_wiring() -> None:
    table = load_hook().render_import_graph()
    service = row(table, "apf_companion.service")
    assert "`apf_companion.navigator`" in service[1]
    product_rows = [r for r in table.splitlines() if r.startswith("| `apf_companion")]
    assert product_rows and not any("`sim" in r.split("|")[2] for r in product_rows)  # the product never imports sim


def test_the_simulator_page_lists_every_bundled_world() -> None:
    """docs/simulator-usage.md names the bundled example worlds; a world added to sim/world/examples/ must be there."""
    from sim.world import bundled_world_names

    text = (DOCS / "simulator-usage.md").read_text()
    listing = text[text.index("## World files") :]
    listing = listing[: listing.index("```")]
    missing = [
        name for name in bundled_world_names() if not re.search(rf"(?<![\w-]){re.escape(name)}(?![\w-])", listing)
    ]
    assert missing == []

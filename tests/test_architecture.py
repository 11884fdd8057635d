"""The layout the guide asks for, checked from the source: the import graph points one way
(docs/architecture.md), the docs link only to files that ship and to headings that exist, and nothing
points at DESIGN.md."""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "odmo_cli"

# Floors from the bottom up (docs/architecture.md): a module may import its own floor and those below.
FLOORS = [
    ["errors", "config", "parallel", "device", "io", "measures"],
    ["geometry"],
    ["formats", "data"],
    ["models"],
    ["checkpoint"],
    ["training", "generation"],
    ["evaluation", "ship"],
    ["cli", "__main__"],
]
# The package root holds the entry points and small shared utilities; everything else lives in a subpackage.
ROOT_MODULES = {"__init__", "__main__", "errors", "config", "parallel", "device", "io", "checkpoint", "ship"}


def module_name(path: Path) -> str:
    rel = path.relative_to(REPO).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def imports(path: Path) -> set[str]:
    """Every odmo_cli module `path` imports, at the top or inside a function."""
    tree = ast.parse(path.read_text(), str(path))
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("odmo_cli"):
            found.add(node.module)
            for alias in node.names:  # `from odmo_cli.models import a2m` imports a module
                candidate = f"{node.module}.{alias.name}"
                if (REPO / Path(*candidate.split("."))).with_suffix(".py").is_file():
                    found.add(candidate)
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("odmo_cli")}
    return found


def graph() -> dict[str, set[str]]:
    modules = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    out = {}
    for name, path in modules.items():
        # a package's __init__ is imported with any of its modules; the arrow worth checking is the module's own
        out[name] = {m for m in imports(path) if m != name and m in modules and not name.startswith(m + ".")}
    return out


def stage(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "odmo_cli"


def floor(module: str) -> int:
    s = stage(module)
    if s == "odmo_cli":
        return 0
    return next(i for i, names in enumerate(FLOORS) if s in names)


def test_every_module_has_a_floor():
    assert all(floor(m) >= 0 for m in graph())


def test_the_package_root_holds_only_entry_points_and_shared_utilities():
    assert {p.stem for p in PACKAGE.glob("*.py")} <= ROOT_MODULES


def test_imports_point_down_or_sideways_only():
    up = sorted(f"{a} -> {b}" for a, targets in graph().items() for b in targets if floor(b) > floor(a))
    assert up == []


@pytest.mark.parametrize("source, target", [
    ("models", "training"), ("models", "data"), ("generation", "ship"), ("evaluation", "ship"),
    ("training", "evaluation"), ("training", "generation"), ("generation", "training"),
])
def test_no_arrow_between(source, target):
    arrows = [f"{a} -> {b}" for a, targets in graph().items() for b in targets
              if stage(a) == source and stage(b) == target]
    assert arrows == []


def test_no_import_cycles():
    g = graph()
    seen, on_stack, cycles = set(), [], []

    def visit(node):
        if node in on_stack:
            cycles.append(on_stack[on_stack.index(node):] + [node])
            return
        if node in seen:
            return
        seen.add(node)
        on_stack.append(node)
        for nxt in sorted(g[node]):
            visit(nxt)
        on_stack.pop()

    for node in sorted(g):
        visit(node)
    assert cycles == []


# -- docs ---------------------------------------------------------------------------------------

DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def local_links(page: Path) -> list[str]:
    """The link targets of a page outside its code blocks, web addresses (scheme:...) left out."""
    return [t for t in LINK.findall(FENCE.sub("", page.read_text())) if not re.match(r"^[a-z]+:", t)]


def test_local_links_skip_web_addresses_and_code_blocks(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("[a](docs/x.md) [b](https://example.org/y) [c](#here)\n```md\n[d](z.md)\n```\n[e](mailto:me)\n")
    assert local_links(page) == ["docs/x.md", "#here"]


@pytest.mark.parametrize("page", DOCS, ids=lambda p: p.name)
def test_relative_links_resolve_to_files_in_the_repository(page):
    missing = []
    for target in local_links(page):
        if target.startswith("#"):
            continue  # an anchor on the page itself
        path = (page.parent / target.split("#")[0]).resolve()
        if not path.exists() or REPO not in path.parents:
            missing.append(target)
    assert missing == []


@functools.lru_cache(maxsize=None)  # a page is linked to many times: parse its headings once
def heading_anchors(page: Path) -> frozenset[str]:
    """The anchors GitHub gives a page's headings: lower case, punctuation but - and _ dropped,
    spaces as -, a repeated one suffixed -1, -2, ... (headings inside code blocks are not headings)."""
    anchors: set[str] = set()
    for title in re.findall(r"^#+[ \t]+(.+?)[ \t]*$", FENCE.sub("", page.read_text()), re.M):
        slug = re.sub(r"[^\w\- ]", "", title.lower()).replace(" ", "-")
        n, anchor = 0, slug
        while anchor in anchors:
            n += 1
            anchor = f"{slug}-{n}"
        anchors.add(anchor)
    return frozenset(anchors)


def test_heading_anchors_follow_githubs_rule(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("# Stage 9 now: a wider decoder (shipped; 2026-12-06)\n## Mode discovery\n## Mode discovery\n"
                    "```sh\n# a comment, not a heading\n```\n### L_energy, `odmo eval`\n")
    assert heading_anchors(page) == {"stage-9-now-a-wider-decoder-shipped-2026-12-06", "mode-discovery",
                                     "mode-discovery-1", "l_energy-odmo-eval"}


@pytest.mark.parametrize("page", DOCS, ids=lambda p: p.name)
def test_links_to_a_heading_name_one_that_exists(page):
    missing = []
    for target in local_links(page):
        if "#" not in target:
            continue
        file, anchor = target.split("#", 1)
        linked = (page.parent / file).resolve() if file else page
        if linked.suffix == ".md" and linked.exists() and anchor not in heading_anchors(linked):
            missing.append(target)
    assert missing == []


def test_readme_is_two_screens_and_starts_with_the_quick_start():
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= 200
    first_screen = "\n".join(lines[:50])
    assert "<!-- ci:install -->" in first_screen and "<!-- ci:test -->" in first_screen


def test_nothing_points_at_a_design_file_that_does_not_ship():
    texts = [p for p in [*PACKAGE.rglob("*.py"), *DOCS] if "DESIGN.md" in p.read_text()]
    assert texts == []
    from typer.testing import CliRunner

    from odmo_cli.cli import app

    for command in (["sample", "--help"], ["eval", "--help"], ["ship", "--help"], ["train", "odmo", "--help"]):
        res = CliRunner().invoke(app, command, env={"COLUMNS": "200"})
        assert res.exit_code == 0 and "DESIGN" not in res.stdout and ".py" not in res.stdout, command

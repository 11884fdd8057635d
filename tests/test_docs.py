"""The docs stay a reference: short pages, no dated history in them or in the code's comments, and the
lab pages (docs/lab/, what was tried and decided) linked correctly and indexed.

The rule on dates: a reference page (docs/*.md) may name a date only where it says when its numbers were
measured, written "measured on YYYY-MM-DD" (or a range, "measured on D1 to D2"); anything else dated
(what was shipped when, what changed since) belongs in docs/lab/, which is exempt, or in git history.
The package's source (comments, docstrings, messages) names no date at all."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from test_architecture import heading_anchors

REPO = Path(__file__).resolve().parents[1]
REFERENCE = sorted((REPO / "docs").glob("*.md"))
LAB = sorted((REPO / "docs" / "lab").glob("*.md"))
DATE = r"20\d\d-\d\d-\d\d"
MEASURED_ON = re.compile(rf"measured\s+on\s+{DATE}(?:(?:\s+to\s+|\s+and\s+|,\s+){DATE})*", re.I)
# the names experiments had while they were run (the E line, S9H, S8H, CF6B, C7, T2, ...): lab pages only
EXPERIMENT = re.compile(r"\bE[1-5]'|\bE[1-5]\b|\bE line\b|\bS\d+[A-Z]+\d*\b|\bC[2-7]\b|\bT[1-3]\b|\bC[EFW]6B?\b")


def undated_lines(text: str) -> list[str]:
    """The lines of text that hold a date outside a "measured on DATE" statement."""
    kept = MEASURED_ON.sub(lambda m: re.sub(r"\S", "x", m.group(0)), text)  # same length, line breaks kept
    return [line for line, masked in zip(text.splitlines(), kept.splitlines()) if re.search(DATE, masked)]


def test_undated_lines_allow_only_measurement_dates():
    text = ("Measured on 2026-12-06; one run.\nmeasured on\n2026-12-01 to 2026-12-03, and 2026-12-04 (beside).\n"
            "shipped until 2026-12-05\n")
    assert undated_lines(text) == ["2026-12-01 to 2026-12-03, and 2026-12-04 (beside).", "shipped until 2026-12-05"]


@pytest.mark.parametrize("name", ["training.md", "results.md"])
def test_training_and_results_are_reference_pages_of_at_most_400_lines(name):
    lines = len((REPO / "docs" / name).read_text().splitlines())
    assert lines <= 400, f"docs/{name} has {lines} lines: keep it a reference, move history to docs/lab/"


@pytest.mark.parametrize("page", REFERENCE, ids=lambda p: p.name)
def test_reference_pages_date_only_their_measurements(page):
    assert undated_lines(page.read_text()) == []


@pytest.mark.parametrize("page", REFERENCE, ids=lambda p: p.name)
def test_reference_pages_name_no_experiments(page):
    found = [(n, m.group(0)) for n, line in enumerate(page.read_text().splitlines(), 1)
             for m in EXPERIMENT.finditer(line)]
    assert found == []


def test_no_dates_in_the_package_source():
    """Comments and docstrings say what and why; when something happened is in git and docs/lab/."""
    dated = [f"{path.relative_to(REPO)}:{n}" for path in sorted((REPO / "odmo_cli").rglob("*.py"))
             for n, line in enumerate(path.read_text().splitlines(), 1) if re.search(DATE, line)]
    assert dated == []


# -- the lab pages -----------------------------------------------------------------------------

LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def local_links(page: Path) -> list[str]:
    return [t for t in LINK.findall(FENCE.sub("", page.read_text())) if not re.match(r"^[a-z]+:", t)]




@pytest.mark.parametrize("page", LAB, ids=lambda p: p.name)
def test_lab_links_resolve_to_files_and_headings(page):
    broken = []
    for target in local_links(page):
        file, _, anchor = target.partition("#")
        path = (page.parent / file).resolve() if file else page
        if not path.exists() or REPO not in path.parents:
            broken.append(target)
        elif anchor and path.suffix == ".md" and anchor not in heading_anchors(path):
            broken.append(target)
    assert broken == []


def test_every_lab_page_is_in_the_lab_index():
    index = (REPO / "docs" / "lab" / "README.md").read_text()
    assert [p.name for p in LAB if p.name != "README.md" and f"]({p.name})" not in index] == []


def test_the_reference_pages_link_the_lab_index():
    assert "lab/README.md" in (REPO / "docs" / "results.md").read_text()

"""results/NOTES.md: every relative link resolves, no machine path, no claim of work under way.

NOTES.md holds the investigations behind the published results; each claim points at a file under
results/ that holds its evidence, so a link that no longer resolves means a claim without evidence.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

RESULTS = Path(__file__).resolve().parent.parent / "results"
NOTES = RESULTS / "NOTES.md"

# [text](target) and [text](target "title"); images ![alt](target) match too.
INLINE_LINK = re.compile(r"\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
# [label]: target
REFERENCE_LINK = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+\"[^\"]*\")?\s*$", re.MULTILINE)
ABSOLUTE_PATH = re.compile(r"/(work|root|tmp|home)/")
# Substrings, so "rerunning" counts too; whitespace (line breaks included) may split the phrase.
UNDER_WAY = {
    "running": re.compile(r"running", re.IGNORECASE),
    "in progress": re.compile(r"in\s+progress", re.IGNORECASE),
}


def _text() -> str:
    return NOTES.read_text(encoding="utf-8")


def _targets(text: str) -> list[str]:
    return INLINE_LINK.findall(text) + REFERENCE_LINK.findall(text)


def _local_path(target: str) -> str | None:
    """The file part of a link to check, or None for a web link or an anchor in this file."""
    if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE):  # http:, https:, mailto: ...
        return None
    path = target.split("#", 1)[0].split("?", 1)[0]
    return path or None


def test_notes_exists() -> None:
    assert NOTES.is_file(), f"{NOTES} is missing"


def test_links_parse() -> None:
    assert _targets("[a](x/y.md) and [b](https://e.org) and [c](#top)\n[d]: z.md\n") == [
        "x/y.md",
        "https://e.org",
        "#top",
        "z.md",
    ]
    assert _local_path("https://e.org/a") is None
    assert _local_path("#anchor") is None
    assert _local_path("online/x/report/stages.md#seed-1") == "online/x/report/stages.md"


def test_every_relative_link_resolves() -> None:
    targets = _targets(_text())
    assert targets, "NOTES.md links no evidence at all"
    missing = []
    for target in targets:
        path = _local_path(target)
        if path is None:
            continue
        if path.startswith("/"):
            missing.append(f"{target} (absolute)")
        elif not (RESULTS / path).exists():
            missing.append(target)
    assert not missing, "links in results/NOTES.md that resolve to nothing under results/: " + (
        ", ".join(sorted(set(missing)))
    )


def test_no_absolute_machine_paths() -> None:
    hits = [
        f"line {number}: {line.strip()}"
        for number, line in enumerate(_text().splitlines(), 1)
        if ABSOLUTE_PATH.search(line)
    ]
    assert not hits, "absolute paths in results/NOTES.md:\n" + "\n".join(hits)


@pytest.mark.parametrize("phrase", sorted(UNDER_WAY))
def test_nothing_said_to_be_under_way(phrase: str) -> None:
    hits = [
        f"line {number}: {line.strip()}"
        for number, line in enumerate(_text().splitlines(), 1)
        if UNDER_WAY[phrase].search(line)
    ]
    text = _text()
    # the phrase split over two lines
    hits += [f"...{m.group(0)}..." for m in UNDER_WAY[phrase].finditer(text) if "\n" in m.group(0)]
    message = f"results/NOTES.md says {phrase!r}; say what is published instead:\n"
    assert not hits, message + "\n".join(hits)

"""The guides (docs/guide/) say how to do a thing; measurements, device timings, commit hashes and issue numbers
live in docs/results.md, docs/benchmarks.md and docs/records/history.md, which the guides point to."""

import re
from pathlib import Path

import pytest

GUIDES = Path(__file__).resolve().parents[1] / "docs" / "guide"
NOT_IN_A_GUIDE = {
    "an issue number": r"\bissues? \d+|#\d{2,}",
    "a commit hash": r"\b(?=[0-9a-f]*\d)(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b",
    "a device timing": r"\b(?:H100|H200|A100)s?\b",
    "a throughput": r"img/s|images/s|cells/hour|cells per hour",
    "a speed-up": r"\b\d+(?:\.\d+)?x (?:faster|slower|the)\b",
    "a measured difference with its interval": r"[+-]\d\.\d{3,} \[[+-]?\d",
}


@pytest.mark.parametrize("guide", ["studies.md", "training.md", "camera.md"])
def test_a_guide_holds_no_measurements_hashes_or_issue_numbers(guide):
    """Before: studies.md and training.md were bullets of ~1,000 words mixing how-to with H100 and H200 timings,
    img/s, measured differences with their intervals, 'issue 28' and 'pytorch#115388' (33 such places)."""
    text = (GUIDES / guide).read_text()
    found = [f"{guide}:{text[:m.start()].count(chr(10)) + 1}: {name}: {m.group(0)!r}"
             for name, pattern in NOT_IN_A_GUIDE.items() for m in re.finditer(pattern, text)]
    assert found == []


@pytest.mark.parametrize("guide", ["studies.md", "training.md"])
def test_a_guide_is_sections_of_short_bullets(guide):
    """A bullet of a guide is one thing to do, not a page: none over 250 words (studies.md had one of ~1,000)."""
    text = (GUIDES / guide).read_text()
    bullets = re.split(r"\n(?=- |#)", text)
    longest = max(len(bullet.split()) for bullet in bullets if bullet.startswith("- "))
    assert longest <= 250 and text.count("\n## ") >= 5

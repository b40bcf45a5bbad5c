"""Papers are cited one way, so one grep finds each: ``Hasler Equation 9``, ``Hasler §2.3``,
``Hasler Figure 5``, ``Rupprecht Table 1`` (DESIGN.md, Conventions). The abbreviated forms
(``Eq. 9``, ``Sec. 3``, ``Fig. 5``, ``Equation (10)``) are refused wherever a reader looks."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
WHERE = ["src", "docs", "benchmarks", "README.md"]
SUFFIXES = {".py", ".md", ".txt", ".json", ".toml", ".rst"}
# "Eq. 9", "Eqs. 2", "Sec. 3.2", "Fig. 5", "Fig 5", "Eq.(10)", and "Equation (10)" (numbered in parentheses).
OLD_FORM = re.compile(r"\b(?:Eqs?|Secs?|Figs?)\.?\s*\(?\d|\bEquations?\s*\(\d")


def _files():
    for name in WHERE:
        path = ROOT / name
        if path.is_file():
            yield path
        elif path.is_dir():
            yield from sorted(p for p in path.rglob("*") if p.suffix in SUFFIXES and "__pycache__" not in p.parts)


@pytest.mark.parametrize("text, old", [
    ("the rotations of Eq. 9", True), ("(Sec. 4.1)", True), ("Rupprecht Fig. 6", True), ("Equation (10)", True),
    ("Hasler's Eq.11", True), ("Fig 5", True),
    ("Hasler Equation 9", False), ("Rupprecht §3.2", False), ("Hasler Figure 5", False), ("Secant 3", False),
])
def test_the_pattern_itself(text, old):
    assert bool(OLD_FORM.search(text)) is old


def test_citations_have_one_form():
    bad = []
    for path in _files():
        for n, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            m = OLD_FORM.search(line)
            if m:
                bad.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()[:100]}")
    assert not bad, ("cite papers as 'Hasler Equation 9', 'Rupprecht §3.2', 'Hasler Figure 5', 'Rupprecht Table 1':\n"
                     + "\n".join(bad))

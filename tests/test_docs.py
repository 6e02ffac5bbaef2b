"""The docs name only files that exist: every backticked repository path in README.md and docs/,
and every test they cite as ``tests/file.py::test_name`` exists in that file."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
TOP = {p.name for p in REPO.iterdir() if not p.name.startswith(".") or p.name == ".ci"}


def _paths(text: str) -> list[str]:
    out = []
    for tok in re.findall(r"`([^`\s]+)`", text):
        first = tok.split("/", 1)[0]
        if "/" in tok and first in TOP and not re.search(r"[<>*…|]", tok) and first not in ("runs",):
            out.append(tok.rstrip("/"))
    return out


def test_docs_name_only_existing_files() -> None:
    docs = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
    for doc in docs:
        for p in _paths(doc.read_text()):
            path, _, test = p.partition("::")
            test = test.split("[", 1)[0]  # a parametrised case, test_x[indoor], is test_x
            assert (REPO / path).exists(), f"{doc.relative_to(REPO)} names {path}, which does not exist"
            if test:
                assert f"def {test}(" in (REPO / path).read_text(), f"{doc.relative_to(REPO)} cites {p}: no such test"

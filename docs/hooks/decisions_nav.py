"""mkdocs hook: list every decision record (docs/architecture/decisions/NNNN-*.md) in the nav.

mkdocs.yml names only the decisions index; the records follow it in number order, so a new
record appears in the navigation without editing mkdocs.yml (and strict mode, which fails on a
page missing from the nav, stays on).
"""

from __future__ import annotations

import re
from pathlib import Path

INDEX = "architecture/decisions/index.md"
RECORD = re.compile(r"\d{4}-[^/]+\.md")


def _records(docs_dir: str) -> list[str]:
    folder = Path(docs_dir) / "architecture" / "decisions"
    names = sorted(p.name for p in folder.glob("*.md") if RECORD.fullmatch(p.name))
    return [f"architecture/decisions/{name}" for name in names]


def _extend(items: list, records: list[str]) -> bool:
    """Append the records to the nav list that holds the decisions index; True once done."""
    for item in items:
        value = next(iter(item.values())) if isinstance(item, dict) else item
        if value == INDEX:
            items.extend(r for r in records if r not in items)
            return True
        if isinstance(value, list) and _extend(value, records):
            return True
    return False


def on_config(config, **kwargs):
    if config.nav is not None:
        _extend(config.nav, _records(config.docs_dir))
    return config

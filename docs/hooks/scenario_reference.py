"""mkdocs hook: render the scenario schema into docs/reference/scenario.md.

The page holds a marker line; the tables replacing it come from `autopower.model.schema`, the
same schema the loader checks files against, so the reference cannot drift from the code.
"""

from __future__ import annotations

from autopower.model.schema import render_markdown

PAGE = "reference/scenario.md"
MARKER = "<!-- scenario-schema -->"


def on_page_markdown(markdown: str, page, **kwargs) -> str:
    if page.file.src_uri != PAGE:
        return markdown
    if MARKER not in markdown:
        raise ValueError(f"{PAGE}: the marker {MARKER} is missing; the schema has nowhere to go")
    return markdown.replace(MARKER, render_markdown(level=3))

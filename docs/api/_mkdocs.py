"""Build support for ``mkdocs build`` (see ``mkdocs.yml``); not a documentation page.

Two small adapters between the sources as written and mkdocs:

* ``SphinxRolesToMarkdown``, a Griffe extension: the docstrings cross-reference with Sphinx roles
  (``:class:`Scenario```, ``:func:`~swarmpc.x.y```), which mkdocstrings renders as markdown, where
  the role would show as literal text. Each role becomes an inline code span (``~`` keeps the last
  component, as in Sphinx). A numpydoc section (``Parameters``...) ends only at the next section
  header, so a closing prose paragraph written after the parameters would be read as a parameter;
  such a paragraph is moved in front of the first section, where numpydoc keeps prose.
* ``on_page_markdown``, a mkdocs hook: a table cell such as ``[m] [the scenarios' own: off]`` is
  plain text on GitHub but a reference link ``[text][id]`` to mkdocs-autorefs, which then warns
  about an unknown target. The space between two bracket groups outside code is escaped.
"""

from __future__ import annotations

import re
from typing import Any

ROLE = re.compile(r":(?:py:)?(?:func|meth|class|attr|data|mod|obj|exc|const|term|ref):`~?([^`]+)`")
SECTION = re.compile(r"^(?P<title>[A-Z][A-Za-z ]+)\n(?P<rule>-{3,})$", re.MULTILINE)
ITEM_SECTIONS = {
    "Parameters",
    "Other Parameters",
    "Returns",
    "Yields",
    "Receives",
    "Raises",
    "Warns",
    "Attributes",
    "Methods",
    "Functions",
    "Classes",
    "Modules",
}
"""The numpydoc sections that hold lists of items (Notes, Examples and the like hold free text)."""
PARAMETER_LINE = re.compile(r"^\*{0,2}[\w.]+(?:\s*,\s*\*{0,2}[\w.]+)*(?:\s+:.*)?$")


def _role(match: re.Match[str]) -> str:
    target = match.group(1)
    if match.group(0).split("`", 1)[1].startswith("~"):
        target = target.rsplit(".", 1)[-1]
    return f"``{target}``"


def convert_roles(text: str) -> str:
    """Sphinx cross-reference roles as markdown code spans."""
    return ROLE.sub(_role, text)


def hoist_trailing_prose(text: str) -> str:
    """Move prose paragraphs that follow a numpydoc item section in front of the first section.

    A paragraph inside an item section (``ITEM_SECTIONS``) is prose when its first line is not
    indented and does not look like an item line (``name``, ``name : type``, ``a, b : type``).
    """
    first = SECTION.search(text)
    if first is None:
        return text
    head, body = text[: first.start()], text[first.start() :]
    blocks = body.split("\n\n")
    kept: list[str] = []
    moved: list[str] = []
    section = ""
    for block in blocks:
        first_line = block.split("\n", 1)[0]
        header = SECTION.match(block)
        if header:
            section = header.group("title").strip()
        is_prose = (
            header is None
            and section in ITEM_SECTIONS
            and first_line.strip()
            and not first_line.startswith((" ", "\t", ">>>"))
            and not PARAMETER_LINE.match(first_line.strip())
        )
        (moved if is_prose else kept).append(block)
    if not moved:
        return text
    return head.rstrip("\n") + "\n\n" + "\n\n".join(moved) + "\n\n" + "\n\n".join(kept)


try:
    from griffe import Extension, Object
except ImportError:  # only mkdocs' hook is used
    Extension = object  # type: ignore[assignment,misc]
    Object = Any  # type: ignore[assignment,misc]


class SphinxRolesToMarkdown(Extension):  # type: ignore[misc,valid-type]
    """Rewrite each loaded docstring: roles as code spans, trailing prose before the sections."""

    def on_instance(self, *, obj: Object, **kwargs: Any) -> None:
        docstring = getattr(obj, "docstring", None)
        if docstring is not None:
            docstring.value = hoist_trailing_prose(convert_roles(docstring.value))


FENCE = re.compile(r"^```.*?^```", re.DOTALL | re.MULTILINE)
CODE_SPAN = re.compile(r"`[^`\n]*`")
BRACKETS_IN_A_ROW = re.compile(r"\](\s)\[")


def _escape_outside_code(text: str) -> str:
    pieces: list[str] = []
    last = 0
    for match in CODE_SPAN.finditer(text):
        pieces.append(BRACKETS_IN_A_ROW.sub(r"]\1\\[", text[last : match.start()]))
        pieces.append(match.group(0))
        last = match.end()
    pieces.append(BRACKETS_IN_A_ROW.sub(r"]\1\\[", text[last:]))
    return "".join(pieces)


def on_page_markdown(markdown: str, **kwargs: Any) -> str:
    """Escape ``] [`` outside code so that two bracketed notes are not read as a reference link."""
    pieces: list[str] = []
    last = 0
    for match in FENCE.finditer(markdown):
        pieces.append(_escape_outside_code(markdown[last : match.start()]))
        pieces.append(match.group(0))
        last = match.end()
    pieces.append(_escape_outside_code(markdown[last:]))
    return "".join(pieces)

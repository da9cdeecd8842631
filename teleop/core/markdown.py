"""Markdown tables: the one writer of every table the project prints or embeds in docs/
(docs embed some verbatim and tests compare them, so the format is fixed: ``| a | b |``
rows, ``| --- | ---: |`` under the header)."""

from __future__ import annotations

from collections.abc import Iterable, Sequence

LEFT, RIGHT = "l", "r"
_RULES = {LEFT: "---", RIGHT: "---:"}


def table(header: Sequence[str], rows: Iterable[Sequence[object]], align: str = "") -> list[str]:
    """The table's lines: ``header``, its rule, a line per row (each cell as ``str``).

    ``align`` has a letter per column, ``l`` (left) or ``r`` (right, for figures); columns
    it does not reach are left-aligned. A row of another width than the header is a
    ValueError (a cell lost or one too many would shift every column after it)."""
    if len(align) > len(header) or set(align) - set(_RULES):
        raise ValueError(f"align {align!r}: at most {len(header)} letters of 'l' and 'r'")
    rules = [_RULES[a] for a in align.ljust(len(header), LEFT)]
    lines = [_row(header), _row(rules)]
    for row in rows:
        if len(row) != len(header):
            raise ValueError(f"a row of {len(row)} cells in a table of {len(header)}: {row}")
        lines.append(_row([str(cell) for cell in row]))
    return lines


def _row(cells: Sequence[str]) -> str:
    return "| " + " | ".join(cells) + " |"

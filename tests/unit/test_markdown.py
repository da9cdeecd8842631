"""The one table writer: its format (docs embed its tables verbatim) and its refusals."""

from __future__ import annotations

import pytest

from teleop.core import markdown


def test_a_table_has_its_header_rule_and_rows_with_figures_right_aligned():
    lines = markdown.table(
        ("hop", "p50 (ms)", "note"), [("a -> b", 0.5, ""), ("b -> c", 12, "x")], "lr"
    )
    assert lines == [
        "| hop | p50 (ms) | note |",
        "| --- | ---: | --- |",
        "| a -> b | 0.5 |  |",
        "| b -> c | 12 | x |",
    ]


def test_a_row_of_another_width_or_a_bad_alignment_is_refused():
    with pytest.raises(ValueError, match="a row of 1 cells in a table of 2"):
        markdown.table(("a", "b"), [("only one",)])
    with pytest.raises(ValueError, match="align"):
        markdown.table(("a", "b"), [], "lrr")
    with pytest.raises(ValueError, match="align"):
        markdown.table(("a", "b"), [], "c")

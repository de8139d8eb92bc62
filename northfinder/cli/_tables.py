"""Tables that fit the terminal: a wide table is split by columns into several tables (its key
columns repeated in each), so that no number is ever cut to "…" at 80 columns.

A shared CLI module (find's summary, replay, campaign); rich measures nothing here: the widths are
the cells' own (rich.cells.cell_len), a header may wrap at its spaces, a cell never does.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

BORDER_PER_COLUMN = 3
"""A boxed rich column's cost besides its content: one padding space either side and its rule."""


def column_width(header: str, cells: Sequence[str]) -> int:
    """The narrowest the column can be: its widest cell (never cut), its header's longest word."""
    from rich.cells import cell_len

    words = [cell_len(w) for w in header.split()] or [0]
    return max([max(words), *(cell_len(c) for c in cells)])


def split_columns(widths: Sequence[int], total_width: int, keep: int = 1) -> list[list[int]]:
    """Column indices of each table: the first `keep` columns in every one, the others in order,
    as many per table as fit `total_width` (at least one, even if it alone is wider)."""
    key = list(range(keep))
    base = 1 + sum(widths[k] + BORDER_PER_COLUMN for k in key)
    groups: list[list[int]] = []
    current: list[int] = []
    used = base
    for k in range(keep, len(widths)):
        need = widths[k] + BORDER_PER_COLUMN
        if current and used + need > total_width:
            groups.append(key + current)
            current, used = [], base
        current.append(k)
        used += need
    if current or not groups:
        groups.append(key + current)
    return groups


def fitted_tables(
    title: str, headers: Sequence[str], rows: Sequence[Sequence[str]], width: int, keep: int = 1
) -> list[Any]:
    """rich Tables holding `headers` × `rows`, split by columns to fit `width` (see split_columns);
    the titles say "(continued)" after the first. Numbers are right-aligned and never wrapped."""
    from rich.cells import cell_len
    from rich.markup import escape
    from rich.table import Table

    widths = [column_width(h, [r[k] for r in rows]) for k, h in enumerate(headers)]
    whole = [max(w, cell_len(h)) for w, h in zip(widths, headers, strict=True)]
    if len(split_columns(whole, width, keep)) == 1:
        widths = whole  # wide enough for one table with every header on one line
    tables = []
    groups = split_columns(widths, width, keep)
    for n, group in enumerate(groups):
        t = Table(title=title if n == 0 else f"{title} (continued)")
        for k in group:
            t.add_column(escape(headers[k]), justify="right", width=widths[k],
                         overflow="fold")
        for r in rows:
            t.add_row(*(escape(r[k]) for k in group))
        tables.append(t)
    return tables


def print_fitted(console: Any, title: str, headers: Sequence[str], rows: Sequence[Sequence[str]],
                 keep: int = 1) -> None:
    """Print `fitted_tables` at the console's width."""
    for table in fitted_tables(title, headers, rows, console.width, keep):
        console.print(table)


def print_table_fitted(console: Any, table: Any, keep: int = 1) -> None:
    """Print a rich Table already built (its cells as markup) split by columns to the console's
    width as `fitted_tables` does, each column keeping its justification; for tables built
    elsewhere (the history's), so that their code changes by one line."""
    from rich.cells import cell_len
    from rich.table import Table

    headers = [str(c.header) for c in table.columns]
    cells = [[str(x) for x in c._cells] for c in table.columns]
    rows = list(zip(*cells, strict=True)) if cells else []
    widths = [column_width(h, col) for h, col in zip(headers, cells, strict=True)]
    whole = [max(w, cell_len(h)) for w, h in zip(widths, headers, strict=True)]
    if len(split_columns(whole, console.width, keep)) == 1:
        widths = whole
    title = str(table.title or "")
    for n, group in enumerate(split_columns(widths, console.width, keep)):
        t = Table(title=title if n == 0 else f"{title} (continued)")
        for k in group:
            t.add_column(headers[k], justify=table.columns[k].justify, width=widths[k], overflow="fold")
        for r in rows:
            t.add_row(*(r[k] for k in group))
        console.print(t)

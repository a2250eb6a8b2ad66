"""Parsing of whitespace- or comma-separated point tables (``.xyz``, ``.txt``, ``.csv``, ``.pts``).

The preamble (blank lines, ``#`` or ``//`` comments, an optional header line naming the columns,
the point count of a ``.pts`` file) is examined line by line; the numeric body is parsed in one
call of :func:`numpy.loadtxt` (its C parser reads 50k lines in a few tens of milliseconds). Only
when that fails is the body scanned again in Python, to name the first bad line.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

#: Prefixes of comment lines; a comment made only of names (``//X Y Z``) can be the header.
COMMENT_PREFIXES = ("#", "//")
_QUOTE_CHARS = 40
#: Columns at most of a point table. A point's attributes (intensity, colour, normal, labels,
#: returns, time ...) number a dozen or two; a line of hundreds of numbers is a cloud written
#: transposed or without line breaks, which would be read as one point with as many fields.
#: (The same bound as a ``.npy`` array's, :data:`kbs.io.readers._NPY_MAX_COLUMNS`.)
MAX_COLUMNS = 64


class TableError(ValueError):
    """A text table that cannot be parsed; the message says where and why (one line)."""


@dataclass(frozen=True)
class Table:
    """A parsed numeric table.

    Attributes
    ----------
    values : np.ndarray, shape (N, C), float64
        One row per data line.
    names : tuple[str, ...] or None
        The C column names of the header line, or None when the file has no header.
    count, count_line : int or None
        The point count a line holding one whole number before the data announces (a ``.pts``
        file's first line), and that line's number (1-based); None when there is none.
    header_line : int or None
        The line number of the header (1-based), None when there is none.
    """

    values: np.ndarray
    names: tuple[str, ...] | None
    count: int | None = None
    count_line: int | None = None
    header_line: int | None = None


def _quote(line: str) -> str:
    line = line.strip()
    return repr(line if len(line) <= _QUOTE_CHARS else line[:_QUOTE_CHARS] + "...")


def _delimiter(line: str) -> str | None:
    """``","`` for a comma-separated line, None (any whitespace) otherwise."""
    return "," if "," in line else None


def _split(line: str, delimiter: str | None) -> list[str]:
    if delimiter is None:
        return line.split()
    return [token.strip() for token in line.split(delimiter)]


def _strip_comment(line: str) -> str:
    for prefix in COMMENT_PREFIXES:
        cut = line.find(prefix)
        if cut >= 0:
            line = line[:cut]
    return line


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _header_names(line: str) -> tuple[str, ...] | None:
    """The column names of a header line, or None if it is not made only of names."""
    text = line.lstrip("#/").strip()
    names = tuple(token.strip("\"'") for token in _split(text, _delimiter(text)))
    if not names or not all(names) or any(_is_number(name) for name in names):
        return None
    return names


def _separator_hint(line: str) -> str:
    """A hint for a line whose columns are separated by semicolons, or ``""``."""
    if ";" not in line:
        return ""
    return " (columns separated by ';'? they are read separated by blanks or by commas)"


def _find_bad_line(body: str, first_lineno: int, n_columns: int, delimiter: str | None) -> str | None:
    """Describe the first line of ``body`` that is not a row of ``n_columns`` numbers."""
    for lineno, line in enumerate(body.split("\n"), start=first_lineno):
        stripped = _strip_comment(line).strip()
        if not stripped:
            continue
        tokens = _split(stripped, delimiter)
        if len(tokens) != n_columns:
            return f"line {lineno} has {len(tokens)} columns, expected {n_columns}: {_quote(line)}"
        for token in tokens:
            if not _is_number(token):
                return f"line {lineno}: {token!r} is not a number: {_quote(line)}"
    return None


def parse_table(text: str) -> Table:
    """Parse a point table.

    Parameters
    ----------
    text : str
        The whole file. Data lines hold at least three numbers separated by whitespace or by
        commas (decided on the first data line). Before them may come blank lines, comments
        (``#``, ``//``), a header naming every column (``x,y,z,label`` or ``//X Y Z``) and a line
        holding only the point count (``.pts``). Comments may also follow the data.

    Returns
    -------
    Table
        The (N, C) values, 3 <= C <= :data:`MAX_COLUMNS`, the header names if there is a header,
        and the point count if a line announces one.

    Raises
    ------
    TableError
        No data line (the first line that is not a row of numbers is quoted), fewer than three
        or more than :data:`MAX_COLUMNS` columns, a header whose length differs from the data's,
        a lone number before the data that is not a whole number, or a line that is not a row of
        C numbers (its 1-based number and a quote are given).
    """
    if "\x00" in text[:4096]:
        raise TableError("binary data, not a text table")
    header: tuple[str, ...] | None = None
    header_lineno = 0
    header_commented = False
    count: int | None = None
    count_line: int | None = None
    texts: list[tuple[int, str]] = []  # the first lines made of words, not numbers
    lineno = 0
    pos = 0
    while pos < len(text):
        end = text.find("\n", pos)
        end = len(text) if end < 0 else end
        line = text[pos:end]
        lineno += 1
        stripped = line.strip()
        if stripped.startswith(COMMENT_PREFIXES):
            names = _header_names(stripped)
            if names is not None:
                header, header_lineno, header_commented = names, lineno, True
        elif stripped:
            tokens = _split(stripped, _delimiter(stripped))
            numeric = [_is_number(token) for token in tokens]
            if all(numeric) and len(tokens) > 1:
                break  # the first data line
            if not all(numeric) and any(numeric):
                bad = tokens[numeric.index(False)]
                raise TableError(f"line {lineno}: {bad!r} is not a number: {_quote(line)}{_separator_hint(line)}")
            if not all(numeric):
                header, header_lineno, header_commented = _header_names(stripped), lineno, False
                if len(texts) < 2:
                    texts.append((lineno, line))
            else:  # a single number before the data: the point count of a .pts file
                value = float(tokens[0])
                if not value.is_integer():
                    raise TableError(f"line {lineno}: a lone number before the data is a point count, and "
                                     f"{tokens[0]!r} is not a whole number: {_quote(line)}")
                count, count_line = int(value), lineno
        pos = end + 1
    else:
        message = "no data line (expected rows of at least 3 numbers: x y z ...)"
        hinted = next(((n, words) for n, words in texts if _separator_hint(words)), None)
        if hinted is not None:
            message += f": line {hinted[0]} holds {_quote(hinted[1])}{_separator_hint(hinted[1])}"
        elif len(texts) > 1:
            message += f": line {texts[1][0]} is not a row of numbers: {_quote(texts[1][1])}"
        elif texts:
            message += f": line {texts[0][0]} holds names, not numbers: {_quote(texts[0][1])}"
        raise TableError(message)

    delimiter = _delimiter(stripped)
    n_columns = len(tokens)
    if n_columns < 3:
        raise TableError(
            f"line {lineno} has {n_columns} columns; at least 3 (x y z) are needed: {_quote(line)}"
        )
    if n_columns > MAX_COLUMNS:
        raise TableError(
            f"line {lineno} has {n_columns:,} columns, more than the {MAX_COLUMNS} of a point table (one point "
            f"a line: x y z, then its attributes); a cloud written transposed or without line breaks?"
        )
    if header is not None and len(header) != n_columns:
        if not header_commented:
            raise TableError(
                f"the header on line {header_lineno} names {len(header)} columns "
                f"but line {lineno} has {n_columns}"
            )
        header = None  # a comment that merely looks like names
    body = text[pos:]
    try:
        values = np.loadtxt(
            io.StringIO(body),
            dtype=np.float64,
            delimiter=delimiter,
            # a two-character comment prefix slows numpy's parser by a quarter: only when needed
            comments=COMMENT_PREFIXES if "//" in body else "#",
            ndmin=2,
        )
    except ValueError as exc:
        problem = _find_bad_line(body, lineno, n_columns, delimiter)
        raise TableError(problem or f"cannot parse the numbers: {str(exc).splitlines()[0]}") from exc
    if values.shape[1] != n_columns:  # pragma: no cover - loadtxt enforces a constant count
        raise TableError(f"expected {n_columns} columns, parsed {values.shape[1]}")
    return Table(values=values, names=header, count=count, count_line=count_line,
                 header_line=header_lineno if header is not None else None)

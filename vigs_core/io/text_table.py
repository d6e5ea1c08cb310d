"""Line-oriented numeric text tables (EuRoC CSV, TUM text) with errors that name file and line.

Stamps are kept exact: EuRoC writes integer nanoseconds (about 1.4e18, beyond float64's 2^53), TUM writes
decimal seconds; both become ``int`` nanoseconds without passing through ``float``.
"""
from __future__ import annotations

import math
import re
import warnings
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

_WHITESPACE_OR_COMMA = re.compile(r"[,\s]+")
_NS_PER_S = Decimal(1_000_000_000)


class SkippedRowsWarning(UserWarning):
    """Rows of a text table left out (:func:`read_stamped_rows` ``skip_nonfinite``)."""


class MalformedFileError(ValueError):
    """A text file that does not have the expected layout.

    Attributes:
        path: the file.
        line: 1-based line number of the offending line (0 when the problem is the file as a whole).
    """

    def __init__(self, path: str | Path, line: int, message: str) -> None:
        where = f"{path}, line {line}" if line > 0 else f"{path}"
        super().__init__(f"{where}: {message}")
        self.path = Path(path)
        self.line = line


def seconds_to_ns(text: str) -> int:
    """Exact integer nanoseconds of a decimal seconds string (``"1403715274.30214"``, ``"1.5e-3"``).

    Parsed with :class:`decimal.Decimal`, so no digit is lost to binary floating point; digits below
    1 ns are rounded half-to-even. Raises ``ValueError`` for anything that is not a finite number.
    """
    try:
        value = Decimal(text)
    except InvalidOperation:
        raise ValueError(f"'{text}' is not a decimal number of seconds") from None
    if not value.is_finite():
        raise ValueError(f"'{text}' is not a finite number of seconds")
    return int((value * _NS_PER_S).to_integral_value(rounding=ROUND_HALF_EVEN))


def ns_to_seconds_text(t_ns: int) -> str:
    """Decimal seconds with all 9 digits of the nanoseconds, e.g. ``1403715274302140000 -> "1403715274.302140000"``."""
    t_ns = int(t_ns)
    sign = "-" if t_ns < 0 else ""
    whole, frac = divmod(abs(t_ns), 1_000_000_000)
    return f"{sign}{whole}.{frac:09d}"


def data_lines(path: str | Path) -> Iterator[tuple[int, str]]:
    """``(line_number, stripped_text)`` of every line that is neither blank nor a ``#`` comment."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    with path.open("r", encoding="utf-8") as f:
        for number, line in enumerate(f, start=1):
            text = line.strip()
            if text and not text.startswith("#"):
                yield number, text


def comment_lines(path: str | Path, limit: int = 20) -> list[str]:
    """The ``#`` comment lines among the first ``limit`` lines (headers such as ``#timestamp [ns],...``)."""
    out = []
    with Path(path).open("r", encoding="utf-8") as f:
        for _, line in zip(range(limit), f):
            if line.lstrip().startswith("#"):
                out.append(line.strip())
    return out


def split_fields(text: str, separator: str) -> list[str]:
    """Fields of one line: ``separator`` is ``"comma"`` (CSV) or ``"whitespace_or_comma"`` (TUM)."""
    if separator == "comma":
        return [field.strip() for field in text.split(",")]
    if separator == "whitespace_or_comma":
        return _WHITESPACE_OR_COMMA.split(text.strip())
    raise ValueError(f"separator must be 'comma' or 'whitespace_or_comma', got '{separator}'")


def read_stamped_rows(
    path: str | Path,
    column_counts: Sequence[int],
    separator: str,
    stamp: str,
    layout: str,
    skip_nonfinite: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a table whose first column is a stamp and whose other columns are finite floats.

    Args:
        path: the text file; blank lines and ``#`` comments are skipped.
        column_counts: accepted numbers of columns (stamp included); every row must have the count of
            the first data row.
        separator: ``"comma"`` or ``"whitespace_or_comma"`` (see :func:`split_fields`).
        stamp: ``"ns"`` (integer nanoseconds, EuRoC) or ``"s"`` (decimal seconds, TUM).
        layout: human-readable column list used in error messages.
        skip_nonfinite: a row whose values parse but are not all finite (``nan``, ``inf``: a sensor driver's
            invalid sample) is left out with a :class:`SkippedRowsWarning` naming the lines, instead of an error.

    Returns:
        ``t_ns`` (N,) int64, ``values`` (N, C-1) float64 and ``line_numbers`` (N,) int64 (1-based line
        of each row in the file, for later error messages).

    Raises:
        MalformedFileError: wrong column count, a stamp or value that does not parse, or no data rows.
    """
    stamps: list[int] = []
    rows: list[list[float]] = []
    numbers: list[int] = []
    skipped: list[int] = []
    n_columns = None
    unit = "integer nanoseconds" if stamp == "ns" else "decimal seconds"
    for number, text in data_lines(path):
        fields = split_fields(text, separator)
        if n_columns is None:
            if len(fields) not in column_counts:
                counts = " or ".join(str(c) for c in column_counts)
                raise MalformedFileError(
                    path, number, f"expected {counts} columns ({layout}), found {len(fields)}: '{text[:80]}'"
                )
            n_columns = len(fields)
        elif len(fields) != n_columns:
            raise MalformedFileError(
                path, number, f"expected {n_columns} columns like the first data row ({layout}), found {len(fields)}"
            )
        try:
            t = int(fields[0]) if stamp == "ns" else seconds_to_ns(fields[0])
        except ValueError:
            raise MalformedFileError(
                path, number, f"column 1 (time stamp) must be {unit}, found '{fields[0]}'"
            ) from None
        try:
            values = [float(field) for field in fields[1:]]
        except ValueError:
            values = []
        if len(values) != n_columns - 1 or not all(map(math.isfinite, values)):
            if skip_nonfinite and len(values) == n_columns - 1:
                skipped.append(number)
                continue
            column = next(i for i, field in enumerate(fields[1:], start=2) if not _is_finite_float(field))
            raise MalformedFileError(
                path, number, f"column {column} must be a finite number ({layout}), found '{fields[column - 1]}'"
            )
        stamps.append(t)
        rows.append(values)
        numbers.append(number)
    if n_columns is None:
        raise MalformedFileError(path, 0, f"no data rows; expected lines of {layout}")
    if skipped:
        shown = ", ".join(map(str, skipped[:5])) + (", ..." if len(skipped) > 5 else "")
        warnings.warn(f"{path}: {len(skipped)} rows with a non-finite value left out (lines {shown})",
                      SkippedRowsWarning, stacklevel=2)
    values_array = np.array(rows, dtype=np.float64).reshape(len(rows), n_columns - 1)
    return np.array(stamps, dtype=np.int64), values_array, np.array(numbers, dtype=np.int64)


def _is_finite_float(text: str) -> bool:
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def normalized_quaternions(path: str | Path, quat: np.ndarray, line_numbers: np.ndarray) -> np.ndarray:
    """Unit quaternions (N, 4); rows whose norm is not within 1e-2 of 1 are a layout error, not rounding.

    Files store quaternions rounded to a few digits, so norms of ``1 +- 1e-6`` are normal and are
    normalised away; a norm far from 1 means swapped or missing columns.
    """
    norm = np.linalg.norm(quat, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > 1e-2)
    if len(bad):
        row = int(bad[0])
        raise MalformedFileError(
            path, int(line_numbers[row]), f"quaternion norm {norm[row]:.4g}; expected a unit quaternion"
        )
    return quat / norm[:, None]


def stamp_order(path: str | Path, t_ns: np.ndarray, line_numbers: np.ndarray, keep_first: bool = False) -> np.ndarray:
    """Indices that sort rows by stamp (stable); a stamp that occurs twice is an error, or with ``keep_first``
    (trajectories to evaluate, which evo reads with repeated stamps) only its first row is kept, with a warning.

    Recorded files are almost always sorted already; sorting here means consumers never see time run
    backwards, and a repeated stamp (zero time step, ambiguous association) is reported with both lines.
    """
    order = np.argsort(t_ns, kind="stable")
    repeated = np.flatnonzero(np.diff(t_ns[order]) == 0)
    if len(repeated):
        first, second = order[repeated[0]], order[repeated[0] + 1]
        problem = f"time stamp {t_ns[second]} ns repeats the stamp of line {line_numbers[first]}"
        if not keep_first:
            raise MalformedFileError(path, int(line_numbers[second]), f"{problem}; expected unique stamps")
        warnings.warn(f"{path}:{int(line_numbers[second])}: {problem}; {len(repeated)} repeated stamp(s) in all, "
                      "the first row of each is kept", stacklevel=2)
        order = np.delete(order, repeated + 1)
    return order

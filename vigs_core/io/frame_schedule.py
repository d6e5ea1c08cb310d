"""Which frames a live run tracked, and when: ``frames_processed.txt`` of the frontend node.

One line per tracked frame, in order: its stamp (ns), followed, for a frame tracked during a keyframe's work, by
the index of the yield point it was tracked at (:attr:`vigs_core.frontend.odometry.DenseOdometry.yield_points`
then; see that module's "live callers"). Frames of the input not listed were skipped. ``vigs run --frames-from``
replays the run from it: the same frames, tracked at the same points, give the same trajectory. A file of stamps
only (one column) replays the skips, with every frame tracked between frames.
"""
from __future__ import annotations

from pathlib import Path


def write_frame_schedule(path: str | Path, rows: list[tuple[int, int | None]]) -> None:
    """Write ``rows`` of (stamp ns, yield point or None) in the format of the module docstring."""
    Path(path).write_text("".join(f"{t}\n" if y is None else f"{t} {y}\n" for t, y in rows))


def read_frame_schedule(path: str | Path) -> dict[int, int | None]:
    """{stamp (ns): yield point or None} of a schedule file ('#' comments and blank lines skipped). Raises
    ValueError naming the line when a line is not one or two integers."""
    out: dict[int, int | None] = {}
    for n, line in enumerate(Path(path).read_text().splitlines(), start=1):
        fields = line.split("#", 1)[0].replace(",", " ").split()
        if not fields:
            continue
        try:
            if len(fields) > 2:
                raise ValueError
            values = [int(x) for x in fields]
        except ValueError:
            raise ValueError(f"{path}:{n}: expected a stamp (ns) and optionally a yield point, got {line!r}") from None
        out[values[0]] = values[1] if len(values) == 2 else None
    if not out:
        raise ValueError(f"{path}: no frame stamps")
    return out

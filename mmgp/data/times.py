"""A log's wall-clock start: the optional metadata ``start_time`` (CONTRACT 1.2, section 1).

``start_time`` is the wall-clock time of the log's first sample, ISO 8601 with its UTC offset
(``2026-11-27T09:30:00+00:00``; ``Z`` is the same offset). A time without an offset is refused:
whose local time it was cannot be known later, and a fleet compares logs from many machines.
Converters write it in UTC from the recording's absolute stamps (:func:`wall_clock_iso`).
"""
from __future__ import annotations

import os
from datetime import datetime, timedelta, timezone

from ..errors import InputError

START_TIME_KEY = "start_time"
EXAMPLE = "2026-11-27T09:30:00+00:00"
# Stamps before 2000 or from 2100 on are no wall clock: a simulator's time counted from 0, a
# controller's uptime, or a unit mistake (ms read as s). No start time is made from them.
WALL_CLOCK_RANGE_S = (946_684_800.0, 4_102_444_800.0)


def parse_start_time(text: str, file: str | os.PathLike | None = None) -> datetime:
    """The aware datetime of a ``start_time`` value; an InputError naming the file and the key
    when it is not ISO 8601 with an offset."""
    raw = str(text).strip()
    if raw[-1:] in ("Z", "z"):  # Python 3.10's parser knows only the +00:00 spelling
        raw = raw[:-1] + "+00:00"
    try:
        stamp = datetime.fromisoformat(raw)
    except ValueError:
        stamp = None
    if stamp is None or stamp.tzinfo is None:
        why = "has no UTC offset" if stamp is not None else "is not an ISO 8601 time"
        raise InputError(f"metadata '{START_TIME_KEY}' is {text!r}: it {why}; expected ISO 8601 with its "
                         f"offset, e.g. {EXAMPLE}", file=file)
    return stamp


def format_start_time(stamp: datetime) -> str:
    """``stamp`` in UTC as ISO 8601 with ``+00:00`` (microseconds shown when not zero)."""
    return stamp.astimezone(timezone.utc).isoformat()


def wall_clock_iso(seconds: float | None = None, *, ns: int | None = None) -> str | None:
    """The ``start_time`` of a first sample stamped ``seconds`` (or integer ``ns``) after the Unix
    epoch, or None when that stamp is no wall clock (outside 2000-2100, see WALL_CLOCK_RANGE_S)."""
    if ns is not None:
        whole, rest = divmod(int(ns), 1_000_000_000)
        seconds_f = float(whole)
    elif seconds is not None:
        whole, rest = None, 0
        seconds_f = float(seconds)
    else:
        return None
    if not (WALL_CLOCK_RANGE_S[0] <= seconds_f < WALL_CLOCK_RANGE_S[1]):
        return None
    if whole is None:  # float seconds: datetime rounds to the microsecond
        return format_start_time(datetime.fromtimestamp(seconds_f, tz=timezone.utc))
    # integer ns: whole seconds exactly, the rest truncated to the microsecond datetime holds
    stamp = datetime.fromtimestamp(whole, tz=timezone.utc) + timedelta(microseconds=rest // 1000)
    return format_start_time(stamp)

"""What long library work tells whoever listens: the stage it starts now.

The library never prints. At natural points of long work (loading and differentiating logs, the
start of the EM, the friction check's refits, the held-out score, each stage of a diagnosis, each
log of a fleet) it calls :func:`report`; a command's progress display (:mod:`mmgp.cli.common`)
listens with :func:`listening` and shows the stage as a line or on its bar. Without a listener a
report costs a list lookup. Listeners hear reports from every thread of the process.

``done`` / ``total`` (optional) place the stage in a counted sequence named ``work`` (e.g.
``"diagnosis"``: stage 3 of 10), so that a display can give its bar a total up front.
"""
from __future__ import annotations

import contextlib
import threading
from typing import Callable, Iterator, Optional

Listener = Callable[..., None]

_listeners: list = []
_lock = threading.Lock()


def report(message: str, *, work: str = "", done: Optional[int] = None, total: Optional[int] = None) -> None:
    """Tell the listeners that ``message`` (a few words: "EM start: one GP on every sample") begins
    now; ``done`` of ``total`` steps of ``work`` are finished before it."""
    for fn in list(_listeners):
        fn(message, work=work, done=done, total=total)


@contextlib.contextmanager
def listening(fn: Listener) -> Iterator[None]:
    """Call ``fn(message, work=, done=, total=)`` on every :func:`report` inside the block."""
    with _lock:
        _listeners.append(fn)
    try:
        yield
    finally:
        with _lock:
            _listeners.remove(fn)

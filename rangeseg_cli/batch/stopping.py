"""Cooperative stop requests: long loops of one image ask whether to stop.

A batch asked to stop (Ctrl-C, SIGTERM) stops between images; an image
whose holdsite search runs for minutes (a long footprint at a fine
``rotation_step``) would hold it that long. The batch runs each image
inside :func:`stop_checks` with a check that raises once a stop is
requested; the library's long loops call :func:`checkpoint`, which runs the
check of the enclosing :func:`stop_checks` (nothing outside one). The
library itself handles no signal: whoever installs the check decides how a
stop is requested and what it raises.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar

_check: ContextVar[Callable[[], None] | None] = ContextVar("rangeseg_stop_check", default=None)


@contextmanager
def stop_checks(check: Callable[[], None]) -> Iterator[None]:
    """Within the block, :func:`checkpoint` calls ``check`` (which raises to stop).

    Parameters
    ----------
    check
        Called at each checkpoint of this thread; it raises (e.g.
        ``KeyboardInterrupt``) when the work is to stop, else returns.
    """
    token = _check.set(check)
    try:
        yield
    finally:
        _check.reset(token)


def checkpoint() -> None:
    """Call the check of the enclosing :func:`stop_checks`, if any (it may raise)."""
    check = _check.get()
    if check is not None:
        check()

"""Signals during a run: a termination request ends it cleanly, between two pairs, never inside one.

SIGINT (Ctrl-C) raises ``KeyboardInterrupt``. :func:`terminate_as_interrupt`
makes SIGTERM and SIGHUP do the same, so that a ``kill`` or a closed terminal
take the same path: ``finally`` blocks run, temporary files are removed, the
database keeps whole pairs only. It also replaces the handlers that COLMAP's
logging library installs, which print a C++ stack dump on SIGTERM.
:func:`interrupts_deferred` holds these signals while one pair is written.
"""

from __future__ import annotations

import contextlib
import signal
import threading

__all__ = ["Terminated", "terminate_as_interrupt", "interrupts_deferred", "interrupt_in", "HANDLED"]

#: The signals turned into an interrupt (those that exist on this platform).
HANDLED = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


class Terminated(KeyboardInterrupt):
    """The run was asked to stop by a signal other than SIGINT (``signum`` says which)."""

    def __init__(self, signum: int):
        super().__init__(f"stopped by {signal.Signals(signum).name}")
        self.signum = signum


def interrupt_in(exc: BaseException | None) -> KeyboardInterrupt | None:
    """The ``KeyboardInterrupt`` (or :class:`Terminated`) that ``exc`` is or was caused by, if any.

    An interrupt raised while numba runs Python code inside a compiled kernel (unpickling a
    constant, say) comes out as a ``SystemError`` ("returned a result with an exception set"),
    sometimes several of them deep; the interrupt is at the end of their cause chain.
    """
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _raise(signum, frame):
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise Terminated(signum)


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextlib.contextmanager
def terminate_as_interrupt():
    """SIGTERM and SIGHUP raise :class:`Terminated` (a ``KeyboardInterrupt``) inside the block.

    A no-op outside the main thread; a signal that was ignored (``nohup``) stays ignored.
    """
    if not _main_thread():
        yield
        return
    previous = {}
    for s in HANDLED:
        if s != signal.SIGINT and signal.getsignal(s) is not signal.SIG_IGN:
            previous[s] = signal.signal(s, _raise)
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


@contextlib.contextmanager
def interrupts_deferred():
    """Hold SIGINT, SIGTERM and SIGHUP until the block ends, then deliver them.

    pycolmap's transaction commits even when an exception leaves it, so an
    interrupt between two writes would commit half a pair.
    """
    if not _main_thread():
        yield
        return
    caught = []
    previous = {}
    for s in HANDLED:
        h = signal.getsignal(s)
        if h not in (signal.SIG_IGN, None) and not (s != signal.SIGINT and h is signal.SIG_DFL):
            previous[s] = signal.signal(s, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        if caught:
            signal.raise_signal(caught[0])

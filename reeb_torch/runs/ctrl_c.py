"""What a Ctrl-C (SIGINT) does in each phase of a ``reeb`` command: a user's Ctrl-C always
ends it with exit code 130 and one line, or with the exit code of the run that has already
finished; never with a traceback or killed by the signal (exit -2).

=============================  ===============================================================
phase                          a Ctrl-C ...
=============================  ===============================================================
importing the command,         ends the process at once: ``interrupted``, exit 130
parsing its options            (:func:`exit_at_once`; nothing is done yet, nothing to save)
the command runs               raises ``KeyboardInterrupt`` (:func:`interrupts`), which the
                               runs catch to save what is done (``reeb propose``: exit 130)
the command has finished       ends the process at once with the finished command's exit code
(interpreter shutdown)         (:func:`exits_with`; its output is written), and is ignored
                               after the exit functions, where Python soon runs no handler
                               and the default action would kill it (exit -2)
=============================  ===============================================================

While a run writes a row, :class:`CriticalSection` defers a Ctrl-C (and SIGTERM) to the end
of the write, so a row is either wholly in the output or not at all;
:func:`caused_by_interrupt` tells a Ctrl-C that came out wrapped in another exception.

Standard library only: it is imported before anything heavy."""

from __future__ import annotations

import atexit
import os
import signal
import sys
import threading

__all__ = ["exit_at_once", "interrupts", "exits_with", "restore", "exit_code", "CriticalSection",
           "caused_by_interrupt"]


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()  # only it may set handlers


def _set(handler):
    """Install ``handler`` for SIGINT; the one before (``None`` off the main thread)."""
    if not _main_thread():
        return None
    return signal.signal(signal.SIGINT, handler)


def _interrupted_now(signum, frame) -> None:
    os.write(2, b"interrupted\n")
    os._exit(130)


def exit_at_once():
    """Until :func:`interrupts` or :func:`restore`: a Ctrl-C writes ``interrupted`` on stderr
    and ends the process with exit code 130. Returns the handler it replaced."""
    return _set(_interrupted_now)


def interrupts() -> None:
    """Python's own handling: a Ctrl-C raises ``KeyboardInterrupt`` where the program is."""
    _set(signal.default_int_handler)


def restore(previous) -> None:
    """Put back the handler :func:`exit_at_once` replaced."""
    if previous is not None:
        _set(previous)


def exit_code(e: BaseException | None) -> int:
    """The exit code a command ending with ``e`` (``None``: it returned) leaves the process with."""
    if e is None:
        return 0
    code = getattr(e, "exit_code", None)  # click's Exit and ClickException
    if isinstance(code, int):
        return code
    if isinstance(e, SystemExit):
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    return 1


_FINISHED: list[int] = []  # the exit code, once the command has finished


def _ignore_from_now() -> None:
    if _FINISHED:
        _set(signal.SIG_IGN)


atexit.register(_ignore_from_now)  # registered first, so it runs last of the exit functions


def exits_with(code: int) -> None:
    """The command has finished with ``code``: from now on a Ctrl-C ends the process at once
    with that code (its output is written; the standard streams are flushed first), through
    Python's exit functions (``atexit``); after the last of them, where Python soon runs no
    handler and the signal's default action would kill the process, it is ignored."""
    def handler(signum, frame) -> None:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # noqa: BLE001 - a closed or broken stream: exit all the same
                pass
        os._exit(code)

    if _main_thread():
        _set(handler)
        _FINISHED[:] = [code]


def caused_by_interrupt(e: BaseException) -> bool:
    """Whether ``e`` is, or was raised while handling, a :class:`KeyboardInterrupt`: a
    Ctrl-C that lands inside a library's own Python code can come out wrapped (numba,
    loading a cached kernel, turns it into a ``SystemError``)."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__  # type: ignore[assignment]
    return False


class CriticalSection:
    """Defers Ctrl-C (and SIGTERM) while a row is being written, so that a row is either
    wholly in the output or not at all, and the counts in the summary match the file.

    Install :meth:`handler` for SIGINT/SIGTERM; outside a ``with`` block it raises
    :class:`KeyboardInterrupt` at once, inside it the interrupt is raised when the block
    ends.
    """

    def __init__(self) -> None:
        self._depth = 0
        self._pending = False

    def interrupt(self) -> None:
        """What the signal handler does: interrupt now, or at the end of the write."""
        if self._depth:
            self._pending = True
        else:
            raise KeyboardInterrupt

    def handler(self, signum: int, frame: object) -> None:
        self.interrupt()

    def install(self) -> dict:
        """Install :meth:`handler` for SIGINT and SIGTERM; return the previous handlers."""
        previous = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.getsignal(sig)
            signal.signal(sig, self.handler)
        return previous

    def __enter__(self) -> "CriticalSection":
        self._depth += 1
        return self

    def __exit__(self, exc_type, *exc: object) -> None:
        self._depth -= 1
        if not self._depth and self._pending and exc_type is None:
            self._pending = False
            raise KeyboardInterrupt

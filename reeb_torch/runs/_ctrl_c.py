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

Standard library only: it is imported before anything heavy."""

from __future__ import annotations

import atexit
import os
import signal
import sys
import threading

__all__ = ["exit_at_once", "interrupts", "exits_with", "restore", "exit_code"]


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

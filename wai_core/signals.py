"""SIGINT and SIGTERM as exceptions, so that temporary outputs are cleaned up.

:func:`catch_signals` (used by the ``wai`` command) turns both into exceptions within its block;
:func:`raise_if_interrupted` raises a caught one again at checkpoints (some libraries swallow
``KeyboardInterrupt``); the output policy (:mod:`wai_core.outputs`) holds them back over the
few file-system steps that must not be cut in half.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

__all__ = ["CaughtSignal", "Terminated", "catch_signals", "raise_if_interrupted"]

class Terminated(BaseException):
    """Raised by :func:`catch_signals`' SIGTERM handler (like ``KeyboardInterrupt`` for SIGINT):
    not an ``Exception``, so only clean-up code (``finally``, ``except BaseException``) sees it."""


@dataclass
class CaughtSignal:
    """What :func:`catch_signals` caught: the signal number (None: none yet)."""

    signum: int | None = None

    @property
    def exit_code(self) -> int:
        """128 + the signal number (130 for SIGINT, 143 for SIGTERM)."""
        return 128 + (self.signum or signal.SIGINT)

    @property
    def message(self) -> str:
        """One word for the user: ``interrupted`` or ``terminated``."""
        return "terminated" if self.signum == signal.SIGTERM else "interrupted"

    def exception(self) -> BaseException:
        """The exception the signal stands for."""
        return Terminated() if self.signum == signal.SIGTERM else KeyboardInterrupt()


_CAUGHT: list[CaughtSignal] = []


def raise_if_interrupted() -> None:
    """Raise the caught signal's exception again if :func:`catch_signals` caught one.

    Some libraries swallow ``KeyboardInterrupt`` (trimesh wraps its optional imports in
    ``except BaseException``); checkpoints call this so that such a signal still stops the work
    before anything is committed.
    """
    if _CAUGHT and _CAUGHT[-1].signum is not None:
        raise _CAUGHT[-1].exception()


@contextlib.contextmanager
def catch_signals() -> Iterator[CaughtSignal]:
    """Within the block, SIGINT raises ``KeyboardInterrupt`` and SIGTERM :class:`Terminated`,
    and the signal is remembered (see :func:`raise_if_interrupted`); the previous handlers are
    restored at the end. Outside the main thread it changes nothing."""
    caught = CaughtSignal()
    if threading.current_thread() is not threading.main_thread():
        yield caught
        return

    def handler(signum: int, frame: Any) -> None:
        caught.signum = signum
        raise caught.exception()

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    _CAUGHT.append(caught)
    try:
        yield caught
    finally:
        _CAUGHT.remove(caught)
        for s, h in previous.items():
            signal.signal(s, h)


@contextlib.contextmanager
def _signals_deferred() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back during a few file-system steps that must not be cut in
    half (a rename pair, a clean-up); they are delivered at the end of the block."""
    main = threading.current_thread() is threading.main_thread()
    mask = {signal.SIGINT, signal.SIGTERM}
    old = signal.pthread_sigmask(signal.SIG_BLOCK, mask) if main else None
    try:
        yield
    finally:
        if old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)

"""A real Ctrl-C where torch's lazy imports put one: inside a class definition."""

from __future__ import annotations

import os
import signal


class SignalsWhenNamed:
    """A class attribute whose ``__set_name__`` sends this process SIGINT, as a Ctrl-C lands
    while torch defines its dataclasses on a lazy import: Python's own handler raises the
    KeyboardInterrupt there, and ``type.__new__`` wraps it in a RuntimeError."""

    def __set_name__(self, owner, name):
        os.kill(os.getpid(), signal.SIGINT)


def define_a_class_under_sigint(_args=None):
    """Define a class holding :class:`SignalsWhenNamed` (raises the wrapped interrupt) with
    Python's own SIGINT handler in place (a pytest-xdist worker ignores SIGINT), then put back
    the handler there was."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        class Defined:
            field = SignalsWhenNamed()

        return Defined
    finally:
        signal.signal(signal.SIGINT, previous)

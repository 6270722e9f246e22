"""A Ctrl-C that lands inside a class definition (a lazy import of torch's) surfaces as a
RuntimeError; sim.interrupts still reads it as the interruption it is."""

from __future__ import annotations

import pytest

from sim.interrupts import caused_by_interrupt
from tests.signals import define_a_class_under_sigint


def test_an_interrupt_inside_a_class_definition_is_wrapped_and_still_recognised():
    with pytest.raises(RuntimeError, match="__set_name__") as caught:
        define_a_class_under_sigint()
    assert isinstance(caught.value.__cause__, KeyboardInterrupt)
    assert caused_by_interrupt(caught.value)


def test_other_errors_are_not_taken_for_interrupts():
    assert caused_by_interrupt(KeyboardInterrupt())
    try:
        try:
            raise ValueError("first")
        except ValueError:
            raise RuntimeError("while handling")      # noqa: B904 - the context is the point
    except RuntimeError as exc:
        assert not caused_by_interrupt(exc)
    looped = ValueError("loop")
    looped.__context__ = RuntimeError("back")
    looped.__context__.__context__ = looped
    assert not caused_by_interrupt(looped)

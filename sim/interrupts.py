"""Whether an exception is what a Ctrl-C (SIGINT, or the SIGTERM a guard turns into one) left.

A KeyboardInterrupt raised by a signal handler surfaces wherever the main thread was. Inside
an import that defines a class with fields (torch imports ``torch._dynamo`` lazily, on the
first optimiser built), Python reports it as ``RuntimeError: Error calling __set_name__ ...``
with the KeyboardInterrupt as its cause; elsewhere it may be the context of an exception a
``finally`` raised. Either way the run was interrupted, and a command says so and exits 130
rather than print a traceback as if it had failed.
"""

from __future__ import annotations


def caused_by_interrupt(exc: BaseException) -> bool:
    """True if ``exc`` is a KeyboardInterrupt or one is in its chain of causes and contexts."""
    seen: set[int] = set()
    link: BaseException | None = exc
    while link is not None and id(link) not in seen:
        if isinstance(link, KeyboardInterrupt):
            return True
        seen.add(id(link))
        link = link.__cause__ or link.__context__
    return False

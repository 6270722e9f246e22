"""Zenoh's own log, read back by the process that runs Zenoh: what only the Rust side reports.

eclipse-zenoh 1.10 gives Python no count of what its access control denied or of the TLS
handshakes a listener refused: the wheel is built without Zenoh's ``stats`` feature (the admin
key ``@/<zid>/router/metrics`` answers ``zenoh_build_info`` alone) and zenoh-python's bridge to
Python ``logging`` is compiled out (``src/lib.rs``: ``// mod logging;``). Zenoh does *log* both
through Rust ``tracing``, once :func:`zenoh.init_log_from_env_or` installed its formatter, and
that formatter writes to the process's standard output, file descriptor 1, one line per event::

    <time> <LEVEL> [<thread name>] ThreadId(<n>) <target>: <message>

:class:`ZenohLogTap` reads those lines back while it runs: it points fd 1 at a pipe, a reader
thread hands each line to ``on_line`` and writes every line ``on_line`` does not take (Python's
own ``print``, Zenoh's other targets) through to where fd 1 pointed before. Zenoh's log
subscriber is process-wide and installed once (:func:`install_log`, without colour codes); one
tap at a time. Cost: each line costs Zenoh a format and a pipe write and the reader a Python
call; a reader that falls behind fills the pipe (1 MiB) and Zenoh's threads then wait on it
(measured under a flood: README, *What the router refuses is counted*).
"""

from __future__ import annotations

import fcntl
import logging
import os
import re
import select
import sys
import threading
from collections.abc import Callable
from typing import NamedTuple

import zenoh

log = logging.getLogger(__name__)

PIPE_BYTES = 1 << 20   # [bytes] asked of the kernel for the pipe (Linux F_SETPIPE_SZ)
_F_SETPIPE_SZ = 1031
_ANSI = re.compile(rb"\x1b\[[0-9;]*m")
_LINE = re.compile(r"\S+\s+(?P<level>TRACE|DEBUG|INFO|WARN|ERROR)\s+(?:\S+\s+)?ThreadId\((?P<thread>\d+)\)"
                   r"\s+(?P<target>[\w:]+):\s(?P<message>.*)")


class LogLine(NamedTuple):
    level: str      # TRACE, DEBUG, INFO, WARN or ERROR
    thread: int     # the Rust thread that logged it
    target: str     # module path, e.g. zenoh::net::routing::interceptor::access_control
    message: str


def strip_colour(raw: bytes) -> bytes:
    """``raw`` without ANSI colour codes (Zenoh's formatter adds them unless NO_COLOR is set)."""
    return _ANSI.sub(b"", raw) if b"\x1b" in raw else raw


def parse_line(raw: bytes) -> LogLine | None:
    """One line of Zenoh's log, or None for anything else."""
    m = _LINE.fullmatch(strip_colour(raw).decode("utf-8", "replace").rstrip("\r\n"))
    if m is None:
        return None
    return LogLine(m["level"], int(m["thread"]), m["target"], m["message"])


_installed: str | None = None


def install_log(directives: str) -> bool:
    """Install Zenoh's log formatter with ``directives`` (``tracing`` EnvFilter syntax) added to
    ``RUST_LOG``'s own, once per process; False when it was installed before with other
    directives (they stay: Zenoh cannot change them at run time). A formatter someone else
    installed first (a direct ``zenoh.init_log_from_env_or``) wins unseen: check a line arrives."""
    global _installed
    if _installed is not None:
        return _installed == directives
    saved = {name: os.environ.get(name) for name in ("RUST_LOG", "NO_COLOR")}
    try:
        if saved["RUST_LOG"]:        # RUST_LOG replaces the fallback: give Zenoh both
            os.environ["RUST_LOG"] = f"{saved['RUST_LOG']},{directives}"
        os.environ["NO_COLOR"] = "1"  # read once, when the formatter is built
        zenoh.init_log_from_env_or(directives)
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
    _installed = directives
    return True


class ZenohLogTap:
    """Hands each line written to fd 1 (bytes, without its newline) to ``on_line(raw) -> bool``
    (True: taken, not passed through) from :meth:`start` to :meth:`stop` (a context manager).
    Never raises from the reader: an exception in ``on_line`` is logged once and the line
    passed through."""

    _active: ZenohLogTap | None = None
    _lock = threading.Lock()

    def __init__(self, on_line: Callable[[bytes], bool]):
        self.on_line = on_line
        self._saved: int | None = None
        self._read_fd: int | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._failed = False

    def start(self) -> None:
        """Point fd 1 at the pipe; raises RuntimeError while another tap runs."""
        with ZenohLogTap._lock:
            if ZenohLogTap._active is not None:
                raise RuntimeError("another ZenohLogTap is reading Zenoh's log in this process")
            ZenohLogTap._active = self
        sys.stdout.flush()
        read_fd, write_fd = os.pipe()
        try:
            fcntl.fcntl(write_fd, _F_SETPIPE_SZ, PIPE_BYTES)
        except OSError:   # not Linux, or above /proc/sys/fs/pipe-max-size: the default 64 KiB
            pass
        self._saved, self._read_fd = os.dup(1), read_fd
        os.dup2(write_fd, 1)
        os.close(write_fd)
        self._thread = threading.Thread(target=self._read, name="zenoh-log-tap", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Give fd 1 back and read what is left in the pipe. Idempotent."""
        if self._thread is None:
            return
        sys.stdout.flush()
        os.dup2(self._saved, 1)     # the pipe's write end goes (unless a child inherited it)
        self._stop.set()
        self._thread.join(timeout=5.0)
        os.close(self._saved)
        self._thread = None
        with ZenohLogTap._lock:
            ZenohLogTap._active = None

    def _read(self) -> None:
        pending = b""
        try:
            while True:
                ready, _, _ = select.select([self._read_fd], [], [], 0.1)
                chunk = os.read(self._read_fd, 1 << 16) if ready else b""
                if not chunk and (ready or self._stop.is_set()):
                    break                        # end of file, or stopped with nothing left
                *lines, pending = (pending + chunk).split(b"\n")
                self._pass(b"".join(line + b"\n" for line in lines if not self._take(line)))
        finally:
            self._pass(pending)
            os.close(self._read_fd)

    def _take(self, raw: bytes) -> bool:
        try:
            return bool(self.on_line(raw))
        except Exception:
            if not self._failed:
                self._failed = True
                log.exception("zenoh log tap: a handler failed; passing its lines through")
            return False

    def _pass(self, data: bytes) -> None:
        while data:
            data = data[os.write(self._saved, data):]

    def __enter__(self) -> ZenohLogTap:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


__all__ = ["LogLine", "ZenohLogTap", "install_log", "parse_line", "strip_colour"]

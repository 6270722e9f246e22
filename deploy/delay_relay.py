"""A slow link for trying a fleet on one machine: a TCP relay on 127.0.0.1 that holds every
byte, each way, for a delay that jitters (no root and no kernel queueing discipline needed, as
``tc netem`` would be).

A Zenoh peer connects to the relay's port instead of the other peer's; the relay opens the real
connection and copies both ways (``tests/deploy/test_jittery_link.py``,
``bench/jittery_link.py``). Each chunk read is written on after ``delay_s`` plus a uniform
jitter in ``[-jitter_s, +jitter_s]`` [s], never before the chunk read ahead of it (TCP keeps
the order, so a late chunk holds up the ones behind it, as on a real link). Nothing is
dropped: TCP resends what a lossy link loses, and what arrives late is what the fleet sees.
One fleet-sim process publishes every robot's state on one connection, so chunks of one
tick's burst reach the bridge spread over up to twice the jitter, as states of robots on
links of their own would.
"""

from __future__ import annotations

import heapq
import socket
import threading
import time

import numpy as np


class DelayRelay:
    """Relay ``127.0.0.1:port`` -> ``127.0.0.1:target_port`` (module docstring); a context manager."""

    def __init__(self, target_port: int, delay_s: float, jitter_s: float = 0.0, seed: int = 0):
        if not 0.0 <= jitter_s <= delay_s:
            raise ValueError(f"DelayRelay: jitter_s must be in [0, delay_s], got {jitter_s} for {delay_s}")
        self.target_port, self.delay_s, self.jitter_s = target_port, delay_s, jitter_s
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._server = socket.create_server(("127.0.0.1", 0))
        self.port = self._server.getsockname()[1]
        self._closed = threading.Event()
        self._sockets: list[socket.socket] = [self._server]
        self.delays: list[float] = []        # every chunk's hold [s], both ways
        threading.Thread(target=self._accept, daemon=True).start()

    def __enter__(self) -> DelayRelay:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._closed.set()
        for s in self._sockets:
            try:
                s.close()
            except OSError:
                pass

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                client, _ = self._server.accept()
                upstream = socket.create_connection(("127.0.0.1", self.target_port))
            except OSError:
                return
            for s in (client, upstream):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self._sockets.append(s)
            for src, dst in ((client, upstream), (upstream, client)):
                self._pipe(src, dst)

    def _hold(self) -> float:
        with self._lock:
            hold = self.delay_s + float(self._rng.uniform(-self.jitter_s, self.jitter_s))
            self.delays.append(hold)
        return hold

    def _pipe(self, src: socket.socket, dst: socket.socket) -> None:
        """Copy ``src`` to ``dst``: a reader stamps each chunk with its release time, a writer
        sends it then."""
        queue: list[tuple[float, int, bytes]] = []
        ready = threading.Condition()

        def read() -> None:
            last, k = 0.0, 0
            while not self._closed.is_set():
                try:
                    data = src.recv(65536)
                except OSError:
                    data = b""
                release = max(last, time.monotonic() + self._hold()) if data else last
                last, k = release, k + 1
                with ready:
                    heapq.heappush(queue, (release, k, data))
                    ready.notify()
                if not data:
                    return

        def write() -> None:
            while True:
                with ready:
                    while not queue:
                        ready.wait()
                    release, _, data = heapq.heappop(queue)
                wait = release - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                try:
                    if not data:
                        dst.shutdown(socket.SHUT_WR)
                        return
                    dst.sendall(data)
                except OSError:
                    return

        threading.Thread(target=read, daemon=True).start()
        threading.Thread(target=write, daemon=True).start()

"""The slow-link relay (deploy/delay_relay.py): each chunk held for its delay, in order."""

from __future__ import annotations

import socket
import threading
import time

from deploy.delay_relay import DelayRelay


def test_the_relay_holds_each_chunk_for_its_delay_and_keeps_the_order():
    """An echo server behind the relay: 40 numbered messages come back in order, each no sooner
    than two holds of at least ``delay - jitter`` (there and back), and the holds drawn jitter
    across the whole range."""
    server = socket.create_server(("127.0.0.1", 0))

    def echo() -> None:
        conn, _ = server.accept()
        while data := conn.recv(4096):
            conn.sendall(data)

    threading.Thread(target=echo, daemon=True).start()
    with DelayRelay(server.getsockname()[1], 0.03, 0.02, seed=1) as relay:
        client = socket.create_connection(("127.0.0.1", relay.port))
        sent, received, buffer = {}, [], b""
        for k in range(40):
            sent[k] = time.monotonic()
            client.sendall(f"{k:04d}".encode())
            time.sleep(0.005)
        while len(received) < 40:
            buffer += client.recv(4096)
            while len(buffer) >= 4:
                received.append((int(buffer[:4]), time.monotonic()))
                buffer = buffer[4:]
        client.close()
    assert [k for k, _ in received] == list(range(40))
    assert min(t - sent[k] for k, t in received) >= 2 * 0.01
    assert min(relay.delays) < 0.015 and max(relay.delays) > 0.045
    server.close()

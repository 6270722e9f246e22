"""The fleet's transmit settings: a burst of one tick's messages survives a starved CPU.

Real Zenoh sessions on 127.0.0.1; the publisher is a separate process pinned to one CPU at
nice 19, and a busy loop on that CPU starves it (what a loaded controller host does to Zenoh's
transmit thread).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from deploy.certs import ROUTER, NodeFiles, make_certs
from deploy.network import (
    TX_QUEUE_BATCHES,
    TX_QUEUE_KEY,
    TransportConfig,
    free_tcp_port,
    set_tx_queue,
)
from deploy.router import RouterConfig

PROC = Path(__file__).with_name("starved_publisher_proc.py")
ROBOTS, BURSTS = 50, 20


def queue_sizes(config: zenoh.Config) -> set[int]:
    return set(json.loads(config.get_json(TX_QUEUE_KEY)).values())


def test_every_node_gets_the_fleet_transmit_queue_unless_its_file_sets_one(tmp_path):
    assert queue_sizes(zenoh.Config()) == {2}          # Zenoh's own default, which drops bursts
    assert queue_sizes(TransportConfig(listen=("tcp/127.0.0.1:7447",)).to_zenoh()) == {TX_QUEUE_BATCHES}
    assert queue_sizes(TransportConfig(connect=("tcp/127.0.0.1:7447",), mode="client").to_zenoh()) == {16}
    make_certs(str(tmp_path), [ROUTER])
    router = RouterConfig("f", ("r0",), NodeFiles.in_dir(str(tmp_path), ROUTER), ("tls/127.0.0.1:7447",))
    assert queue_sizes(router.to_zenoh()) == {16}
    plain = tmp_path / "plain.json5"
    listen = 'listen: { endpoints: ["tcp/127.0.0.1:7447"] }, '
    plain.write_text('{ ' + listen + 'transport: { link: { tx: { lease: 2500 } } } }')
    assert queue_sizes(TransportConfig(zenoh_config=str(plain)).to_zenoh()) == {16}
    own = tmp_path / "own.json5"
    own.write_text('{ ' + listen + 'transport: { link: { tx: { queue: { size: { interactive_high: 4 } } } } } }')
    sizes = json.loads(TransportConfig(zenoh_config=str(own)).to_zenoh().get_json(TX_QUEUE_KEY))
    assert sizes["interactive_high"] == 4 and sizes["data"] == 2     # the file's, untouched
    config = zenoh.Config()
    assert set_tx_queue(set_tx_queue(config)) is config and queue_sizes(config) == {16}


def _received_under_starvation(settings: str) -> tuple[int, int]:
    """(sent, received) of BURSTS bursts of ROBOTS messages from a starved publisher process."""
    port = free_tcp_port()
    cpu = max(os.sched_getaffinity(0))
    received, lock = [0], threading.Lock()

    def count(_sample) -> None:
        with lock:
            received[0] += 1

    with zenoh.open(TransportConfig(listen=(f"tcp/127.0.0.1:{port}",)).to_zenoh()) as session:
        subscriber = session.declare_subscriber("starved/**", count)
        child = subprocess.Popen([sys.executable, str(PROC), str(port), settings, str(ROBOTS),
                                  str(BURSTS), str(cpu)], stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE, text=True)
        hog = None
        try:
            assert child.stdout.readline().strip() == "ready"
            time.sleep(0.5)                                   # the subscription reaches the child
            hog = subprocess.Popen([sys.executable, "-c", f"import os; os.sched_setaffinity(0, {{{cpu}}})\n"
                                    "while True: pass"])
            time.sleep(0.1)
            child.stdin.write("go\n")
            child.stdin.flush()
            line = child.stdout.readline().strip()
            assert line.startswith("sent "), line
        finally:
            if hog is not None:
                hog.kill()
                hog.wait()
            child.kill()
            child.wait()
        time.sleep(0.3)
        subscriber.undeclare()
    return int(line.split()[1]), received[0]


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs a second CPU for the receiver")
def test_a_starved_publisher_loses_no_message_of_its_bursts():
    sent, received = _received_under_starvation("fleet")
    assert (sent, received) == (ROBOTS * BURSTS, ROBOTS * BURSTS)


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs a second CPU for the receiver")
def test_with_express_publishers_and_zenohs_default_queue_the_same_bursts_lose_messages():
    """The teeth of the test above: the settings the links had before drop part of each burst."""
    sent, received = _received_under_starvation("express")
    assert sent == ROBOTS * BURSTS and received < sent, received

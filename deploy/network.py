"""How a node joins a fleet's Zenoh network: the key layout, the node's transport settings.

Key layout (``<fleet>`` and ``<rid>`` follow :func:`deploy.wire.check_name`; never '@')::

    formation/<fleet>/robot/<rid>/state   robot -> controller  STATE (deploy.wire)
    formation/<fleet>/robot/<rid>/cmd     controller -> robot  CMD
    formation/<fleet>/robot/<rid>/alive   liveliness token of the robot
    formation/<fleet>/ctrl/alive          liveliness token of the controller
    formation/<fleet>/ctrl/operator       an operator's e-stop requests (queries; deploy.bridge)
    formation/<fleet>/estop               ESTOP, latched (deploy.transport)

:class:`TransportConfig` is a node's Zenoh configuration: peer or client of a router, endpoints,
scouting, lease, and mutual TLS with the fleet's certificates (:mod:`deploy.security`).
"""

from __future__ import annotations

import json
import re
import socket
from dataclasses import dataclass

import zenoh

from deploy.certs import NodeFiles
from deploy.security import tls_block
from deploy.wire import check_name

KEY_ROOT = "formation"
ENDPOINT_RE = re.compile(r"[a-z][a-z0-9\-]*/\S+")
LOOPBACK_RE = re.compile(r"[a-z][a-z0-9\-]*/(127(\.\d{1,3}){3}|localhost|\[::1\]):\d+(#\S*)?")

def declare_data_publisher(session: zenoh.Session, key: str, congestion_control: zenoh.CongestionControl,
                           express: bool = False) -> zenoh.Publisher:
    """The publisher of one robot's states or commands: priority INTERACTIVE_HIGH, not express
    (``express=True`` only to measure the settings the links had before 2026-12-03).

    Why not express: an express message is a batch of its own, and Zenoh drops a DROP message
    that waits more than 1 ms (``wait_before_drop``) for a free batch of its priority's queue (2
    batches by default). So a controller publishing its commands in a burst, or a fleet
    simulation its states, lost whole messages whenever the one transmit thread was descheduled
    for a millisecond: on this project's 2-core host ``bench/fleet_loop.py`` got no answer within
    100 ms on up to 52 ticks in 1000 at 5 robots and 13-122 at 50. Without express, the messages
    of one burst share a batch (Zenoh sends a batch at once when the link is idle and batches
    only under back-pressure): the same bench had no unanswered tick in 27 rows (9 as shipped, 18
    with a 16-batch queue), and p50 fell at 50 robots (TLS router 9.8-11.7 against 15.7-17.6 ms),
    with no change at 5 (docs/results/fleet_loop_before_after_2026-12-03.json).
    ``tests/deploy/test_data_publishers.py`` starves a publisher's CPU: 1000 of 1000 messages
    arrive, against 98-211 with express publishers.

    A longer transmit queue (16 batches) adds nothing once bursts share a batch, and on a link
    too slow for the traffic it only lets more old messages wait: Zenoh's default stays. On such
    a link (``bench/link_congestion.py``: 50 messages every 20 ms over 1 Mbit/s) messages arrive
    late either way, 0.6-1.0 s at the median (TCP and the shaper hold them before Zenoh can drop
    any); these publishers deliver more of them than express ones (91-97 against 73-84 %, p99
    age 1.6-1.8 against 0.85-1.9 s, six runs each). The bridge sees the delay in the round trips
    it measures (``command_delay_s``), and the safety filter predicts every robot over it.
    """
    return session.declare_publisher(key, congestion_control=congestion_control,
                                      priority=zenoh.Priority.INTERACTIVE_HIGH, express=express)


class FleetKeys:
    """Key expressions of one fleet."""

    def __init__(self, fleet: str):
        self.fleet = check_name(fleet, "fleet name")
        self.prefix = f"{KEY_ROOT}/{fleet}"
        self.ctrl_alive = f"{self.prefix}/ctrl/alive"
        self.operator = f"{self.prefix}/ctrl/operator"     # an operator's requests to the controller
        self.estop = f"{self.prefix}/estop"
        self.all_states = f"{self.prefix}/robot/*/state"
        self.all_robot_alive = f"{self.prefix}/robot/*/alive"
        self.sightings = f"{self.prefix}/tracker/sightings"   # SIGHTING messages (deploy.tracker)

    def state(self, robot: str) -> str:
        return f"{self.prefix}/robot/{check_name(robot)}/state"

    def cmd(self, robot: str) -> str:
        return f"{self.prefix}/robot/{check_name(robot)}/cmd"

    def robot_alive(self, robot: str) -> str:
        return f"{self.prefix}/robot/{check_name(robot)}/alive"

    def robot_in(self, key: str, leaf: str) -> str | None:
        """The robot name in ``formation/<fleet>/robot/<rid>/<leaf>``, or None if the key differs."""
        head, tail = f"{self.prefix}/robot/", f"/{leaf}"
        if not (key.startswith(head) and key.endswith(tail)):
            return None
        name = key[len(head):len(key) - len(tail)]
        try:
            return check_name(name)
        except ValueError:
            return None

@dataclass(frozen=True)
class TransportConfig:
    """How a node joins the Zenoh network.

    Attributes:
        listen: endpoints to listen on, e.g. ``("tcp/127.0.0.1:7447",)``; empty = listen nowhere.
        connect: endpoints of peers to connect to, e.g. the controller's listen endpoint.
        multicast_scouting: discover peers by UDP multicast (off by default; off in tests).
        gossip_scouting: learn further peers through connected ones (Zenoh's default: on).
        lease_ms: link lease (``transport/link/tx/lease``). A frozen peer is declared gone,
            and its liveliness tokens dropped, after about this long (Zenoh default 10000).
        mode: ``"peer"`` (nodes link to each other, one host or a trusted network) or
            ``"client"`` (through a router: ``formation router``, :mod:`deploy.security`).
        tls: the node's certificate files (:class:`deploy.certs.NodeFiles`): every link is
            mutual TLS with the fleet CA, and every endpoint must be ``tls/...``.
        insecure: allow plain links to endpoints off this host's loopback. Without it such an
            endpoint needs ``tls``: a fleet on a network is authenticated by default.
        zenoh_config: a Zenoh configuration file (JSON5) for any Zenoh setting. It is the base:
            the fields above are written over it only where they say something (endpoints
            given, ``lease_ms``, ``tls``, client mode); scouting is then the file's.
    """

    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    gossip_scouting: bool = True
    lease_ms: int | None = None
    mode: str = "peer"
    tls: NodeFiles | None = None
    insecure: bool = False
    zenoh_config: str | None = None

    def __post_init__(self) -> None:
        for field in ("listen", "connect"):
            endpoints = getattr(self, field)
            if isinstance(endpoints, str):
                raise ValueError(f"TransportConfig.{field} must be a tuple of endpoints, "
                                 f"not the string {endpoints!r}: write ({endpoints!r},)")
            object.__setattr__(self, field, tuple(endpoints))
            for endpoint in endpoints:
                if not isinstance(endpoint, str) or not ENDPOINT_RE.fullmatch(endpoint):
                    raise ValueError(f"TransportConfig.{field}: {endpoint!r} is not a Zenoh "
                                     "endpoint; write e.g. 'tcp/127.0.0.1:7447'")
        if self.lease_ms is not None and (not isinstance(self.lease_ms, int)
                                          or self.lease_ms < 100):
            raise ValueError(f"TransportConfig.lease_ms={self.lease_ms!r} must be an int >= 100 "
                             "(milliseconds) or None for Zenoh's default")
        if self.mode not in ("peer", "client"):
            raise ValueError(f"TransportConfig.mode must be 'peer' or 'client', got {self.mode!r}")
        if self.mode == "client" and not self.connect:
            raise ValueError("TransportConfig: a client needs the router's endpoint in connect")
        self._check_plain(self.listen + self.connect)

    def _check_plain(self, endpoints: tuple[str, ...] | list[str]) -> None:
        """With certificates every endpoint is tls/; without, none off loopback unless insecure."""
        if self.tls is not None:
            plain = [e for e in endpoints if not e.startswith("tls/")]
            if plain:
                raise ValueError(f"TransportConfig: with certificates every endpoint is tls/...; "
                                 f"got {plain}")
        elif not self.insecure:
            remote = [e for e in endpoints if not LOOPBACK_RE.fullmatch(e)]
            if remote:
                raise ValueError(f"endpoints {remote} are off this host: give certificates "
                                 "(--certs DIR, from `formation certs`) and tls/ endpoints, or "
                                 "--insecure for a plain link on a trusted network")

    def loopback_only(self) -> bool:
        """Whether every endpoint (at least one) is on this host's loopback (127.0.0.0/8,
        ``localhost``, ``[::1]``): then every peer runs on this host and shares its monotonic
        clock, so a receiver can judge a message's age and refuse one from the future."""
        endpoints = self.listen + self.connect
        return bool(endpoints) and self.mode == "peer" and not self.multicast_scouting and all(
            LOOPBACK_RE.fullmatch(e) for e in endpoints)

    def to_zenoh(self) -> zenoh.Config:
        if self.zenoh_config is None:
            config = zenoh.Config()
            config.insert_json5("mode", json.dumps(self.mode))
            config.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
            config.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
            config.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
            config.insert_json5("scouting/gossip/enabled", json.dumps(self.gossip_scouting))
        else:
            try:
                config = zenoh.Config.from_file(str(self.zenoh_config))
            except zenoh.ZError as err:
                raise ValueError(f"--zenoh-config {self.zenoh_config}: not a Zenoh configuration "
                                 f"file: {err}") from None
            if self.mode != "peer":
                config.insert_json5("mode", json.dumps(self.mode))
            for key, endpoints in (("listen/endpoints", self.listen), ("connect/endpoints", self.connect)):
                if endpoints:
                    config.insert_json5(key, json.dumps(list(endpoints)))
            self._check_plain(_endpoints_of(config))
        if self.lease_ms is not None:
            config.insert_json5("transport/link/tx/lease", str(self.lease_ms))
        if self.tls is not None:
            config.insert_json5("transport/link/tls", json.dumps(tls_block(self.tls)))
        return config

    def open(self) -> zenoh.Session:
        return zenoh.open(self.to_zenoh())


def _endpoints_of(config: zenoh.Config) -> list[str]:
    """Every listen and connect endpoint of a Zenoh configuration (lists, or lists per mode)."""
    out: list[str] = []
    for key in ("listen/endpoints", "connect/endpoints"):
        value = json.loads(config.get_json(key))
        for item in (value.values() if isinstance(value, dict) else [value]):
            out.extend(item if isinstance(item, list) else [])
    return out


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago on ``host`` (for tests and local fleets)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])

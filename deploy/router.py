"""The fleet's Zenoh router: mutual TLS on every link and the fleet's access control.

``formation router --fleet F --scenario paper-5 --certs DIR --listen tls/0.0.0.0:7447`` opens an
in-process Zenoh router (``zenohd`` is not needed) with the router certificate of ``DIR``
(:mod:`deploy.certs`) and :func:`deploy.security.fleet_acl` for the scenario's robots. The
controller and the robots connect to it as clients (``--certs DIR --connect tls/HOST:7447``).
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterable
from dataclasses import dataclass

import zenoh

from deploy.certs import ROUTER, NodeFiles
from deploy.network import ENDPOINT_RE
from deploy.security import fleet_acl, tls_block
from deploy.wire import check_name


@dataclass(frozen=True)
class RouterConfig:
    """fleet: fleet name; robots: robot ids the access control knows; certs: the router's
    files; listen: ``tls/...`` endpoints; lease_ms: link lease (None: Zenoh's 10 s)."""

    fleet: str
    robots: tuple[str, ...]
    certs: NodeFiles
    listen: tuple[str, ...] = ("tls/127.0.0.1:7447",)
    lease_ms: int | None = None

    def __post_init__(self) -> None:
        check_name(self.fleet)
        object.__setattr__(self, "robots", tuple(self.robots))
        for rid in self.robots:
            check_name(rid)
        object.__setattr__(self, "listen", tuple(self.listen))
        if not self.listen:
            raise ValueError("router: give at least one --listen endpoint, e.g. tls/0.0.0.0:7447")
        for endpoint in self.listen:
            if not (ENDPOINT_RE.fullmatch(endpoint) and endpoint.startswith("tls/")):
                raise ValueError(f"router: {endpoint!r} must be a tls/HOST:PORT endpoint "
                                 "(every link is mutual TLS)")

    def to_zenoh(self) -> zenoh.Config:
        config = zenoh.Config()
        config.insert_json5("mode", '"router"')
        config.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("transport/link/tls", json.dumps(tls_block(self.certs)))
        config.insert_json5("access_control", json.dumps(fleet_acl(self.fleet, self.robots)))
        if self.lease_ms is not None:
            config.insert_json5("transport/link/tx/lease", str(self.lease_ms))
        return config


class Router:
    """An open router session (a context manager); :meth:`serve` blocks until :meth:`stop`."""

    def __init__(self, config: RouterConfig):
        self.config = config
        self.session = zenoh.open(config.to_zenoh())
        self._stop = threading.Event()

    def serve(self) -> None:
        self._stop.wait()

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        self.session.close()

    def __enter__(self) -> Router:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def router_config(fleet: str, robots: Iterable[str], certs_dir: str, listen: Iterable[str],
                  lease_ms: int | None = None) -> RouterConfig:
    return RouterConfig(fleet, tuple(robots), NodeFiles.in_dir(certs_dir, ROUTER), tuple(listen), lease_ms)

"""The fleet's Zenoh router: mutual TLS on every link and the fleet's access control.

``formation router --fleet F --scenario paper-5 --certs DIR --listen tls/0.0.0.0:7447`` opens an
in-process Zenoh router (``zenohd`` is not needed) with the router certificate of ``DIR``
(:mod:`deploy.certs`) and :func:`deploy.security.fleet_acl` for the scenario's robots. The
controller and the robots connect to it as clients (``--certs DIR --connect tls/HOST:7447``).

What the router refuses is counted (:mod:`deploy.access_log`, read from Zenoh's own log by
:mod:`deploy.zenoh_log`, the only place eclipse-zenoh 1.10 reports it): messages its access control
denied, by the sender's certificate common name, message kind and key, and TLS links it refused,
by reason. :meth:`Router.serve` logs new ones at most once a second (:class:`RejectLog`), e.g.::

    router f1: 21 refusals in the last 1.0 s: {'denied r1: Put formation/f1/robot/r0/cmd': 20,
        'refused link: received fatal alert: DecryptError': 1}

and :meth:`Router.summary` holds the totals (``formation router`` prints it on exit). A refusal
never stops the router: the message or link is dropped and the router goes on.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Iterable
from dataclasses import dataclass

import zenoh

from deploy.access_log import DIRECTIVES, AccessLog
from deploy.certs import ROUTER, NodeFiles, check_robot_ids
from deploy.network import ENDPOINT_RE
from deploy.reject_log import RejectLog
from deploy.security import fleet_acl, tls_block
from deploy.wire import check_name
from deploy.zenoh_log import ZenohLogTap, install_log

log = logging.getLogger(__name__)
ACL_SEEN_TIMEOUT_S = 2.0  # [s] how long the router waits to see Zenoh's log report its ACL on


@dataclass(frozen=True)
class RouterConfig:
    """fleet: fleet name; robots: robot ids the access control knows; certs: the router's
    files; listen: ``tls/...`` endpoints; lease_ms: link lease (None: Zenoh's 10 s); count: count
    what the router refuses (module docstring; this process's fd 1 then passes through a pipe,
    and Zenoh's log formatter stays installed for the rest of the process, writing to fd 1: off
    by default here, where the process is someone else's; ``formation router``, a process of its
    own, turns it on)."""

    fleet: str
    robots: tuple[str, ...]
    certs: NodeFiles
    listen: tuple[str, ...] = ("tls/127.0.0.1:7447",)
    lease_ms: int | None = None
    count: bool = False

    def __post_init__(self) -> None:
        check_name(self.fleet, "fleet name (--fleet)")
        object.__setattr__(self, "robots", tuple(self.robots))
        for rid in self.robots:
            check_name(rid)
        check_robot_ids(self.robots)
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
    """An open router session (a context manager); :meth:`serve` blocks until :meth:`stop`,
    logging refusals at most once per ``report_interval_s`` [s]."""

    def __init__(self, config: RouterConfig, report_interval_s: float = 1.0):
        self.config = config
        self.access = AccessLog()
        self.counting = False     # refusals are being counted (Zenoh's log reaches the tap)
        self._tap = self._open_tap() if config.count else None
        try:
            self.session = zenoh.open(config.to_zenoh())
        except BaseException:
            self._close_tap()
            raise
        if self._tap is not None:
            self.counting = self.access.acl_enabled.wait(ACL_SEEN_TIMEOUT_S)
            if not self.counting:
                log.warning("router %s: Zenoh's log did not reach the router (set up elsewhere in "
                            "this process?): refusals are not counted", config.fleet)
        self._reject_log = RejectLog(f"router {config.fleet}", self.access.snapshot,
                                     report_interval_s, what="refusals")
        self._stop = threading.Event()

    def _open_tap(self) -> ZenohLogTap | None:
        if not install_log(DIRECTIVES):
            log.warning("router %s: Zenoh's log was set up before with other directives: refusals "
                        "are not counted", self.config.fleet)
            return None
        tap = ZenohLogTap(self.access.take)
        try:
            tap.start()
        except RuntimeError as err:      # another router of this process reads the log
            log.warning("router %s: %s: refusals are not counted", self.config.fleet, err)
            return None
        return tap

    def _close_tap(self) -> None:
        if self._tap is not None:
            self._tap.stop()
            self._tap = None

    def serve(self) -> None:
        while not self._stop.wait(0.2):
            self._reject_log.poll()

    def stop(self) -> None:
        self._stop.set()

    def summary(self) -> dict:
        """``counting`` (False: the counts below are not known) and the totals of
        :meth:`deploy.access_log.AccessLog.report`: denied, withheld, refused_links."""
        return {"fleet": self.config.fleet, "counting": self.counting, **self.access.report()}

    def close(self) -> None:
        """Close the session, then give fd 1 back (the session's last lines are still counted)."""
        try:
            self.session.close()
        finally:
            self._close_tap()

    def __enter__(self) -> Router:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def router_config(fleet: str, robots: Iterable[str], certs_dir: str, listen: Iterable[str],
                  lease_ms: int | None = None, count: bool = True) -> RouterConfig:
    return RouterConfig(fleet, tuple(robots), NodeFiles.in_dir(certs_dir, ROUTER), tuple(listen),
                        lease_ms, count)

"""Mutual TLS and the fleet's access control on a real Zenoh router on 127.0.0.1 (in process)."""

from __future__ import annotations

import json
import time

import pytest
import zenoh

from deploy.certs import CONTROLLER, ROUTER, NodeFiles, common_name, make_certs
from deploy.network import TransportConfig, free_tcp_port
from deploy.router import Router, RouterConfig
from deploy.security import fleet_acl

pytestmark = pytest.mark.realtime   # Zenoh sessions and a router with access control

FLEET, ROBOTS = "sec", ("r0", "r1", "r2")
K = f"formation/{FLEET}"


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("certs")
    make_certs(folder, [ROUTER, CONTROLLER, "fleet-sim", "operator", "tracker", *ROBOTS])
    rogue = tmp_path_factory.mktemp("rogue")       # a CA of its own: a self-signed "controller"
    make_certs(rogue, [CONTROLLER])
    return folder, rogue


def client(folder, node: str, port: int) -> zenoh.Session:
    return TransportConfig(connect=(f"tls/127.0.0.1:{port}",), mode="client",
                           tls=NodeFiles.in_dir(folder, node)).open()


def exchange(folder, port: int) -> dict[str, list]:
    """The controller, r0 and an intruder holding r1's certificate, through the router: who
    receives what. The intruder commands r0, forges r2's state, releases the e-stop and reports
    an obstacle that is not there; the tracker reports one."""
    got: dict[str, list] = {"r0_cmd": [], "states": [], "estop": [], "sightings": []}
    with client(folder, CONTROLLER, port) as ctrl, client(folder, "r0", port) as r0, \
            client(folder, "r1", port) as intruder, client(folder, "tracker", port) as tracker:
        subs = [r0.declare_subscriber(f"{K}/robot/r0/cmd", lambda s: got["r0_cmd"].append(s.payload.to_bytes())),
                r0.declare_subscriber(f"{K}/estop", lambda s: got["estop"].append(s.payload.to_bytes())),
                ctrl.declare_subscriber(f"{K}/robot/*/state",
                                        lambda s: got["states"].append((str(s.key_expr), s.payload.to_bytes()))),
                ctrl.declare_subscriber(f"{K}/tracker/sightings", lambda s: got["sightings"].append(s.payload.to_bytes()))]
        time.sleep(0.5)                              # declarations travel through the router
        ctrl.put(f"{K}/robot/r0/cmd", b"genuine")
        ctrl.put(f"{K}/estop", b"engage")
        r0.put(f"{K}/robot/r0/state", b"r0")
        intruder.put(f"{K}/robot/r0/cmd", b"forged")
        intruder.put(f"{K}/robot/r2/state", b"forged")
        intruder.put(f"{K}/estop", b"release")
        intruder.put(f"{K}/robot/r1/state", b"r1")   # its own: allowed
        intruder.put(f"{K}/tracker/sightings", b"forged")
        tracker.put(f"{K}/tracker/sightings", b"seen")
        tracker.put(f"{K}/robot/r0/cmd", b"tracker")  # not its key
        time.sleep(0.5)
        del subs
    return got


def test_only_the_controller_commands_and_a_robot_speaks_only_for_itself(certs, monkeypatch):
    folder, _ = certs
    port = free_tcp_port()
    config = RouterConfig(FLEET, ROBOTS, NodeFiles.in_dir(folder, ROUTER), (f"tls/127.0.0.1:{port}",))
    with Router(config):
        got = exchange(folder, port)
    assert got["r0_cmd"] == [b"genuine"]
    assert got["estop"] == [b"engage"]
    assert sorted(got["states"]) == [(f"{K}/robot/r0/state", b"r0"), (f"{K}/robot/r1/state", b"r1")]
    assert got["sightings"] == [b"seen"]
    # teeth: the same exchange on a router without the access control lets every forgery through
    open_acl = dict(fleet_acl(FLEET, ROBOTS), enabled=False)
    monkeypatch.setattr("deploy.router.fleet_acl", lambda *_: open_acl)
    port = free_tcp_port()
    config = RouterConfig(FLEET, ROBOTS, NodeFiles.in_dir(folder, ROUTER), (f"tls/127.0.0.1:{port}",))
    with Router(config):
        got = exchange(folder, port)
    assert sorted(got["r0_cmd"]) == [b"forged", b"genuine", b"tracker"]
    assert sorted(got["sightings"]) == [b"forged", b"seen"]
    assert sorted(got["estop"]) == [b"engage", b"release"]
    assert (f"{K}/robot/r2/state", b"forged") in got["states"]


def test_no_link_without_a_certificate_of_the_fleet_ca(certs):
    folder, rogue = certs
    port = free_tcp_port()
    config = RouterConfig(FLEET, ROBOTS, NodeFiles.in_dir(folder, ROUTER), (f"tls/127.0.0.1:{port}",))
    with Router(config):
        with pytest.raises(zenoh.ZError):            # a self-signed "controller"
            client(rogue, CONTROLLER, port)
        plain = zenoh.Config()                        # no certificate at all, plain tcp
        plain.insert_json5("mode", '"client"')
        plain.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        with pytest.raises(zenoh.ZError):
            zenoh.open(plain)
        with client(folder, CONTROLLER, port):       # the genuine one links
            pass


def test_certificates_name_their_node_and_bad_requests_name_the_fix(tmp_path, certs):
    folder, _ = certs
    assert common_name(folder / "r2.pem") == "r2"
    assert oct((folder / "r2.key").stat().st_mode & 0o777) == "0o600"
    with pytest.raises(ValueError, match="node names"):
        make_certs(tmp_path, ["bad name"])
    with pytest.raises(FileNotFoundError, match="formation certs --out"):
        NodeFiles.in_dir(tmp_path, "r7")
    with pytest.raises(ValueError, match="off this host"):
        TransportConfig(connect=("tcp/10.0.0.2:7447",))
    with pytest.raises(ValueError, match="every endpoint is tls"):
        TransportConfig(connect=("tcp/127.0.0.1:7447",), mode="client", tls=NodeFiles.in_dir(folder, "r0"))
    with pytest.raises(ValueError, match="tls/HOST:PORT"):
        RouterConfig(FLEET, ROBOTS, NodeFiles.in_dir(folder, ROUTER), ("tcp/127.0.0.1:7447",))


def test_only_the_operator_and_the_controller_reach_the_operator_channel(certs):
    """The controller answers on ctrl/operator; the operator's query gets the answer, a robot's
    certificate gets none."""
    folder, _ = certs
    port = free_tcp_port()
    config = RouterConfig(FLEET, ROBOTS, NodeFiles.in_dir(folder, ROUTER), (f"tls/127.0.0.1:{port}",))
    with Router(config), client(folder, CONTROLLER, port) as ctrl:
        queryable = ctrl.declare_queryable(f"{K}/ctrl/operator",
                                           lambda q: q.reply(f"{K}/ctrl/operator", b"answered"))
        time.sleep(0.5)

        def ask(node: str) -> list[bytes]:
            with client(folder, node, port) as s:
                return [r.ok.payload.to_bytes() for r in s.get(f"{K}/ctrl/operator", timeout=1.0)
                        if r.ok is not None]

        assert ask("operator") == [b"answered"]
        assert ask("r1") == []
        del queryable


def _refused_links(router, at_least: int, timeout_s: float = 5.0) -> dict:
    """The router's report once it counts ``at_least`` refused links (the TLS warning follows the
    client's error by a moment), or after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while sum(router.summary()["refused_links"].values()) < at_least and time.monotonic() < deadline:
        time.sleep(0.05)
    return router.summary()


def test_the_router_counts_what_it_refuses_and_nothing_of_the_controller(certs):
    """A forged command, state, e-stop and sighting from robot r1's (valid) certificate, and a
    command from the tracker's, are denied and counted under their names with their keys; a self-signed "controller" and a client without a
    certificate are refused links, counted by reason; the genuine controller counts nothing."""
    folder, rogue = certs
    port = free_tcp_port()
    config = RouterConfig(FLEET, ROBOTS, NodeFiles.in_dir(folder, ROUTER), (f"tls/127.0.0.1:{port}",),
                          count=True)
    with Router(config) as router:
        assert router.counting
        got = exchange(folder, port)
        before = router.summary()
        with pytest.raises(zenoh.ZError):                 # does not trust the router
            client(rogue, CONTROLLER, port)
        forged = NodeFiles(folder / "ca.pem", rogue / "controller.pem", rogue / "controller.key")
        with pytest.raises(zenoh.ZError):                 # trusts it, but the router not it
            TransportConfig(connect=(f"tls/127.0.0.1:{port}",), mode="client", tls=forged).open()
        plain = zenoh.Config()
        plain.insert_json5("mode", '"client"')
        plain.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        with pytest.raises(zenoh.ZError):
            zenoh.open(plain)
        after = _refused_links(router, 3)
    assert got["r0_cmd"] == [b"genuine"]
    assert before["refused_links"] == {}
    assert after["denied"] == before["denied"]            # a refused link sends no message
    assert set(after["denied"]) == {"r1", "tracker"}      # nothing of the controller, nor of r0
    assert after["denied"]["r1"]["Put formation/sec/robot/r0/cmd"] == 1
    assert after["denied"]["r1"]["Put formation/sec/estop"] == 1
    assert after["denied"]["r1"]["Put formation/sec/tracker/sightings"] == 1
    assert after["denied"]["tracker"] == {"Put formation/sec/robot/r0/cmd": 1}
    assert after["withheld"] == {}
    assert sum(after["refused_links"].values()) == 3        # one line each, by reason
    assert after["refused_links"].get("invalid peer certificate: BadSignature") == 1

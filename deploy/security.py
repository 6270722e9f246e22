"""Who may say what on a fleet's Zenoh network: mutual TLS and the router's access control.

Topology: one Zenoh router (``formation router``) listens on ``tls/...``; the controller
(``bridge``), the robots and simulated fleets (``fleet-sim``) connect to it as clients. Every link
is TLS with client certificates (``enable_mtls``): a node without a certificate signed by the
fleet CA (:mod:`deploy.certs`) cannot open a link at all. The router then matches each link's
certificate common name against :func:`fleet_acl`, ``default_permission: deny``, and lets through
only (keys under ``formation/<fleet>/``)::

    controller     puts      robot/*/cmd, estop          (commands and the fleet e-stop)
                   declares  subscribers on robot/*/state, liveliness subscriber on robot/*/alive,
                             its liveliness token ctrl/alive, the estop queryable (and replies)
    robot <rid>    puts      robot/<rid>/state           (its own state, nothing else)
                   declares  its token robot/<rid>/alive; subscribers on robot/<rid>/cmd and
                             estop, a liveliness subscriber on ctrl/alive; queries estop
    fleet-sim      the rights of every robot and of the tracker (one process simulating the
                   fleet and the intruders its tracker sees)
    operator       queries ctrl/operator                 (formation estop: engage, release, status)
    tracker        puts      tracker/sightings           (obstacles it sees: deploy.tracker)

and towards each node (egress) only what it may read: the controller everything under the fleet,
a robot its own command, the e-stop and the controller's token. A robot's certificate can
therefore neither command another robot, nor forge another robot's state, nor raise or release
the e-stop, nor pose as the controller (the controller's token is the controller's). The
enforcement is on the router: clients do not route for each other, so no link bypasses it.
The router counts what its access control denies and the links TLS refuses, from Zenoh's own log
(:mod:`deploy.access_log`; the denials are TRACE lines); the nodes themselves count what still
arrives malformed or stale (``rejects``).
"""

from __future__ import annotations

from collections.abc import Iterable

from deploy.certs import CONTROLLER, FLEET_SIM, OPERATOR, TRACKER, NodeFiles

ALL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                "liveliness_token", "declare_liveliness_subscriber", "liveliness_query")
"""The message kinds of Zenoh 1.x access control."""


def tls_block(files: NodeFiles, verify_name: bool = True) -> dict:
    """``transport/link/tls`` of a node: its certificate for both listening and connecting, the
    fleet CA as the only root, client certificates required (``enable_mtls``)."""
    return {"root_ca_certificate": str(files.ca), "enable_mtls": True,
            "listen_private_key": str(files.key), "listen_certificate": str(files.cert),
            "connect_private_key": str(files.key), "connect_certificate": str(files.cert),
            "verify_name_on_connect": verify_name}


def _rule(rule_id: str, flow: str, messages: Iterable[str], keys: Iterable[str]) -> dict:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": list(messages),
            "key_exprs": list(keys)}


def _robot_rules(prefix: str, rid: str, tag: str) -> list[dict]:
    """What robot ``rid`` (``*``: every robot) may send and receive (module docstring)."""
    own = f"{prefix}/robot/{rid}"
    return [
        _rule(f"{tag}-put", "ingress", ("put", "liveliness_token"), (f"{own}/state", f"{own}/alive")),
        _rule(f"{tag}-declare", "ingress",
              ("declare_subscriber", "declare_liveliness_subscriber", "query", "liveliness_query"),
              (f"{own}/cmd", f"{prefix}/estop", f"{prefix}/ctrl/alive")),
        _rule(f"{tag}-receive", "egress",
              ("put", "liveliness_token", "reply", "declare_queryable", "declare_subscriber",
               "declare_liveliness_subscriber", "query"),
              (f"{own}/**", f"{prefix}/estop", f"{prefix}/ctrl/alive")),
    ]


def fleet_acl(fleet: str, robots: Iterable[str]) -> dict:
    """The router's ``access_control`` block for ``fleet`` and its ``robots`` (module docstring)."""
    prefix = f"formation/{fleet}"
    rules = [
        _rule("controller-put", "ingress", ("put",), (f"{prefix}/robot/*/cmd", f"{prefix}/estop")),
        _rule("controller-declare", "ingress",
              ("declare_subscriber", "declare_liveliness_subscriber", "liveliness_token",
               "declare_queryable", "reply", "liveliness_query"), (f"{prefix}/**",)),
        _rule("controller-receive", "egress", ALL_MESSAGES, (f"{prefix}/**",)),
    ]
    rules += [_rule("operator-ask", "ingress", ("query",), (f"{prefix}/ctrl/operator",)),
              _rule("operator-answer", "egress", ("reply", "declare_queryable"), (f"{prefix}/ctrl/operator",))]
    rules.append(_rule("tracker-put", "ingress", ("put",), (f"{prefix}/tracker/sightings",)))
    subjects = [{"id": CONTROLLER, "cert_common_names": [CONTROLLER]},
                {"id": FLEET_SIM, "cert_common_names": [FLEET_SIM]},
                {"id": OPERATOR, "cert_common_names": [OPERATOR]},
                {"id": TRACKER, "cert_common_names": [TRACKER]}]
    policies = [{"rules": ["controller-put", "controller-declare", "controller-receive"],
                 "subjects": [CONTROLLER]},
                {"rules": ["operator-ask", "operator-answer"], "subjects": [OPERATOR]},
                {"rules": ["tracker-put"], "subjects": [TRACKER]}]
    sim_rules = _robot_rules(prefix, "*", FLEET_SIM)
    rules += sim_rules
    policies.append({"rules": [r["id"] for r in sim_rules] + ["tracker-put"], "subjects": [FLEET_SIM]})
    for rid in robots:
        own = _robot_rules(prefix, rid, f"robot-{rid}")
        rules += own
        subjects.append({"id": f"robot-{rid}", "cert_common_names": [rid]})
        policies.append({"rules": [r["id"] for r in own], "subjects": [f"robot-{rid}"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}

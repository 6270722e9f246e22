"""A fleet's certificates: one CA, and one certificate per node whose common name is its identity.

``formation certs --out DIR --robot-ids r0,r1,r2`` writes, into ``DIR``::

    ca.pem, ca.key              the fleet CA (keep ca.key off the robots: it signs new nodes)
    controller.pem/.key         the controller (bridge)
    fleet-sim.pem/.key          a simulated fleet (one process holding every robot's rights)
    operator.pem/.key           an operator (``formation estop``: engage, release, status)
    router.pem/.key             the Zenoh router
    r0.pem/.key, ...            one per robot

Keys are ECDSA P-256 (what rustls, Zenoh's TLS, accepts), written with mode 0600. Each node's
certificate carries its name as common name (the identity the router's access control matches,
``cert_common_names``) and as a DNS name, plus ``localhost``, ``127.0.0.1`` and the ``--host``
names or addresses given, so a client that verifies the name it connects to
(``verify_name_on_connect``) accepts the router at any of them. Every certificate may serve
and connect (server and client auth): a Zenoh node does both. Files are written atomically; an
existing CA is reused, so adding a robot later signs it with the same CA.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from sim.files import atomic_path

CONTROLLER, FLEET_SIM, ROUTER, OPERATOR, TRACKER = "controller", "fleet-sim", "router", "operator", "tracker"
ROLES = (ROUTER, CONTROLLER, FLEET_SIM, OPERATOR, TRACKER)
CA = "ca"                                # ca.pem, ca.key: no node may take this name
_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_\-]{0,62}")


def check_robot_ids(robots: Iterable[str]) -> list[str]:
    """``robots`` as a list, each an id a robot's certificate can carry: 1-63 letters, digits,
    '-' or '_', and neither a role's name (its certificate would be that role's, with its rights
    at the router) nor ``ca`` (the CA's files). Raises ValueError naming the ids and the fix."""
    robots = list(robots)
    bad = [r for r in robots if not isinstance(r, str) or not _NAME_RE.fullmatch(r)]
    if bad:
        raise ValueError(f"robot ids must be 1-63 letters, digits, '-' or '_' (ids in certificates): got {bad}")
    twice = sorted({r for r in robots if robots.count(r) > 1})
    if twice:
        raise ValueError(f"robot ids {twice} are given twice: give each robot id once")
    taken = [r for r in robots if r in (*ROLES, CA)]
    if taken:
        raise ValueError(f"robot ids {taken} are names of the fleet's own nodes or CA "
                         f"({', '.join((*ROLES, CA))}): name the robots otherwise, e.g. r0, r1")
    return robots


@dataclass(frozen=True)
class NodeFiles:
    """The three files a node needs: the fleet CA and its own certificate and key."""

    ca: Path
    cert: Path
    key: Path

    @classmethod
    def in_dir(cls, folder: str | Path, node: str) -> NodeFiles:
        """``node``'s files in a ``formation certs`` folder; an error names what is missing."""
        folder = Path(folder)
        files = cls(folder / "ca.pem", folder / f"{node}.pem", folder / f"{node}.key")
        missing = [str(p) for p in (files.ca, files.cert, files.key) if not p.is_file()]
        if missing:
            raise FileNotFoundError(f"certificates for {node!r} not found: {', '.join(missing)}; "
                                    f"run: formation certs --out {folder} (names: controller, "
                                    "fleet-sim, router, operator, tracker and the robots given with --robot-ids)")
        for path in (files.ca, files.cert):
            _load(path, x509.load_pem_x509_certificate, f"run: formation certs --out {folder}")
        _load(files.key, _private_key, f"run: formation certs --out {folder}")
        return files


def _private_key(data: bytes):
    return serialization.load_pem_private_key(data, password=None)


def _load(path: Path, parse, fix: str):
    """``parse(path's bytes)``; a ValueError names the file and the fix."""
    try:
        return parse(path.read_bytes())
    except ValueError as exc:
        raise ValueError(f"{path}: not a PEM certificate or key ({exc}); {fix}") from None


def _write(path: Path, data: bytes, secret: bool) -> None:
    with atomic_path(path) as tmp:
        if secret:                       # before the key is in it
            os.chmod(tmp, 0o600)
        tmp.write_bytes(data)


def _key_bytes(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _ca(folder: Path, days: int) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """The folder's CA, made on first use."""
    cert_path, key_path = folder / "ca.pem", folder / "ca.key"
    if cert_path.is_file() != key_path.is_file():   # a new CA would orphan every node's certificate
        missing = key_path if cert_path.is_file() else cert_path
        raise FileNotFoundError(f"{missing} is missing beside {cert_path if missing == key_path else key_path}: "
                                "put it back to sign with the fleet's CA (or remove both to make a new CA, "
                                "then issue every node again)")
    if cert_path.is_file():
        fix = "restore it, or remove ca.pem and ca.key to make a new CA (then issue every node again)"
        return _load(cert_path, x509.load_pem_x509_certificate, fix), _load(key_path, _private_key, fix)
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "formation fleet CA")])
    now = dt.datetime.now(dt.UTC)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False,
                                         encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    _write(key_path, _key_bytes(key), secret=True)
    _write(cert_path, cert.public_bytes(serialization.Encoding.PEM), secret=False)
    return cert, key


def _alt_names(node: str, hosts: Iterable[str]) -> list[x509.GeneralName]:
    names: list[x509.GeneralName] = []
    for host in dict.fromkeys([node, "localhost", "127.0.0.1", *hosts]):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return names


def make_certs(folder: str | Path, nodes: Iterable[str], hosts: Iterable[str] = (), days: int = 365) -> dict[str, NodeFiles]:
    """Write the CA (if new) and a certificate and key for each of ``nodes`` (module docstring);
    returns each node's files."""
    folder = Path(folder)
    nodes, hosts = list(dict.fromkeys(nodes)), list(hosts)
    bad = [n for n in nodes if not isinstance(n, str) or not _NAME_RE.fullmatch(n)]
    if bad:
        raise ValueError(f"node names must be 1-63 letters, digits, '-' or '_': got {bad}")
    if CA in nodes:     # its files would overwrite the CA's and lose the fleet's trust root
        raise ValueError(f"no node may be named {CA!r}: {CA}.pem and {CA}.key are the fleet CA's")
    if not isinstance(days, int) or days < 1:
        raise ValueError(f"days must be a positive integer, got {days!r}")
    folder.mkdir(parents=True, exist_ok=True)
    ca_cert, ca_key = _ca(folder, days)
    now = dt.datetime.now(dt.UTC)
    out = {}
    for node in nodes:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (x509.CertificateBuilder()
                .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, node)]))
                .issuer_name(ca_cert.subject).public_key(key.public_key())
                .serial_number(x509.random_serial_number())
                .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
                .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                .add_extension(x509.SubjectAlternativeName(_alt_names(node, hosts)), critical=False)
                .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                      ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
                .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                               critical=False)
                .sign(ca_key, hashes.SHA256()))
        _write(folder / f"{node}.key", _key_bytes(key), secret=True)
        _write(folder / f"{node}.pem", cert.public_bytes(serialization.Encoding.PEM), secret=False)
        out[node] = NodeFiles(folder / "ca.pem", folder / f"{node}.pem", folder / f"{node}.key")
    return out


def common_name(cert_path: str | Path) -> str:
    """The common name of a PEM certificate (a node's identity)."""
    cert = x509.load_pem_x509_certificate(Path(cert_path).read_bytes())
    return cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value

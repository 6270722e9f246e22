"""deploy.certs: a fleet's CA is never replaced behind its back; a damaged file is named."""

from __future__ import annotations

import pytest

from deploy.certs import ROUTER, NodeFiles, make_certs


def test_a_missing_ca_key_is_refused_rather_than_replaced_by_a_new_ca(tmp_path):
    """Before, 'formation certs --out DIR --robot-ids r2' with ca.key moved off the machine made a new
    CA over ca.pem (exit 0), and every certificate issued before stopped verifying."""
    make_certs(tmp_path, ["r0"])
    ca = (tmp_path / "ca.pem").read_bytes()
    (tmp_path / "ca.key").rename(tmp_path / "elsewhere.key")
    with pytest.raises(FileNotFoundError, match=r"ca.key is missing beside .*ca.pem: put it back"):
        make_certs(tmp_path, ["r2"])
    assert (tmp_path / "ca.pem").read_bytes() == ca and not (tmp_path / "r2.pem").exists()
    (tmp_path / "elsewhere.key").rename(tmp_path / "ca.key")
    make_certs(tmp_path, ["r2"])                              # back in place: signed by the same CA
    assert (tmp_path / "ca.pem").read_bytes() == ca


@pytest.mark.parametrize("damaged", ["ca.pem", "router.pem", "router.key"])
def test_a_damaged_certificate_file_is_named_with_the_fix(tmp_path, damaged):
    """Before, a damaged router.pem surfaced as Zenoh's 'peer sent no certificates' and a damaged
    ca.pem as cryptography's message, neither naming the file."""
    make_certs(tmp_path, [ROUTER])
    (tmp_path / damaged).write_text("garbage\n")
    with pytest.raises(ValueError, match=rf"{damaged}: not a PEM certificate or key .*formation certs --out"):
        NodeFiles.in_dir(tmp_path, ROUTER)
    if damaged == "ca.pem":
        with pytest.raises(ValueError, match=r"ca.pem: not a PEM certificate or key .*remove ca.pem and ca.key"):
            make_certs(tmp_path, ["r0"])


def test_a_bad_fleet_name_is_reported_as_the_fleet_name(tmp_path):
    """It was reported as a 'robot id'."""
    from deploy.router import RouterConfig

    make_certs(tmp_path, [ROUTER])
    with pytest.raises(ValueError, match=r"fleet name \(--fleet\) 'f/1' is not allowed"):
        RouterConfig("f/1", ("r0",), NodeFiles.in_dir(tmp_path, ROUTER))


def test_no_node_may_take_the_ca_files_and_no_robot_a_role_name(tmp_path, capsys):
    """Before, a robot named 'ca' wrote its certificate and key over ca.pem and ca.key (every
    node's certificate then stopped verifying), and a robot named 'controller' was handed the
    controller's certificate, rights and all."""
    from deploy.router import RouterConfig
    from stack.cli import main

    make_certs(tmp_path, [ROUTER])
    ca = (tmp_path / "ca.pem").read_bytes(), (tmp_path / "ca.key").read_bytes()
    with pytest.raises(ValueError, match="'ca'.*fleet CA"):
        make_certs(tmp_path, ["r0", "ca"])
    assert ((tmp_path / "ca.pem").read_bytes(), (tmp_path / "ca.key").read_bytes()) == ca
    for robots in ("r0,ca", "r0,controller", "fleet-sim"):
        assert main(["certs", "--out", str(tmp_path), "--robot-ids", robots]) == 2
        assert "name the robots otherwise" in capsys.readouterr().err
    assert ((tmp_path / "ca.pem").read_bytes(), (tmp_path / "ca.key").read_bytes()) == ca
    assert not (tmp_path / "controller.pem").exists()
    for robots in (("r0", "operator"), ("ca",)):
        with pytest.raises(ValueError, match="name the robots otherwise"):
            RouterConfig("f", robots, NodeFiles.in_dir(tmp_path, ROUTER))
    # an id the wire takes but a certificate cannot carry is refused where the router is made
    with pytest.raises(ValueError, match=r"robot ids must be .*'r\.0'"):
        RouterConfig("f", ("r.0",), NodeFiles.in_dir(tmp_path, ROUTER))

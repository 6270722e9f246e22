"""`formation bridge`'s controllers, in process: the scripted fleet controller across episodes."""

from __future__ import annotations

import pytest

from sim.pymunk_world import PymunkWorld
from sim.scenario import make_scenario
from stack.commands.bridge import build_stack
from stack.pipeline import run_episode


def test_the_scripted_fleet_controller_plans_afresh_each_episode():
    """One stack over three pymunk episodes, reset between them as the bridge resets it at a fleet
    episode boundary: every episode ends home. Before the wrapper passed the reset on, episodes 2
    and 3 ran on the first one's finished plan, heading straight for the targets through the object,
    and ended 0.196 m off with the filter intervening every tick."""
    sc = make_scenario("paper-5")
    world, stack = PymunkWorld(sc), build_stack(sc, "scripted", safety=True, mec=True)
    results = [run_episode(world, stack, seed) for seed in range(3)]
    assert [m.success for m in results] == [True, True, True]
    assert max(m.final_distance for m in results) < 0.005


def test_the_transport_flags_make_the_nodes_transport_and_refuse_what_cannot_work(tmp_path):
    import argparse

    import pytest

    from deploy.certs import make_certs
    from stack.commands import argtypes

    parser = argparse.ArgumentParser()
    argtypes.add_transport_flags(parser, "controller")
    plain = argtypes.transport_config(parser.parse_args(["--connect", "tcp/127.0.0.1:7447", "--lease-ms", "1000"]))
    assert (plain.mode, plain.connect, plain.lease_ms, plain.tls) == ("peer", ("tcp/127.0.0.1:7447",), 1000, None)
    make_certs(tmp_path, ["controller", "r0"])
    tls = argtypes.transport_config(parser.parse_args(["--certs", str(tmp_path), "--connect", "tls/10.0.0.1:7447"]))
    assert tls.mode == "client" and tls.tls.cert == tmp_path / "controller.pem"
    robot = argtypes.transport_config(parser.parse_args(["--certs", str(tmp_path), "--identity", "r0",
                                                         "--connect", "tls/10.0.0.1:7447"]))
    assert robot.tls.key == tmp_path / "r0.key"
    with pytest.raises(ValueError, match="listens nowhere"):
        argtypes.transport_config(parser.parse_args(["--certs", str(tmp_path), "--listen", "tls/127.0.0.1:1",
                                                     "--connect", "tls/10.0.0.1:7447"]))
    with pytest.raises(ValueError, match="--insecure"):
        argtypes.transport_config(parser.parse_args(["--connect", "tcp/10.0.0.1:7447"]))
    insecure = argtypes.transport_config(parser.parse_args(["--connect", "tcp/10.0.0.1:7447", "--insecure"]))
    assert insecure.connect == ("tcp/10.0.0.1:7447",)


def test_the_rearm_alarm_threshold_is_a_flag_that_refuses_zero(capsys):
    import pytest

    from stack.cli import build_parser

    parser = build_parser()
    base = ["bridge", "--fleet", "f", "--policy", "scripted"]
    assert parser.parse_args(base).rearm_alarm_after == 10
    assert parser.parse_args([*base, "--rearm-alarm-after", "3"]).rearm_alarm_after == 3
    with pytest.raises(SystemExit) as done:
        parser.parse_args([*base, "--rearm-alarm-after", "0"])
    assert done.value.code == 2 and "--rearm-alarm-after" in capsys.readouterr().err


def test_a_recorded_stack_closes_a_record_per_episode_and_chunk_and_survives_a_failed_write(tmp_path, capsys):
    """Two pymunk episodes through the bridge's stack recording in 50-tick files: episode 1 (128
    ticks) gives files of 50, 50 and 28 ticks (the last closed by the reset), episode 2 of 50, 50
    and 28 (the last at close). The third file's name is taken by a folder: that record is
    reported and skipped, the others are written."""
    import numpy as np

    from stack.cli import main
    from stack.recorder import RecordedStack, load_record

    sc = make_scenario("paper-3")
    (tmp_path / "rec" / "record_00002.npz").mkdir(parents=True)
    stack = RecordedStack(build_stack(sc, "scripted", safety=True, mec=True), tmp_path / "rec", 50, {"fleet": "f"})
    world = PymunkWorld(sc)
    results = [run_episode(world, stack, seed) for seed in range(2)]
    written = stack.close()
    assert [m.success for m in results] == [True, True]
    names = [f"record_0000{k}.npz" for k in (0, 1, 3, 4, 5)]
    assert sorted(p.name for p in written) == names and stack.failed == [str(tmp_path / "rec" / "record_00002.npz")]
    assert "record_00002.npz not written" in capsys.readouterr().err
    records = [load_record(tmp_path / "rec" / name) for name in names]
    assert [(r.steps, r.meta["closed_by"], r.meta["index"]) for r in records] == [
        (50, "chunk", 0), (50, "chunk", 1), (50, "chunk", 3), (50, "chunk", 4), (28, "exit", 5)]
    np.testing.assert_allclose(records[2].time[0], 0.0, atol=1e-12)        # episode 2 starts afresh
    assert records[0].meta["fleet"] == "f" and records[0].meta["scenario"]["name"] == "paper-3"
    (tmp_path / "file").write_text("x")
    with pytest.raises(SystemExit) as done:      # refused while the flags are read
        main(["bridge", "--fleet", "f", "--policy", "scripted", "--record", str(tmp_path / "file")])
    assert done.value.code == 2
    assert "argument --record: " in capsys.readouterr().err


def test_the_lease_flag_is_refused_below_100_ms_by_every_command_that_takes_it(capsys):
    import pytest

    from stack.cli import build_parser

    parser = build_parser()
    for base in (["bridge", "--fleet", "f", "--policy", "scripted"], ["fleet-sim", "--fleet", "f"],
                 ["router", "--fleet", "f", "--certs", "c"]):
        assert parser.parse_args([*base, "--lease-ms", "100"]).lease_ms == 100
        for bad in ("-5", "99", "1.5"):
            with pytest.raises(SystemExit) as done:
                parser.parse_args([*base, "--lease-ms", bad])
            assert done.value.code == 2 and "--lease-ms" in capsys.readouterr().err, (base, bad)


def test_node_flags_are_refused_at_start_not_after_the_run(tmp_path, capsys):
    """--report naming a folder was accepted, and the whole run's report was lost to an
    IsADirectoryError at exit; --ticks -1 ran nothing and exited 0; estop --timeout nan raised
    from Zenoh."""
    import pytest

    from stack.cli import build_parser

    parser = build_parser()
    nodes = (["bridge", "--fleet", "f", "--policy", "scripted"], ["fleet-sim", "--fleet", "f"],
             ["router", "--fleet", "f", "--certs", "c"])
    cases = [([*base, "--report", str(tmp_path)], "--report") for base in nodes]
    cases += [([*base, "--ticks", "-1"], "--ticks") for base in nodes[:2]]
    cases += [(["estop", "--fleet", "f", "--timeout", bad], "--timeout") for bad in ("nan", "inf", "-1")]
    for argv, flag in cases:
        with pytest.raises(SystemExit) as done:
            parser.parse_args(argv)
        assert done.value.code == 2 and f"argument {flag}" in capsys.readouterr().err, argv
    assert parser.parse_args([*nodes[0], "--report", str(tmp_path / "r.json"), "--ticks", "0"]).ticks == 0


def test_fleet_sim_names_a_bad_fleet():
    """An empty --fleet surfaced as a traceback from inside the run (a lock-stepped run without a
    limit keeping every tick: tests/deploy/test_fleet_sim.py)."""
    import pytest

    from deploy.fleet_sim import FleetSimConfig
    from deploy.network import TransportConfig
    from sim.scenario import make_scenario

    for bad in ("", "a b"):
        with pytest.raises(ValueError, match=r"fleet name \(--fleet\)"):
            FleetSimConfig(bad, make_scenario("paper-3"), TransportConfig(listen=("tcp/127.0.0.1:7447",)))


def test_the_router_names_a_robot_given_twice():
    import pytest

    from deploy.certs import check_robot_ids

    with pytest.raises(ValueError, match=r"\['r0'\] are given twice"):
        check_robot_ids(["r0", "r1", "r0"])

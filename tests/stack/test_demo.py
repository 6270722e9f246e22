"""`formation demo --quick` end to end: training, transfer, export, fleet-sim + bridge processes
over loopback Zenoh, report files; then `--resume` on the finished folder redoes nothing."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from controllers.mappo import converged_episode, evaluate, load_actor
from deploy.export import TOLERANCE, check_export
from sim.scenario import transport_scenario
from stack.cli import main
from stack.demo.fleet import tracking_noise_floor
from stack.demo.report import FIGURES
from stack.demo.state import STAGES
from tests.stack.conftest import QUICK_BUDGET
from tests.xdist_groups import DEMO

# One worker holds the quick demo (a session fixture) and runs these tests. Not `realtime`: the
# fleet stage runs fleet-sim and bridge lock-stepped, so a busy machine slows it, not its numbers.
pytestmark = DEMO

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _snapshot(out: Path) -> dict[str, tuple[int, int]]:
    """(size, mtime_ns) of every file under ``out``."""
    return {str(p.relative_to(out)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(out.rglob("*")) if p.is_file()}


def test_quick_demo_writes_every_file(quick_run):
    out = quick_run
    for name in ("report.md", "report.html", "metrics.json", "stages.json", "policy.pt",
                 "policy.pt2", "policy.onnx", "policy.golden.npz", "train-3/checkpoint.pt", "train-5/checkpoint.pt",
                 "fleet/sim.json", "fleet/bridge.json", "train-generalist/checkpoint.pt",
                 "generalist/policy.onnx", "generalist/policy.golden.npz", "fleet-unseen/sim.json",
                 "fleet-unseen/bridge.json", *FIGURES.values()):
        assert (out / name).is_file(), name
    book = json.loads((out / "stages.json").read_text())
    assert list(book["stages"]) == list(STAGES)
    assert all(stage["done"] for stage in book["stages"].values())
    assert book["settings"]["quick"] is True


def test_report_embeds_the_figures_it_links(quick_run):
    out = quick_run
    md = (out / "report.md").read_text()
    linked = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert sorted(linked) == sorted(FIGURES.values())
    page = (out / "report.html").read_text()
    uris = re.findall(r'<img [^>]*src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert len(uris) == len(FIGURES)
    assert sorted(base64.b64decode(u) for u in uris) == sorted((out / f).read_bytes() for f in linked)
    assert all(base64.b64decode(u).startswith(PNG_MAGIC) for u in uris)
    assert ".png\"" not in page  # no image is referenced as a file
    m = json.loads((out / "metrics.json").read_text())
    for text in (md, page):       # the report says plainly whether each run converged
        for robots in ("3", "5", "generalist"):
            t = m["train"][robots]
            if t["converged"]:
                assert f"converged at episode {t['converged_episode']}" in text
            else:
                assert f"did not converge within its budget of {t['budget']} episodes" in text.lower()


def test_metrics_are_complete_and_consistent(quick_run):
    out = quick_run
    m = json.loads((out / "metrics.json").read_text())
    assert m["complete"] is True and all(s["done"] for s in m["stages"].values())
    for robots in ("3", "5", "generalist"):
        t = m["train"][robots]
        evals = _jsonl(out / f"train-{robots}" / "eval.jsonl")
        rule = converged_episode([e["episodes"] for e in evals], [e["success_rate"] for e in evals],
                                 t["success_threshold"])
        assert t["converged_episode"] == rule
        assert t["converged"] is (rule is not None)
        assert t["success"] == evals[-1]["success_rate"]
        assert t["budget"] == QUICK_BUDGET and (t["converged"] or t["episodes"] >= QUICK_BUDGET)
        assert t["eval_episodes"] == 16
    assert {r: m["train"][r]["init_from"] for r in ("3", "5", "generalist")} == {
        "3": None, "5": "train-3/checkpoint.pt", "generalist": None}   # only the transfer starts from paper-3
    assert json.loads((out / "train-5" / "result.json").read_text())["transferred_from"].endswith(
        "train-3/checkpoint.pt")
    assert m["zero_shot_3to5"] == m["zero_shot"]["success"]
    assert m["zero_shot"]["episodes"] == 16

    ex = m["export"]
    assert ex["verified"] is True and ex["max_abs_diff"] <= TOLERANCE
    assert ex["policy"] == "policy.onnx" and set(ex["files"]) == {"torchscript", "pt2", "onnx"}
    for name in ex["files"].values():
        assert check_export(out / name).max_abs_diff <= TOLERANCE

    fl = m["fleet"]
    rows = fl["per_episode"]
    sim = json.loads((out / "fleet" / "sim.json").read_text())
    bridge = json.loads((out / "fleet" / "bridge.json").read_text())
    assert fl["episodes"] == 2 == len(rows) == len(sim["episodes"]) == len(bridge["episodes"])
    assert [r["episode"] for r in rows] == [0, 1] and [r["seed"] for r in rows] == [0, 1]
    assert fl["success_rate"] == pytest.approx(np.mean([r["success"] for r in rows]))
    assert fl["final_distance"] == pytest.approx(np.mean([r["final_distance"] for r in rows]))
    assert fl["collisions"] == sum(r["collisions"] for r in rows) == 0   # the safety filter's job
    assert fl["interventions"] == sum(r["interventions"] for r in rows)
    for r, s in zip(rows, sim["episodes"], strict=True):
        assert r["ticks"] == 128 == s["ticks"]
        assert np.asarray(s["positions"]).shape == (129, 5, 2)
        assert np.asarray(s["contacts"]).shape == (128, 5, 3)
        assert 0 <= r["interventions"] <= r["bridge_ticks"]
        if sim["lockstep_timeouts"] == 0 and bridge["robot_counts"] == [[0, 5]]:
            assert r["bridge_ticks"] == 128   # every burst answered once, episodes told apart by seq
    # The MEC keeps the robots on the nominal model: what is left is the measurement noise.
    floor = tracking_noise_floor(fl["model_error"], 0.05, 0.5)
    assert fl["tracking_noise_floor_m"] == pytest.approx(floor)
    assert 0.8 * floor < fl["tracking_error_m"] < 1.5 * floor
    assert fl["tick_ms"]["p50"] <= fl["tick_ms"]["p99"]
    assert fl["round_trip_ms"]["p50"] <= fl["round_trip_ms"]["p99"]
    assert bridge["controller_faults"] == 0 and bridge["estops"] == 0
    assert sim["lossless"] and bridge["lossless"]   # a lock-stepped fleet loses no message


def test_the_generalist_trains_on_three_sizes_and_its_table_and_unseen_fleet_are_real(quick_run):
    out = quick_run
    m = json.loads((out / "metrics.json").read_text())
    config = json.loads((out / "train-generalist" / "config.json").read_text())
    assert config["team_sizes"] == [3, 4, 5] and config["penalty_curriculum"] == 3.0
    assert config["init_from"] is None                      # from scratch, beside paper-3
    table = m["zero_shot_table"]
    assert [r["robots"] for r in table] == list(range(1, 9))
    assert [r["robots"] for r in table if r["trained"]] == [3, 4, 5]
    assert all(r["episodes"] == 16 for r in table)
    # A row is what the checkpoint does on that layout: evaluated again, the same numbers.
    actor = load_actor(out / "train-generalist" / "checkpoint.pt")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)                  # as the demo ran it
    try:
        again = evaluate(actor, transport_scenario(6), episodes=16, seed=3_000_000)
    finally:
        torch.set_num_threads(threads)
    row = table[5]
    assert (row["success"], row["collision_rate"]) == (again.success_rate, again.collision_rate)
    assert row["final_distance"] == pytest.approx(again.final_distance, rel=1e-6)

    ex = m["train"]["generalist"]["export"]
    assert ex["policy"] == "generalist/policy.onnx" and ex["verified"] is True
    assert check_export(out / ex["policy"]).max_abs_diff <= TOLERANCE

    fu = m["fleet_unseen"]
    sim = json.loads((out / "fleet-unseen" / "sim.json").read_text())
    assert fu["scenario"] == "transport-6" and fu["policy"] == "generalist/policy.onnx"
    assert fu["episodes"] == 2 == len(sim["episodes"])
    for s in sim["episodes"]:
        assert np.asarray(s["positions"]).shape == (129, 6, 2)   # six robots, never trained on
    assert fu["collisions"] == 0                                  # the safety filter's job
    assert fu["success_rate"] == pytest.approx(np.mean([r["success"] for r in fu["per_episode"]]))


def test_resume_of_a_finished_run_skips_every_stage(quick_run, capsys):
    before = _snapshot(quick_run)
    assert main(["demo", "--quick", "--out", str(quick_run), "--resume"]) == 0
    printed = capsys.readouterr().out
    assert printed.count("done earlier, skipped") == len(STAGES)
    assert _snapshot(quick_run) == before


def test_a_used_folder_is_refused_without_resume(quick_run, capsys):
    before = _snapshot(quick_run)
    assert main(["demo", "--quick", "--out", str(quick_run)]) == 2
    assert "--resume" in capsys.readouterr().err
    assert _snapshot(quick_run) == before

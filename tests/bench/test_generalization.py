"""bench/generalization.py: the grid's layouts, bad options, and a tiny policy judged on the grid."""

from __future__ import annotations

import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from bench.generalization import LAYOUTS, judge, layout  # noqa: E402


def test_layouts_are_the_transport_task_mirrored_enlarged_and_hexagonal():
    base, mirrored = layout("transport", 4), layout("mirrored", 4)
    np.testing.assert_array_equal(mirrored.starts, base.targets)
    np.testing.assert_array_equal(mirrored.targets, base.starts)
    large = layout("large-object", 4).polygon
    assert np.ptp(large[:, 0]) == pytest.approx(0.24) and np.ptp(large[:, 1]) == pytest.approx(0.36)
    hexagon = layout("hexagon", 4).polygon
    assert len(hexagon) == 6
    np.testing.assert_allclose(np.linalg.norm(hexagon - 0.5, axis=1), 0.15)
    with pytest.raises(ValueError, match="unknown layout"):
        layout("spiral", 3)


def test_an_unknown_layout_option_exits_2_naming_it():
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "generalization.py"), "--layouts", "spiral"],
                          capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 2 and "spiral" in proc.stderr


def test_a_policy_is_judged_on_every_cell_of_the_grid_in_both_worlds(tmp_path):
    from controllers.mappo import MAPPOConfig, train

    small = {"embed_dim": 16, "num_heads": 2, "hidden_sizes": [32]}
    run = train(MAPPOConfig(num_envs=2, total_episodes=2, eval_episodes=2, progress=False,
                            actor=dict(small), critic=dict(small)), tmp_path / "run")
    args = types.SimpleNamespace(layouts=list(LAYOUTS), robots=[1, 3], episodes=2, pymunk_episodes=1)
    rows = judge(run.checkpoint, args)
    cells = {(r["layout"], r["robots"], r["world"]) for r in rows}
    assert cells == {(lay, n, w) for lay in LAYOUTS for n in (1, 3) for w in ("batched", "pymunk")}
    for r in rows:
        assert r["success"] in (0.0, 0.5, 1.0) and r["collisions"] in (0.0, 0.5, 1.0)
        assert r["final_distance_mm"] is None or r["final_distance_mm"] > 0

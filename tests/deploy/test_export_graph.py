"""deploy/export/graph.py: the typed actor's export graph computes the actor's own rows."""

from __future__ import annotations

import pytest
import torch

from controllers.policy import ActorConfig, build_actor
from deploy.export.contract import PolicyContract
from deploy.export.graph import TypedRows, kind_table
from sim.scenario import MAX_ROBOTS


def test_the_kind_table_by_hand():
    table = kind_table(7)
    assert table.shape == (8, 7, 4)
    assert table[7].argmax(1).tolist() == [0, 1, 1, 1, 2, 2, 3]     # 3 robots: self, 3 targets, 2 others, object
    assert table[3].argmax(1).tolist()[:3] == [0, 1, 3] and table[3, 3:].abs().sum() == 0
    assert table[4].abs().sum() == 0 and table[7].sum() == 7          # even T holds no team


@pytest.mark.parametrize("config", [
    ActorConfig(),                                              # the default: formation frame, 2-layer embeddings
    ActorConfig(embed_hidden=0, num_heads=2, hidden_sizes=(64, 32)),
    ActorConfig(frame="world", velocity_damping=0.5, embed_dim=32, num_heads=8),
    ActorConfig(velocity_damping=0.7, hidden_sizes=(32, 16)),  # damping in the turned frame, limit 2
    ActorConfig(token_layers=2),                                # token blocks (moved from the identity below)
], ids=["default", "linear-embedding", "world-frame-damped", "turned-damped-limit2", "token-blocks"])
def test_typed_rows_give_the_actors_rows_for_every_team_and_any_mask(config):
    torch.manual_seed(3)
    actor = build_actor(config, 3, accel_limit=2.0 if config.velocity_damping == 0.7 else 1.0).eval()
    with torch.no_grad():
        for block in actor.mixers:
            block.out.weight.normal_(0.0, 0.2)
            block.feed[2].weight.normal_(0.0, 0.2)
    graph = TypedRows(actor)
    generator = torch.Generator().manual_seed(4)
    for n in (1, 2, 5, 16, MAX_ROBOTS):
        t = 2 * n + 1
        tokens = torch.randn(6, t, 4, generator=generator) * 0.3
        read = torch.rand(6, t, generator=generator) > 0.3
        read[:, 0] = True
        read[0] = True                                          # one row sees everything
        f = torch.where(read.unsqueeze(-1), tokens, torch.zeros(()))
        with torch.no_grad():
            want, got = actor.rows(tokens, read), graph.rows(f, read)
        assert float((got - want).abs().max()) <= 1e-6, n
        assert float(want.abs().max()) > 1e-3                   # the actions are not all ~0


def test_turned_scenes_get_turned_actions_and_non_finite_rows_brake():
    """Through the whole exported contract: a quarter turn of every token (about the arena's
    centre) turns the actions alike, and a read NaN answers its row alone with 0, flagged."""
    torch.manual_seed(5)
    actor = build_actor(ActorConfig(), 3).eval()
    contract = PolicyContract.for_export(actor)
    generator = torch.Generator().manual_seed(6)
    tokens = torch.randn(4, 9, 4, generator=generator) * 0.3
    mask = torch.ones(4, 9, dtype=torch.bool)
    turn = torch.tensor([[0.0, -1.0], [1.0, 0.0]])
    turned = (tokens.view(4, 9, 2, 2) @ turn.t()).view(4, 9, 4)
    with torch.no_grad():
        a, ok = contract(tokens, mask)
        b, _ = contract(turned, mask)
        tokens[2, 4, 1] = float("nan")
        c, ok_nan = contract(tokens, mask)
    assert ok.all() and float((b - a @ turn.t()).abs().max()) <= 1e-6
    assert ok_nan.tolist() == [True, True, False, True]
    assert c[2].tolist() == [0.0, 0.0] and torch.equal(c[[0, 1, 3]], a[[0, 1, 3]])


def test_the_onnx_graph_stays_small():
    """An interpreter pays about 1 us per node at 5 robots: the graph's size is its speed. The
    default actor's file keeps B and T free, gathers nothing by N but its one table row, and has
    no more nodes than at this writing (58, 4 of them the quarter turn's tie rule; the actor's
    own graph: 133)."""

    from deploy.export.formats import onnx_model

    torch.manual_seed(0)
    proto = onnx_model(PolicyContract.for_export(build_actor(ActorConfig(), 3).eval()).eval(), None)
    nodes = [n.op_type for n in proto.graph.node]
    dims = [[d.dim_param for d in i.type.tensor_type.shape.dim[:2]] for i in proto.graph.input]
    assert dims == [["batch", "tokens"], ["batch", "tokens"]]
    assert len(nodes) <= 58, nodes
    assert nodes.count("Shape") == 1 and "Expand" not in nodes

"""bench/_common.py: what every benchmark's JSON document records of the code that made it."""

from __future__ import annotations

import json
import sys

from tests.bench import ROOT

sys.path.insert(0, str(ROOT / "bench"))
import _common  # noqa: E402


def test_a_document_records_the_checkout_it_started_from(monkeypatch, capsys):
    """A long run outlives commits made beside it: the document names the checkout at the start
    (the code that ran) and, when the checkout changed meanwhile, the one at the end beside it."""
    monkeypatch.setattr(_common, "GIT_AT_START", {"commit": "0" * 40, "dirty": False})
    _common.print_json({"x": 1})
    made = json.loads(capsys.readouterr().out)["provenance"]
    assert made["git"] == {"commit": "0" * 40, "dirty": False}
    assert len(made["git_at_end"]["commit"]) == 40 and made["git_at_end"]["commit"] != "0" * 40
    monkeypatch.setattr(_common, "GIT_AT_START", made["git_at_end"])
    _common.print_json({"x": 1})
    again = json.loads(capsys.readouterr().out)["provenance"]
    assert again["git"] == made["git_at_end"] and "git_at_end" not in again

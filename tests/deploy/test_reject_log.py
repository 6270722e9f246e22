"""deploy.reject_log: rejections logged while running, at most once per interval."""

from __future__ import annotations

import logging

import pytest

from deploy.reject_log import RejectLog


def test_new_rejections_are_logged_once_per_interval_with_their_reasons(caplog):
    counts, now = {}, [0.0]
    rl = RejectLog("bridge f", lambda: dict(counts), interval_s=1.0, clock=lambda: now[0])
    caplog.set_level(logging.WARNING, logger="deploy.reject_log")
    assert rl.poll() is None                               # nothing yet
    counts.update(STALE=2)
    now[0] = 0.5
    assert rl.poll() is None                               # too soon
    now[0] = 1.0
    assert rl.poll() == {"STALE": 2}
    counts.update(STALE=3, FROM_FUTURE=1)
    now[0] = 1.5
    assert rl.poll() is None
    now[0] = 2.5
    assert rl.poll() == {"FROM_FUTURE": 1, "STALE": 1}     # only what is new
    now[0] = 9.0
    assert rl.poll() is None                               # nothing new: no line
    assert [r.getMessage() for r in caplog.records] == [
        "bridge f: 2 messages rejected in the last 1.0 s: {'STALE': 2}",
        "bridge f: 2 messages rejected in the last 1.5 s: {'FROM_FUTURE': 1, 'STALE': 1}"]
    with pytest.raises(ValueError, match="interval_s"):
        RejectLog("x", dict, interval_s=0)

"""The bridge's operator channel: ``formation estop --engage|--release|--status`` queries
``formation/<fleet>/ctrl/operator`` (only the operator's certificate may, :mod:`deploy.security`);
:class:`deploy.transport.FleetLink` hands each request to :func:`operator_answer`.

``engage`` latches the fleet e-stop at once (reason :data:`ESTOP_OPERATOR`); ``release`` clears it
only while no live robot is silent past ``estop_after_s`` (the rule that raises it would raise it
again at once), and publishes the clearing ESTOP even if this controller never raised one (the
robots may hold the latch of the controller before a restart); ``status`` reports. Every answer
carries the e-stop state and the live robot silent longest at the bridge's last tick.
"""

from __future__ import annotations

import logging

from deploy.transport import FleetLink

log = logging.getLogger(__name__)

ESTOP_OPERATOR = 2       # reason code of an e-stop an operator engaged (formation estop)


def operator_answer(request: str, link: FleetLink, silence: tuple[str, float] | None,
                    estop_after_s: float) -> dict:
    """Carry out ``request`` (module docstring) on ``link``; ``silence``: (robot, seconds) of the
    live robot silent longest, or None. Returns the JSON-able answer (``ok`` False: refused,
    with a ``reason``)."""
    status = {"estop": "engaged" if link.estop_engaged else "released",
              "silent_robot": None if silence is None else silence[0],
              "silence_s": None if silence is None else round(float(silence[1]), 3)}
    if request == "engage":
        log.warning("operator: raising the fleet e-stop")
        link.raise_estop(ESTOP_OPERATOR)
        return {"ok": True, **status, "estop": "engaged"}
    if request == "release":
        if silence is not None and silence[1] > estop_after_s:
            return {"ok": False, **status, "reason": f"robot {silence[0]} has been silent for "
                    f"{silence[1]:.2f} s (> estop_after_s {estop_after_s} s): bring it "
                    "back or take it off the link first"}
        # published even when this controller never raised one: robots may still hold the latch
        # of a controller before a restart, and leave it only on a newer ESTOP with ENGAGED clear
        log.warning("operator: releasing the fleet e-stop")
        link.clear_estop()
        return {"ok": True, **status, "estop": "released"}
    if request == "status":
        return {"ok": True, **status}
    return {"ok": False, **status, "reason": f"unknown request {request!r}: engage, release or status"}


__all__ = ["ESTOP_OPERATOR", "operator_answer"]

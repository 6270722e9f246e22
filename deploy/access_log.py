"""What a fleet's router refused, counted from Zenoh's log (:mod:`deploy.zenoh_log`).

Two kinds of refusal, as eclipse-zenoh 1.10.2 logs them on the router (read at the source,
``zenoh/src/net/routing/interceptor/access_control.rs`` and
``io/zenoh-links/zenoh-link-tls/src/unicast.rs``, and seen on this machine):

* **denied** (access control, target :data:`ACL_TARGET`, TRACE): a message a node sent and the
  router dropped (``ingress``), or one the router kept from a node (``egress``). Zenoh logs each
  decision as either ``<zid> on <subject> is unauthorized to Put (ingress) on <key>`` (decided
  now; ``<subject>`` carries ``CertCommonName(<cn>)``, the node's identity) or ``Using cached
  result: <zid> is unauthorized to ...`` (decided before: the identity is the one seen with that
  zid). Right after ``ACL (ingress): caching permissions for `<key>` ...`` the same thread
  logs its decision for all nine message kinds in a fixed order: a cache being filled, not
  messages, so those lines are skipped. A node that matches no subject of the access control is
  denied everything without a line unless the decision is cached: those go uncounted.
* **refused links** (TLS listener, target :data:`TLS_TARGET`, WARN): one line per handshake the
  router's listener failed, e.g. ``received fatal alert: DecryptError`` (a client that does not
  trust the router's CA: a self-signed one) or ``received corrupt message of type
  InvalidContentType`` (plain TCP on the TLS port). The line names no peer address.

:class:`AccessLog` counts them; ``snapshot()`` feeds :class:`deploy.reject_log.RejectLog`
(logged while running, at most once a second) and ``report()`` the router's exit report. Every
allowed message is a TRACE line too (``... is authorized to ...``): :meth:`AccessLog.take` drops
those and counts cached denials by their bytes (a few string tests a line), parsing each distinct
line once, when a report is made.
"""

from __future__ import annotations

import re
import threading
from collections import Counter

from deploy.zenoh_log import parse_line, strip_colour

ACL_TARGET = "zenoh::net::routing::interceptor::access_control"
TLS_TARGET = "zenoh_link_tls::unicast"
DIRECTIVES = f"{ACL_TARGET}=trace,{TLS_TARGET}=warn"
"""What Zenoh must log for :class:`AccessLog` (``tracing`` EnvFilter directives)."""

CACHE_ORDER = ("Query", "Reply", "Put", "Delete", "Declare/Undeclare Subscriber",
               "Declare/Undeclare Queryable", "Declare/Undeclare Liveliness Token",
               "Liveliness Query", "Declare Liveliness Subscriber")
"""The message kinds in the order Zenoh fills a key's permission cache."""

_ACL = f" {ACL_TARGET}: ".encode()
_TLS = f" {TLS_TARGET}: ".encode()
_CACHED_PREFIX, _DENIED = b"Using cached result: ", b" is unauthorized to "
_DECIDED = re.compile(r"(?P<zid>[0-9a-f]+) on (?P<subject>\S+) is (?P<verdict>un)?authorized to "
                      r"(?P<kind>.+) \((?P<flow>ingress|egress)\) on (?P<key>\S+)")
_CACHED = re.compile(r"Using cached result: (?P<zid>[0-9a-f]+) is unauthorized to "
                     r"(?P<kind>.+) \((?P<flow>ingress|egress)\) on (?P<key>\S+)")
_CACHING = re.compile(r"ACL \((?:ingress|egress)\): caching permissions for `(?P<key>\S+)` \.\.\.")
_COMMON_NAME = re.compile(r"CertCommonName\(([^)]*)\)")
_HINT = re.compile(r"\.? Hint: .*$")
_NOT_A_REFUSAL = ("Cannot monitor expiration",)   # a TLS warning about a link that stays
_MEMO = 4096   # distinct decision lines parsed and kept


class AccessLog:
    """Counts of denied messages by (flow, identity, kind, key) and of refused links by reason;
    :meth:`take` is a :class:`deploy.zenoh_log.ZenohLogTap` handler. Thread-safe."""

    def __init__(self) -> None:
        self.acl_enabled = threading.Event()   # Zenoh said "Access control is enabled"
        self._decided: Counter[tuple[str, str, str, str]] = Counter()  # (flow, zid, kind, key)
        self._cached: Counter[bytes] = Counter()       # cached denial lines, by their bytes
        self._refused: Counter[str] = Counter()
        self._names: dict[str, str] = {}               # zid -> certificate common name
        self._caching: dict[int, tuple[str, int]] = {}  # thread -> (key, kinds filled)
        self._memo: dict[bytes, re.Match | None] = {}
        self._lock = threading.Lock()

    def take(self, raw: bytes) -> bool:
        """Count one line of Zenoh's log if it is a refusal; True for every line of the two
        targets (they are counted here, not passed through)."""
        raw = strip_colour(raw)
        at = raw.find(_ACL)
        if at < 0:
            if _TLS not in raw:
                return False
            self._take_tls(raw)
            return True
        message = raw[at + len(_ACL):].rstrip()
        if message.startswith(_CACHED_PREFIX):
            if _DENIED in message:
                with self._lock:
                    self._cached[message] += 1
            return True
        with self._lock:
            self._take_acl(raw, message)
        return True

    def _take_tls(self, raw: bytes) -> None:
        line = parse_line(raw)
        if line is not None and line.level in ("WARN", "ERROR") \
                and not line.message.startswith(_NOT_A_REFUSAL):
            with self._lock:
                self._refused[_HINT.sub("", line.message)] += 1

    def _take_acl(self, raw: bytes, message: bytes) -> None:
        """A decision made now, the start of a cache being filled, or the access control on."""
        decided = self._memo.get(message, False)
        if decided is False:
            if len(self._memo) >= _MEMO:
                self._memo.clear()
            decided = self._memo[message] = _DECIDED.fullmatch(message.decode("utf-8", "replace"))
        if decided is None:
            text = message.decode("utf-8", "replace")
            caching = _CACHING.fullmatch(text)
            if caching:
                self._caching[_thread(raw)] = (caching["key"], 0)
            elif text == "Access control is enabled":
                self.acl_enabled.set()
            return
        cn = _COMMON_NAME.search(decided["subject"])
        if cn:
            self._names[decided["zid"]] = cn[1]
        if self._caching and self._filling_cache(_thread(raw), decided["key"], decided["kind"]):
            return
        if decided["verdict"]:
            self._decided[(decided["flow"], decided["zid"], decided["kind"], decided["key"])] += 1

    def _filling_cache(self, thread: int, key: str, kind: str) -> bool:
        """Whether a decision line belongs to the cache this thread is filling: same key, kinds
        in :data:`CACHE_ORDER` (several subjects may repeat a kind)."""
        state = self._caching.get(thread)
        if state is None:
            return False
        index = CACHE_ORDER.index(kind) if kind in CACHE_ORDER else -1
        if state[0] != key or index < state[1]:
            del self._caching[thread]
            return False
        self._caching[thread] = (key, index)
        return True

    def _totals(self) -> tuple[Counter[tuple[str, str, str, str]], Counter[str]]:
        """(flow, identity, kind, key) -> n, reason -> n; call with the lock held."""
        out: Counter[tuple[str, str, str, str]] = Counter()
        for (flow, zid, kind, key), n in self._decided.items():
            out[(flow, self._names.get(zid, f"zid {zid}"), kind, key)] += n
        for message, n in self._cached.items():
            m = _CACHED.fullmatch(message.decode("utf-8", "replace"))
            if m:
                out[(m["flow"], self._names.get(m["zid"], f"zid {m['zid']}"), m["kind"], m["key"])] += n
        return out, Counter(self._refused)

    def snapshot(self) -> dict[str, int]:
        """Counts as ``{"denied <identity>: <kind> <key>": n, "refused link: <reason>": n}``,
        ingress denials and refused links only (egress withholds what a node never sent)."""
        with self._lock:
            denied, refused = self._totals()
        out = {f"denied {who}: {kind} {key}": n
               for (flow, who, kind, key), n in sorted(denied.items()) if flow == "ingress"}
        out.update((f"refused link: {reason}", n) for reason, n in sorted(refused.items()))
        return out

    def report(self) -> dict:
        """JSON-able totals: ``denied`` (ingress) and ``withheld`` (egress) as
        ``{identity: {"<kind> <key>": n}}``, ``refused_links`` as ``{reason: n}``."""
        with self._lock:
            denied, refused = self._totals()
        flows: dict[str, dict[str, dict[str, int]]] = {"ingress": {}, "egress": {}}
        for (flow, who, kind, key), n in sorted(denied.items()):
            flows[flow].setdefault(who, {})[f"{kind} {key}"] = n
        return {"denied": flows["ingress"], "withheld": flows["egress"],
                "refused_links": dict(sorted(refused.items()))}


def _thread(raw: bytes) -> int:
    """The ``ThreadId(<n>)`` of a log line (-1 if it has none)."""
    at = raw.find(b"ThreadId(")
    end = raw.find(b")", at)
    return int(raw[at + 9:end]) if at >= 0 and end > at else -1


__all__ = ["ACL_TARGET", "AccessLog", "CACHE_ORDER", "DIRECTIVES", "TLS_TARGET"]

"""Zenoh sessions for zenrl processes: the only module of zenrl that imports ``zenoh`` (roles
reach the network through :class:`Node`; tests/unit/test_boundaries.py keeps it so).

Facts about Zenoh 1.x this module is built on:

* every zenrl process is a ``client`` of one router (a Python process can itself be the router:
  :func:`open_router`); multicast scouting is off and endpoints are explicit;
* a plain Python callback (:meth:`Node.subscribe`) runs on a Python thread that Zenoh feeds
  through an *unbounded* channel: a callback slower than its senders lets that channel grow
  without limit. A receiver of bulk data pulls instead (:meth:`Node.inbox`): a bounded FIFO that
  Zenoh's receive thread fills without the GIL and that blocks it when full, so back-pressure
  reaches the senders;
* data that must arrive is put with ``CongestionControl.BLOCK`` (the default DROP loses data);
  receivers must never stall for 5 s or the sender's link is closed, so receivers here either do
  cheap work in the callback or hand off to a bounded queue with a counted drop policy;
* large messages are refused before sending (:mod:`zenrl.common.protocol` caps sizes);
* sessions are closed explicitly (:class:`Node` is a context manager; SIGTERM sets a stop event
  so that the ``finally`` runs); never fork after ``zenoh.open()``: child processes use ``spawn``.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from typing import Any, Callable, Iterable

import zenoh

from zenrl.common import signals
from zenrl.common.errors import RemoteTimeout, TransportError

log = logging.getLogger(__name__)

#: Environment variable naming the router endpoint clients connect to.
ROUTER_ENV = "ZENRL_ROUTER"
DEFAULT_ROUTER = "tcp/127.0.0.1:7447"

_log_inited = False


def init_zenoh_logging(level: str = "warn") -> None:
    """Turn on Zenoh's own log (once per process). Without it, a link closed by the BLOCK fuse
    or a dropped message is silent. ``RUST_LOG`` overrides ``level``."""
    global _log_inited
    if not _log_inited:
        zenoh.init_log_from_env_or(level)
        _log_inited = True


#: What Zenoh's receive cap allows above twice ``transport.max_message_bytes`` (headers).
RX_HEADROOM_BYTES = 64 * 1024


def router_endpoint(explicit: str | None = None) -> str:
    """The router endpoint: ``explicit`` if given, else ``$ZENRL_ROUTER``, else the default."""
    return explicit or os.environ.get(ROUTER_ENV) or DEFAULT_ROUTER


def _config(doc: dict[str, Any]) -> zenoh.Config:
    return zenoh.Config.from_json5(json.dumps(doc))


def client_config(endpoint: str, connect_timeout_s: float = 30.0,
                  extra: dict[str, Any] | None = None, config_file: str | None = None) -> zenoh.Config:
    """Client-mode config: connect to ``endpoint`` only, no scouting, wait up to
    ``connect_timeout_s`` for the router to come up (0 fails at once). ``config_file`` (JSON5,
    e.g. TLS root CA and user/password for a secured router) is the base these go on top of."""
    settings: dict[str, Any] = {
        "mode": "client",
        "connect/endpoints": [endpoint],
        "connect/timeout_ms": int(connect_timeout_s * 1000),
        "scouting/multicast/enabled": False,
    }
    if config_file is None:
        doc: dict[str, Any] = {}
        for k, v in settings.items():
            _merge(doc, _nest(k, v))
        _merge(doc, extra or {})
        return _config(doc)
    try:
        cfg = zenoh.Config.from_file(config_file)
    except zenoh.ZError as e:
        raise TransportError(f"client config {config_file!r} is invalid: {e}") from e
    for k, v in settings.items():
        cfg.insert_json5(k, json.dumps(v))
    for k, v in _paths(extra or {}):
        cfg.insert_json5(k, json.dumps(v))
    return cfg


def _paths(tree: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """``{"a": {"b": 1}}`` -> ``[("a/b", 1)]`` (leaves only)."""
    out: list[tuple[str, Any]] = []
    for k, v in tree.items():
        path = f"{prefix}/{k}" if prefix else k
        if isinstance(v, dict) and v:
            out.extend(_paths(v, path))
        else:
            out.append((path, v))
    return out


def _nest(path: str, value: Any) -> dict[str, Any]:
    parts = path.split("/")
    out: dict[str, Any] = {parts[-1]: value}
    for p in reversed(parts[:-1]):
        out = {p: out}
    return out


def router_config(listen: Iterable[str], extra: dict[str, Any] | None = None,
                  connect: Iterable[str] = ()) -> zenoh.Config:
    """Router-mode config listening on ``listen``. ``connect``: other routers to link to (a host
    router names the central one), so that clients of either reach every other client."""
    doc: dict[str, Any] = {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}},
    }
    if connect:
        doc["connect"] = {"endpoints": list(connect)}
    _merge(doc, extra or {})
    return _config(doc)


def _merge(dst: dict[str, Any], src: dict[str, Any]) -> None:
    for k, v in src.items():
        if isinstance(v, dict) and isinstance(dst.get(k), dict):
            _merge(dst[k], v)
        else:
            dst[k] = v


def open_router(listen: Iterable[str] = (DEFAULT_ROUTER,), config_file: str | None = None,
                connect: Iterable[str] = (), replace_listen: bool = False) -> zenoh.Session:
    """Open an in-process Zenoh router (for ``zenrl run``, ``zenrl router`` and tests).

    With ``config_file`` the router is configured from that JSON5 file (e.g.
    ``deploy/zenoh/router.json5``) and ``listen`` is ignored unless ``replace_listen``.
    ``connect`` (if not empty) names other routers to link to: a host router names the central
    one. A router retries its ``connect`` endpoints by itself, so a host router may start before
    the router it links to, and relinks when that one restarts."""
    init_zenoh_logging()
    listen, connect = list(listen), list(connect)
    if config_file:
        try:
            cfg = zenoh.Config.from_file(config_file)
            if replace_listen:
                cfg.insert_json5("listen/endpoints", json.dumps(listen))
            if connect:
                cfg.insert_json5("connect/endpoints", json.dumps(connect))
        except zenoh.ZError as e:
            raise TransportError(f"router config {config_file!r} is invalid: {e}") from e
    else:
        cfg = router_config(listen, connect=connect)
    try:
        return zenoh.open(cfg)
    except zenoh.ZError as e:
        where = config_file if config_file and not replace_listen else listen
        raise TransportError(f"could not start a Zenoh router on {where} (connect: {connect or 'none'}): {e}") from e


def open_session(endpoint: str | None = None, connect_timeout_s: float = 30.0,
                 extra: dict[str, Any] | None = None, config_file: str | None = None) -> zenoh.Session:
    """Open a client session to the router (see :func:`router_endpoint`)."""
    init_zenoh_logging()
    ep = router_endpoint(endpoint)
    cfg = client_config(ep, connect_timeout_s, extra, config_file)
    # zenoh.open waits for the router (up to connect_timeout_s) in native code; it runs on a
    # thread of its own so that a stop signal meanwhile (Ctrl-C on a mistyped --router, a
    # container stopped while its router is down) ends the wait at once
    done = threading.Event()
    lock = threading.Lock()
    box: dict[str, Any] = {}

    def opener() -> None:
        try:
            s = zenoh.open(cfg)
        except BaseException as e:  # noqa: BLE001 - handed to the waiting thread
            box["error"] = e
            done.set()
            return
        with lock:
            late = box.get("abandoned", False)
            if not late:
                box["session"] = s
        if late:  # nobody waits for it any more: close it, never leave a session open
            s.close()
        done.set()

    threading.Thread(target=opener, name="zenoh-open", daemon=True).start()
    while not done.wait(0.1):
        if signals.stopping.is_set():
            with lock:
                if "session" not in box:
                    box["abandoned"] = True
                    raise TransportError(f"stopped while waiting for the Zenoh router at {ep}")
    if "session" in box:
        return box["session"]
    e = box.get("error")
    if isinstance(e, zenoh.ZError):
        raise TransportError(f"could not connect to the Zenoh router at {ep}: {e}") from e
    raise e if e is not None else TransportError(f"could not connect to the Zenoh router at {ep}")


def config_section(path: str, key: str) -> Any:
    """One section of the Zenoh JSON5 config file ``path`` as plain data, e.g.
    ``config_section(f, "transport/auth/usrpwd")`` -> ``{"user": ..., "password": ...,
    "dictionary_file": ...}`` (``None`` values where unset). Raises :class:`TransportError`
    naming the file when it cannot be read."""
    try:
        return json.loads(zenoh.Config.from_file(path).get_json(key))
    except zenoh.ZError as e:
        raise TransportError(f"Zenoh config {path!r} is invalid: {e}") from e


def write_config(template: str, out: str, sections: dict[str, Any]) -> None:
    """Write the Zenoh config file ``template`` with ``sections`` (``{"path/in/config": value}``)
    replaced to ``out``, as JSON (every setting spelled out; comments are not kept). The Zenoh
    id is left unset, so that every router started from ``out`` draws its own."""
    try:
        cfg = zenoh.Config.from_file(template)
        for k, v in sections.items():
            cfg.insert_json5(k, json.dumps(v))
        doc = json.loads(str(cfg))
    except zenoh.ZError as e:
        raise TransportError(f"Zenoh config {template!r}: {e}") from e
    doc.pop("id", None)
    with open(out, "w") as f:
        json.dump(doc, f, indent=1)


class Node:
    """One process's Zenoh session plus the entities it declared; closes them all on exit.

    Usage::

        with Node(endpoint) as node:
            pub = node.publisher(keys.transitions("a0"))
            node.subscribe(keys.weights, on_weights)
            ...

    Every data publisher uses ``BLOCK`` congestion control; ``low_priority=True`` puts it at
    ``DATA_LOW`` so that large weight messages do not delay small queries on the same link.
    """

    def __init__(self, endpoint: str | None = None, connect_timeout_s: float = 30.0,
                 session: zenoh.Session | None = None, extra: dict[str, Any] | None = None,
                 config_file: str | None = None) -> None:
        self.session = session if session is not None else open_session(endpoint, connect_timeout_s, extra, config_file)
        self._entities: list[Any] = []
        self._closed = False
        self._published = False
        #: pause before closing a session that published (queued messages leave first)
        self.close_linger_s = 0.0

    @classmethod
    def from_config(cls, tcfg: Any, max_rx_bytes: int | None = None) -> "Node":
        """A node for a :class:`~zenrl.common.config.TransportConfig`; ``max_rx_bytes``: the
        largest message this node takes (default ``tcfg.max_message_bytes``), for a role whose
        inputs are bounded tighter than what it sends (the replay: chunks vs sample replies)."""
        # Zenoh's own receive cap (1 GiB by default) at twice zenrl's message cap: a larger message
        # is dropped (by Zenoh, uncounted) as its fragments arrive, not reassembled and copied in
        # full before decoding refuses it (a peer could otherwise cost a receiver 2 GiB a message);
        # one up to twice the cap still reaches zenrl, which refuses and counts it
        rx = {"max_message_size": 2 * int(max_rx_bytes or tcfg.max_message_bytes) + RX_HEADROOM_BYTES}
        node = cls(tcfg.router, tcfg.connect_timeout_s, config_file=tcfg.client_config,
                   extra={"transport": {"shared_memory": {"enabled": bool(tcfg.shared_memory)}, "link": {"rx": rx}}})
        node.close_linger_s = tcfg.close_linger_s
        return node

    # -- context management ---------------------------------------------------------------
    def __enter__(self) -> "Node":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._published and self.close_linger_s > 0:
            time.sleep(self.close_linger_s)
        for e in reversed(self._entities):
            try:
                e.undeclare()
            except zenoh.ZError as err:  # session may already be gone (router down)
                log.debug("undeclare failed: %s", err)
        self._entities.clear()
        self.session.close()

    # -- declarations ---------------------------------------------------------------------
    def publisher(self, key: str, low_priority: bool = False, express: bool = False) -> zenoh.Publisher:
        pub = self.session.declare_publisher(
            key,
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.DATA_LOW if low_priority else zenoh.Priority.DATA,
            express=express,
        )
        self._entities.append(pub)
        self._published = True
        return pub

    def put(self, key: str, payload: bytes, low_priority: bool = False) -> None:
        """One-off put with BLOCK congestion control."""
        self._published = True
        self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK,
                         priority=zenoh.Priority.DATA_LOW if low_priority else zenoh.Priority.DATA)

    def subscribe(self, key: str, callback: Callable[[str, bytes], None]) -> zenoh.Subscriber:
        """Call ``callback(key, payload_bytes)`` for each sample, on Zenoh's thread for this
        subscriber (calls are serialized). The callback must return quickly and must not raise;
        exceptions are logged and swallowed so that one bad message stops nothing."""

        def handler(sample: zenoh.Sample) -> None:
            try:
                callback(str(sample.key_expr), sample.payload.to_bytes())
            except Exception:  # a handler bug must not kill Zenoh's delivery thread
                log.exception("subscriber callback on %s failed", key)

        sub = self.session.declare_subscriber(key, handler)
        self._entities.append(sub)
        return sub

    def inbox(self, key: str, capacity: int) -> "Inbox":
        """Receive ``key``'s samples into a bounded FIFO of ``capacity`` that the caller pulls from
        (:class:`Inbox`): no Python thread per subscriber and no GIL taken by Zenoh's receive
        thread, which waits while the FIFO is full (back-pressure to the senders). The caller must
        keep pulling (or drop what it cannot take, :meth:`Inbox.get_nowait`): a receive thread
        blocked for 5 s makes the sending side close the link. :meth:`withdraw` (or closing the
        node) closes the inbox; a blocked :meth:`Inbox.get` then returns None."""
        sub = self.session.declare_subscriber(key, zenoh.handlers.FifoChannel(max(1, int(capacity))))
        self._entities.append(sub)
        return Inbox(sub)

    def subscribe_latest(self, key: str) -> "LatestValue":
        """Keep only the newest payload on ``key`` (never blocks the sender)."""
        lv = LatestValue()
        self.subscribe(key, lv.set)
        return lv

    def queryable(self, key: str, handler: Callable[[bytes], bytes | None]) -> zenoh.Queryable:
        """Answer queries on ``key``: ``handler(request_payload) -> reply_payload`` (``None``
        sends no reply). The query is always finished, so callers never wait for a timeout."""

        def on_query(query: zenoh.Query) -> None:
            with query:
                try:
                    req = query.payload.to_bytes() if query.payload is not None else b""
                    rep = handler(req)
                    if rep is not None:
                        query.reply(query.key_expr, rep)
                except Exception:  # one bad query must not stop the service
                    log.exception("queryable %s failed", key)

        q = self.session.declare_queryable(key, on_query)
        self._entities.append(q)
        return q

    def query(self, key: str, payload: bytes | None = None, timeout_s: float = 5.0) -> bytes:
        """Send one query and return the first OK reply's payload; raise
        :class:`RemoteTimeout` if none arrives within ``timeout_s``."""
        replies = self.session.get(key, payload=payload, timeout=timeout_s)
        for reply in replies:
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
            log.warning("error reply on %s: %s", key, reply.err.payload.to_string() if reply.err else "?")
        raise RemoteTimeout(f"no reply on {key} within {timeout_s} s")

    def query_async(self, key: str, payload: bytes | None, timeout_s: float,
                    on_reply: Callable[[bytes | None], None]) -> None:
        """Send a query without waiting; ``on_reply(payload)`` is called once with the first OK
        reply, or with ``None`` if there was none before the timeout."""
        done = threading.Event()

        def cb(reply: zenoh.Reply) -> None:
            if reply.ok is not None and not done.is_set():
                done.set()
                on_reply(reply.ok.payload.to_bytes())

        def on_drop() -> None:  # called when the query is finalised (all replies or timeout)
            if not done.is_set():
                done.set()
                on_reply(None)

        # indirect=False: run the callbacks on the Zenoh thread that has the reply. The default
        # (indirect=True) starts a Python thread per handler, i.e. per query: ~270 thread starts
        # a second in a CartPole learner. Callbacks here must be short and never block.
        self.session.get(key, zenoh.handlers.Callback(cb, on_drop, indirect=False), payload=payload, timeout=timeout_s)

    def token(self, key: str) -> Any:
        """Declare a liveliness token (undeclared on close, or by :meth:`withdraw`). Raises
        :class:`TransportError` when the session cannot declare it (e.g. it is closed)."""
        try:
            tok = self.session.liveliness().declare_token(key)
        except zenoh.ZError as e:
            raise TransportError(f"could not declare the liveliness token {key}: {e}") from e
        self._entities.append(tok)
        return tok

    def withdraw(self, entity: Any) -> bool:
        """Undeclare a token (or subscriber, queryable) declared through this node, now. Never
        raises: when the session is already gone (router down, closing) the failure is logged
        and False returned, so that a caller that is stopping goes on stopping."""
        if entity in self._entities:
            self._entities.remove(entity)
        try:
            entity.undeclare()
        except zenoh.ZError as e:
            log.debug("undeclare failed: %s", e)
            return False
        return True

    def alive_now(self, key: str, timeout_s: float = 2.0) -> list[str]:
        """Keys of the liveliness tokens alive now that match ``key``."""
        return [str(r.ok.key_expr) for r in self.session.liveliness().get(key, timeout=timeout_s) if r.ok is not None]


class Received:
    """One sample taken from an :class:`Inbox`: its ``key``, its size ``nbytes``, and
    :meth:`data`, its payload copied out of Zenoh's buffers (a sample dropped unread is never
    copied)."""

    __slots__ = ("key", "_payload")

    def __init__(self, key: str, payload: Any) -> None:
        self.key = key
        self._payload = payload

    @property
    def nbytes(self) -> int:
        return len(self._payload)

    def data(self) -> bytes:
        return self._payload.to_bytes()


class Inbox:
    """A subscription's samples in a bounded FIFO, pulled by the owner's thread (see
    :meth:`Node.inbox`). ``subscription`` is what :meth:`Node.withdraw` takes."""

    def __init__(self, subscription: Any) -> None:
        self.subscription = subscription
        self._handler = subscription.handler

    def get(self) -> Received | None:
        """The next sample, waiting for one with the GIL released; None once the inbox is closed
        (withdrawn, or its session closed) and empty."""
        try:
            s = self._handler.recv()
        except zenoh.ZError:  # "channel is empty and closed"
            return None
        return Received(str(s.key_expr), s.payload)

    def get_nowait(self) -> Received | None:
        """The next sample if one is queued, else None (also when closed)."""
        try:
            s = self._handler.try_recv()
        except zenoh.ZError:
            return None
        return None if s is None else Received(str(s.key_expr), s.payload)


class LatestValue:
    """A thread-safe slot holding the newest payload (a RingChannel of one, for callbacks)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._value: bytes | None = None
        self._count = 0
        self._event = threading.Event()

    def set(self, key: str, payload: bytes) -> None:
        with self._lock:
            self._value = payload
            self._count += 1
        self._event.set()

    def take(self) -> bytes | None:
        """Return the newest payload not yet taken, or ``None``."""
        with self._lock:
            v, self._value = self._value, None
            self._event.clear()
            return v

    def wait(self, timeout_s: float) -> bytes | None:
        self._event.wait(timeout_s)
        return self.take()

    @property
    def received(self) -> int:
        return self._count

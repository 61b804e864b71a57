"""The secured router of the cluster (deploy/zenoh/router-secure.json5), run in-process with
certificates from deploy/zenoh/gen-certs.sh and the role client configs
(deploy/zenoh/client-<role>.json5): TLS and user/password keep unknown clients out, and the
access control keeps an actor from publishing weights or priorities, or from answering the
learner's sample queries, while the traffic each role needs still flows."""

from __future__ import annotations

import json
import shutil
import subprocess
import threading
from pathlib import Path

import pytest

from tests.conftest import ROOT, free_port, wait_until

pytestmark = pytest.mark.integration

ZENOH_DIR = ROOT / "deploy" / "zenoh"


def gen_certs(out: Path) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed (needed by deploy/zenoh/gen-certs.sh)")
    subprocess.run(["bash", str(ZENOH_DIR / "gen-certs.sh"), str(out)], check=True, capture_output=True, timeout=60)
    return out


def secure_router_config(endpoint: str, certs: Path, users: Path = ZENOH_DIR / "users.txt"):
    """router-secure.json5 with the container paths and the listen port replaced, and no plugins
    (an in-process router cannot load the REST plugin zenohd uses for its health check)."""
    import zenoh

    cfg = zenoh.Config.from_file(str(ZENOH_DIR / "router-secure.json5"))
    cfg.insert_json5("listen/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("transport/link/tls/listen_private_key", json.dumps(str(certs / "router-key.pem")))
    cfg.insert_json5("transport/link/tls/listen_certificate", json.dumps(str(certs / "router.pem")))
    cfg.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users)))
    cfg.insert_json5("plugins", "{}")
    return cfg


def client_config_file(role: str, certs: Path | None, out_dir: Path, password: str | None = None,
                       drop_auth: bool = False) -> Path:
    """deploy/zenoh/client-<role>.json5 with the CA path mapped to ``certs`` (``None``: no CA of
    ours, i.e. the system's roots), written to ``out_dir`` for ``transport.client_config``."""
    import zenoh

    src = zenoh.Config.from_file(str(ZENOH_DIR / f"client-{role}.json5"))
    transport = json.loads(src.get_json("transport"))
    transport["link"]["tls"]["root_ca_certificate"] = None if certs is None else str(certs / "ca.pem")
    if password is not None:
        transport["auth"]["usrpwd"]["password"] = password
    if drop_auth:
        transport["auth"]["usrpwd"] = {"user": None, "password": None, "dictionary_file": None}
    name = f"client-{role}{'-badpw' if password else ''}{'-noauth' if drop_auth else ''}{'-noca' if certs is None else ''}.json"
    path = out_dir / name
    path.write_text(json.dumps({"transport": transport}))
    return path


@pytest.fixture
def secure_router(tmp_path):
    """The secured router in this process on a free TLS port: yields (endpoint, certs dir)."""
    import zenoh

    from zenrl.common.transport import init_zenoh_logging

    init_zenoh_logging("error")  # refused handshakes are logged as errors by design
    certs = gen_certs(tmp_path / "certs")
    ep = f"tls/127.0.0.1:{free_port()}"
    session = zenoh.open(secure_router_config(ep, certs))
    yield ep, certs
    session.close()


class Inbox:
    """Collects (key suffix, payload) of every sample a subscriber gets."""

    def __init__(self) -> None:
        self.items: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()

    def __call__(self, key: str, payload: bytes) -> None:
        with self._lock:
            self.items.append((key.split("/", 2)[2], payload))

    def has(self, key: str, payload: bytes | None = None) -> bool:
        with self._lock:
            return any(k == key and (payload is None or p == payload) for k, p in self.items)

    def payloads(self, key: str) -> list[bytes]:
        with self._lock:
            return [p for k, p in self.items if k == key]


def test_wrong_password_no_credentials_or_untrusted_ca_cannot_connect(secure_router, tmp_path):
    from zenrl.common.errors import TransportError
    from zenrl.common.transport import Node

    ep, certs = secure_router
    for cfg in (client_config_file("actor", certs, tmp_path, password="not-the-password"),
                client_config_file("actor", certs, tmp_path, drop_auth=True),
                client_config_file("actor", None, tmp_path)):
        with pytest.raises(TransportError):
            Node(ep, connect_timeout_s=0.0, config_file=str(cfg)).close()
    # the right credentials do connect (so the failures above are about the credentials)
    Node(ep, connect_timeout_s=0.0, config_file=str(client_config_file("actor", certs, tmp_path))).close()


def test_acl_actor_cannot_publish_weights_or_priorities_but_its_data_flows(secure_router, tmp_path):
    from zenrl.common.protocol import Keys
    from zenrl.common.transport import Node

    ep, certs = secure_router
    k = Keys("acl-test")

    def node(role: str) -> Node:
        return Node(ep, connect_timeout_s=5.0, config_file=str(client_config_file(role, certs, tmp_path)))

    replay, learner, actor, other_actor, evaluator, monitor = (
        node(r) for r in ("replay", "learner", "actor", "actor", "evaluator", "monitor"))
    try:
        at_learner, at_actor, at_replay, at_evaluator = Inbox(), Inbox(), Inbox(), Inbox()
        for n, inbox in ((learner, at_learner), (other_actor, at_actor), (evaluator, at_evaluator)):
            n.subscribe(k.weights, inbox)
            n.subscribe(k.stats_all, inbox)
        replay.subscribe(k.transitions_all, at_replay)
        replay.subscribe(k.priorities, at_replay)
        replay.subscribe(k.episodes_all, at_replay)
        # a replay that answers sample queries, and an actor trying to answer them as well
        replay.queryable(k.sample, lambda _req: b"from-replay")
        actor.queryable(k.sample, lambda _req: b"from-actor")
        learner.queryable(k.weights_query, lambda _req: b"weights-from-learner")

        # the learner's weights reach the actors and the evaluator (declarations are in place)
        n_sent = [0]

        def learner_weights_arrived() -> bool:
            n_sent[0] += 1
            learner.put(k.weights, b"real")
            return at_actor.has("weights", b"real") and at_evaluator.has("weights", b"real")

        wait_until(learner_weights_arrived, 10, "the learner's weights at an actor and the evaluator", 0.2)
        assert at_learner.payloads("weights") == [b"real"] * len(at_learner.payloads("weights"))

        # the actor's stats reach the learner and the other actor (the sentinel used below)
        stats_key = k.stats("actor", "a1")

        def stats_arrived() -> bool:
            actor.put(stats_key, b"warm-up")
            return at_learner.has("stats/actor/a1") and at_actor.has("stats/actor/a1")

        wait_until(stats_arrived, 10, "the actor's stats at the learner and the other actor", 0.2)

        # publishers see who subscribes (the actor's replay client holds chunks while no replay
        # matches), also through wildcard subscriptions (the monitor's stats/**)
        tx = actor.publisher(k.transitions("a1"))
        wait_until(lambda: tx.matching_status.matching, 10, "the replay's subscription seen by the actor")
        at_monitor = Inbox()
        monitor.subscribe(k.stats_all, at_monitor)
        learner_stats = learner.publisher(k.stats("learner", "learner"))
        wait_until(lambda: learner_stats.put(b"learner-stats") or at_monitor.has("stats/learner/learner"), 10,
                   "the learner's stats (declared publisher) at the monitor (wildcard subscriber)", 0.2)

        # forged weights and priorities, then (same session, same priority, so in order on the
        # same link) messages the actor may send: once those arrived, the forged ones would have
        actor.put(k.weights, b"forged")
        actor.put(k.priorities, b"forged")
        actor.put(k.stats("learner", "learner"), b"forged")  # nor may it speak as the learner
        actor.put(k.transitions("a1"), b"transitions")
        actor.put(k.episodes("a1"), b"episodes")
        actor.put(stats_key, b"sentinel")
        wait_until(lambda: at_learner.has("stats/actor/a1", b"sentinel") and at_actor.has("stats/actor/a1", b"sentinel"),
                   10, "the actor's sentinel stats")
        wait_until(lambda: at_replay.has("transitions/a1", b"transitions") and at_replay.has("episodes/a1", b"episodes"),
                   10, "the actor's transitions and episodes at the replay")
        assert b"forged" not in at_learner.payloads("weights")
        assert b"forged" not in at_actor.payloads("weights")
        assert b"forged" not in at_evaluator.payloads("weights")
        assert not at_replay.payloads("replay/priorities"), "an actor's priority update reached the replay"
        assert b"forged" not in at_learner.payloads("stats/learner/learner"), "an actor published as the learner"
        assert b"forged" not in at_monitor.payloads("stats/learner/learner"), "an actor published as the learner"

        # the learner's priorities do reach the replay
        wait_until(lambda: learner.put(k.priorities, b"priorities") or at_replay.has("replay/priorities", b"priorities"),
                   10, "the learner's priorities at the replay", 0.2)

        # sample queries are answered by the replay only; actors cannot sample; weights queries work
        import zenoh

        def answers(n: Node, key: str) -> list[bytes]:
            replies = n.session.get(key, timeout=3.0, consolidation=zenoh.ConsolidationMode.NONE)
            return sorted(r.ok.payload.to_bytes() for r in replies if r.ok is not None)

        assert answers(learner, k.sample) == [b"from-replay"]
        assert answers(other_actor, k.sample) == []
        assert answers(other_actor, k.weights_query) == [b"weights-from-learner"]

        # an actor may hold its own liveliness token but not one of another role
        actor.token(k.alive("actor", "a1"))
        actor.token(k.alive("learner", "fake"))
        learner.token(k.alive("learner", "learner"))
        wait_until(lambda: set(replay.alive_now(k.alive_all, 1.0)) >= {k.alive("actor", "a1"), k.alive("learner", "learner")},
                   10, "the liveliness tokens")
        assert k.alive("learner", "fake") not in replay.alive_now(k.alive_all, 1.0)
    finally:
        for n in (replay, learner, actor, other_actor, evaluator, monitor):
            n.close()

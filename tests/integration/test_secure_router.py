"""The secured router of the cluster (deploy/zenoh/router-secure.json5), run in-process with
certificates from deploy/zenoh/gen-certs.sh and the client configs (deploy/zenoh/client-<role>.json5,
client-actor-<i>.json5): TLS and user/password keep unknown clients out; the access control
keeps an actor from publishing weights or priorities, or from answering the learner's sample
queries, and binds each actor login to its own keys and exploration slot (it can neither
publish as another actor nor hold another's slot), while the traffic each role needs flows.
The same holds for a credential set written by `zenrl credentials` (fresh passwords)."""

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


def secure_router_config(endpoint: str, certs: Path, users: Path = ZENOH_DIR / "users.txt",
                         src: Path = ZENOH_DIR / "router-secure.json5"):
    """router-secure.json5 (or ``src``) with the container paths and the listen port replaced,
    and no plugins (an in-process router cannot load the REST plugin zenohd uses for its health
    check)."""
    import zenoh

    cfg = zenoh.Config.from_file(str(src))
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
    for cfg in (client_config_file("actor-0", certs, tmp_path, password="not-the-password"),
                client_config_file("actor-0", certs, tmp_path, drop_auth=True),
                client_config_file("actor-0", None, tmp_path)):
        with pytest.raises(TransportError):
            Node(ep, connect_timeout_s=0.0, config_file=str(cfg)).close()
    # the right credentials do connect (so the failures above are about the credentials)
    Node(ep, connect_timeout_s=0.0, config_file=str(client_config_file("actor-0", certs, tmp_path))).close()


def test_acl_actor_cannot_publish_weights_or_priorities_but_its_data_flows(secure_router, tmp_path):
    from zenrl.common.protocol import Keys
    from zenrl.common.transport import Node

    ep, certs = secure_router
    k = Keys("acl-test")

    def node(role: str) -> Node:
        return Node(ep, connect_timeout_s=5.0, config_file=str(client_config_file(role, certs, tmp_path)))

    replay, learner, actor, other_actor, evaluator, monitor = (
        node(r) for r in ("replay", "learner", "actor-0", "actor-1", "evaluator", "monitor"))
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
        stats_key = k.stats("actor", "actor-0")

        def stats_arrived() -> bool:
            actor.put(stats_key, b"warm-up")
            return at_learner.has("stats/actor/actor-0") and at_actor.has("stats/actor/actor-0")

        wait_until(stats_arrived, 10, "the actor's stats at the learner and the other actor", 0.2)

        # publishers see who subscribes (the actor's replay client holds chunks while no replay
        # matches), also through wildcard subscriptions (the monitor's stats/**)
        tx = actor.publisher(k.transitions("actor-0"))
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
        actor.put(k.transitions("actor-0"), b"transitions")
        actor.put(k.episodes("actor-0"), b"episodes")
        actor.put(stats_key, b"sentinel")
        wait_until(lambda: at_learner.has("stats/actor/actor-0", b"sentinel") and at_actor.has("stats/actor/actor-0", b"sentinel"),
                   10, "the actor's sentinel stats")
        wait_until(lambda: at_replay.has("transitions/actor-0", b"transitions") and at_replay.has("episodes/actor-0", b"episodes"),
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
        actor.token(k.alive("actor", "actor-0"))
        actor.token(k.alive("learner", "fake"))
        learner.token(k.alive("learner", "learner"))
        wait_until(lambda: set(replay.alive_now(k.alive_all, 1.0)) >= {k.alive("actor", "actor-0"), k.alive("learner", "learner")},
                   10, "the liveliness tokens")
        assert k.alive("learner", "fake") not in replay.alive_now(k.alive_all, 1.0)
    finally:
        for n in (replay, learner, actor, other_actor, evaluator, monitor):
            n.close()


def test_each_actor_login_publishes_only_as_itself_and_holds_only_its_slot(tmp_path):
    """A fresh credential set (`zenrl credentials`): actor-0 cannot publish transitions, unrolls,
    gradients, episodes or stats as actor-1 (the replay and the learner never get them), cannot
    hold actor-1's liveliness token or take its slot 1, nor publish weights or priorities;
    actor-1's own messages and slot do get through."""
    import zenoh

    from zenrl.actor.slots import claim_slot
    from zenrl.common.protocol import Keys
    from zenrl.common.transport import Node, init_zenoh_logging
    from zenrl.identity import make_credentials, read_users

    init_zenoh_logging("error")
    certs = gen_certs(tmp_path / "certs")
    creds = tmp_path / "creds"
    made = make_credentials(ZENOH_DIR, creds, actors=3, ca=str(certs / "ca.pem"))
    assert made["written"] and "actor-2" in made["users"]
    assert not any(p.endswith("-dev-password") for p in read_users(creds / "users.txt").values())
    ep = f"tls/127.0.0.1:{free_port()}"
    router = zenoh.open(secure_router_config(ep, certs, creds / "users.txt", creds / "router-secure.json5"))
    k = Keys("identity-test")

    def node(user: str) -> Node:
        return Node(ep, connect_timeout_s=5.0, config_file=str(creds / f"client-{user}.json5"))

    replay, learner, a, b = node("replay"), node("learner"), node("actor-0"), node("actor-1")
    try:
        at_replay, at_learner = Inbox(), Inbox()
        for key in (k.transitions_all, k.episodes_all, k.stats_all, k.priorities):
            replay.subscribe(key, at_replay)
        for key in (k.gradients_all, k.unrolls_all, k.weights):
            learner.subscribe(key, at_learner)
        # both actors' own keys reach the replay and the learner (so the subscriptions are in place)
        for n, me in ((a, "actor-0"), (b, "actor-1")):
            wait_until(lambda: n.put(k.stats("actor", me), b"warm-up") or at_replay.has(f"stats/actor/{me}"), 10,
                       f"{me}'s stats at the replay", 0.2)
            wait_until(lambda: n.put(k.gradients(me), b"own") or at_learner.has(f"gradients/{me}", b"own"), 10,
                       f"{me}'s gradients at the learner", 0.2)

        # actor-0 speaks as actor-1, and as the learner; then (same session, same priority: in
        # order) messages it may send: once those arrived, the forged ones would have
        for key in (k.transitions("actor-1"), k.unrolls("actor-1"), k.gradients("actor-1"), k.episodes("actor-1"),
                    k.stats("actor", "actor-1"), k.weights, k.priorities):
            a.put(key, b"forged")
        for key in (k.transitions("actor-0"), k.unrolls("actor-0"), k.episodes("actor-0")):
            a.put(key, b"own")
        a.put(k.stats("actor", "actor-0"), b"sentinel")
        wait_until(lambda: at_replay.has("stats/actor/actor-0", b"sentinel"), 10, "actor-0's sentinel")
        wait_until(lambda: at_replay.has("transitions/actor-0", b"own") and at_learner.has("unrolls/actor-0", b"own")
                   and at_replay.has("episodes/actor-0", b"own"), 10, "actor-0's own transitions, unrolls, episodes")
        for inbox in (at_replay, at_learner):
            forged = [key for key, p in inbox.items if p == b"forged"]
            assert not forged, f"actor-0's login published {forged}"
        # actor-1's own transitions do get through
        wait_until(lambda: b.put(k.transitions("actor-1"), b"own") or at_replay.has("transitions/actor-1", b"own"), 10,
                   "actor-1's transitions at the replay", 0.2)

        # slots: actor-0 declares tokens for slot 1 (in its own name, which would win the claim
        # since "actor-0" < "actor-1", and in actor-1's) and actor-1's liveliness token before
        # actor-1 claims: the router lets none of them out, so actor-1 gets its slot 1, and every
        # other process sees actor-1 alone on it and actor-0 on its own slot 0
        a.token(k.slot_token(1, "actor-0"))
        a.token(k.slot_token(1, "actor-1"))
        a.token(k.alive("actor", "actor-1"))
        assert claim_slot(a, k, "actor-0", only=0)[0] == 0
        slot, _ = claim_slot(b, k, "actor-1", only=1, attempts=1)
        assert slot == 1
        holders = sorted(k.parse_slot(x) for x in replay.alive_now(k.slot_holders(), 2.0))
        assert holders == [(0, "actor-0"), (1, "actor-1")], holders
        assert k.alive("actor", "actor-1") not in replay.alive_now(k.alive_all, 1.0)
    finally:
        for n in (replay, learner, a, b):
            n.close()
        router.close()


def _zenrl(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    import sys

    return subprocess.run([sys.executable, "-m", "zenrl.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


def _error_lines(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if ln.startswith("zenrl: error:")]


def test_services_refuse_development_passwords_unless_allowed(tmp_path, procs):
    """Every service whose login holds one of the repository's development passwords exits with
    EXIT_CONFIG and one line naming the fix; --allow-dev-credentials lets it go on (to the next
    step: here, a router that is not there). An actor refuses an id that is not its login's."""
    from zenrl import EXIT_CONFIG
    from zenrl.common.transport import Node

    certs = gen_certs(tmp_path / "certs")
    nowhere = f"tls/127.0.0.1:{free_port()}"
    common = ("--config", "configs/cluster_cartpole.yaml", "--router", nowhere, "--set", "transport.connect_timeout_s=0")
    for role, login in (("replay", "replay"), ("learner", "learner"), ("evaluator", "evaluator"),
                        ("exporter", "monitor"), ("actor", "actor-0")):
        cfg = client_config_file(login, certs, tmp_path)
        r = _zenrl(role, *common, "--set", f"transport.client_config={cfg}")
        lines = _error_lines(r.stderr)
        assert r.returncode == EXIT_CONFIG and len(lines) == 1, (role, r.returncode, r.stderr[-2000:])
        assert "development password" in lines[0] and "--allow-dev-credentials" in lines[0] \
            and "zenrl credentials" in lines[0] and repr(login) in lines[0], lines[0]
    # allowed: the replay goes on and fails only for want of a router
    r = _zenrl("replay", *common, "--set", f"transport.client_config={client_config_file('replay', certs, tmp_path)}",
               "--allow-dev-credentials")
    assert r.returncode not in (0, EXIT_CONFIG) and "development password" not in r.stderr, r.stderr[-2000:]
    assert "could not connect" in r.stderr, r.stderr[-2000:]
    # an actor logged in as actor-0 cannot be actor-1, nor take slot 1
    for flag in (("--id", "actor-1"), ("--slot", "1")):
        r = _zenrl("actor", *common, "--set", f"transport.client_config={client_config_file('actor-0', certs, tmp_path)}",
                   "--allow-dev-credentials", *flag)
        lines = _error_lines(r.stderr)
        assert r.returncode == EXIT_CONFIG and len(lines) == 1 and "'actor-0'" in lines[0], (flag, r.stderr[-2000:])

    # the router: the committed users file holds development passwords
    router_cfg = tmp_path / "router.json"
    router_cfg.write_text(str(secure_router_config(nowhere, certs)))
    r = _zenrl("router", "--router-config", str(router_cfg))
    lines = _error_lines(r.stderr)
    assert r.returncode == EXIT_CONFIG and len(lines) == 1, r.stderr[-2000:]
    assert "development passwords" in lines[0] and "actor-0" in lines[0] and "--allow-dev-credentials" in lines[0]
    procs.zenrl("router", ["router", "--router-config", str(router_cfg), "--allow-dev-credentials"])
    Node(nowhere, 30.0, config_file=str(client_config_file("actor-0", certs, tmp_path))).close()

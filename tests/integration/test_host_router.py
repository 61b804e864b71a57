"""Host routers (`zenrl router --connect`, deploy/zenoh/host-router*.json5) linked to a central
router, each router a separate OS process: clients of a host router reach the clients of the
central router and of other host routers both ways; the host router may start before the
central one; in secured mode the routers talk TLS with the host router's own credentials, the
per-role access control holds on the host router for its local clients, and the central router
bounds what a host may send (no weights from a host)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.conftest import ROOT, free_port, wait_until
from tests.integration.test_secure_router import Inbox, client_config_file, gen_certs

pytestmark = pytest.mark.integration

ZENOH_DIR = ROOT / "deploy" / "zenoh"


def _router_file(src: str, tmp: Path, certs: Path | None, name: str) -> Path:
    """``deploy/zenoh/<src>`` with the container paths mapped to ``certs`` and the REST plugin
    off (an in-process router cannot load it), written as JSON for ``--router-config``."""
    import zenoh

    cfg = zenoh.Config.from_file(str(ZENOH_DIR / src))
    doc = json.loads(cfg.get_json("transport"))
    if certs is not None:
        tls = doc["link"]["tls"]
        cert = Path(tls["listen_certificate"]).stem  # router (central) or host-router
        tls["listen_private_key"] = str(certs / f"{cert}-key.pem")
        tls["listen_certificate"] = str(certs / f"{cert}.pem")
        tls["root_ca_certificate"] = str(certs / "ca.pem")
        doc["auth"]["usrpwd"]["dictionary_file"] = str(ZENOH_DIR / "users.txt")
    cfg.insert_json5("transport", json.dumps(doc))
    cfg.insert_json5("plugins", "{}")
    out = tmp / name
    out.write_text(str(cfg))  # the whole config as JSON
    return out


def _start_router(procs, name: str, listen: str, config: Path | None = None, connect: str | None = None):
    # the committed configs admit the development passwords (users.txt): allowed here explicitly
    args = ["router", "--listen", listen, "--log-level", "WARNING", "--allow-dev-credentials"]
    if config is not None:
        args += ["--router-config", str(config)]
    if connect is not None:
        args += ["--connect", connect]
    return procs.zenrl(name, args)


def test_host_router_links_to_central_both_ways(procs, tmp_path):
    from zenrl.common.protocol import Keys
    from zenrl.common.transport import Node

    k = Keys("hostrouter-plain")
    central, host = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    # the host router starts first: it keeps retrying the central router by itself
    _start_router(procs, "host-router", host, _router_file("host-router.json5", tmp_path, None, "host.json"), central)
    _start_router(procs, "central-router", central)
    with Node(central, 20.0) as learner, Node(host, 20.0) as actor, Node(host, 20.0) as actor2:
        at_actor, at_actor2, at_learner = Inbox(), Inbox(), Inbox()
        actor.subscribe(k.weights, at_actor)
        actor2.subscribe(k.weights, at_actor2)
        learner.subscribe(k.transitions_all, at_learner)
        wait_until(lambda: learner.put(k.weights, b"w") or (at_actor.has("weights") and at_actor2.has("weights")),
                   30, "weights from the central router's client at both clients of the host router", 0.2)
        wait_until(lambda: actor.put(k.transitions("a0"), b"t") or at_learner.has("transitions/a0", b"t"),
                   30, "transitions from a host router's client at the central router's client", 0.2)


def test_secured_host_router(procs, tmp_path):
    from zenrl.common.errors import TransportError
    from zenrl.common.protocol import Keys
    from zenrl.common.transport import Node, init_zenoh_logging

    init_zenoh_logging("error")
    certs = gen_certs(tmp_path / "certs")
    k = Keys("hostrouter-secure")
    central, host = f"tls/127.0.0.1:{free_port()}", f"tls/127.0.0.1:{free_port()}"
    _start_router(procs, "central-router", central, _router_file("router-secure.json5", tmp_path, certs, "central.json"))
    _start_router(procs, "host-router", host, _router_file("host-router-secure.json5", tmp_path, certs, "host.json"),
                  central)

    def node(role: str, ep: str) -> Node:
        return Node(ep, connect_timeout_s=20.0, config_file=str(client_config_file(role, certs, tmp_path)))

    # TLS and passwords hold on the host router too
    with pytest.raises(TransportError):
        Node(host, 0.0, config_file=str(client_config_file("actor-0", certs, tmp_path, password="wrong"))).close()

    learner, replay = node("learner", central), node("replay", central)
    actor, evaluator = node("actor-0", host), node("evaluator", host)
    impostors: list[Node] = []
    try:
        at_actor, at_evaluator, at_learner, at_replay = Inbox(), Inbox(), Inbox(), Inbox()
        actor.subscribe(k.weights, at_actor)
        evaluator.subscribe(k.weights, at_evaluator)
        learner.subscribe(k.weights, at_learner)
        learner.subscribe(k.stats_all, at_learner)
        evaluator.subscribe(k.stats_all, at_evaluator)
        replay.subscribe(k.transitions_all, at_replay)
        replay.subscribe(k.priorities, at_replay)
        learner.queryable(k.weights_query, lambda _req: b"weights-from-learner")

        wait_until(lambda: learner.put(k.weights, b"real") or (at_actor.has("weights", b"real")
                                                                and at_evaluator.has("weights", b"real")),
                   30, "the learner's weights at the actor and the evaluator behind the host router", 0.2)
        wait_until(lambda: actor.put(k.stats("actor", "actor-0"), b"warm-up") or (
            at_learner.has("stats/actor/actor-0") and at_evaluator.has("stats/actor/actor-0")),
            30, "the actor's stats at the learner (central) and the evaluator (same host)", 0.2)

        # clients of the host router (login actor-1) that take a Zenoh id of their choosing (the
        # host router once trusted the central router by its id). With the link to the central
        # router up (the weights above crossed it), the central router's own id is refused, and
        # the fixed id it used to have buys nothing beyond the login (below: no weights, no other
        # actor's transitions)
        (central_zid,) = [str(z) for z in learner.session.info.routers_zid()]
        impostor_config = str(client_config_file("actor-1", certs, tmp_path))
        with pytest.raises(TransportError):
            Node(host, 3.0, config_file=impostor_config, extra={"id": central_zid}).close()
        impostor = Node(host, 20.0, config_file=impostor_config, extra={"id": "5a3e71c0ffee0001"})
        impostors.append(impostor)
        wait_until(lambda: impostor.put(k.stats("actor", "actor-1"), b"warm-up") or at_learner.has("stats/actor/actor-1"),
                   30, "the impostor's own stats at the learner", 0.2)

        # forged weights and priorities, then allowed messages on the same link (in order): once
        # the sentinel arrived at both, the forged ones would have too
        for n in (actor, *impostors):
            n.put(k.weights, b"forged")
            n.put(k.priorities, b"forged")
            n.put(k.transitions("actor-0" if n is not actor else "actor-1"), b"forged")  # another actor's
        actor.put(k.transitions("actor-0"), b"transitions")
        for n in impostors:
            n.put(k.stats("actor", "actor-1"), b"impostor-sentinel")
        actor.put(k.stats("actor", "actor-0"), b"sentinel")
        wait_until(lambda: at_learner.has("stats/actor/actor-0", b"sentinel") and at_evaluator.has("stats/actor/actor-0", b"sentinel")
                   and at_learner.has("stats/actor/actor-1", b"impostor-sentinel"), 20, "the actors' sentinel stats")
        wait_until(lambda: at_replay.has("transitions/actor-0", b"transitions"), 20, "the actor's transitions at the replay")
        assert not [key for key, p in at_replay.items if p == b"forged"], "another actor's transitions reached the replay"
        assert b"forged" not in at_learner.payloads("weights"), "an actor's weights crossed to the central router"
        assert b"forged" not in at_evaluator.payloads("weights"), "an actor's weights reached a client of its own host router"
        assert not at_replay.payloads("replay/priorities"), "an actor's priority update reached the replay"
        assert actor.query(k.weights_query, timeout_s=5.0) == b"weights-from-learner"
    finally:
        for n in (actor, evaluator, learner, replay, *impostors):
            n.close()


def test_router_connect_flag_replaces_config_endpoints(tmp_path):
    """--listen replaces the file's endpoints (--connect's is checked by the first test: the
    file's `central:7447` would not resolve here); a bad file is an error naming it."""
    import zenoh

    from zenrl.common.errors import TransportError
    from zenrl.common.transport import open_router

    central = f"tcp/127.0.0.1:{free_port()}"
    host = f"tcp/127.0.0.1:{free_port()}"
    cfg = _router_file("host-router.json5", tmp_path, None, "host.json")
    r = open_router([host], str(cfg), connect=[central], replace_listen=True)
    try:
        # the router listens on `host`, not on the file's port: a client connects at once
        s = zenoh.open(zenoh.Config.from_json5(json.dumps(
            {"mode": "client", "connect": {"endpoints": [host]}, "scouting": {"multicast": {"enabled": False}}})))
        s.close()
    finally:
        r.close()
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    with pytest.raises(TransportError, match="bad.json5"):
        open_router([host], str(bad), replace_listen=True)


def test_host_router_acl_is_the_central_one_for_local_clients():
    """host-router-secure.json5 repeats the central router's per-role rules (for the clients on
    its host): they must not drift apart. It adds only the link to the central router, named by
    the common name of the central router's certificate (gen-certs.sh), never by a Zenoh id; the
    central router adds only the host routers' policy."""
    import zenoh

    def load(name: str) -> tuple[dict, zenoh.Config]:
        cfg = zenoh.Config.from_file(str(ZENOH_DIR / name))
        return json.loads(cfg.get_json("access_control")), cfg

    central, central_cfg = load("router-secure.json5")
    host, host_cfg = load("host-router-secure.json5")
    assert host["enabled"] and host["default_permission"] == "deny"
    assert [r for r in host["rules"] if r["id"] != "upstream-all"] == central["rules"]
    assert [s for s in host["subjects"] if s["id"] != "central-router"] == \
        [s for s in central["subjects"] if s["id"] != "host-routers"]
    assert [p for p in host["policies"] if p["id"] != "central-router"] == \
        [p for p in central["policies"] if p["id"] != "host-router"]
    upstream = next(s for s in host["subjects"] if s["id"] == "central-router")
    assert upstream["cert_common_names"] == ["zenrl-central-router"]
    assert not any(s.get("zids") for s in host["subjects"] + central["subjects"]), "a subject trusted by Zenoh id"
    assert "/CN=$2" in (ZENOH_DIR / "gen-certs.sh").read_text() and "issue router zenrl-central-router" in \
        (ZENOH_DIR / "gen-certs.sh").read_text()
    # the host router's own login is a user of the central router, and that user's policy
    # allows no weights, priorities or sample answers
    users = dict(line.split(":", 1) for line in (ZENOH_DIR / "users.txt").read_text().split())
    auth = json.loads(host_cfg.get_json("transport/auth/usrpwd"))
    assert users[auth["user"]] == auth["password"]
    subject = next(s["id"] for s in central["subjects"] if auth["user"] in (s.get("usernames") or []))
    rules = {r for p in central["policies"] if subject in p["subjects"] for r in p["rules"]}
    assert not rules & {"learner-publish", "learner-serve-declare", "replay-serve-declare"}

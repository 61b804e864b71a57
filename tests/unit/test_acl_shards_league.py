"""The secured routers' access control (deploy/zenoh/router-secure.json5, host-router-secure.json5,
as committed and as `zenrl credentials` expands it) on the sharded replay's keys
(transitions/<k>/<actor>, replay/<k>/sample, replay/<k>/priorities) and the league's keys
(league/opponent, league/weights, league/table, league/results/<actor>): each login may send
exactly what it may send on the unsharded keys, and the league login alone serves the league.

Rules are evaluated with Zenoh's own key-expression inclusion (a message is allowed when a rule of
one of the login's policies names its message, flow and a key expression that includes its key)."""

from __future__ import annotations

import pytest

from tests.conftest import ROOT

ZENOH_DIR = ROOT / "deploy" / "zenoh"
RUN = "run1"
LEAGUE_RUN = "lg7"
AGENT_RUN = f"{LEAGUE_RUN}.main"  # a learning agent's processes: <league-run-id>.<agent>
LOGINS = ("learner", "replay", "evaluator", "monitor", "league", "hostrouter", "actor-0", "actor-1")


def _acl(name: str, actors: int | None = None) -> dict:
    from zenrl.common.transport import config_section
    from zenrl.identity import expand_acl

    acl = config_section(str(ZENOH_DIR / name), "access_control")
    return acl if actors is None else expand_acl(acl, actors)


def allowed(acl: dict, user: str, flow: str, message: str, key: str) -> bool:
    """Whether ``acl`` lets login ``user`` send (ingress) / be sent (egress) ``message`` on ``key``."""
    import zenoh

    subjects = {s["id"] for s in acl["subjects"] if user in (s.get("usernames") or [])}
    rule_ids = {r for p in acl["policies"] if set(p["subjects"]) & subjects for r in p["rules"]}
    k = zenoh.KeyExpr(key)
    return any(flow in r["flows"] and message in r["messages"]
               and any(zenoh.KeyExpr(e).includes(k) for e in r["key_exprs"])
               for r in acl["rules"] if r["id"] in rule_ids)


def who(acl: dict, flow: str, message: str, key: str, logins=LOGINS) -> set[str]:
    return {u for u in logins if allowed(acl, u, flow, message, key)}


ACLS = [("router-secure.json5", None), ("router-secure.json5", 3), ("host-router-secure.json5", None)]


@pytest.mark.parametrize("name,actors", ACLS)
def test_shard_keys_have_the_unsharded_keys_rules(name, actors):
    acl = _acl(name, actors)
    central = name == "router-secure.json5"
    for shard in (0, 5, 63):
        # actor-<i> publishes transitions to a shard only under its own id (host routers: any actor's)
        for me in ("actor-0", "actor-1"):
            key = f"zenrl/{RUN}/transitions/{shard}/{me}"
            assert who(acl, "ingress", "put", key) == {me} | ({"hostrouter"} if central else set()), (name, key)
            # the same as on the unsharded key
            assert who(acl, "ingress", "put", key) == who(acl, "ingress", "put", f"zenrl/{RUN}/transitions/{me}")
        # only the replay subscribes to and receives a shard's transitions and priorities
        for key in (f"zenrl/{RUN}/transitions/{shard}/*", f"zenrl/{RUN}/replay/{shard}/priorities"):
            assert who(acl, "ingress", "declare_subscriber", key) == {"replay"}, (name, key)
            assert who(acl, "egress", "put", key.replace("*", "actor-0")) == {"replay"}, (name, key)
        # only the learner sends priorities to a shard
        assert who(acl, "ingress", "put", f"zenrl/{RUN}/replay/{shard}/priorities") == {"learner"}
        # only the replay answers a shard's sample queries, only the learner asks them
        sample = f"zenrl/{RUN}/replay/{shard}/sample"
        assert who(acl, "ingress", "declare_queryable", sample) == {"replay"}
        assert who(acl, "ingress", "reply", sample) == {"replay"}
        assert who(acl, "egress", "query", sample) == {"replay"}
        assert who(acl, "ingress", "query", sample) == {"learner"}
        assert who(acl, "egress", "reply", sample) == {"learner"}
        for msg, flow in (("declare_queryable", "ingress"), ("reply", "ingress"), ("query", "ingress"),
                          ("reply", "egress")):
            assert who(acl, flow, msg, sample) == who(acl, flow, msg, f"zenrl/{RUN}/replay/sample"), (msg, flow)
    # the shard keys cannot be stretched: no login may put two segments deeper, nor on a shard's sample key
    assert not who(acl, "ingress", "put", f"zenrl/{RUN}/transitions/0/x/actor-0")
    assert not who(acl, "ingress", "put", f"zenrl/{RUN}/replay/0/sample")


@pytest.mark.parametrize("name,actors", ACLS)
def test_league_keys_only_the_league_serves_actors_ask_and_report_as_themselves(name, actors):
    acl = _acl(name, actors)
    central = name == "router-secure.json5"
    lk = f"zenrl/{LEAGUE_RUN}/league"
    actors_here = {"actor-0", "actor-1"}
    for q in ("opponent", "weights", "table"):
        # only the league answers the league's queryables
        for msg, flow in (("declare_queryable", "ingress"), ("reply", "ingress"), ("query", "egress")):
            assert who(acl, flow, msg, f"{lk}/{q}") == {"league"}, (name, q, msg, flow)
    for q in ("opponent", "weights"):
        assert who(acl, "ingress", "query", f"{lk}/{q}") == actors_here | ({"hostrouter"} if central else set())
        assert who(acl, "egress", "reply", f"{lk}/{q}") == actors_here | ({"hostrouter"} if central else set())
    # `zenrl league status` (the monitor login) reads the table
    assert who(acl, "ingress", "query", f"{lk}/table") == {"monitor"}
    assert who(acl, "egress", "reply", f"{lk}/table") == {"monitor"}
    # results: actor-<i> only under its own id; only the league hears them
    for me in ("actor-0", "actor-1"):
        assert who(acl, "ingress", "put", f"{lk}/results/{me}") == {me} | ({"hostrouter"} if central else set())
    assert who(acl, "ingress", "declare_subscriber", f"{lk}/results/*") == {"league"}
    assert who(acl, "egress", "put", f"{lk}/results/actor-0") == {"league"}
    # the league follows a learning agent's weights broadcast, which only the learner publishes,
    # and holds its own liveliness token and stats
    assert "league" in who(acl, "ingress", "declare_subscriber", f"zenrl/{AGENT_RUN}/weights")
    assert "league" in who(acl, "egress", "put", f"zenrl/{AGENT_RUN}/weights")
    assert who(acl, "ingress", "put", f"zenrl/{AGENT_RUN}/weights") == {"learner"}
    assert who(acl, "ingress", "liveliness_token", f"zenrl/{LEAGUE_RUN}/alive/league/league") == {"league"}
    assert who(acl, "ingress", "put", f"zenrl/{LEAGUE_RUN}/stats/league/league") == {"league"}
    # and nothing else: no weights, priorities, transitions or sample answers
    for key, msg in ((f"zenrl/{AGENT_RUN}/replay/priorities", "put"),
                     (f"zenrl/{AGENT_RUN}/transitions/actor-0", "put"),
                     (f"zenrl/{AGENT_RUN}/replay/sample", "declare_queryable"),
                     (f"zenrl/{AGENT_RUN}/learner/weights", "reply")):
        assert not allowed(acl, "league", "ingress", msg, key), key
    # an agent's processes (run <league-run>.<agent>) get the rules of any run
    assert who(acl, "ingress", "put", f"zenrl/{AGENT_RUN}/transitions/1/actor-1") == \
        {"actor-1"} | ({"hostrouter"} if central else set())


def test_credentials_make_a_league_login_with_a_fresh_password(tmp_path):
    from zenrl.common.transport import config_section
    from zenrl.identity import is_dev_password, make_credentials, read_users

    made = make_credentials(ZENOH_DIR, tmp_path / "c", actors=2, ca="/ca/ca.pem")
    assert "league" in made["users"]
    users = read_users(tmp_path / "c" / "users.txt")
    assert "league" in users and not is_dev_password(users["league"])
    auth = config_section(str(tmp_path / "c" / "client-league.json5"), "transport/auth/usrpwd")
    assert (auth["user"], auth["password"]) == ("league", users["league"])
    acl = config_section(str(tmp_path / "c" / "router-secure.json5"), "access_control")
    assert who(acl, "ingress", "declare_queryable", f"zenrl/{LEAGUE_RUN}/league/opponent") == {"league"}
    # the committed development login matches the committed users file
    committed = config_section(str(ZENOH_DIR / "client-league.json5"), "transport/auth/usrpwd")
    assert read_users(ZENOH_DIR / "users.txt")["league"] == committed["password"] == "league-dev-password"

"""Secured-mode identities (zenrl/identity.py): the committed development set is consistent and
every password in it is recognised as a development one; `zenrl credentials` writes a fresh,
consistent set; an actor's id and slot are bound to its login."""

from __future__ import annotations

import json
import os
import stat

import pytest

from tests.conftest import ROOT

ZENOH_DIR = ROOT / "deploy" / "zenoh"


def _clean(x):
    """Zenoh spells unset subject fields as null: drop them before comparing."""
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items() if v is not None}
    if isinstance(x, list):
        return [_clean(v) for v in x]
    return x


def _acl(path):
    from zenrl.common.transport import config_section

    return _clean(config_section(str(path), "access_control"))


def test_every_password_in_the_repository_is_a_development_one():
    from zenrl.common.transport import config_section
    from zenrl.identity import is_dev_password, read_users

    users = read_users(ZENOH_DIR / "users.txt")
    assert users and all(is_dev_password(p) for p in users.values()), users
    clients = sorted(ZENOH_DIR.glob("client-*.json5"))
    assert len(clients) >= 6
    for f in clients:
        auth = config_section(str(f), "transport/auth/usrpwd")
        assert is_dev_password(auth["password"]) and users[auth["user"]] == auth["password"], f.name
    host = config_section(str(ZENOH_DIR / "host-router-secure.json5"), "transport/auth/usrpwd")
    assert is_dev_password(host["password"]) and users[host["user"]] == host["password"]
    assert not is_dev_password("x" * 32) and not is_dev_password(None) and not is_dev_password("")


def test_committed_acl_is_the_expansion_for_two_actors_and_names_every_user():
    from zenrl.identity import expand_acl, read_users

    users = set(read_users(ZENOH_DIR / "users.txt"))
    for name in ("router-secure.json5", "host-router-secure.json5"):
        acl = _acl(ZENOH_DIR / name)
        assert _clean(expand_acl(acl, 2)) == acl, f"{name}: per-actor entries differ from zenrl credentials'"
        named = {u for s in acl["subjects"] for u in s.get("usernames", [])}
        assert named == users - ({"hostrouter"} if name.startswith("host") else set()), name
        rule_ids = [r["id"] for r in acl["rules"]]
        assert len(rule_ids) == len(set(rule_ids))
        # no actor login may put on any key with a wildcard in the actor id
        for p in acl["policies"]:
            if p["id"].startswith("actor"):
                for r in (r for r in acl["rules"] if r["id"] in p["rules"] and "put" in r["messages"]
                          and r["flows"] == ["ingress"]):
                    assert all(k.endswith("/" + p["id"]) for k in r["key_exprs"]), (name, p["id"], r)


def test_expand_acl_binds_each_actor_to_its_own_keys_and_slot():
    from zenrl.identity import expand_acl

    acl = expand_acl(_acl(ZENOH_DIR / "router-secure.json5"), 5)
    rules = {r["id"]: r for r in acl["rules"]}
    assert next(s for s in acl["subjects"] if s["id"] == "actors")["usernames"] == [f"actor-{i}" for i in range(5)]
    for i in range(5):
        me = f"actor-{i}"
        pol = next(p for p in acl["policies"] if p["id"] == me)
        assert pol["subjects"] == [me]
        keys = [k for r in pol["rules"] for k in rules[r]["key_exprs"]]
        assert sorted(keys) == sorted([f"zenrl/*/{d}/{me}" for d in ("transitions", "unrolls", "gradients", "episodes")]
                                      + [f"zenrl/*/transitions/*/{me}", f"zenrl/*/league/results/{me}",
                                         f"zenrl/*/stats/actor/{me}", f"zenrl/*/alive/actor/{me}", f"zenrl/*/slots/{i}/{me}"])
    assert "actor-5" not in {s["id"] for s in acl["subjects"]}
    with pytest.raises(Exception, match="at least one"):
        expand_acl(acl, 0)


def test_make_credentials_writes_a_fresh_consistent_set_once(tmp_path):
    from zenrl.common.transport import config_section
    from zenrl.identity import is_dev_password, make_credentials, read_users

    out = tmp_path / "creds"
    made = make_credentials(ZENOH_DIR, out, actors=3, ca="/ca/ca.pem")
    assert made["written"]
    users = read_users(out / "users.txt")
    assert set(users) == {"learner", "replay", "evaluator", "monitor", "league", "hostrouter",
                          "actor-0", "actor-1", "actor-2"}
    assert len(set(users.values())) == len(users) and not any(is_dev_password(p) for p in users.values())
    for f in out.iterdir():
        assert stat.S_IMODE(os.stat(f).st_mode) == 0o600, f.name
    for u in users:
        if u != "hostrouter":
            auth = config_section(str(out / f"client-{u}.json5"), "transport/auth/usrpwd")
            assert (auth["user"], auth["password"]) == (u, users[u])
            assert config_section(str(out / f"client-{u}.json5"), "transport/link/tls/root_ca_certificate") == "/ca/ca.pem"
    for name in ("router-secure.json5", "host-router-secure.json5"):
        acl = _acl(out / name)
        assert {u for s in acl["subjects"] for u in s.get("usernames", [])} >= {"actor-0", "actor-1", "actor-2"}
        assert "id" not in json.loads((out / name).read_text()), "a fixed Zenoh id in a generated router config"
    host = config_section(str(out / "host-router-secure.json5"), "transport/auth/usrpwd")
    assert host["password"] == users["hostrouter"]
    # a second run keeps the set (the first `up` makes it, later ones reuse it); --force remakes it
    assert not make_credentials(ZENOH_DIR, out, actors=5)["written"]
    assert read_users(out / "users.txt") == users
    assert make_credentials(ZENOH_DIR, out, actors=1, force=True)["written"]
    assert set(read_users(out / "users.txt")) & set(users) == {"learner", "replay", "evaluator", "monitor", "league",
                                                                "hostrouter", "actor-0"}
    assert read_users(out / "users.txt")["learner"] != users["learner"]


def test_bind_actor_and_dev_checks(tmp_path, monkeypatch):
    from zenrl.common.errors import ConfigError
    from zenrl.identity import ALLOW_DEV_ENV, bind_actor, check_dev_credentials

    monkeypatch.delenv(ALLOW_DEV_ENV, raising=False)
    a3 = tmp_path / "a3.json"
    a3.write_text(json.dumps({"transport": {"auth": {"usrpwd": {"user": "actor-3", "password": "s3cret-" + "x" * 20}}}}))
    assert bind_actor(str(a3), None, None) == ("actor-3", 3)
    assert bind_actor(str(a3), "actor-3", 3) == ("actor-3", 3)
    for actor_id, slot in (("actor-4", None), (None, 0)):
        with pytest.raises(ConfigError, match="actor-3"):
            bind_actor(str(a3), actor_id, slot)
    assert bind_actor(None, "x", 2) is None
    assert bind_actor(str(ZENOH_DIR / "client-learner.json5"), None, None) is None
    check_dev_credentials(str(a3), allow=False)  # a real password passes
    check_dev_credentials(None, allow=False)  # no secured mode
    with pytest.raises(ConfigError, match="development password"):
        check_dev_credentials(str(ZENOH_DIR / "client-actor-0.json5"), allow=False)
    check_dev_credentials(str(ZENOH_DIR / "client-actor-0.json5"), allow=True)
    monkeypatch.setenv(ALLOW_DEV_ENV, "1")
    check_dev_credentials(str(ZENOH_DIR / "client-actor-0.json5"), allow=False)


def test_actor_logins_are_taken_once_each_until_released(tmp_path):
    """Replicas of one template share the pool: each takes a different login, the first free
    one; a login is free again once the process holding it is gone (its lock closed)."""
    import subprocess
    import sys

    from zenrl import identity
    from zenrl.common.errors import ConfigError

    pool = tmp_path / "pool"
    identity.make_credentials(ZENOH_DIR, pool, actors=3)
    # another process holds actor-0 (as a running actor container would)
    holder = subprocess.Popen([sys.executable, "-c", "import sys; from zenrl.identity import take_actor_login; "
                               f"print(take_actor_login({str(pool)!r}), flush=True); sys.stdin.read()"],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip().endswith("client-actor-0.json5")
        before = len(identity._taken)
        assert identity.take_actor_login(pool).endswith("client-actor-1.json5")
        assert identity.take_actor_login(pool).endswith("client-actor-2.json5")
        with pytest.raises(ConfigError, match="every actor login"):
            identity.take_actor_login(pool)
        identity._taken.pop(before).close()  # the holder of actor-1 exits
        assert identity.take_actor_login(pool).endswith("client-actor-1.json5")
    finally:
        holder.communicate("", timeout=30)
        while len(identity._taken) > before:
            identity._taken.pop().close()
    assert identity.take_actor_login(pool).endswith("client-actor-0.json5")  # the other process is gone
    identity._taken.pop().close()
    with pytest.raises(ConfigError, match="no actor login"):
        identity.take_actor_login(tmp_path)

"""Identities of a secured zenrl cluster: who each process logs in to the router as, what the
router's access control lets that login send, and the checks a process makes before it starts.

* Every role logs in with a user name and password of its own (``learner``, ``replay``,
  ``evaluator``, ``monitor``, ``league``; host routers ``hostrouter``), and every actor with one of its own:
  user ``actor-<i>``. The router's access control (deploy/zenoh/router-secure.json5, expanded
  by :func:`expand_acl`) lets ``actor-<i>`` publish only ``transitions/actor-<i>``,
  ``unrolls/actor-<i>``, ``gradients/actor-<i>``, ``episodes/actor-<i>``, a replay shard's
  ``transitions/<k>/actor-<i>``, a league's ``league/results/actor-<i>`` and
  ``stats/actor/actor-<i>``, and hold only the tokens ``alive/actor/actor-<i>`` and
  ``slots/<i>/actor-<i>``: it can neither speak as another actor nor hold another's slot.
* An actor logged in as ``actor-<i>`` is actor ``actor-<i>`` on exploration slot ``i``
  (:func:`bind_actor`); it refuses to start with another id or slot, which the router would drop.
* ``zenrl credentials --out DIR`` (:func:`make_credentials`) writes a fresh set: random
  passwords, the users file, one client config per role and per actor, and the central and host
  router configs with the access control expanded for that many actors.
* The passwords in the repository (``<user>-dev-password``) are for development: a process whose
  credentials hold one refuses to start (:func:`check_dev_credentials`) unless told
  ``--allow-dev-credentials`` (or ``ZENRL_ALLOW_DEV_CREDENTIALS=1``).
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import secrets
from pathlib import Path
from typing import Any

from zenrl.common.errors import ConfigError, TransportError
from zenrl.common.transport import config_section, write_config

#: the roles other than actors, each one login (client-<role>.json5)
ROLE_USERS = ("learner", "replay", "evaluator", "monitor", "league")
#: the login of host routers at the central router
HOST_ROUTER_USER = "hostrouter"
#: every development password in the repository is ``<user>-dev-password``
DEV_PASSWORD_SUFFIX = "-dev-password"
#: set to 1: as --allow-dev-credentials (for the children of ``zenrl run`` and containers)
ALLOW_DEV_ENV = "ZENRL_ALLOW_DEV_CREDENTIALS"
#: the ACL subject listing every actor login (the rules all actors share)
ACTORS_SUBJECT = "actors"
#: a directory of actor logins (client-actor-<i>.json5) of which an actor takes the first free one
ACTOR_LOGINS_ENV = "ZENRL_ACTOR_LOGINS"

_ACTOR_USER = re.compile(r"^actor-(\d+)$")
_PER_ACTOR_ID = re.compile(r"^actor-\d+(-publish|-tokens)?$")
_ACTOR_DATA = ("transitions", "unrolls", "gradients", "episodes")


def actor_user(i: int) -> str:
    return f"actor-{int(i)}"


def actor_index(user: str | None) -> int | None:
    """``"actor-3"`` -> 3; any other user (or none) -> ``None``."""
    m = _ACTOR_USER.match(user or "")
    return int(m.group(1)) if m else None


def is_dev_password(password: str | None) -> bool:
    return bool(password) and str(password).endswith(DEV_PASSWORD_SUFFIX)


def dev_allowed(flag: bool) -> bool:
    return flag or os.environ.get(ALLOW_DEV_ENV, "") in ("1", "true", "yes")


# ---------------------------------------------------------------------------------------------
# What a process logs in as
# ---------------------------------------------------------------------------------------------
def client_login(client_config: str | None) -> tuple[str | None, str | None]:
    """(user, password) of a client config file (``transport.client_config``); ``(None, None)``
    without a file or without user/password in it (not secured mode)."""
    if not client_config:
        return None, None
    try:
        auth = config_section(client_config, "transport/auth/usrpwd") or {}
    except TransportError as e:
        raise ConfigError(f"transport.client_config: {e}") from None
    return auth.get("user"), auth.get("password")


def check_dev_credentials(client_config: str | None, allow: bool) -> None:
    """Refuse (:class:`ConfigError`, one line) a client config that logs in with one of the
    repository's development passwords, unless ``allow``."""
    user, password = client_login(client_config)
    if is_dev_password(password) and not dev_allowed(allow):
        raise ConfigError(f"transport.client_config {client_config!r} logs in as {user!r} with the repository's "
                          "development password: make fresh credentials (zenrl credentials --out DIR) or pass "
                          "--allow-dev-credentials")


def check_router_dev_credentials(router_config: str | None, allow: bool) -> None:
    """The same for a router config: its own login (a host router's) and every user of its
    users file (``transport/auth/usrpwd/dictionary_file``, relative to the working directory)."""
    if not router_config or dev_allowed(allow):
        return
    try:
        auth = config_section(router_config, "transport/auth/usrpwd") or {}
    except TransportError as e:
        raise ConfigError(f"--router-config: {e}") from None
    dev = [auth["user"]] if is_dev_password(auth.get("password")) else []
    users_file = auth.get("dictionary_file")
    if users_file and os.path.isfile(users_file):
        dev += [u for u, p in read_users(users_file).items() if is_dev_password(p)]
    if dev:
        raise ConfigError(f"--router-config {router_config!r} admits the repository's development passwords "
                          f"(users {', '.join(sorted(set(dev)))}): make fresh credentials (zenrl credentials --out DIR) "
                          "or pass --allow-dev-credentials")


def bind_actor(client_config: str | None, actor_id: str | None, slot: int | None) -> tuple[str, int] | None:
    """The actor id and exploration slot of an actor logged in as ``actor-<i>``: ``("actor-<i>",
    i)``; a different ``actor_id`` or ``slot`` asked for is a :class:`ConfigError` (the router
    would drop everything it sends). ``None`` without such a login (id and slot are free)."""
    user, _ = client_login(client_config)
    i = actor_index(user)
    if i is None or user is None:
        return None
    if actor_id is not None and actor_id != user:
        raise ConfigError(f"actor --id {actor_id!r} is not the id of its credentials ({user!r}, "
                          f"transport.client_config {client_config!r}): the router drops what another id sends; drop --id")
    if slot is not None and slot != i:
        raise ConfigError(f"actor slot {slot} is not the slot of its credentials ({user!r} holds slot {i}); "
                          "drop --slot / actor.slot")
    return user, i


#: lock files of the logins this process took (kept open: closing one frees the login)
_taken: list[Any] = []


def take_actor_login(pool: str | Path) -> str:
    """The first actor login of ``pool`` (``client-actor-<i>.json5``, lowest ``i`` first) that no
    other process on this machine holds: an exclusive ``flock`` on the file, held until this
    process exits (also when it crashes), so that replicas started from one template (``docker
    compose --scale actor=N``, sharing the credentials volume) get distinct identities. Returns
    the file's path; :class:`ConfigError` when every login is taken."""
    files = sorted(Path(pool).glob("client-actor-*.json5"), key=lambda f: actor_index(f.stem[len("client-"):]) or 0)
    files = [f for f in files if actor_index(f.stem[len("client-"):]) is not None]
    if not files:
        raise ConfigError(f"{ACTOR_LOGINS_ENV}={str(pool)!r} holds no actor login (client-actor-<i>.json5)")
    for f in files:
        fh = open(f, "rb")
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.close()
            continue
        _taken.append(fh)
        return str(f)
    raise ConfigError(f"every actor login in {str(pool)!r} is taken ({len(files)} actors run): make more with "
                      "zenrl credentials --actors N --force (and restart the router)")


# ---------------------------------------------------------------------------------------------
# Making credentials
# ---------------------------------------------------------------------------------------------
def read_users(path: str | Path) -> dict[str, str]:
    """A Zenoh users file (``user:password`` per line) as a dict."""
    out = {}
    for line in Path(path).read_text().splitlines():
        if line.strip():
            user, _, password = line.strip().partition(":")
            out[user] = password
    return out


def actor_acl(i: int) -> tuple[list[dict[str, Any]], dict[str, Any], dict[str, Any]]:
    """The access-control rules, subject and policy of actor login ``actor-<i>``: what it alone
    may publish and which tokens it alone may hold."""
    uid = actor_user(i)
    rules = [
        {"id": f"{uid}-publish", "permission": "allow", "flows": ["ingress"], "messages": ["put"],
         "key_exprs": [f"zenrl/*/{k}/{uid}" for k in _ACTOR_DATA]
         # a sharded replay's input (transitions/<shard>/<actor>) and a league's match results
         + [f"zenrl/*/transitions/*/{uid}", f"zenrl/*/league/results/{uid}", f"zenrl/*/stats/actor/{uid}"]},
        {"id": f"{uid}-tokens", "permission": "allow", "flows": ["ingress"], "messages": ["liveliness_token"],
         "key_exprs": [f"zenrl/*/alive/actor/{uid}", f"zenrl/*/slots/{int(i)}/{uid}"]},
    ]
    return rules, {"id": uid, "usernames": [uid]}, {"id": uid, "subjects": [uid], "rules": [r["id"] for r in rules]}


def expand_acl(acl: dict[str, Any], actors: int) -> dict[str, Any]:
    """``acl`` (a router's ``access_control``) with the per-actor entries replaced by those of
    ``actor-0`` .. ``actor-<actors-1>`` (:func:`actor_acl`) and the shared ``actors`` subject
    listing exactly those logins."""
    if actors < 1:
        raise ConfigError(f"actors={actors}: a secured cluster needs at least one actor login")
    out = dict(acl)
    rules = [r for r in acl["rules"] if not _PER_ACTOR_ID.match(r["id"])]
    subjects = [s for s in acl["subjects"] if not _PER_ACTOR_ID.match(s["id"])]
    policies = [p for p in acl["policies"] if not _PER_ACTOR_ID.match(p.get("id") or "")]
    if not any(s["id"] == ACTORS_SUBJECT for s in subjects):
        raise ConfigError(f"the access control has no {ACTORS_SUBJECT!r} subject (the rules every actor shares)")
    subjects = [dict(s, usernames=[actor_user(i) for i in range(actors)]) if s["id"] == ACTORS_SUBJECT else s
                for s in subjects]
    for i in range(actors):
        r, s, p = actor_acl(i)
        rules += r
        subjects.append(s)
        policies.append(p)
    out.update(rules=rules, subjects=subjects, policies=policies)
    return out


def client_doc(user: str, password: str, ca: str) -> dict[str, Any]:
    """A client config (``transport.client_config``): trust ``ca``, log in as ``user``."""
    return {"transport": {"link": {"tls": {"root_ca_certificate": ca}},
                          "auth": {"usrpwd": {"user": user, "password": password}}}}


def write_actor_login(logins: str | Path, index: int | str, out: str | Path) -> None:
    """Write login ``actor-<index>`` of ``logins`` (``actor-logins.json``) to ``out`` (a client
    config, owner-readable only): a Kubernetes actor pod's init container, with ``index`` its
    StatefulSet ordinal. :class:`ConfigError` when there is no such login."""
    user = actor_user(int(index))
    doc = json.loads(Path(logins).read_text()).get(user)
    if doc is None:
        raise ConfigError(f"{str(logins)!r} has no login {user}: make more actor logins (prepare.sh NAMESPACE ACTORS, "
                          "zenrl credentials --actors N) or run fewer actors")
    fd = os.open(out, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        json.dump(doc, f)


def make_credentials(templates: str | Path, out: str | Path, actors: int, ca: str = "/certs/ca.pem",
                     dev: bool = False, force: bool = False, owner: tuple[int, int] | None = None,
                     users_file: str | None = None) -> dict[str, Any]:
    """Write a credential set to ``out``: ``users.txt``, ``client-<role>.json5`` for every role
    and ``client-actor-<i>.json5`` for ``i < actors`` (all of these also in ``actor-logins.json``),
    and ``router-secure.json5`` /
    ``host-router-secure.json5`` made from those in ``templates`` (deploy/zenoh) with the access
    control expanded for ``actors`` and the host router's own password. Passwords are random
    (``dev``: the repository's development ones). An existing set (``out/users.txt``) is kept
    unless ``force``. ``owner``: (uid, gid) of every file (a root setup container writing for
    the non-root services); files are readable by their owner only. ``users_file``: where the
    routers will read users.txt (default: the templates' path, /zenoh/users.txt). Returns
    ``{"written": bool, "dir", "actors", "users"}``."""
    out, templates = Path(out), Path(templates)
    if (out / "users.txt").exists() and not force:
        return {"written": False, "dir": str(out), "users": sorted(read_users(out / "users.txt"))}
    for name in ("router-secure.json5", "host-router-secure.json5"):
        if not (templates / name).is_file():
            raise ConfigError(f"--templates {str(templates)!r} has no {name} (give deploy/zenoh)")
    out.mkdir(parents=True, exist_ok=True)
    for stale in out.glob("client-actor-*.json5"):  # logins of an earlier, larger set
        stale.unlink()
    users = [*ROLE_USERS, HOST_ROUTER_USER, *(actor_user(i) for i in range(actors))]
    passwords = {u: f"{u}{DEV_PASSWORD_SUFFIX}" if dev else secrets.token_urlsafe(24) for u in users}

    def write(name: str, text: str) -> None:
        path = out / name
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.chmod(path, 0o600)
        if owner is not None:
            os.chown(path, *owner)

    for u in users:
        if u != HOST_ROUTER_USER:
            write(f"client-{u}.json5", json.dumps(client_doc(u, passwords[u], ca), indent=1) + "\n")
    for name, extra in (("router-secure.json5", {}),
                        ("host-router-secure.json5", {"transport/auth/usrpwd/password": passwords[HOST_ROUTER_USER]})):
        acl = config_section(str(templates / name), "access_control")
        if users_file:
            extra = {**extra, "transport/auth/usrpwd/dictionary_file": users_file}
        tmp = out / f".{name}.tmp"
        write_config(str(templates / name), str(tmp), {"access_control": expand_acl(acl, actors), **extra})
        write(name, tmp.read_text())
        tmp.unlink()
    # every actor login in one file, for a Kubernetes Secret (write_actor_login picks one out)
    write("actor-logins.json", json.dumps({actor_user(i): client_doc(actor_user(i), passwords[actor_user(i)], ca)
                                           for i in range(actors)}) + "\n")
    # written last: its presence marks a complete set
    write("users.txt", "".join(f"{u}:{passwords[u]}\n" for u in users))
    return {"written": True, "dir": str(out), "actors": actors, "users": users}

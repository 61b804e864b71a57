"""Health check of one zenrl process, from its own liveliness token and stats, for container
probes (Kubernetes ``exec`` probes, Docker health checks)::

    python -m zenrl.health --role learner --id learner [--stats-within-s 30] [--unreachable-ok]
    python -m zenrl.health --role actor --id-prefix 'actor-{hostname}-'
    python -m zenrl.health --role replay --id replay --config league.yaml --agent exploiter
    python -m zenrl.health --role league --id league

The router, run id and client config come from the same environment as the roles
(``ZENRL_ROUTER``, ``ZENRL__RUN_ID``, ``ZENRL__TRANSPORT__CLIENT_CONFIG``; ``--config`` for a
file). ``--agent <id>`` means what it means on the roles: the process is that league agent's,
under the run id ``<run>.<id>`` (the config's ``league.agents``). Healthy (exit 0) when the router holds the process's liveliness token
(``zenrl/<run>/alive/<role>/<id>``) and, with ``--stats-within-s``, the process published its
stats within that time (its main loop is not stuck) and those stats name no stalled thread (the
role loop's ``stalled``: a thread such as the replay's ingest that has finished no unit of work
for a while although its input waits). Otherwise exit 1 with a one-line reason.

``--unreachable-ok`` is for liveness probes: when the router itself cannot be reached the check
passes, because restarting this process would not bring the router back (readiness probes
leave it off, so a pod cut off from the router takes no traffic). ``{hostname}`` in ``--id`` or
``--id-prefix`` is replaced by this machine's host name (a pod's name in Kubernetes): actor ids
are ``actor-<hostname>-<pid>``; ``{ordinal}`` in ``--id`` by the host name's last ``-<n>`` (a
StatefulSet pod's index), ``{login}`` by the user name of ``transport.client_config`` (a secured
actor's id is its login's, ``actor-<i>``).

Prints one JSON object: ``{"ok": bool, "role", "ids": [...], "reason": str}``.
"""

from __future__ import annotations

import argparse
import json
import logging
import socket
import sys
import threading
import time

from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.common.errors import ConfigError, TransportError, ZenrlError
from zenrl.common.transport import Node

log = logging.getLogger(__name__)


def check(role: str, ident: str | None, prefix: str | None, stats_within_s: float | None,
          unreachable_ok: bool, config: str | None = None, connect_timeout_s: float = 3.0,
          agent: str | None = None) -> dict:
    """The health of the matching process(es) of ``role`` as a dict (``ok``: healthy);
    ``agent``: a league agent's process, as the roles' ``--agent`` resolves it."""
    cfg = load_config(config)
    if agent:
        # imported here: a probe without --agent need not load the league's code
        from zenrl.launcher.league_run import agent_config

        cfg = agent_config(cfg, agent)
    run_id = cfg.run_id or "default"
    k = P.Keys(run_id)
    host = socket.gethostname()
    ident = resolve_id(ident, host, cfg.transport.client_config) if ident else None
    prefix = prefix.replace("{hostname}", host) if prefix else None
    out: dict = {"ok": False, "role": role, "run_id": run_id, "ids": [], "reason": ""}
    try:
        node = Node(cfg.transport.router, connect_timeout_s, config_file=cfg.transport.client_config)
    except TransportError as e:
        out["ok"] = unreachable_ok
        out["reason"] = f"router unreachable: {e}"
        return out
    with node:
        latest: dict[str, dict] = {}
        lock = threading.Lock()

        def on_stats(_key: str, payload: bytes) -> None:
            try:
                m = P.Stats.decode(payload)
            except P.ProtocolError:
                return
            if m.role == role:
                with lock:
                    latest[m.id] = m.values

        if stats_within_s:
            node.subscribe(k.stats_all, on_stats)
        ids = [k.parse_alive(x)[1] for x in node.alive_now(k.alive_role(role), min(connect_timeout_s, 2.0))]
        ids = [i for i in ids if (ident is None or i == ident) and (prefix is None or i.startswith(prefix))]
        out["ids"] = sorted(ids)
        if ids and stats_within_s:
            deadline = time.monotonic() + stats_within_s
            while time.monotonic() < deadline:
                with lock:
                    if set(latest) & set(ids):
                        break
                time.sleep(0.05)
        with lock:
            seen = dict(latest)
        want = ident or (prefix + "*" if prefix else "*")
        out["ok"], out["reason"] = judge(role, f"{k.prefix}/alive/{role}/{want}", want, ids, seen, stats_within_s)
        return out


def judge(role: str, token: str, want: str, ids: list[str], stats: dict[str, dict],
          stats_within_s: float | None) -> tuple[bool, str]:
    """The verdict from what was seen: ``ids`` holding the liveliness ``token`` and, per id, the
    values of the newest stats it published while we listened (``stats_within_s`` None: stats
    are not asked for). Returns ``(healthy, one-line reason)``."""
    if not ids:
        return False, f"no liveliness token {token} at the router"
    if not stats_within_s:
        return True, "alive"
    seen = {i: stats[i] for i in sorted(ids) if i in stats}
    if not seen:
        return False, f"{role} {want} holds its token but published no stats within {stats_within_s} s"
    stalled = {i: v.get("stalled") for i, v in seen.items() if v.get("stalled")}
    if stalled:
        i, names = next(iter(stalled.items()))
        return False, f"{role} {i} is alive but stalled: thread {names} makes no progress while its input waits"
    return True, "alive and publishing stats"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m zenrl.health", description=__doc__.split("\n\n")[0])
    p.add_argument("--role", required=True, choices=("actor", "learner", "replay", "evaluator", "league"),
                   help="the process's role")
    p.add_argument("--id", dest="ident", help="its exact id ({hostname}, {ordinal}: the hostname's last -<n>, and "
                   "{login}: the user name of its client config, are replaced)")
    p.add_argument("--id-prefix", help="or a prefix of its id, e.g. 'actor-{hostname}-'")
    p.add_argument("--stats-within-s", type=float, help="also require a stats message within this many seconds")
    p.add_argument("--unreachable-ok", action="store_true", help="pass when the router cannot be reached (liveness)")
    p.add_argument("--config", "-c", help="YAML config file (else the environment alone)")
    p.add_argument("--agent", metavar="ID", help="a league agent's process (a key of the config's league.agents), as "
                   "the role's --agent: look under its run id <run>.<ID>")
    p.add_argument("--connect-timeout-s", type=float, default=3.0, help="how long to wait for the router")
    return p


def resolve_id(ident: str, host: str, client_config: str | None) -> str:
    """``--id`` with its placeholders replaced: ``{hostname}`` by ``host``, ``{ordinal}`` by the
    host name's last ``-<n>`` (a StatefulSet pod's index: zenrl-actor-3 -> 3, the secured actor's
    login actor-<i>), ``{login}`` by the user name of ``client_config`` (a secured actor's id is
    its login's, also where the login is not the pod's ordinal)."""
    ident = ident.replace("{hostname}", host).replace("{ordinal}", host.rsplit("-", 1)[-1])
    if "{login}" in ident:
        from zenrl.identity import client_login

        user, _ = client_login(client_config)
        if not user:
            raise ConfigError(f"--id {ident!r} names {{login}}, and transport.client_config "
                              f"{client_config!r} holds no login")
        ident = ident.replace("{login}", user)
    return ident


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    try:
        out = check(args.role, args.ident, args.id_prefix, args.stats_within_s, args.unreachable_ok, args.config,
                    args.connect_timeout_s, args.agent)
    except ZenrlError as e:
        sys.stdout.write(json.dumps({"ok": False, "role": args.role, "reason": str(e)}) + "\n")
        return 1
    sys.stdout.write(json.dumps(out) + "\n")
    return 0 if out["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())

"""The cluster deployment: docker-compose.yml (+ docker-compose.secure.yml) and deploy/.

* Validation: the compose files parse, every service has an image or a build, every file and
  volume they mount exists (or is written by deploy/zenoh/gen-certs.sh, or by the secured file's
  one-shot ``credentials`` service into its volume), every variable has a
  default, every command parses with zenrl's own CLI, every ZENRL__ variable and the mounted
  config resolve to a valid configuration, and the router image is the installed eclipse-zenoh.
* The cluster as local processes: each service's ``command`` runs as an OS process
  (``python -m zenrl.cli <command...>``) with that service's environment, ``router`` resolved
  to 127.0.0.1, the router container replaced by an in-process router opened from the same
  JSON5 file (free port, no plugins), container paths mapped to the repo and a tmp dir; three
  actors; learning proceeds; the learner is stopped with SIGTERM and restarted, and resumes
  from its checkpoint; everything stops cleanly.
* The cluster on a real Docker engine (where ``docker info`` answers and the images build;
  otherwise skipped with the reason): ``up -d --build``, the first update within 60 s, ``status``,
  ``--scale actor=4``, ``stop`` + ``up`` resumes, a crashed learner process is restarted by the
  engine and resumes, ``down``; the secured variant makes fresh credentials on its first ``up``,
  refuses a client without credentials or with the repository's development password, drops an
  actor's attempt to publish weights or to publish as another actor, and gives ``--scale actor=3``
  three distinct identities. Failures show the engine's own output.
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import re
import shutil
import signal
import subprocess
import threading
import time
import uuid
from pathlib import Path
from typing import Any, Callable

import pytest
import yaml

from tests.conftest import ROOT, Procs, free_port, wait_until

pytestmark = pytest.mark.integration

COMPOSE = ROOT / "docker-compose.yml"
SECURE = ROOT / "docker-compose.secure.yml"
LEAGUE = ROOT / "docker-compose.league.yml"
LEAGUE_SECURE = ROOT / "docker-compose.league-secure.yml"
DOCKERFILE = ROOT / "deploy" / "Dockerfile"
ZENOH_DIR = ROOT / "deploy" / "zenoh"
CERTS_DIR = ZENOH_DIR / "certs"  # written by gen-certs.sh, not in git
ZENOH_PORT = 7447
# keys of a Zenoh config that hold file paths (mapped from the container to this machine)
ZENOH_PATH_KEYS = ("transport/link/tls/listen_private_key", "transport/link/tls/listen_certificate",
                   "transport/link/tls/root_ca_certificate", "transport/auth/usrpwd/dictionary_file")

# budgets: learner updates, not wall-clock time; the deadlines only bound a hung run
UPDATES_BEFORE_RESTART = 300
UPDATES_AFTER_RESTART = 150


# ---------------------------------------------------------------------------------------------
# Reading compose files the way `docker compose` does (the subset these files use)
# ---------------------------------------------------------------------------------------------
_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?::?-([^}]*))?\}")


def interpolate(value: Any, env: dict[str, str]) -> Any:
    """``${VAR}`` / ``${VAR:-default}`` substitution in every string of ``value``."""
    if isinstance(value, str):
        return _VAR.sub(lambda m: env.get(m.group(1)) or (m.group(2) or ""), value).replace("$$", "$")
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    return value


def parse_volume(spec: str) -> tuple[str, str]:
    """Short volume syntax ``source:target[:mode]`` -> (source, target)."""
    parts = spec.split(":")
    return parts[0], parts[1]


def _merge_service(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if k == "volumes":  # merged by target path
            merged = {parse_volume(s)[1]: s for s in base.get(k, [])}
            merged.update({parse_volume(s)[1]: s for s in v})
            out[k] = list(merged.values())
        elif k == "ports":
            out[k] = list(dict.fromkeys([*base.get(k, []), *v]))
        elif isinstance(v, dict) and isinstance(base.get(k), dict):
            out[k] = {**base[k], **v} if k == "environment" else _merge_service(base[k], v)
        else:
            out[k] = v
    return out


def load_compose(*files: Path, env: dict[str, str] | None = None) -> dict[str, Any]:
    """The merged, interpolated compose model of ``files`` (later files override)."""
    model: dict[str, Any] = {"services": {}, "volumes": {}}
    for f in files:
        # interpolated before merging, as compose does: volumes merge by their (interpolated) target
        doc = interpolate(yaml.safe_load(f.read_text()), dict(env or {}))
        for name, svc in doc.get("services", {}).items():
            model["services"][name] = _merge_service(model["services"].get(name, {}), svc)
        model["volumes"].update(doc.get("volumes") or {})
    return model


def raw_variables(*files: Path) -> list[tuple[str, str | None]]:
    """Every ``${VAR[:-default]}`` in ``files``: (name, default or None)."""
    return [(m.group(1), m.group(2)) for f in files for m in _VAR.finditer(f.read_text())]


def setup_services(model: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """One-shot services of the zenrl image that run before the router (the secured file's
    ``credentials``): no restart policy, no profile."""
    return {n: s for n, s in model["services"].items()
            if (s.get("build") or {}).get("target") == "zenrl" and s.get("restart") == "no" and not s.get("profiles")}


def zenrl_services(model: dict[str, Any], profiles: tuple[str, ...] = ()) -> dict[str, dict[str, Any]]:
    """Services running the zenrl image, active with ``profiles`` (not the setup services)."""
    setup = setup_services(model)
    return {n: s for n, s in model["services"].items()
            if (s.get("build") or {}).get("target") == "zenrl" and n not in setup
            and (not s.get("profiles") or set(s["profiles"]) & set(profiles))}


def router_service(model: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    (name, svc), = [(n, s) for n, s in model["services"].items() if str(s.get("image", "")).startswith("eclipse/zenoh:")]
    return name, svc


def host_path(svc: dict[str, Any], path: str, named_volumes: dict[str, Path],
              bind_overrides: dict[Path, Path] | None = None) -> str:
    """A container path of ``svc`` -> the path on this machine (bind mounts relative to the
    repo, named volumes to ``named_volumes``); other strings are returned unchanged."""
    for spec in svc.get("volumes", []):
        src, target = parse_volume(spec)
        if path == target or path.startswith(target.rstrip("/") + "/"):
            if src.startswith((".", "/")):
                base = (ROOT / src).resolve()
                for old, new in (bind_overrides or {}).items():
                    if base == old or old in base.parents:
                        base = new / base.relative_to(old)
            else:
                base = named_volumes[src]
            return str(base) + path[len(target):]
    return path


# ---------------------------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------------------------
def test_compose_files_are_complete_and_consistent():
    from zenrl.cli import build_parser
    from zenrl.common.config import load_config

    for files in ((COMPOSE,), (COMPOSE, SECURE), (COMPOSE, LEAGUE), (COMPOSE, LEAGUE, SECURE, LEAGUE_SECURE)):
        # every variable has a default: `docker compose up` needs no .env
        for name, default in raw_variables(*files):
            assert default is not None, f"${{{name}}} in {[f.name for f in files]} has no default"
        defaults = dict(raw_variables(*files))
        assert defaults.get("ZENRL_TORCH_INDEX_URL") == "https://download.pytorch.org/whl/cpu"
        assert defaults.get("ZENRL_BUILD_NETWORK") == "default"
        model = load_compose(*files)
        services = model["services"]
        # what is published on the host is bound to loopback unless the user says otherwise
        for name, svc in services.items():
            for port in svc.get("ports", []):
                assert str(port).startswith("127.0.0.1:"), f"service {name} publishes {port} on every interface"
        assert {"router", "replay", "learner", "actor", "evaluator", "tensorboard"} <= set(services)
        for name, svc in services.items():
            assert svc.get("image") or svc.get("build"), f"service {name} has neither image nor build"
            if svc.get("build"):
                assert (ROOT / svc["build"]["context"] / svc["build"]["dockerfile"]).is_file()
                assert svc["build"].get("network") == "default", f"service {name}: build network not from ZENRL_BUILD_NETWORK"
                target = svc["build"].get("target")
                assert target is None or re.search(rf"^FROM .* AS {target}$", DOCKERFILE.read_text(), re.M), (name, target)
            for spec in svc.get("volumes", []):
                src, _ = parse_volume(spec)
                if src.startswith((".", "/")):
                    p = (ROOT / src).resolve()
                    if CERTS_DIR in p.parents:  # generated: gen-certs.sh must write it
                        assert p.name in (ZENOH_DIR / "gen-certs.sh").read_text(), (name, spec)
                    else:
                        assert p.exists(), f"service {name} mounts {src}, which does not exist"
                else:
                    assert src in model["volumes"], f"service {name} uses undeclared volume {src}"
            for dep, cond in (svc.get("depends_on") or {}).items():
                assert dep in services and cond["condition"] in ("service_healthy", "service_started",
                                                                 "service_completed_successfully"), (name, dep)
                if cond["condition"] == "service_completed_successfully":
                    assert dep in setup_services(model), (name, dep)

        rname, router = router_service(model)
        assert router["image"] == f"eclipse/zenoh:{importlib.metadata.version('eclipse-zenoh')}"
        assert "healthcheck" in router
        # (secured: written into a volume by the setup service: test_secure_compose_makes_fresh_credentials)
        config_file = host_path(router, router["command"][router["command"].index("-c") + 1],
                                {v: Path("/nonexistent") for v in model["volumes"]})
        assert Path(config_file).is_file() or Path(config_file).parent == Path("/nonexistent"), config_file

        parser = build_parser()
        zs = zenrl_services(model, profiles=("gpu", "tools"))
        assert {"replay", "learner", "learner-gpu", "actor", "evaluator", "status"} <= set(zs)
        for name, svc in zs.items():
            args = parser.parse_args(svc["command"])  # exits (fails the test) on an unknown option
            assert svc["depends_on"][rname]["condition"] == "service_healthy", name
            env = {k: str(v) for k, v in svc["environment"].items()}
            proto, host = re.match(r"^(tcp|tls)/([^:]+):(\d+)$", env["ZENRL_ROUTER"]).group(1, 2)
            assert host == rname
            assert (proto == "tls") == (SECURE in files), (name, env["ZENRL_ROUTER"])
            if SECURE in files:  # a login of the credentials volume, or the router refuses it
                assert {"ZENRL__TRANSPORT__CLIENT_CONFIG", "ZENRL_ACTOR_LOGINS"} & set(env), f"{name} has no login"
            # the config the service reads, with its environment, is valid
            named = {v: Path("/nonexistent") for v in model["volumes"]}
            cfg = load_config(host_path(svc, args.config, named), environ=env)
            assert cfg.run_id and cfg.runs_dir == "/runs"
            for var in ("ZENRL__TRANSPORT__CLIENT_CONFIG", "ZENRL_ACTOR_LOGINS"):
                if var in env:  # in the volume the setup service writes (test_secure_compose_makes_fresh_credentials)
                    assert Path("/nonexistent") in Path(host_path(svc, env[var] + "/x", named)).parents, (name, var)
            if svc.get("restart") != "no":
                assert svc.get("restart") in ("always", "unless-stopped", "on-failure"), name

        if LEAGUE in files:
            _check_league_services(zs, parser)
        for name, svc in setup_services(model).items():
            parser.parse_args(svc["command"])
        actor = zs["actor"]
        assert "--slot" not in actor["command"] and "--id" not in actor["command"]
        assert "container_name" not in actor and "ports" not in actor, "actors must be scalable"
        for name in ("learner", "learner-gpu"):
            assert "--auto-resume" in zs[name]["command"]
            assert int(zs[name]["stop_grace_period"].rstrip("s")) >= 30, "the learner needs time to checkpoint"
        assert zs["learner-gpu"]["deploy"]["resources"]["reservations"]["devices"][0]["capabilities"] == ["gpu"]


def _check_league_services(zs: dict[str, dict[str, Any]], parser: Any) -> None:
    """The league overlay: the league service, and every agent of the config's league has its
    replay, learner and actors (--agent), whose resolved configs are that agent's."""
    from zenrl.common.config import load_config
    from zenrl.launcher.league_run import agent_config

    assert {"league", "league-status", "replay-exploiter", "learner-exploiter", "actor-exploiter"} <= set(zs)
    named = {"runs": Path("/nonexistent")}
    by_agent: dict[str, set[str]] = {}
    for name, svc in zs.items():
        args = parser.parse_args(svc["command"])
        env = {k: str(v) for k, v in svc["environment"].items()}
        cfg = load_config(host_path(svc, args.config, named), environ=env)
        assert cfg.league.enabled, name
        if name in ("exporter", "status"):  # they watch the main agent's processes
            assert cfg.run_id == "league-cluster.main", name
            continue
        assert cfg.run_id == "league-cluster", name
        if name in ("league", "league-status"):
            continue
        assert getattr(args, "agent", None), f"{name}: a league cluster's {svc['command'][0]} needs --agent"
        acfg = agent_config(cfg, args.agent)
        assert acfg.run_id == f"league-cluster.{args.agent}" and acfg.league.self_reset, name
        by_agent.setdefault(args.agent, set()).add(svc["command"][0])
        if svc["command"][0] == "learner":
            assert "--auto-resume" in svc["command"], name
        if svc["command"][0] == "actor":
            assert "--slot" not in svc["command"] and "--id" not in svc["command"], name
        if svc["command"][0] in ("replay", "learner"):
            assert any(parse_volume(v)[1] == "/runs" for v in svc["volumes"]), name
            assert svc.get("restart") == "unless-stopped", name  # a reset exits 75 for the engine to restart
    assert set(by_agent) == set(cfg.league.agents)
    for agent, roles in by_agent.items():
        assert {"replay", "learner", "actor"} <= roles, (agent, roles)
    # the agents' replays share the host: each checks its ring against its share of the memory
    replays = [n for n, svc in zs.items() if svc["command"][0] == "replay"]
    for name in replays:
        env = {k: str(v) for k, v in zs[name]["environment"].items()}
        rcfg = load_config(host_path(zs[name], parser.parse_args(zs[name]["command"]).config, named), environ=env)
        assert rcfg.replay.replays_per_machine == len(replays), (name, rcfg.replay.replays_per_machine)


@pytest.mark.parametrize("files", [(COMPOSE, SECURE), (COMPOSE, LEAGUE, SECURE, LEAGUE_SECURE)],
                         ids=["cluster", "league"])
def test_secure_compose_makes_fresh_credentials(tmp_path, files):
    """The secured compose file makes its credentials on the first `up` (the one-shot
    `credentials` service, which the router waits for) and every service reads its login from
    that volume: no service mounts the repository's development passwords; each role's login is
    its own (a league's second agent too), every actor of any agent takes one from the pool.
    Running the service's command writes exactly the files the router and the services are given."""
    import zenoh

    from zenrl.cli import build_parser
    from zenrl.identity import is_dev_password, make_credentials, read_users

    model = load_compose(*files)
    (setup_name, setup), = setup_services(model).items()
    args = build_parser().parse_args(setup["command"])
    assert args.func.__name__ == "cmd_credentials" and not args.dev and not args.force
    out_volume = next(parse_volume(v)[0] for v in setup["volumes"] if parse_volume(v)[1] == args.out)
    assert out_volume in model["volumes"]

    def in_credentials(svc: dict[str, Any], path: str) -> str:
        """``path`` of ``svc`` as a file name in the credentials volume (or fail)."""
        for spec in svc["volumes"]:
            src, target = parse_volume(spec)
            if path.startswith(target.rstrip("/") + "/"):
                assert src == out_volume, (path, spec)
                return path[len(target.rstrip("/")) + 1:]
        raise AssertionError(f"{path} is not in a volume")

    # the router: waits for the set, reads its config and users file from it
    rname, router = router_service(model)
    assert router["depends_on"][setup_name]["condition"] == "service_completed_successfully"
    creds = tmp_path / "credentials"
    templates = host_path(setup, args.templates, {})
    made = make_credentials(templates, creds, args.actors, ca=args.ca, users_file=args.users_file)
    assert made["written"] and args.actors >= 2
    router_cfg = in_credentials(router, router["command"][router["command"].index("-c") + 1])
    users_path = json.loads(zenoh.Config.from_file(str(creds / router_cfg)).get_json("transport/auth/usrpwd/dictionary_file"))
    users = read_users(creds / in_credentials(router, users_path))
    assert not any(is_dev_password(p) for p in users.values())
    # every zenrl service: its login from that volume (actors: the pool of actor logins)
    for name, svc in zenrl_services(model, profiles=("gpu", "tools", "monitoring")).items():
        env = svc["environment"]
        assert not any("deploy/zenoh/users.txt" in v or "deploy/zenoh/client-" in v for v in svc["volumes"]), name
        role = svc["command"][0]
        if role == "actor":
            pool = creds / in_credentials(svc, env["ZENRL_ACTOR_LOGINS"] + "/x")
            logins = sorted(pool.parent.glob("client-actor-*.json5"))
            assert len(logins) == args.actors, name
            client_files = logins
        else:
            client_files = [creds / in_credentials(svc, env["ZENRL__TRANSPORT__CLIENT_CONFIG"])]
        for f in client_files:
            auth = json.loads(zenoh.Config.from_file(str(f)).get_json("transport/auth/usrpwd"))
            assert users.get(auth["user"]) == auth["password"], (name, f.name)
            if role == "actor":
                assert re.fullmatch(r"actor-\d+", auth["user"]), (name, auth["user"])
            else:  # the role's own login; watchers (status, exporter, league status) the monitor's
                watcher = role in ("status", "exporter") or svc["command"][:2] == ["league", "status"]
                assert auth["user"] == ("monitor" if watcher else role), (name, auth["user"])
            ca = json.loads(zenoh.Config.from_file(str(f)).get_json("transport/link/tls/root_ca_certificate"))
            assert host_path(svc, ca, {}) == str(CERTS_DIR / "ca.pem"), (name, ca)
    acl = json.loads(zenoh.Config.from_file(str(creds / router_cfg)).get_json("access_control"))
    assert {u for s in acl["subjects"] for u in (s.get("usernames") or [])} == set(users)


def test_dockerfile_installs_every_package():
    import tomllib

    text = DOCKERFILE.read_text()
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    for src in set(pyproject["tool"]["setuptools"]["package-dir"].values()):
        assert re.search(rf"^COPY {src}/ ", text, re.M), f"Dockerfile does not copy {src}/"
    assert re.search(r'^ENTRYPOINT \["zenrl"\]$', text, re.M)
    assert re.search(r"^USER (?!root)\w+", text, re.M)
    assert "download.pytorch.org/whl/cpu" in text
    # no `# syntax=` line: BuildKit would fetch that frontend image from a registry
    assert not re.search(r"^#\s*syntax=", text, re.M | re.I)
    # zenrl is installed from a wheel built in another stage: the final image holds no source
    # tree, which would shadow the installed package from its working directory
    zenrl_stage = text[text.index("AS zenrl"):]
    assert "COPY --from=wheel" in zenrl_stage and "pip install --no-deps /tmp/wheels/" in zenrl_stage
    assert not re.search(r"^COPY (zenrl|common|actor|learner|replay|games)/", zenrl_stage, re.M)
    # dependencies are installed before zenrl itself (build cache)
    assert zenrl_stage.index("pip install -r") < zenrl_stage.index("COPY --from=wheel")


# ---------------------------------------------------------------------------------------------
# The cluster, two ways: local OS processes, or docker compose
# ---------------------------------------------------------------------------------------------
class Monitor:
    """Listens to the run's stats and eval messages through the router."""

    def __init__(self, endpoint: str, run_id: str, config_file: str | None = None) -> None:
        from zenrl.common import protocol as P
        from zenrl.common.transport import Node

        self._P = P
        self.keys = P.Keys(run_id)
        self.node = Node(endpoint, 60.0, config_file=config_file)
        self.lock = threading.Lock()
        self.learner_updates: list[int] = []
        self.evals: list[float] = []
        self.actors: dict[str, dict[str, Any]] = {}
        self.node.subscribe(self.keys.stats_all, self._on_stats)
        self.node.subscribe(self.keys.eval, self._on_eval)

    def _on_stats(self, _key: str, payload: bytes) -> None:
        m = self._P.Stats.decode(payload)
        with self.lock:
            if m.role == "learner":
                self.learner_updates.append(int(m.values["updates"]))
            elif m.role == "actor":
                self.actors[m.id] = dict(m.values)

    def _on_eval(self, _key: str, payload: bytes) -> None:
        m = self._P.EvalResult.decode(payload)
        with self.lock:
            self.evals.append(float(m.returns.mean()))

    def updates(self) -> int:
        with self.lock:
            return max(self.learner_updates, default=-1)

    def forget_learner(self) -> None:
        with self.lock:
            self.learner_updates.clear()

    def close(self) -> None:
        self.node.close()


class LocalCluster:
    """Runs the compose services as local processes against an in-process router."""

    def __init__(self, files: tuple[Path, ...], tmp: Path, procs: Procs, run_id: str,
                 bind_overrides: dict[Path, Path] | None = None) -> None:
        self.model = load_compose(*files, env={"ZENRL_RUN_ID": run_id})
        self.tmp, self.procs, self.run_id = tmp, procs, run_id
        self.bind_overrides = bind_overrides or {}
        self.named = {v: tmp / "volumes" / v for v in self.model["volumes"]}
        for p in self.named.values():
            p.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self._actor_logins: Path | None = None
        for name, svc in setup_services(self.model).items():  # before the router, as compose does
            self._run_setup(name, svc)
        self.router_name, router = router_service(self.model)
        self._router = self._open_router(router)
        self.services = zenrl_services(self.model, profiles=("tools",))
        self.running: dict[str, list[Any]] = {}
        self.endpoint = self._endpoint(router_proto=self._router_proto)

    # -- the router ---------------------------------------------------------------------------
    def _path(self, svc: dict[str, Any], path: str) -> str:
        return host_path(svc, path, self.named, self.bind_overrides)

    def _open_router(self, svc: dict[str, Any]):
        import zenoh

        from zenrl.common.transport import init_zenoh_logging

        init_zenoh_logging("error")
        cfg = zenoh.Config.from_file(self._path(svc, svc["command"][svc["command"].index("-c") + 1]))
        eps = json.loads(cfg.get_json("listen/endpoints"))
        self._router_proto = eps[0].split("/", 1)[0]
        cfg.insert_json5("listen/endpoints", json.dumps([f"{self._router_proto}/127.0.0.1:{self.port}"]))
        for key in ZENOH_PATH_KEYS:
            value = json.loads(cfg.get_json(key))
            if value:
                cfg.insert_json5(key, json.dumps(self._path(svc, value)))
        cfg.insert_json5("plugins", "{}")  # zenohd's REST plugin (health check) is not loadable here
        return zenoh.open(cfg)

    def _run_setup(self, name: str, svc: dict[str, Any]) -> None:
        import sys

        args = [self._map(svc, str(a)) for a in svc["command"]]
        if "--owner" in args:  # the container's root chowns to the services' user; not here
            i = args.index("--owner")
            del args[i:i + 2]
        r = subprocess.run([sys.executable, "-m", "zenrl.cli", *args], cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, f"setup service {name}: {r.stderr[-2000:]}"

    def _endpoint(self, router_proto: str) -> str:
        return f"{router_proto}/127.0.0.1:{self.port}"

    # -- zenrl services -----------------------------------------------------------------------
    def _client_config(self, svc: dict[str, Any], path: str) -> str:
        """The service's client config with its container paths mapped, as a tmp JSON file."""
        import zenoh

        transport = json.loads(zenoh.Config.from_file(self._path(svc, path)).get_json("transport"))
        tls = transport["link"]["tls"]
        if tls.get("root_ca_certificate"):
            tls["root_ca_certificate"] = self._path(svc, tls["root_ca_certificate"])
        out = self.tmp / f"client-{uuid.uuid4().hex[:8]}.json"
        out.write_text(json.dumps({"transport": transport}))
        return str(out)

    def _map(self, svc: dict[str, Any], value: str) -> str:
        m = re.match(r"^(tcp|tls)/([^:/]+):(\d+)$", value)
        if m and m.group(2) in self.model["services"] and int(m.group(3)) == ZENOH_PORT:
            return f"{m.group(1)}/127.0.0.1:{self.port}"
        return self._path(svc, value) if value.startswith("/") else value

    def service_env(self, name: str) -> dict[str, str]:
        svc = self.services[name]
        env = {k: self._map(svc, str(v)) for k, v in svc.get("environment", {}).items()}
        if "ZENRL__TRANSPORT__CLIENT_CONFIG" in env:
            env["ZENRL__TRANSPORT__CLIENT_CONFIG"] = self._client_config(svc, svc["environment"]["ZENRL__TRANSPORT__CLIENT_CONFIG"])
        if "ZENRL_ACTOR_LOGINS" in env:
            env["ZENRL_ACTOR_LOGINS"] = str(self._logins(svc, svc["environment"]["ZENRL_ACTOR_LOGINS"]))
        return env

    def _logins(self, svc: dict[str, Any], pool: str) -> Path:
        """The pool of actor logins with container paths mapped: one copy that every actor
        process of this cluster shares (so that each takes a different login, as containers do)."""
        if self._actor_logins is None:
            self._actor_logins = self.tmp / "actor-logins"
            self._actor_logins.mkdir()
            for f in Path(self._path(svc, pool)).glob("client-actor-*.json5"):
                Path(self._client_config(svc, str(f))).rename(self._actor_logins / f.name)
        return self._actor_logins

    def service_args(self, name: str) -> list[str]:
        svc = self.services[name]
        return [self._map(svc, str(a)) for a in svc["command"]]

    def start(self, name: str, replicas: int = 1) -> None:
        for i in range(replicas):
            pname = f"{name}-{len(self.running.get(name, [])) + 1}"
            p = self.procs.zenrl(pname, self.service_args(name), self.service_env(name))
            self.running.setdefault(name, []).append((pname, p))

    def up(self, actors: int) -> None:
        for name, svc in self.services.items():
            if "tools" not in (svc.get("profiles") or []):
                self.start(name, actors if name == "actor" else 1)

    def stop(self, name: str, timeout_s: float = 60.0) -> list[int]:
        codes = []
        for pname, p in self.running.pop(name, []):
            p.send_signal(signal.SIGTERM)
            try:
                codes.append(p.wait(timeout=timeout_s))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
                raise AssertionError(f"{pname} did not stop within {timeout_s} s of SIGTERM")
        return codes

    def logs(self, name: str) -> str:
        return "".join(self.procs.log(f"{name}-{i}") for i in range(1, 10))

    def status(self) -> dict[str, Any]:
        import sys

        out = subprocess.run([sys.executable, "-m", "zenrl.cli", *self.service_args("status")], cwd=ROOT, timeout=60,
                             env=dict(os.environ, **self.service_env("status")), capture_output=True, text=True)
        assert out.returncode == 0, out.stderr[-2000:]
        return json.loads(out.stdout)

    def monitor_client_config(self) -> str | None:
        env = self.service_env("status")
        return env.get("ZENRL__TRANSPORT__CLIENT_CONFIG")

    def down(self) -> dict[str, list[int]]:
        codes = {}
        for name in ("actor", "evaluator", "learner", "replay"):  # the replay last, as `zenrl run` does
            codes[name] = self.stop(name)
        for name in list(self.running):
            codes[name] = self.stop(name)
        self._router.close()
        return codes

    def leftovers(self) -> list[int]:
        pids = [p.pid for _, p in self.procs.procs if p.poll() is None]
        return pids


def _checkpoint_updates(log: str, pattern: str) -> int | None:
    found = re.findall(pattern, log)
    return int(found[-1]) if found else None


def wait_for(cond, timeout_s: float, what: str, cluster, log_of: str | None = None) -> None:
    """:func:`wait_until`, adding the tail of a service's log to the failure message."""
    try:
        wait_until(cond, timeout_s, what, 0.5)
    except AssertionError as e:
        tail = f"\n--- {log_of} log ---\n{cluster.logs(log_of)[-4000:]}" if log_of else ""
        raise AssertionError(f"{e}{tail}") from None


def run_scenario(cluster: LocalCluster, run_id: str, actors: int, restart: bool) -> None:
    """Up with ``actors`` actors; learning proceeds; (restart) SIGTERM the learner, restart it,
    it resumes from its checkpoint; down; every role exited 0 and nothing is left running."""
    cluster.up(actors=actors)
    mon = Monitor(cluster.endpoint, run_id, cluster.monitor_client_config())
    try:
        first = UPDATES_BEFORE_RESTART if restart else UPDATES_BEFORE_RESTART // 3
        wait_for(lambda: mon.updates() >= first, 240, f"learner updates >= {first}", cluster, "learner")
        wait_for(lambda: len(mon.actors) >= actors, 60, f"stats of {actors} actors", cluster, "actor")
        wait_for(lambda: mon.evals, 120, "an evaluation", cluster, "evaluator")
        # actors claimed distinct exploration slots (no --slot given)
        slots = [a.get("slot") for a in mon.actors.values()]
        assert len(set(slots)) == len(slots), f"actors share slots: {slots}"
        status = cluster.status()
        roles = sorted(p["role"] for p in status["processes"])
        assert roles.count("actor") == actors and {"learner", "replay", "evaluator"} <= set(roles), roles

        if restart:
            codes = cluster.stop("learner")
            assert codes == [0], f"learner exit codes {codes}\n{cluster.logs('learner')[-3000:]}"
            saved = _checkpoint_updates(cluster.logs("learner"), r"checkpoint \S*ckpt-(\d+)\.pt")
            assert saved is not None and saved >= first, f"no final checkpoint\n{cluster.logs('learner')[-3000:]}"
            mon.forget_learner()
            cluster.start("learner")
            wait_for(lambda: "resumed from" in cluster.logs("learner"), 120, "the learner to resume", cluster, "learner")
            resumed = _checkpoint_updates(cluster.logs("learner"), r"resumed from \S*ckpt-\d+\.pt: (\d+) updates")
            assert resumed == saved, (resumed, saved)
            target = saved + UPDATES_AFTER_RESTART
            wait_for(lambda: mon.updates() >= target, 240, f"learner updates >= {target} after the restart", cluster, "learner")
            with mon.lock:
                after = list(mon.learner_updates)
            assert min(after) >= saved, f"the restarted learner counted from {min(after)}, not from {saved}"
    finally:
        mon.close()
    codes = cluster.down()
    assert all(c == 0 for cs in codes.values() for c in cs), codes
    assert not cluster.leftovers(), cluster.leftovers()


def test_cluster_learns_scales_and_resumes(tmp_path, procs, run_id):
    """The plain cluster (docker-compose.yml) as local processes: 3 actors, learner restart with
    resume. (The same on a real engine: test_docker_cluster_up_scale_resume_crash_down.)"""
    cluster = LocalCluster((COMPOSE,), tmp_path, procs, run_id)
    run_scenario(cluster, run_id, actors=3, restart=True)
    ckpts = list((tmp_path / "volumes" / "runs" / run_id / "checkpoints").glob("ckpt-*.pt"))
    assert ckpts, "no checkpoint in the runs volume"
    assert list((tmp_path / "volumes" / "runs" / run_id / "tb").rglob("events.out.tfevents.*")), "no TensorBoard events"


def test_secure_cluster_runs_under_acl(tmp_path, procs, run_id):
    """The secured cluster (TLS, passwords, access control) as local processes: every role
    still does its job."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed (needed by deploy/zenoh/gen-certs.sh)")
    certs = tmp_path / "certs"
    subprocess.run(["bash", str(ZENOH_DIR / "gen-certs.sh"), str(certs)], check=True, capture_output=True, timeout=60)
    cluster = LocalCluster((COMPOSE, SECURE), tmp_path, procs, run_id, bind_overrides={CERTS_DIR: certs})
    assert cluster.endpoint.startswith("tls/")
    run_scenario(cluster, run_id, actors=2, restart=False)


# ---------------------------------------------------------------------------------------------
# The cluster on a real Docker engine
# ---------------------------------------------------------------------------------------------
# Machines without a container registry make the base images and serve the CPU torch wheel on
# this loopback index (../shared/tools/docker-engine.sh); builds reach it over the host network.
LOOPBACK_TORCH_INDEX = "http://127.0.0.1:8099/"
# Build errors that mean the images' sources (base images, package indexes) cannot be reached
# from this machine: the docker tests skip on these; any other build error fails them.
UNREACHABLE = re.compile(
    r"Could not find a version that satisfies|No matching distribution found|Temporary failure in name"
    r"|Name or service not known|pull access denied|failed to resolve source metadata|no such host"
    r"|Network is unreachable|Max retries exceeded|manifest unknown|failed to do request"
    r"|Connection refused|repository does not exist", re.I)


def docker_output(r: subprocess.CompletedProcess) -> str:
    """A failed docker command with the engine's own words (stderr first, then stdout)."""
    args = " ".join(map(str, r.args))
    return f"`{args}` exited {r.returncode}\n--- stderr ---\n{(r.stderr or '')[-6000:]}\n--- stdout ---\n{(r.stdout or '')[-3000:]}"


def docker_build_env() -> dict[str, str]:
    """ZENRL_TORCH_INDEX_URL / ZENRL_BUILD_NETWORK as given, else the loopback index where one answers."""
    import urllib.request

    env = {k: os.environ[k] for k in ("ZENRL_TORCH_INDEX_URL", "ZENRL_BUILD_NETWORK") if k in os.environ}
    if "ZENRL_TORCH_INDEX_URL" not in env:
        try:
            with urllib.request.urlopen(LOOPBACK_TORCH_INDEX + "torch/", timeout=2) as r:
                if r.status == 200:
                    env["ZENRL_TORCH_INDEX_URL"] = LOOPBACK_TORCH_INDEX
                    env.setdefault("ZENRL_BUILD_NETWORK", "host")
        except OSError:
            pass
    return env


def docker_available() -> tuple[bool, str]:
    """(True, "") where a Docker engine answers and the compose v2 plugin is installed, else
    (False, the reason in one line)."""
    if shutil.which("docker") is None:
        return False, "no docker CLI"
    try:
        r = subprocess.run(["docker", "info"], capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired) as e:
        return False, f"docker info failed: {e}"
    if r.returncode != 0:
        return False, "no Docker engine reachable (docker info: " + (r.stderr.strip().splitlines() or ["?"])[-1] + ")"
    if subprocess.run(["docker", "compose", "version"], capture_output=True, timeout=20).returncode != 0:
        return False, "the docker compose plugin is not installed"
    return True, ""


@pytest.fixture(scope="module")
def docker_images():
    """Builds the compose images under tags of this test session (so a user's zenrl:latest is
    left alone); yields the environment that makes compose use them; removes the tags after."""
    ok, why = docker_available()
    if not ok:
        pytest.skip(f"docker compose tests skipped: {why}")
    tag = f"zenrltest-{uuid.uuid4().hex[:8]}"
    images = {"ZENRL_IMAGE": f"{tag}:latest", "ZENRL_TENSORBOARD_IMAGE": f"{tag}-tensorboard:latest"}
    env = dict(os.environ, **images, **docker_build_env())
    try:
        r = subprocess.run(["docker", "compose", "-p", tag, "-f", str(COMPOSE), "build"], cwd=ROOT, env=env,
                           capture_output=True, text=True, timeout=1800)
    except subprocess.TimeoutExpired:
        pytest.skip("docker compose tests skipped: the images did not build within 30 min")
    if r.returncode != 0:
        out = (r.stderr or "") + (r.stdout or "")
        m = UNREACHABLE.search(out)
        if m:
            line = next((ln.strip() for ln in out.splitlines() if m.group(0) in ln), m.group(0))
            pytest.skip(f"docker compose tests skipped: the images cannot be built here ({line[:200]})")
        raise AssertionError("the compose images do not build:\n" + docker_output(r))
    yield {**images, **docker_build_env()}
    subprocess.run(["docker", "rmi", *images.values()], capture_output=True, timeout=120)


class DockerCluster:
    """The cluster through `docker compose`, on a free host port, as a project of its own."""

    def __init__(self, files: tuple[Path, ...], run_id: str, images: dict[str, str], actors: int) -> None:
        self.files, self.run_id = files, run_id
        self.project = f"zenrltest{uuid.uuid4().hex[:8]}"
        self.port = free_port()
        self.env = dict(os.environ, **images, ZENRL_RUN_ID=run_id, ZENRL_ROUTER_PORT=str(self.port),
                        TENSORBOARD_PORT=str(free_port()), ZENRL_ACTORS=str(actors))
        self.secure = SECURE in files
        self.endpoint = f"{'tls' if self.secure else 'tcp'}/127.0.0.1:{self.port}"
        if self.secure and not (CERTS_DIR / "ca.pem").is_file():
            subprocess.run(["bash", str(ZENOH_DIR / "gen-certs.sh")], check=True, capture_output=True, timeout=60)

    def compose(self, *args: str, timeout: float = 600, check: bool = True) -> subprocess.CompletedProcess:
        cmd = ["docker", "compose", "-p", self.project]
        for f in self.files:
            cmd += ["-f", str(f)]
        r = subprocess.run([*cmd, *args], cwd=ROOT, env=self.env, capture_output=True, text=True, timeout=timeout)
        if check and r.returncode != 0:
            raise AssertionError(docker_output(r))
        return r

    def containers(self, service: str | None = None) -> list[str]:
        return self.compose("ps", "-a", "-q", *([service] if service else []), check=False).stdout.split()

    def inspect(self, cid: str, fmt: str) -> str:
        r = subprocess.run(["docker", "inspect", "-f", fmt, cid], capture_output=True, text=True, timeout=60)
        if r.returncode != 0:
            raise AssertionError(docker_output(r))
        return r.stdout.strip()

    def exit_codes(self) -> dict[str, int]:
        """Exit code of every stopped zenrl container, by container name."""
        out = {}
        for name in ("replay", "learner", "actor", "evaluator"):
            for cid in self.containers(name):
                out[self.inspect(cid, "{{.Name}}")] = int(self.inspect(cid, "{{.State.ExitCode}}"))
        return out

    def logs(self, name: str) -> str:
        return self.compose("logs", "--no-color", name, check=False).stdout

    def status(self) -> dict[str, Any]:
        out = self.compose("run", "--rm", "-T", "status", timeout=180)
        return json.loads(out.stdout.strip().splitlines()[-1])

    def roles(self) -> list[str]:
        return sorted(p["role"] for p in self.status()["processes"])

    def crash(self, service: str) -> None:
        """SIGKILL the service's zenrl process inside its container (a crash: the engine's
        restart policy applies, unlike `docker kill`, which the engine takes as a manual stop).
        ``init: true`` makes PID 1 docker-init, whose only child is the zenrl process."""
        (cid,) = self.containers(service)
        r = subprocess.run(["docker", "exec", cid, "sh", "-c", "kill -KILL $(cat /proc/1/task/1/children)"],
                           capture_output=True, text=True, timeout=60)
        if r.returncode != 0:
            raise AssertionError(docker_output(r))

    def login(self, name: str, out_dir: Path) -> str:
        """``client-<name>.json5`` of the credentials the secured cluster made (read from its
        volume), with the CA path mapped to this machine, as a file for ``transport.client_config``."""
        r = self.compose("run", "--rm", "-T", "--no-deps", "--entrypoint", "cat", "credentials",
                         f"/credentials/client-{name}.json5", timeout=180)
        doc = json.loads(r.stdout)
        doc["transport"]["link"]["tls"]["root_ca_certificate"] = str(CERTS_DIR / "ca.pem")
        path = out_dir / f"client-{name}-{self.project}.json"
        path.write_text(json.dumps(doc))
        return str(path)

    def cleanup(self) -> None:
        self.compose("down", "-v", "--remove-orphans", timeout=300, check=False)


def _wait_roles(cluster: DockerCluster, want: Callable[[list[str]], bool], timeout_s: float, what: str) -> list[str]:
    seen: list[list[str]] = []

    def check() -> bool:
        seen.append(cluster.roles())
        return want(seen[-1])

    wait_for(check, timeout_s, f"{what} (status listed {seen[-1] if seen else 'nothing'})", cluster, "actor")
    return seen[-1]


def _updates_at_resume(log: str) -> list[int]:
    return [int(n) for n in re.findall(r"resumed from \S*ckpt-\d+\.pt: (\d+) updates", log)]


# the first of these tests also waits for the module's image build (docker_images, up to 30 min)
@pytest.mark.timeout(2400)
def test_docker_cluster_up_scale_resume_crash_down(docker_images, run_id):
    """The plain cluster on a real engine: up (first update within 60 s), status, scale to 4
    actors, stop + up resumes, a crashed learner process is restarted and resumes, down."""
    cluster = DockerCluster((COMPOSE,), run_id, docker_images, actors=2)
    try:
        t0 = time.monotonic()
        cluster.compose("up", "-d", "--build", timeout=900)
        t_up = time.monotonic()  # the containers run from here (the images were built by the fixture)
        mon = Monitor(cluster.endpoint, run_id)
        try:
            wait_for(lambda: mon.updates() >= 1, max(1.0, 60 - (time.monotonic() - t_up)),
                     f"the first learner update within 60 s of `up` (which took {t_up - t0:.0f} s)", cluster, "learner")
            wait_for(lambda: mon.evals, 120, "an evaluation", cluster, "evaluator")
            everyone = lambda n: lambda roles: roles.count("actor") == n and {"learner", "replay", "evaluator"} <= set(roles)  # noqa: E731
            _wait_roles(cluster, everyone(2), 60, "status listing the replay, the learner, the evaluator and 2 actors")

            # --no-recreate: after `up --build`, compose (2.40) takes the other services' configs
            # as changed and would recreate them all (the learner then resumes, but restarts)
            cluster.compose("up", "-d", "--no-recreate", "--scale", "actor=4")
            _wait_roles(cluster, everyone(4), 120, "status listing 4 actors after --scale actor=4")
            with mon.lock:
                mon.actors.clear()
            wait_for(lambda: len(mon.actors) >= 4, 60, "stats of 4 actors", cluster, "actor")
            slots = [a.get("slot") for a in mon.actors.values()]
            assert len(set(slots)) == len(slots), f"actors share exploration slots: {slots}"

            # stop + up: every role exits 0 on SIGTERM, the learner resumes from its final checkpoint
            cluster.compose("stop", timeout=300)
            codes = cluster.exit_codes()
            assert codes and all(c == 0 for c in codes.values()), f"exit codes after `stop`: {codes}\n{cluster.logs('replay')[-3000:]}"
            saved = _checkpoint_updates(cluster.logs("learner"), r"checkpoint \S*ckpt-(\d+)\.pt")
            assert saved is not None and saved >= 1, f"no final checkpoint\n{cluster.logs('learner')[-3000:]}"
            mon.forget_learner()
            resumes = len(_updates_at_resume(cluster.logs("learner")))  # the log holds every start of the container
            if resumes:
                log = cluster.logs("learner")
                at = log.index("resumed from")
                raise AssertionError(f"the learner restarted (and resumed) before `stop`\n{log[max(0, at - 6000):at + 300]}")
            cluster.compose("up", "-d")
            wait_for(lambda: len(_updates_at_resume(cluster.logs("learner"))) > resumes, 120, "the learner to resume",
                     cluster, "learner")
            assert _updates_at_resume(cluster.logs("learner"))[-1] == saved
            wait_for(lambda: mon.updates() >= saved + 50, 180, f"learner updates >= {saved + 50} after `up`",
                     cluster, "learner")
            with mon.lock:
                assert min(mon.learner_updates) >= saved, f"counted from {min(mon.learner_updates)}, not {saved}"

            # a crash of the learner process: the restart policy brings it back, resumed
            (learner_cid,) = cluster.containers("learner")
            restarts = int(cluster.inspect(learner_cid, "{{.RestartCount}}"))
            resumes = len(_updates_at_resume(cluster.logs("learner")))
            cluster.crash("learner")
            wait_for(lambda: int(cluster.inspect(learner_cid, "{{.RestartCount}}")) > restarts, 60,
                     "the engine to restart the crashed learner", cluster, "learner")
            wait_for(lambda: len(_updates_at_resume(cluster.logs("learner"))) > resumes, 120,
                     "the restarted learner to resume", cluster, "learner")
            resumed = _updates_at_resume(cluster.logs("learner"))[-1]
            assert resumed >= saved, (resumed, saved)
            mon.forget_learner()
            wait_for(lambda: mon.updates() >= resumed + 50, 180, f"learner updates >= {resumed + 50} after the crash",
                     cluster, "learner")
            with mon.lock:
                assert min(mon.learner_updates) >= resumed
        finally:
            mon.close()
        cluster.compose("stop", timeout=300)
        codes = cluster.exit_codes()
        assert all(c == 0 for c in codes.values()), f"exit codes: {codes}"
        cluster.compose("down", "-v", "--remove-orphans", timeout=300)
        assert not cluster.containers(), "containers left after `down`"
    finally:
        cluster.cleanup()


@pytest.mark.timeout(2400)
def test_docker_secure_cluster_refuses_strangers_and_forged_weights(docker_images, run_id, tmp_path):
    """The secured cluster on a real engine: the first `up` makes fresh credentials; it trains;
    a client without credentials, or with the repository's development password, is refused; an
    actor's login cannot publish weights, nor transitions as another actor; `--scale actor=3`
    gives three distinct identities (actor-0, actor-1, actor-2 on slots 0, 1, 2)."""
    from tests.integration.test_secure_router import Inbox, client_config_file
    from zenrl.common.errors import TransportError
    from zenrl.common.protocol import Keys
    from zenrl.common.transport import Node

    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed (needed by deploy/zenoh/gen-certs.sh)")
    cluster = DockerCluster((COMPOSE, SECURE), run_id, docker_images, actors=2)
    nodes: list[Any] = []
    try:
        cluster.compose("up", "-d", "--build", timeout=900)
        mon = Monitor(cluster.endpoint, run_id, cluster.login("monitor", tmp_path))
        nodes.append(mon)
        wait_for(lambda: mon.updates() >= 1, 90, "the first learner update", cluster, "learner")
        roles = _wait_roles(cluster, lambda r: r.count("actor") == 2 and {"learner", "replay", "evaluator"} <= set(r),
                            90, "status listing every process")
        assert roles.count("actor") == 2

        # no credentials, or the repository's development password: refused
        for cfg in (client_config_file("actor-0", CERTS_DIR, tmp_path, drop_auth=True),
                    client_config_file("actor-0", CERTS_DIR, tmp_path)):
            with pytest.raises(TransportError):
                Node(cluster.endpoint, connect_timeout_s=0.0, config_file=str(cfg)).close()

        k = Keys(run_id)
        actor = Node(cluster.endpoint, 30.0, config_file=cluster.login("actor-0", tmp_path))
        watcher = Node(cluster.endpoint, 30.0, config_file=cluster.login("evaluator", tmp_path))
        replay_view = Node(cluster.endpoint, 30.0, config_file=cluster.login("replay", tmp_path))
        nodes += [actor, watcher, replay_view]
        inbox, at_replay = Inbox(), Inbox()
        watcher.subscribe(k.weights, inbox)
        watcher.subscribe(k.stats_all, inbox)
        replay_view.subscribe(k.transitions_all, at_replay)
        wait_for(lambda: inbox.payloads("weights"), 60, "the learner's weights at the watcher", cluster, "learner")
        wait_for(lambda: at_replay.payloads("transitions/actor-1"), 60, "actor-1's transitions", cluster, "actor")
        probe = k.stats("actor", "actor-0")
        actor.put(k.weights, b"forged")
        actor.put(k.transitions("actor-1"), b"forged")
        # the same session's later message on an allowed key: once it arrived, the forged ones would have
        wait_for(lambda: actor.put(probe, b"sentinel") or inbox.has(probe.split("/", 2)[2], b"sentinel"), 30,
                 "the actor's sentinel stats at the watcher", cluster, "actor")
        assert b"forged" not in inbox.payloads("weights"), "an actor's credentials published weights"
        assert b"forged" not in at_replay.payloads("transitions/actor-1"), "actor-0's login published as actor-1"

        # a third replica takes the next free login: three identities on three slots
        cluster.compose("up", "-d", "--no-recreate", "--scale", "actor=3")
        with mon.lock:
            mon.actors.clear()
        want = {"actor-0": 0, "actor-1": 1, "actor-2": 2}

        def three_identities() -> bool:
            with mon.lock:
                return {i: v.get("slot") for i, v in mon.actors.items() if i in want} == want

        wait_for(three_identities, 120, f"stats of {sorted(want)} on slots 0, 1, 2", cluster, "actor")
        with mon.lock:
            assert set(mon.actors) == set(want), f"actor ids {sorted(mon.actors)}"
    finally:
        for n in nodes:
            n.close()
        try:
            cluster.compose("stop", timeout=300)
            codes = cluster.exit_codes()
        finally:
            cluster.cleanup()
    assert all(c == 0 for c in codes.values()), f"exit codes: {codes}"


@pytest.mark.parametrize("workdir", ["/app", "/tmp"])
def test_docker_image_runs_zenrl_run_from_any_directory(docker_images, workdir):
    """`zenrl run` (the launcher and the children it starts) inside the image, from its working
    directory and from another: no source tree shadows the installed package."""
    r = subprocess.run(["docker", "run", "--rm", "-w", workdir, docker_images["ZENRL_IMAGE"], "run",
                        "--config", "/app/configs/cartpole_apex.yaml", "--no-progress", "--set", "max_updates=200",
                        "--set", "target_return=null", "--set", "max_wall_s=240"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "max_updates 200 reached" in r.stdout + r.stderr, docker_output(r)


class LeagueStats:
    """The league service's newest stats values (``stats/league/league``), merged as they come."""

    def __init__(self, node: Any, run_id: str) -> None:
        from zenrl.common import protocol as P

        self._P = P
        self._latest = node.subscribe_latest(P.Keys(run_id).stats("league", "league"))
        self.seen: dict[str, Any] = {}

    def at_least(self, key: str, want: int) -> bool:
        raw = self._latest.take()
        if raw is not None:
            self.seen.update(self._P.Stats.decode(raw).values)
        return int(self.seen.get(key, 0)) >= want


def _small_league_config(tmp_path: Path, exploiter_reset_s: float) -> Path:
    """configs/cluster_league.yaml made quick for a test: matches of at most 40 steps, a small
    network and replay, league stats every 0.5 s; a file the containers' user can read."""
    doc = yaml.safe_load((ROOT / "configs" / "cluster_league.yaml").read_text())
    doc["env"]["kwargs"].update(match_time=6.0, sudden_death_time=2.0)  # matches of at most 40 steps
    doc["league"].update(exploiter_reset_s=exploiter_reset_s, stats_interval_s=0.5, ticket_rate_per_s=1000,
                         ticket_burst=1000,
                         agents={"main": {"role": "main", "envs_per_actor": 4},
                                 "exploiter": {"role": "exploiter", "envs_per_actor": 2,
                                               "overrides": {"replay.capacity": 5000}}})
    doc["network"]["hidden"] = [32]
    doc["replay"].update(capacity=20000, min_size=200)
    doc["learner"].update(batch_size=32, checkpoint_interval_s=5)
    doc["evaluator"].update(interval_s=30, episodes=2)
    cfg_path = tmp_path / "league.yaml"
    cfg_path.write_text(yaml.safe_dump(doc))
    cfg_path.chmod(0o644)
    return cfg_path


@pytest.mark.timeout(1800)
def test_docker_league_cluster_resets_its_exploiter(docker_images, run_id, tmp_path):
    """docker-compose.league.yml on a real engine: the league and both agents' services come up
    (--agent); when the league starts the exploiter's next generation, its replay, learner and
    actor containers exit with status 75 by themselves, the engine's restart policy starts them
    again, and the new generation plays matches; the main agent's services are not restarted."""
    from zenrl.common.transport import Node

    cfg_path = _small_league_config(tmp_path, exploiter_reset_s=45)
    cluster = DockerCluster((COMPOSE, LEAGUE), run_id, docker_images, actors=1)
    cluster.env.update(ZENRL_LEAGUE_CONFIG=str(cfg_path), ZENRL_EXPLOITER_ACTORS="1")

    def restarts(service: str) -> int:
        return sum(int(cluster.inspect(c, "{{.RestartCount}}")) for c in cluster.containers(service))

    try:
        cluster.compose("up", "-d", timeout=900)
        with Node(cluster.endpoint, 60.0) as node:
            stats = LeagueStats(node, run_id)
            league = stats.at_least
            wait_for(lambda: league("since_games/main", 3), 300, "main's first league matches", cluster, "actor")
            wait_for(lambda: league("generation/exploiter", 1), 300, "the exploiter's second generation", cluster,
                     "league")
            for svc in ("replay-exploiter", "learner-exploiter", "actor-exploiter"):
                wait_for(lambda svc=svc: restarts(svc) >= 1, 180, f"{svc} restarted by the engine", cluster, svc)
                assert "to be started afresh (exit status 75)" in cluster.logs(svc), cluster.logs(svc)[-3000:]
            # the new generation plays (its matches since the reset), its learner started fresh
            stats.seen.pop("since_games/exploiter", None)  # (the count of the old generation)
            wait_for(lambda: league("since_games/exploiter", 3), 300, "matches of the exploiter's new generation",
                     cluster, "actor-exploiter")
            assert "resumed from" not in cluster.logs("learner-exploiter"), cluster.logs("learner-exploiter")[-3000:]
            for svc in ("replay", "learner", "actor", "league"):
                assert restarts(svc) == 0, f"{svc} restarted\n{cluster.logs(svc)[-3000:]}"
    finally:
        cluster.cleanup()


@pytest.mark.timeout(1800)
def test_docker_secure_league_cluster(docker_images, run_id, tmp_path):
    """docker-compose.league-secure.yml over the league and secured files, on a real engine:
    every service connects over TLS with a login of the first `up`'s credentials; both agents'
    actors take distinct actor logins from the one pool (two identities for one actor of each);
    both agents' matches reach the league and both learners train; `league-status` answers with
    the monitor login."""
    from zenrl.common.transport import Node

    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed (needed by deploy/zenoh/gen-certs.sh)")
    cfg_path = _small_league_config(tmp_path, exploiter_reset_s=3600)
    cluster = DockerCluster((COMPOSE, LEAGUE, SECURE, LEAGUE_SECURE), run_id, docker_images, actors=1)
    cluster.env.update(ZENRL_LEAGUE_CONFIG=str(cfg_path), ZENRL_EXPLOITER_ACTORS="1")
    nodes: list[Any] = []
    try:
        cluster.compose("up", "-d", timeout=900)
        login = cluster.login("monitor", tmp_path)
        agents = {a: Monitor(cluster.endpoint, f"{run_id}.{a}", login) for a in ("main", "exploiter")}
        nodes += agents.values()
        node = Node(cluster.endpoint, 60.0, config_file=login)
        nodes.append(node)
        league = LeagueStats(node, run_id).at_least
        for agent, svc in (("main", "actor"), ("exploiter", "actor-exploiter")):
            wait_for(lambda a=agent: league(f"since_games/{a}", 3), 300, f"{agent}'s league matches", cluster, svc)
        for agent, svc in (("main", "learner"), ("exploiter", "learner-exploiter")):
            wait_for(lambda a=agent: agents[a].updates() >= 1, 300, f"{agent}'s learner updates", cluster, svc)

        def ids(agent: str) -> set[str]:
            with agents[agent].lock:
                return set(agents[agent].actors)

        wait_for(lambda: ids("main") and ids("exploiter"), 120, "both agents' actor stats", cluster, "actor")
        main_ids, expl_ids = ids("main"), ids("exploiter")
        assert main_ids | expl_ids == {"actor-0", "actor-1"} and not main_ids & expl_ids, (main_ids, expl_ids)
        out = cluster.compose("run", "--rm", "-T", "league-status", timeout=180)
        table = json.loads(out.stdout.strip().splitlines()[-1])
        assert table["run_id"] == run_id and table["players"], table
    finally:
        for n in nodes:
            n.close()
        cluster.cleanup()

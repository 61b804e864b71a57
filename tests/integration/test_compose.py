"""The cluster deployment: docker-compose.yml (+ docker-compose.secure.yml) and deploy/.

* Validation: the compose files parse, every service has an image or a build, every file and
  volume they mount exists (or is written by deploy/zenoh/gen-certs.sh), every variable has a
  default, every command parses with zenrl's own CLI, every ZENRL__ variable and the mounted
  config resolve to a valid configuration, and the router image is the installed eclipse-zenoh.
* The cluster itself: each service's ``command`` runs as an OS process
  (``python -m zenrl.cli <command...>``) with that service's environment, ``router`` resolved
  to 127.0.0.1, the router container replaced by an in-process router opened from the same
  JSON5 file (free port, no plugins), container paths mapped to the repo and a tmp dir; three
  actors; learning proceeds; the learner is stopped with SIGTERM and restarted, and resumes
  from its checkpoint; everything stops cleanly. With a Docker engine (``docker info``), the
  same scenario drives real ``docker compose`` instead.
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
import uuid
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.conftest import ROOT, Procs, free_port, wait_until

pytestmark = pytest.mark.integration

COMPOSE = ROOT / "docker-compose.yml"
SECURE = ROOT / "docker-compose.secure.yml"
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
        doc = yaml.safe_load(f.read_text())
        for name, svc in doc.get("services", {}).items():
            model["services"][name] = _merge_service(model["services"].get(name, {}), svc)
        model["volumes"].update(doc.get("volumes") or {})
    return interpolate(model, dict(env or {}))


def raw_variables(*files: Path) -> list[tuple[str, str | None]]:
    """Every ``${VAR[:-default]}`` in ``files``: (name, default or None)."""
    return [(m.group(1), m.group(2)) for f in files for m in _VAR.finditer(f.read_text())]


def zenrl_services(model: dict[str, Any], profiles: tuple[str, ...] = ()) -> dict[str, dict[str, Any]]:
    """Services running the zenrl image, active with ``profiles``."""
    return {n: s for n, s in model["services"].items()
            if (s.get("build") or {}).get("target") == "zenrl"
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

    for files in ((COMPOSE,), (COMPOSE, SECURE)):
        # every variable has a default: `docker compose up` needs no .env
        for name, default in raw_variables(*files):
            assert default is not None, f"${{{name}}} in {[f.name for f in files]} has no default"
        model = load_compose(*files)
        services = model["services"]
        assert {"router", "replay", "learner", "actor", "evaluator", "tensorboard"} <= set(services)
        for name, svc in services.items():
            assert svc.get("image") or svc.get("build"), f"service {name} has neither image nor build"
            if svc.get("build"):
                assert (ROOT / svc["build"]["context"] / svc["build"]["dockerfile"]).is_file()
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
                assert dep in services and cond["condition"] in ("service_healthy", "service_started"), (name, dep)

        rname, router = router_service(model)
        assert router["image"] == f"eclipse/zenoh:{importlib.metadata.version('eclipse-zenoh')}"
        assert "healthcheck" in router
        config_file = host_path(router, router["command"][router["command"].index("-c") + 1], {})
        assert Path(config_file).is_file(), config_file

        parser = build_parser()
        zs = zenrl_services(model, profiles=("gpu", "tools"))
        assert {"replay", "learner", "learner-gpu", "actor", "evaluator", "status"} <= set(zs)
        for name, svc in zs.items():
            args = parser.parse_args(svc["command"])  # exits (fails the test) on an unknown option
            assert svc["depends_on"][rname]["condition"] == "service_healthy", name
            env = {k: str(v) for k, v in svc["environment"].items()}
            proto, host = re.match(r"^(tcp|tls)/([^:]+):(\d+)$", env["ZENRL_ROUTER"]).group(1, 2)
            assert host == rname
            assert (proto == "tls") == (files[-1] == SECURE), (name, env["ZENRL_ROUTER"])
            # the config the service reads, with its environment, is valid
            named = {v: Path("/nonexistent") for v in model["volumes"]}
            cfg = load_config(host_path(svc, args.config, named), environ=env)
            assert cfg.run_id and cfg.runs_dir == "/runs"
            if "ZENRL__TRANSPORT__CLIENT_CONFIG" in env:
                assert Path(host_path(svc, env["ZENRL__TRANSPORT__CLIENT_CONFIG"], named)).is_file(), name
            if svc.get("restart") != "no":
                assert svc.get("restart") in ("always", "unless-stopped", "on-failure"), name

        actor = zs["actor"]
        assert "--slot" not in actor["command"] and "--id" not in actor["command"]
        assert "container_name" not in actor and "ports" not in actor, "actors must be scalable"
        for name in ("learner", "learner-gpu"):
            assert "--auto-resume" in zs[name]["command"]
            assert int(zs[name]["stop_grace_period"].rstrip("s")) >= 30, "the learner needs time to checkpoint"
        assert zs["learner-gpu"]["deploy"]["resources"]["reservations"]["devices"][0]["capabilities"] == ["gpu"]


def test_secure_credentials_match_router_users_and_acl():
    import zenoh

    users = dict(line.split(":", 1) for line in (ZENOH_DIR / "users.txt").read_text().split())
    acl = json.loads(zenoh.Config.from_file(str(ZENOH_DIR / "router-secure.json5")).get_json("access_control"))
    assert acl["enabled"] and acl["default_permission"] == "deny"
    rule_ids = [r["id"] for r in acl["rules"]]
    assert len(rule_ids) == len(set(rule_ids)), "duplicate rule ids"
    assert {r for p in acl["policies"] for r in p["rules"]} == set(rule_ids), "a rule is unused or undefined"
    acl_users = {u for s in acl["subjects"] for u in s["usernames"]}
    assert acl_users == set(users)
    for svc in zenrl_services(load_compose(COMPOSE, SECURE), profiles=("gpu", "tools")).values():
        client = host_path(svc, svc["environment"]["ZENRL__TRANSPORT__CLIENT_CONFIG"], {})
        auth = json.loads(zenoh.Config.from_file(client).get_json("transport/auth/usrpwd"))
        assert users.get(auth["user"]) == auth["password"], client


def test_dockerfile_installs_every_package():
    import tomllib

    text = DOCKERFILE.read_text()
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    for src in set(pyproject["tool"]["setuptools"]["package-dir"].values()):
        assert re.search(rf"^COPY {src}/ ", text, re.M), f"Dockerfile does not copy {src}/"
    assert re.search(r'^ENTRYPOINT \["zenrl"\]$', text, re.M)
    assert re.search(r"^USER (?!root)\w+", text, re.M)
    assert "pip install --no-deps ." in text and "download.pytorch.org/whl/cpu" in text
    # dependencies are installed before the sources are copied (build cache)
    assert text.index("pip install -r") < text.index("COPY zenrl/")


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
        return env

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


class DockerCluster:
    """The same operations through `docker compose` (used when a Docker engine is reachable)."""

    def __init__(self, files: tuple[Path, ...], run_id: str) -> None:
        self.files, self.run_id = files, run_id
        self.project = f"zenrltest{uuid.uuid4().hex[:8]}"
        self.port = free_port()
        self.env = dict(os.environ, ZENRL_RUN_ID=run_id, ZENRL_ROUTER_PORT=str(self.port),
                        TENSORBOARD_PORT=str(free_port()), ZENRL_ACTORS="1")
        secure = SECURE in files
        self.endpoint = f"{'tls' if secure else 'tcp'}/127.0.0.1:{self.port}"
        self._monitor_cfg: str | None = None
        if secure:
            if not (CERTS_DIR / "ca.pem").is_file():
                subprocess.run(["bash", str(ZENOH_DIR / "gen-certs.sh")], check=True, timeout=60)
            import zenoh

            transport = json.loads(zenoh.Config.from_file(str(ZENOH_DIR / "client-monitor.json5")).get_json("transport"))
            transport["link"]["tls"]["root_ca_certificate"] = str(CERTS_DIR / "ca.pem")
            self._monitor_cfg = str(CERTS_DIR / f"monitor-{self.project}.json")
            Path(self._monitor_cfg).write_text(json.dumps({"transport": transport}))

    def compose(self, *args: str, timeout: float = 900, check: bool = True) -> subprocess.CompletedProcess:
        cmd = ["docker", "compose", "-p", self.project]
        for f in self.files:
            cmd += ["-f", str(f)]
        return subprocess.run([*cmd, *args], cwd=ROOT, env=self.env, capture_output=True, text=True,
                              timeout=timeout, check=check)

    def up(self, actors: int) -> None:
        self.compose("up", "-d", "--build", "--scale", f"actor={actors}")

    def stop(self, name: str, timeout_s: float = 120.0) -> list[int]:
        self.compose("stop", name, timeout=timeout_s)
        ids = self.compose("ps", "-a", "-q", name).stdout.split()
        return [int(subprocess.run(["docker", "inspect", "-f", "{{.State.ExitCode}}", i], capture_output=True,
                                   text=True, check=True).stdout.strip()) for i in ids]

    def start(self, name: str) -> None:
        self.compose("start", name)

    def logs(self, name: str) -> str:
        return self.compose("logs", "--no-color", name, check=False).stdout

    def status(self) -> dict[str, Any]:
        out = self.compose("run", "--rm", "-T", "status", timeout=120)
        return json.loads(out.stdout.strip().splitlines()[-1])

    def monitor_client_config(self) -> str | None:
        return self._monitor_cfg

    def down(self) -> dict[str, list[int]]:
        codes = {name: self.stop(name) for name in ("actor", "evaluator", "learner", "replay")}
        self.compose("down", "-v", "--remove-orphans", timeout=300)
        if self._monitor_cfg:
            Path(self._monitor_cfg).unlink(missing_ok=True)
        return codes

    def leftovers(self) -> list[str]:
        return self.compose("ps", "-a", "-q", check=False).stdout.split()

    def cleanup(self) -> None:
        self.compose("down", "-v", "--remove-orphans", timeout=300, check=False)


def docker_available() -> tuple[bool, str]:
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


def run_scenario(cluster: LocalCluster | DockerCluster, run_id: str, actors: int, restart: bool) -> None:
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


@pytest.fixture(params=["local", "docker"])
def backend(request):
    if request.param == "docker":
        ok, why = docker_available()
        if not ok:
            pytest.skip(f"docker compose path skipped: {why}")
    return request.param


def test_cluster_learns_scales_and_resumes(backend, tmp_path, procs, run_id):
    """The plain cluster (docker-compose.yml): 3 actors, learner restart with resume."""
    if backend == "local":
        cluster = LocalCluster((COMPOSE,), tmp_path, procs, run_id)
        run_scenario(cluster, run_id, actors=3, restart=True)
        ckpts = list((tmp_path / "volumes" / "runs" / run_id / "checkpoints").glob("ckpt-*.pt"))
        assert ckpts, "no checkpoint in the runs volume"
        assert list((tmp_path / "volumes" / "runs" / run_id / "tb").rglob("events.out.tfevents.*")), "no TensorBoard events"
    else:
        cluster = DockerCluster((COMPOSE,), run_id)
        try:
            run_scenario(cluster, run_id, actors=3, restart=True)
        finally:
            cluster.cleanup()


def test_secure_cluster_runs_under_acl(backend, tmp_path, procs, run_id):
    """The secured cluster (TLS, passwords, access control): every role still does its job."""
    if backend == "local":
        if shutil.which("openssl") is None:
            pytest.skip("openssl is not installed (needed by deploy/zenoh/gen-certs.sh)")
        certs = tmp_path / "certs"
        subprocess.run(["bash", str(ZENOH_DIR / "gen-certs.sh"), str(certs)], check=True, capture_output=True, timeout=60)
        cluster = LocalCluster((COMPOSE, SECURE), tmp_path, procs, run_id, bind_overrides={CERTS_DIR: certs})
        assert cluster.endpoint.startswith("tls/")
        run_scenario(cluster, run_id, actors=2, restart=False)
    else:
        cluster = DockerCluster((COMPOSE, SECURE), run_id)
        try:
            run_scenario(cluster, run_id, actors=2, restart=False)
        finally:
            cluster.cleanup()

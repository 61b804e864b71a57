"""The monitoring path with the real parts: `zenrl run --exporter-port` on CartPole (router,
replay, learner, actors, evaluator, exporter as OS processes), a real Prometheus server scraping
the exporter and evaluating deploy/monitoring/rules.yml. Prometheus's HTTP API must report the
learner's update rate, and once the learner is frozen (SIGSTOP: it neither updates nor exits, so
the launcher does not restart it) the ZenrlLearnerStalled alert must fire. The rule's 2-minute
window is shortened to 8 s in the test's copy of the rules file; nothing else changes."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import urllib.parse
import urllib.request

import pytest
import yaml

from tests.conftest import ROOT, free_port, wait_until, zenrl_pids

pytestmark = pytest.mark.integration

PROMETHEUS, PROMTOOL = shutil.which("prometheus"), shutil.which("promtool")
STALL_S = 8  # the test's learner-stalled window (the shipped rule: 120 s)


def _get(url: str) -> dict | None:
    try:
        with urllib.request.urlopen(url, timeout=5) as r:
            return json.loads(r.read())
    except (OSError, ValueError):
        return None


def _query(base: str, expr: str) -> list[dict]:
    out = _get(f"{base}/api/v1/query?" + urllib.parse.urlencode({"query": expr}))
    return out["data"]["result"] if out and out.get("status") == "success" else []


def _firing(base: str, name: str, run_id: str) -> bool:
    out = _get(f"{base}/api/v1/alerts") or {}
    return any(a["labels"].get("alertname") == name and a["labels"].get("run") == run_id and a["state"] == "firing"
               for a in out.get("data", {}).get("alerts", []))


def _test_rules(tmp_path) -> str:
    """rules.yml with the learner-stalled window shortened to STALL_S seconds."""
    doc = yaml.safe_load((ROOT / "deploy/monitoring/rules.yml").read_text())
    rule = next(r for g in doc["groups"] for r in g["rules"] if r["alert"] == "ZenrlLearnerStalled")
    assert "> 120" in rule["expr"]
    rule["expr"] = rule["expr"].replace("> 120", f"> {STALL_S}")
    path = tmp_path / "rules.yml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return str(path)


@pytest.mark.skipif(PROMETHEUS is None or PROMTOOL is None,
                    reason="prometheus/promtool not installed (Debian: apt-get install prometheus)")
def test_prometheus_scrapes_the_run_and_the_stalled_learner_alert_fires(tmp_path, run_id):
    exporter_port, prom_port = free_port(), free_port()
    base = f"http://127.0.0.1:{prom_port}"
    cfg = {"global": {"scrape_interval": "1s", "evaluation_interval": "1s"},
           "rule_files": [_test_rules(tmp_path)],
           "scrape_configs": [{"job_name": "zenrl", "static_configs": [{"targets": [f"127.0.0.1:{exporter_port}"]}]}]}
    (tmp_path / "prometheus.yml").write_text(yaml.safe_dump(cfg))
    check = subprocess.run([PROMTOOL, "check", "config", str(tmp_path / "prometheus.yml")], capture_output=True,
                           text=True, timeout=60)
    assert check.returncode == 0, check.stdout + check.stderr
    prom_log = open(tmp_path / "prometheus.log", "wb")
    prom = subprocess.Popen([PROMETHEUS, f"--config.file={tmp_path / 'prometheus.yml'}",
                             f"--storage.tsdb.path={tmp_path / 'tsdb'}", f"--web.listen-address=127.0.0.1:{prom_port}"],
                            stdout=prom_log, stderr=subprocess.STDOUT)
    run_log = open(tmp_path / "run.log", "wb")
    run = subprocess.Popen([sys.executable, "-m", "zenrl.cli", "run", "--config", "configs/cartpole_apex.yaml",
                            "--run-id", run_id, "--no-progress", "--exporter-port", str(exporter_port),
                            "--set", f"runs_dir={tmp_path}", "--set", f"transport.listen=[tcp/127.0.0.1:{free_port()}]",
                            "--set", "target_return=null", "--set", "max_wall_s=170", "--set", "learner.log_interval_s=1"],
                           cwd=ROOT, stdout=run_log, stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONSAFEPATH="1"))
    learner: list[int] = []

    def logs() -> str:
        out = [(tmp_path / "run.log").read_text(errors="replace")[-2000:],
               (tmp_path / "prometheus.log").read_text(errors="replace")[-2000:]]
        for f in sorted((tmp_path / run_id / "logs").glob("*.log")):
            out.append(f"--- {f.name}\n" + f.read_text(errors="replace")[-1500:])
        return "\n".join(out)

    try:
        wait_until(lambda: _ready(base), 60, "Prometheus ready", interval_s=0.5)
        rate = f'sum(rate(zenrl_learner_updates_total{{run="{run_id}"}}[10s]))'
        try:
            wait_until(lambda: [r for r in _query(base, rate) if float(r["value"][1]) > 0], 120,
                       "a learner update rate > 0 in Prometheus", interval_s=1.0)
        except AssertionError as e:
            raise AssertionError(f"{e}\n{logs()}") from None
        alive = {r["metric"]["role"]: float(r["value"][1])
                 for r in _query(base, f'zenrl_processes_alive{{run="{run_id}"}}')}
        assert alive.get("actor") == 2 and alive.get("learner") == 1 and alive.get("replay") == 1, alive
        # with the test's 8 s window the alert may fire while the learner starts (the replay holds
        # data before the learner's first update); it must resolve once the learner updates
        wait_until(lambda: not _firing(base, "ZenrlLearnerStalled", run_id), 30,
                   "ZenrlLearnerStalled not firing while the learner updates", interval_s=0.5)

        learner = zenrl_pids(run_id, "learner")
        assert len(learner) == 1, learner
        os.kill(learner[0], signal.SIGSTOP)
        try:
            wait_until(lambda: _firing(base, "ZenrlLearnerStalled", run_id), 60,
                       "the ZenrlLearnerStalled alert firing", interval_s=1.0)
        except AssertionError as e:
            raise AssertionError(f"{e}\n{_get(base + '/api/v1/alerts')}\n{logs()}") from None
        # the replay still holds data and the learner is not restarted: the alert is honest
        assert [r for r in _query(base, f'zenrl_replay_size_items{{run="{run_id}"}}') if float(r["value"][1]) > 0]
    finally:
        for pid in learner:
            try:
                os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
        if run.poll() is None:
            run.send_signal(signal.SIGTERM)
        try:
            run.wait(60)
        except subprocess.TimeoutExpired:
            run.kill()
            run.wait()
        prom.terminate()
        try:
            prom.wait(30)
        except subprocess.TimeoutExpired:
            prom.kill()
            prom.wait()
        prom_log.close()
        run_log.close()
    assert not zenrl_pids(run_id), "processes of the run were left behind"


def _ready(base: str) -> bool:
    try:
        with urllib.request.urlopen(f"{base}/-/ready", timeout=5) as r:
            return r.status == 200
    except OSError:
        return False

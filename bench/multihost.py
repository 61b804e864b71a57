"""Many hosts over a WAN: what 50 ms of round trip between hosts costs an Ape-X run.

The layout of tests/integration/test_multihost.py, on one machine (Linux network namespaces,
needs root): the central router, the replay and the learner on one host; a host router and
``--actors-per-host`` actors on each of two others, each host router linked to the central one
through a userspace relay (tests/integration/wan_relay.py) with a bandwidth cap. Two arms, same
config and cap, one after the other, each on a fresh layout:

  * ``no_delay``  - the relays add no delay;
  * ``delay``     - the relays add 25 ms each way (50 ms round trip between hosts).

After a warm-up (every actor reporting, the learner updating), each arm measures for
``--seconds``: learner updates/s (its update counter), actor env steps/s (the sum of the
actors' counters), the learner's policy lag (its stats: learner version minus the version that
acted, per sampled transition, in versions) and the actors' weights lag (newest weights
version at the central host minus the version an actor acts with, when its stats arrive there:
an upper bound, as the stats crossed the link too). Each rate is also given per CPU second
of the processes that produce it (the machine may be shared: a drop in steps/s with the same
steps per CPU second is CPU taken by others, not the delay). It also reports the bytes down each
host link per byte of weights broadcast (one copy per host: ~1; one per actor would be >= 2).

The last stdout line is one JSON object with ``updates_ratio_vs_no_delay`` and
``env_steps_ratio_vs_no_delay`` (delay / no delay; goal >= 0.9) and the lags in versions.

    sudo python bench/multihost.py                 # 2 x (setup + 60 s)
    sudo python bench/multihost.py --seconds 20    # shorter
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
import uuid
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # tests.integration.multihost

from _common import ROOT, emit, log, machine_info, record_error, stop_on_sigterm, wait_until  # noqa: E402  (bench/ is on sys.path when run as a script)


def arm(name: str, delay_ms: float, args: argparse.Namespace) -> dict:
    from tests.integration.multihost import ThreeHosts

    tmp = Path(tempfile.mkdtemp(prefix=f"zenrl-multihost-{name}-"))
    sets = ["actor.episode_report_s=0.5", "learner.log_interval_s=1", "learner.checkpoint_interval_s=3600",
            "transport.connect_timeout_s=60"]
    hosts = ThreeHosts(tmp, f"mh{uuid.uuid4().hex[:8]}", str(ROOT / args.config), sets,
                       actors_per_host=args.actors_per_host, delay_ms=delay_ms, rate_mbit=args.rate_mbit, evaluator=False)
    try:
        hosts.start()
        w = hosts.watch
        ids = hosts.actor_ids("a") + hosts.actor_ids("b")

        def ready() -> bool:
            if hosts.dead():
                raise RuntimeError(f"{hosts.dead()} died: {hosts.log(hosts.dead()[0])}")
            return all(w.actor(i)[1].get("env_steps", 0) > 0 for i in ids) and w.learner.get("updates", 0) > 0

        wait_until(ready, 180, "every actor stepping and the learner updating")
        time.sleep(args.warmup)
        t0 = time.monotonic()
        u0 = w.learner["updates"]
        s0 = {i: w.actor(i)[1]["env_steps"] for i in ids}
        n0, b0 = w.weights()
        r0 = {h: hosts.relay(h)["down"] for h in ("a", "b")}
        c0 = {i: hosts.cpu_s(f"actor-{i}") for i in ids}
        cl0 = hosts.cpu_s("learner")
        lags = []
        with w.lock:
            k0 = len(w.actor_lags)
        while time.monotonic() - t0 < args.seconds:
            time.sleep(1.0)
            lags.append(float(w.learner.get("policy_lag", 0.0)))
        dt = time.monotonic() - t0
        with w.lock:
            actor_lags = w.actor_lags[k0:]
        u1 = w.learner["updates"]
        s1 = {i: w.actor(i)[1]["env_steps"] for i in ids}
        n1, b1 = w.weights()
        actor_cpu = sum(hosts.cpu_s(f"actor-{i}") - c0[i] for i in ids)
        learner_cpu = hosts.cpu_s("learner") - cl0
        per_host = {h: (hosts.relay(h)["down"] - r0[h]) / max(b1 - b0, 1) for h in ("a", "b")}
        if hosts.dead():
            raise RuntimeError(f"{hosts.dead()} died during the measurement")
        out = {
            "delay_ms_each_way": delay_ms,
            "seconds": round(dt, 1),
            "updates_per_s": round((u1 - u0) / dt, 1),
            "env_steps_per_s": round(sum(s1[i] - s0[i] for i in ids) / dt, 1),
            # per CPU second: what the delay costs apart from the CPU the shared machine gave
            "env_steps_per_actor_cpu_s": round(sum(s1[i] - s0[i] for i in ids) / max(actor_cpu, 1e-9), 1),
            "updates_per_learner_cpu_s": round((u1 - u0) / max(learner_cpu, 1e-9), 2),
            "actor_cpu_share": round(actor_cpu / dt, 2),
            "policy_lag_versions": round(statistics.fmean(lags), 2),
            "actor_weights_lag_versions": round(statistics.fmean(actor_lags), 2),
            "weights_broadcasts": n1 - n0,
            "link_bytes_per_weights_byte": {h: round(v, 3) for h, v in per_host.items()},
        }
        log(f"{name}: {json.dumps(out)}")
        return out
    finally:
        hosts.close()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default="configs/cartpole_apex.yaml")
    p.add_argument("--seconds", type=float, default=60.0, help="measurement window per arm")
    p.add_argument("--warmup", type=float, default=5.0, help="seconds after every process runs, before measuring")
    p.add_argument("--actors-per-host", type=int, default=2)
    p.add_argument("--rate-mbit", type=float, default=100.0, help="bandwidth cap of each host link, each way")
    p.add_argument("--delay-ms", type=float, default=25.0, help="one-way delay of the delayed arm")
    args = p.parse_args()

    from tests.integration.netns import NetHosts, NetnsUnavailable

    stop_on_sigterm()
    t_start = time.perf_counter()
    result: dict = {"bench": "multihost"}
    try:
        NetHosts.check()
        base = arm("no_delay", 0.0, args)
        slow = arm("delay", args.delay_ms, args)
        result.update({
            "layout": f"central (router, replay, learner) + 2 hosts x (host router, {args.actors_per_host} actors)",
            "rate_mbit_per_link": args.rate_mbit,
            "rtt_ms": 2 * args.delay_ms,
            "no_delay": base,
            "delay": slow,
            "updates_ratio_vs_no_delay": round(slow["updates_per_s"] / base["updates_per_s"], 3),
            "env_steps_ratio_vs_no_delay": round(slow["env_steps_per_s"] / base["env_steps_per_s"], 3),
            "env_steps_per_cpu_ratio_vs_no_delay": round(slow["env_steps_per_actor_cpu_s"] / base["env_steps_per_actor_cpu_s"], 3),
            "updates_per_cpu_ratio_vs_no_delay": round(slow["updates_per_learner_cpu_s"] / base["updates_per_learner_cpu_s"], 3),
            "policy_lag_versions": {"no_delay": base["policy_lag_versions"], "delay": slow["policy_lag_versions"]},
            "actor_weights_lag_versions": {"no_delay": base["actor_weights_lag_versions"],
                                           "delay": slow["actor_weights_lag_versions"]},
        })
    except NetnsUnavailable as e:
        result["skipped"] = str(e)
        log(f"multihost: {e}")
    except (Exception, KeyboardInterrupt) as e:
        record_error(result, e)
    result.update(machine_info(t_start))
    return emit(result)


if __name__ == "__main__":
    sys.exit(main())

"""docs/protocol.md's minimal third-party actor (plain zenoh + msgpack + numpy) really feeds a replay."""

import re
import subprocess
import sys

import pytest

from zenrl.common import protocol as P
from zenrl.common.transport import Node
from tests.conftest import ROOT, wait_until

pytestmark = pytest.mark.integration


def test_readme_actor_snippet(router, run_id, procs, tmp_path):
    readme = (ROOT / "docs" / "protocol.md").read_text()
    block = next(b for b in re.findall(r"```python\n(.*?)```", readme, re.S) if "transitions/my-actor" in b)
    code = block.replace("tcp/127.0.0.1:7447", router).replace("zenrl/exp1/", f"zenrl/{run_id}/")
    script = tmp_path / "third_party_actor.py"
    script.write_text(code)
    procs.zenrl("replay", ["replay", "--router", router, "--run-id", run_id, "--set", "replay.stats_interval_s=0.3"])
    keys = P.Keys(run_id)
    with Node(router, 10.0) as node:
        wait_until(lambda: node.alive_now(keys.alive_role("replay"), 0.5), 60, "the replay service")
        stats = node.subscribe_latest(keys.stats("replay", "replay"))
        out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr

        def inserted():
            raw = stats.take()
            return raw is not None and P.Stats.decode(raw).values["inserted_total"] == 32

        wait_until(inserted, 30, "the snippet's 32 transitions in the replay")

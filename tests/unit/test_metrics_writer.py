"""The metrics writer (common/metrics.py): metrics.jsonl and TensorBoard event files, and what it
does when the disk refuses a write. The refusals are real: a child process whose file size
limit (RLIMIT_FSIZE) makes the kernel fail its writes with EFBIG, as a full disk fails them with
ENOSPC."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

from tensorboardX.proto.event_pb2 import Event
from tensorboardX.record_writer import RecordWriter, masked_crc32c

from zenrl.common.metrics import MetricsWriter, read_metrics, tf_record

ROOT = Path(__file__).resolve().parents[2]


def read_events(path: Path) -> tuple[list[Event], bool]:
    """The events of a TFRecord file up to its first torn or corrupt record, and whether the
    file ended cleanly (the reading TensorBoard does, with each record's CRCs checked)."""
    data, out, at = path.read_bytes(), [], 0
    while at < len(data):
        head = data[at:at + 8]
        if len(head) < 8 or struct.unpack("<I", data[at + 8:at + 12].ljust(4, b"\0"))[0] != masked_crc32c(head):
            return out, False
        n = struct.unpack("<Q", head)[0]
        body, crc = data[at + 12:at + 12 + n], data[at + 12 + n:at + 16 + n]
        if len(body) < n or len(crc) < 4 or struct.unpack("<I", crc)[0] != masked_crc32c(body):
            return out, False
        out.append(Event.FromString(body))
        at += 16 + n
    return out, True


def test_a_record_is_framed_as_tensorboardx_frames_it(tmp_path):
    ev = Event(wall_time=1.5, step=7)
    ev.summary.value.add(tag="learner/loss", simple_value=0.25)
    w = RecordWriter(str(tmp_path / "ref"))
    w.write(ev.SerializeToString())
    w.close()
    assert tf_record(ev.SerializeToString()) == (tmp_path / "ref").read_bytes()


def test_scalars_reach_both_files(tmp_path):
    m = MetricsWriter(tmp_path)
    for i in range(3):
        m.write("learner", 10 * i, {"loss": 1.0 / (i + 1), "updates": i, "stalled": "", "flag": True})
    m.close()
    rows = read_metrics(tmp_path)
    assert [(r["source"], r["step"], r["loss"], r["updates"]) for r in rows] == [
        ("learner", 0, 1.0, 0), ("learner", 10, 0.5, 1), ("learner", 20, 1.0 / 3, 2)]
    assert all("stalled" not in r and "flag" not in r for r in rows)  # numbers only
    (events_file,) = (tmp_path / "tb").glob("events.out.tfevents.*")
    events, clean = read_events(events_file)
    assert clean and events[0].file_version == "brain.Event:2"
    got = [(e.step, {v.tag: round(v.simple_value, 6) for v in e.summary.value}) for e in events[1:]]
    assert got == [(10 * i, {"learner/loss": round(1.0 / (i + 1), 6), "learner/updates": float(i)}) for i in range(3)]


#: in a child: writes refused past 64 KiB (RLIMIT_FSIZE, SIGXFSZ ignored: EFBIG), then allowed again
REFUSED = textwrap.dedent("""
    import json, logging, resource, signal, sys, time
    from pathlib import Path
    import zenrl.common.metrics as M
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(levelname)s %(message)s")
    M.TB_RETRY_S = 0.0
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    hard = resource.getrlimit(resource.RLIMIT_FSIZE)[1]
    run = Path(sys.argv[1])
    m = M.MetricsWriter(run)
    resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, hard))
    t0, i = time.monotonic(), 0
    while m.failed_writes < 50:
        m.write("learner", i, {f"v{k}": float(i + k) for k in range(20)})
        i += 1
    refused_s = time.monotonic() - t0
    resource.setrlimit(resource.RLIMIT_FSIZE, (hard, hard))
    for j in range(5):
        m.write("learner", 100000 + j, {"after": float(j)})
    m.close()
    print(json.dumps({"writes": i, "failed": m.failed_writes, "refused_s": refused_s}))
""")


def test_refused_writes_are_counted_said_once_and_the_writer_goes_on(tmp_path):
    p = subprocess.run([sys.executable, "-c", REFUSED, str(tmp_path)], cwd=ROOT, capture_output=True, text=True,
                       timeout=120)  # before: the writer's thread died and the next writes, and the exit, hung
    assert p.returncode == 0, p.stderr[-3000:]
    out = json.loads(p.stdout.splitlines()[-1])
    assert out["failed"] >= 50 and out["refused_s"] < 30, out
    said = [x for x in p.stderr.splitlines() if "cannot write" in x]
    assert len(said) == 1 and "File too large" in said[0] and "going on without it" in said[0], p.stderr[-2000:]
    assert "Traceback" not in p.stderr, p.stderr[-3000:]
    # the lines written before the limit, and after it was lifted, are there; TensorBoard's files
    # end at a torn record at worst, and the events after the lift are in a new file
    rows = read_metrics(tmp_path)
    assert [r["after"] for r in rows if "after" in r] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert len(rows) >= 100, len(rows)
    steps = []
    for f in sorted((tmp_path / "tb").glob("events.out.tfevents.*"), key=lambda f: int(f.name.rsplit(".", 1)[1])):
        events, _ = read_events(f)
        steps += [e.step for e in events if e.summary.value]
    assert steps[:3] == [0, 1, 2] and steps[-5:] == [100000, 100001, 100002, 100003, 100004], steps[-10:]

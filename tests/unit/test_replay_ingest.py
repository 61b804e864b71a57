"""The replay's ingest (replay/ingest.py) keeps going whatever one message does: an exception
other than the protocol's own while one chunk is handled costs that chunk only, is counted as
``rejected_internal`` and by type, and the ingest thread (run by the role loop's supervisor)
handles the next chunk. In process, with an in-memory node."""

import time

import numpy as np

from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.common.roles import Supervisor
from zenrl.replay.service import ReplayService
from zenrl.replay.store import PlainStore

from tests.unit.inbox_fake import FakeInbox

B = 8


def _service(**over):
    sets = {"capacity": 200, "min_size": 1, "check_semantics": False, **over}
    return ReplayService(load_config(None, [f"replay.{k}={v}" for k, v in sets.items()], environ={}), node=None, run_id="r")


def _payload(seq=0, policy_version=0, actor="a0"):
    rng = np.random.default_rng(seq)
    data = {"obs": rng.uniform(-0.4, 0.4, (B, 4)).astype(np.float32), "action": rng.integers(0, 2, B),
            "reward": np.ones(B, np.float32), "next_obs": rng.uniform(-0.4, 0.4, (B, 4)).astype(np.float32),
            "terminated": np.zeros(B, bool), "n": np.ones(B, np.uint8)}
    return P.TransitionBatch(actor, policy_version, seq, data).encode()


#: a policy version past int64 (msgpack carries up to 2**64-1): refused at decode (its range)
HUGE = 2**64 - 1


def _raise_for_evil(monkeypatch, exc=OverflowError):
    """Something between receipt and insert raises an exception other than the protocol's own for
    the chunks of actor ``evil`` (what an unforeseen input would do)."""
    from zenrl.replay import ingest

    real = ingest.Chunk.of

    def of(payload, msg, source=""):
        if msg.actor_id == "evil":
            raise exc("unforeseen")
        return real(payload, msg, source)

    monkeypatch.setattr(ingest.Chunk, "of", staticmethod(of))


def test_an_integer_past_its_range_is_a_protocol_rejection():
    svc = _service()
    assert svc.ingest_many([(_payload(1, HUGE), "zenrl/r/transitions/evil"), (_payload(2), "zenrl/r/transitions/a0")]) == B
    v = svc.stats_values()
    assert v["rejected_field"] == 1 and "rejected_internal" not in v and v["rejected_from/evil"] == 1


def test_an_internal_error_costs_one_chunk_and_is_counted_by_type(monkeypatch):
    _raise_for_evil(monkeypatch)
    svc = _service()
    n = svc.ingest_many([(_payload(0), "zenrl/r/transitions/a0"), (_payload(1, actor="evil"), "zenrl/r/transitions/evil"),
                         (_payload(2), "zenrl/r/transitions/a0")])
    assert n == 2 * B and svc.buffer.inserts_total == 2 * B
    v = svc.stats_values()
    assert v["rejected_internal"] == 1 and v["rejected_internal/OverflowError"] == 1 and v["rejected_total"] == 1
    assert v["rejected_from/evil"] == 1
    # the first chunk of all may be the bad one: storage is then allocated from the next
    fresh = _service()
    assert fresh.ingest_many([(_payload(1, actor="evil"), "evil"), (_payload(2), "a0")]) == B


def test_an_insert_that_raises_is_retried_chunk_by_chunk(monkeypatch):
    """A multi-chunk insert that raises something unexpected (and stored nothing) is retried one
    chunk at a time: the honest chunks of the batch are stored, the one that raises is counted."""
    svc = _service()
    assert svc.ingest(_payload(0)) == B
    real = PlainStore.insert

    def insert(self, chunks):
        if any(c.msg.actor_id == "evil" for c in chunks):
            raise MemoryError("too big")
        return real(self, chunks)

    monkeypatch.setattr(PlainStore, "insert", insert)
    n = svc.ingest_many([(_payload(1), "a0"), (_payload(2, actor="evil"), "evil"), (_payload(3), "a0")])
    assert n == 2 * B and svc.buffer.inserts_total == 3 * B
    v = svc.stats_values()
    assert v["rejected_internal/MemoryError"] == 1 and v["rejected_from/evil"] == 1


class FakeNode:
    """Records declarations; the test calls the callbacks and fills the inboxes as Zenoh's
    threads would."""

    def __init__(self):
        self.subs, self.queryables, self.tokens, self.withdrawn, self.inboxes = {}, {}, [], [], {}

    def inbox(self, key, capacity):
        self.inboxes[key] = FakeInbox(key, capacity)
        return self.inboxes[key]

    def subscribe(self, key, cb):
        self.subs[key] = cb
        return key

    def queryable(self, key, handler):
        self.queryables[key] = handler
        return key

    def token(self, key):
        self.tokens.append(key)
        return key

    def withdraw(self, entity):
        self.withdrawn.append(entity)
        if entity in self.inboxes:
            self.inboxes[entity].close()
        return True


def _wait(cond, timeout_s=10.0):
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.01)


def test_the_ingest_thread_outlives_a_message_that_raises(monkeypatch):
    _raise_for_evil(monkeypatch)
    svc = _service()
    node, sup = FakeNode(), Supervisor()
    svc.start(node, sup)
    inbox = node.inboxes[svc.keys.transitions_all]
    try:
        inbox.put(svc.keys.transitions("evil"), _payload(0, actor="evil"))
        inbox.put(svc.keys.transitions("a0"), _payload(1))
        _wait(lambda: svc.buffer is not None and svc.buffer.inserts_total == B)
        inbox.put(svc.keys.transitions("a0"), _payload(2))
        _wait(lambda: svc.buffer.inserts_total == 2 * B)
        sup.check()  # no RoleFailed: the thread runs
        v = {**svc.report(1.0)[0], **sup.values()}
        assert v["rejected_internal/OverflowError"] == 1 and v["stalled"] == "" and v["errors_total"] == 0
    finally:
        svc.close()
    assert node.withdrawn == [svc.keys.transitions_all]  # the transitions subscriber goes first


def test_close_inserts_what_was_waiting_in_the_inbox(monkeypatch):
    # an inbox of 8 chunks (the byte bound over the chunk cap), batches of one chunk
    svc = _service(queue_max_bytes=8 * 4096, max_chunk_bytes=4096, ingest_batch_chunks=1)
    node, sup = FakeNode(), Supervisor()
    started = []
    real = type(svc.ingestor).ingest_many

    def held(self, items):  # busy with the first chunk until close() has begun: the rest still wait
        started.append(1)
        while len(started) == 1 and not self.closing.is_set():
            time.sleep(0.005)
        return real(self, items)

    monkeypatch.setattr(type(svc.ingestor), "ingest_many", held)
    svc.start(node, sup)
    inbox = node.inboxes[svc.keys.transitions_all]
    assert inbox.capacity == 8
    inbox.put(svc.keys.transitions("a0"), _payload(0))
    _wait(lambda: started)
    for i in range(1, 6):  # waiting when close() comes: it must still insert them all
        inbox.put(svc.keys.transitions("a0"), _payload(i))
    assert inbox.qsize() == 5
    svc.close()
    assert svc.buffer.inserts_total == 6 * B and svc.ingestor.pending() == 0 and inbox.qsize() == 0
    assert node.withdrawn == [svc.keys.transitions_all]
    assert not any(t.is_alive() for t in sup.threads)


class _Closing:
    """The ingest's stop event, whose timed wait stands for the linger: it records each wait
    and puts ``arrive`` into the inbox during it, as Zenoh's receive thread would."""

    def __init__(self, inbox, arrive=(), stopping=False):
        self.inbox, self.arrive, self.stopping, self.waits = inbox, list(arrive), stopping, []

    def wait(self, timeout):
        self.waits.append(timeout)
        for key in self.arrive:
            self.inbox.put(key, _payload(0))
        self.arrive = []
        return self.stopping

    def is_set(self):
        return self.stopping


def _pull(linger, waiting=(), arrive=(), stopping=False, capacity=8):
    """Keys of one batch the ingest gathers from a first chunk ``a`` with ``waiting`` in the
    inbox and ``arrive`` coming during a linger; and the waits it made."""
    from tests.unit.inbox_fake import FakeReceived

    svc = _service(ingest_linger_s=linger)
    inbox = FakeInbox("k", capacity)
    svc.ingestor.inbox, svc.ingestor.inbox_capacity = inbox, capacity
    for key in waiting:
        inbox.put(key, _payload(0))
    svc.ingestor.closing = closing = _Closing(inbox, arrive, stopping)
    keys = [key for _, key in svc.ingestor._pull(FakeReceived("a", _payload(0)))]
    left = []
    while (r := inbox.get_nowait()) is not None:
        left.append(r.key)
    return keys, closing.waits, left


def test_a_short_batch_waits_once_for_more_chunks():
    keys, waits, left = _pull(0.005, waiting=("b",), arrive=("c", "d"))
    assert keys == ["a", "b", "c", "d"] and waits == [0.005] and left == []


def test_a_full_batch_does_not_wait():
    # the first and 8 waiting fill a batch (an inbox of 8 chunks: 9 at most)
    w = [f"w{i}" for i in range(9)]
    keys, waits, left = _pull(0.005, waiting=w[:8])
    assert keys == ["a", *w[:8]] and waits == []
    # what arrives during the one wait is taken up to the batch's bound; the rest stays
    keys, waits, left = _pull(0.005, waiting=w[:5], arrive=("x", "y", "z", "q"), capacity=8)
    assert keys == ["a", *w[:5], "x", "y", "z"] and waits == [0.005] and left == ["q"]


def test_no_linger_and_a_stopping_ingest_take_only_what_waits():
    keys, waits, left = _pull(0, waiting=("b",), arrive=("c",))
    assert keys == ["a", "b"] and waits == []
    keys, waits, left = _pull(0.005, waiting=("b",), arrive=("c",), stopping=True)
    assert keys == ["a", "b"] and left == ["c"]  # the stop ended the wait: c waits for the drain

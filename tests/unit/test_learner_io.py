"""The learner's I/O helpers with in-process fakes: the background sender (priorities merged in
order, failures counted) and the sample prefetcher (requests in flight, retries, prepare, several
batches per request); both threads watched by the role's supervisor."""

import threading

import numpy as np
import pytest

from zenrl.common import protocol as P
from zenrl.common.replay_client import SamplePrefetcher, ZenohReplayClient
from zenrl.common.roles import RoleFailed, Supervisor
from zenrl.learner.sender import BackgroundSender
from tests.conftest import wait_until


class FakePublisher:
    def __init__(self, fail_first: int = 0) -> None:
        self.puts: list[bytes] = []
        self.fail_first = fail_first

    def put(self, payload: bytes) -> None:
        if self.fail_first > 0:
            self.fail_first -= 1
            raise RuntimeError("session closed")
        self.puts.append(payload)


class PublishingNode:
    """A node whose publishers record what is put on them, by key."""

    def __init__(self) -> None:
        self.pubs: dict[str, FakePublisher] = {}

    def publisher(self, key: str, **_kw) -> FakePublisher:
        return self.pubs.setdefault(key, FakePublisher())


def test_sender_merges_queued_priorities_in_order_and_keeps_other_payloads():
    node, weights = PublishingNode(), FakePublisher()
    client = ZenohReplayClient(node, P.Keys("unit"))
    s = BackgroundSender(linger_s=0.5)  # long enough that all four items gather before a send
    # the replay client's verb is the one way priorities go out
    s.send_priorities(client.update_priorities, np.array([1, 2, 3]), np.array([0.1, 0.2, 0.3], np.float32))
    s.send(weights, b"w1")
    s.send_priorities(client.update_priorities, np.array([2, 7]), np.array([0.9, 0.7], np.float32))
    s.send_priorities(client.update_priorities, np.array([8]), np.array([0.8], np.float32))
    s.close()
    prio = node.pubs[P.Keys("unit").priorities]
    assert weights.puts == [b"w1"]
    assert len(prio.puts) == 1
    u = P.PriorityUpdate.decode(prio.puts[0])
    np.testing.assert_array_equal(u.keys, [1, 2, 3, 2, 7, 8])  # key 2 twice: the later value last
    np.testing.assert_allclose(u.priorities, [0.1, 0.2, 0.3, 0.9, 0.7, 0.8], rtol=1e-6)
    assert (s.sent, s.failed, s.dropped) == (2, 0, 0)


def test_sender_without_linger_sends_each_item_and_counts_failed_puts():
    pub = FakePublisher(fail_first=1)
    client = ZenohReplayClient(PublishingNode(), P.Keys("unit"), max_message_bytes=200)
    s = BackgroundSender(linger_s=0.0)
    s.send(pub, b"a")
    wait_until(lambda: s.failed == 1, 5, "the first put to fail", 0.005)
    s.send(pub, b"b")
    s.send_priorities(client.update_priorities, np.arange(100), np.ones(100, np.float32))  # over the 200-byte cap
    s.send(pub, b"c")
    s.close()
    assert pub.puts == [b"b", b"c"]
    assert (s.sent, s.failed) == (2, 2)


class Fatal(BaseException):
    """Not an Exception: kills the thread it is raised in (what supervision must notice)."""


class RaisingPublisher(FakePublisher):
    def __init__(self, error: BaseException) -> None:
        super().__init__()
        self.error = error

    def put(self, payload: bytes) -> None:
        if self.error is not None:
            e, self.error = self.error, None
            raise e
        self.puts.append(payload)


class BlockedPublisher:
    """A put that blocks until released (a congested link under BLOCK congestion control)."""

    def __init__(self) -> None:
        self.entered, self.release = threading.Event(), threading.Event()

    def put(self, payload: bytes) -> None:
        self.entered.set()
        self.release.wait(30)


def test_sender_close_waits_at_most_its_timeout_for_a_blocked_put(caplog):
    pub = BlockedPublisher()
    s = BackgroundSender(linger_s=0.0)
    s.send(pub, b"w")
    wait_until(pub.entered.is_set, 5, "the put to start", 0.005)
    try:
        with caplog.at_level("WARNING"):
            assert s.close(timeout=0.2) is False  # returns, the put still blocked
        assert "still sending after 0.2 s" in caplog.text
    finally:
        pub.release.set()
    s2 = BackgroundSender(linger_s=0.0)
    assert s2.close(timeout=2.0) is True  # nothing queued: stops at once


def test_sender_whose_put_raises_once_counts_it_in_the_supervisor_and_keeps_sending():
    sup = Supervisor()
    pub = RaisingPublisher(ConnectionError("link down"))
    s = BackgroundSender(sup=sup)
    try:
        s.send(pub, b"first")
        wait_until(lambda: sup.errors["ConnectionError"] == 1, 5, "the failed put counted", 0.005)
        s.send(pub, b"next")
        wait_until(lambda: pub.puts == [b"next"], 5, "the next payload sent", 0.005)
        assert s.failed == 1 and s.sent == 1
        assert sup.values()["errors/ConnectionError"] == 1
        sup.check()  # the thread goes on: the role is fine
    finally:
        s.close()
    assert not s._t.is_alive()


def test_a_dead_sender_thread_fails_the_role():
    sup = Supervisor()
    s = BackgroundSender(sup=sup)
    s.send(RaisingPublisher(Fatal()), b"x")
    wait_until(lambda: not s._t.is_alive(), 5, "the sender's thread to die", 0.005)
    with pytest.raises(RoleFailed, match="thread sender failed: Fatal"):
        sup.check()


def test_a_dead_prefetcher_helper_thread_fails_the_role():
    node, sup = FakeNode(), Supervisor()
    betas = iter([0.4, 0.4, 0.4])  # the first requests; the retry after them raises

    def beta():
        try:
            return next(betas)
        except StopIteration:
            raise Fatal() from None

    client = ZenohReplayClient(node, P.Keys("unit"), timeout_s=1.0)
    pf = SamplePrefetcher(client, 4, beta, in_flight=3, backoff_s=0.01).start(sup)
    try:
        assert [t.name for t in sup.threads] == ["sample-retry"]
        sup.check()
        node.take()(None)  # timed out: the helper thread retries, and dies doing it
        wait_until(lambda: not sup.threads[0].is_alive(), 5, "the helper thread to die", 0.005)
        with pytest.raises(RoleFailed, match="thread sample-retry failed"):
            sup.check()
    finally:
        pf.stop()


def test_sender_drops_and_counts_over_its_queue_limit():
    pub = FakePublisher()
    s = BackgroundSender(max_items=3, linger_s=0.5)
    for i in range(5):
        s.send(pub, bytes([i]))
    s.close()
    assert s.dropped == 2
    assert pub.puts == [b"\x00", b"\x01", b"\x02"]


class FakeNode:
    """Records ``query_async`` calls; the test answers them by calling the callbacks."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.pending: list = []
        self.issued = 0
        self.sizes: list[int] = []

    def query_async(self, key, payload, timeout_s, on_reply) -> None:
        req = P.SampleRequest.decode(payload)  # a well-formed request
        with self.lock:
            self.pending.append(on_reply)
            self.issued += 1
            self.sizes.append(req.batch_size)

    def take(self):
        with self.lock:
            return self.pending.pop(0)


def ok_reply(n: int = 4) -> bytes:
    return P.SampleReply(request_id=1, status="ok", replay_size=100, keys=np.arange(n, dtype=np.int64),
                         probabilities=np.full(n, 0.01), weights=np.ones(n, np.float32),
                         data={"obs": np.zeros((n, 3), np.float32)}).encode()


def numbered_reply(n: int) -> bytes:
    """Item i has key i, probability i / 1000, weight i / 100 and observation [i, i, i]."""
    i = np.arange(n)
    return P.SampleReply(request_id=1, status="ok", replay_size=100, keys=i.astype(np.int64),
                         probabilities=i / 1000.0, weights=(i / 100.0).astype(np.float32),
                         data={"obs": np.repeat(i[:, None], 3, 1).astype(np.float32)}).encode()


def make_prefetcher(node, **kw) -> SamplePrefetcher:
    client = ZenohReplayClient(node, P.Keys("unit"), timeout_s=1.0)
    return SamplePrefetcher(client, 4, lambda: 0.4, in_flight=3, backoff_s=0.01, **kw).start()


def test_prefetcher_keeps_requests_in_flight_and_replaces_each_batch_taken():
    node = FakeNode()
    pf = make_prefetcher(node, prepare=lambda s: ("prepared", len(s.keys)))
    try:
        assert node.issued == 3
        assert pf.get(timeout_s=0.05) is None  # nothing answered yet
        node.take()(ok_reply())
        node.take()(ok_reply())
        assert node.issued == 3  # a reply alone issues nothing: ready + in flight == 3
        s = pf.get(timeout_s=1.0)
        assert s is not None and s.prepared == ("prepared", 4) and s.replay_size == 100
        assert node.issued == 4  # taking a batch issued its replacement
        assert pf.get(timeout_s=1.0) is not None
        assert node.issued == 5 and len(node.pending) == 3
    finally:
        pf.stop()


def test_prefetcher_retries_not_ready_timeouts_and_bad_replies_after_a_backoff():
    node = FakeNode()
    calls = []

    def prepare(s):
        calls.append(1)
        if len(calls) == 1:
            raise ValueError("wrong shape")
        return "ok"

    pf = make_prefetcher(node, prepare=prepare)
    try:
        node.take()(P.SampleReply(request_id=1, status="not_ready", reason="min_size 1000 > size 12").encode())
        node.take()(None)  # timed out
        node.take()(b"\x00garbage")
        wait_until(lambda: node.issued == 6, 5, "three retried requests", 0.005)
        assert (pf.not_ready, pf.timeouts, pf.errors) == (1, 1, 1)
        assert pf.last_not_ready_reason == "min_size 1000 > size 12"
        node.take()(ok_reply())  # prepare raises on this one: counted and retried
        wait_until(lambda: node.issued == 7, 5, "the retry after a failed prepare", 0.005)
        assert pf.errors == 2
        node.take()(ok_reply())
        s = pf.get(timeout_s=1.0)
        assert s is not None and s.prepared == "ok"
        assert pf.last_not_ready_reason == ""  # served again: the old reason is not shown as current
    finally:
        pf.stop()


def test_prefetcher_splits_a_reply_into_batches_and_requests_once_per_k_taken():
    node = FakeNode()
    client = ZenohReplayClient(node, P.Keys("unit"), timeout_s=1.0)
    pf = SamplePrefetcher(client, 4, lambda: 0.4, in_flight=2, backoff_s=0.01, batches_per_request=3, seed=1,
                          prepare=lambda s: s.keys.copy()).start()
    try:
        assert node.sizes == [12, 12]  # k * batch_size items per request
        node.take()(numbered_reply(12))
        got = []
        for i in range(3):
            s = pf.get(timeout_s=1.0)
            assert s is not None and len(s.keys) == 4 and s.replay_size == 100
            # rows stay together: every field of a row belongs to the same item
            np.testing.assert_array_equal(s.data["obs"][:, 0], s.keys)
            np.testing.assert_allclose(s.probabilities, s.keys / 1000.0)
            np.testing.assert_allclose(s.weights, s.keys / 100.0, rtol=1e-6)
            np.testing.assert_array_equal(s.prepared, s.keys)
            got.append(s.keys)
            # the replacement request goes out with the last of the k batches, not before
            assert node.issued == (2 if i < 2 else 3)
        keys = np.concatenate(got)
        np.testing.assert_array_equal(np.sort(keys), np.arange(12))  # each item in exactly one batch
        assert not np.array_equal(keys, np.arange(12))  # dealt out at random, not in stratum order
    finally:
        pf.stop()


def test_prefetcher_counts_and_retries_a_reply_of_the_wrong_size():
    node = FakeNode()
    client = ZenohReplayClient(node, P.Keys("unit"), timeout_s=1.0)
    pf = SamplePrefetcher(client, 4, lambda: 0.4, in_flight=1, backoff_s=0.01, batches_per_request=2).start()
    try:
        node.take()(numbered_reply(4))  # 4 items for a request of 8
        wait_until(lambda: node.issued == 2, 5, "the retried request", 0.005)
        assert pf.errors == 1 and pf.get(timeout_s=0.05) is None
        node.take()(numbered_reply(8))
        assert pf.get(timeout_s=1.0) is not None and pf.get(timeout_s=1.0) is not None
        assert node.issued == 3
    finally:
        pf.stop()


def test_prefetcher_refuses_more_items_per_request_than_the_protocol_allows():
    client = ZenohReplayClient(FakeNode(), P.Keys("unit"), timeout_s=1.0)
    with pytest.raises(ValueError, match="batches_per_request=2 with batch_size=40000"):
        SamplePrefetcher(client, 40000, lambda: 0.4, batches_per_request=2)

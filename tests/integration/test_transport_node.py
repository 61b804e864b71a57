"""What roles rely on from common/transport.Node so that they need not import zenoh: a token that
cannot be declared raises the project's TransportError, and withdrawing an entity never raises,
even once the session is gone (a stopping role goes on stopping); an inbox (the replay's intake)
keeps order, loses nothing under BLOCK and closes when withdrawn."""

import time

import pytest

from zenrl.common import protocol as P
from zenrl.common.errors import TransportError
from zenrl.common.transport import Node
from tests.conftest import wait_until

pytestmark = pytest.mark.integration


def test_token_and_withdraw(router, run_id):
    keys = P.Keys(run_id)
    with Node(router, 10.0) as watcher, Node(router, 10.0) as node:
        tok = node.token(keys.quarantined("a7"))
        wait_until(lambda: watcher.alive_now(keys.quarantined("a7"), 0.5), 10, "the token at the router")
        assert node.withdraw(tok)
        wait_until(lambda: not watcher.alive_now(keys.quarantined("a7"), 0.5), 10, "the token gone")
        sub = node.subscribe(keys.transitions_all, lambda k, p: None)
        tok = node.token(keys.quarantined("a8"))
        node.session.close()  # the router went away, or the process is closing
        node.withdraw(sub)
        node.withdraw(tok)
        with pytest.raises(TransportError, match="liveliness token"):
            node.token(keys.quarantined("a9"))


def test_inbox_keeps_order_loses_nothing_and_closes_on_withdraw(router, run_id):
    """Node.inbox: samples in publication order with their keys and bytes, none lost with a
    consumer slower than a BLOCK publisher (the FIFO of 2 holds the sender back), get_nowait
    returns None when empty, and withdrawing the subscription wakes a waiting get() with None."""
    import threading

    keys = P.Keys(run_id)
    with Node(router, 10.0) as rx, Node(router, 10.0) as tx:
        inbox = rx.inbox(keys.transitions_all, 2)
        assert inbox.get_nowait() is None
        pub = tx.publisher(keys.transitions("a3"))
        wait_until(lambda: pub.matching_status.matching, 10, "the inbox to match the publisher")
        payloads = [bytes([i]) * (256 * 1024) for i in range(24)]
        sent = threading.Thread(target=lambda: [pub.put(p) for p in payloads])
        sent.start()
        got = []
        while len(got) < len(payloads):
            r = inbox.get()
            assert r is not None and r.key == keys.transitions("a3") and r.nbytes == 256 * 1024
            got.append(r.data())
            time.sleep(0.01)  # slower than the publisher
        sent.join(10)
        assert got == payloads
        waiter: list = []
        t = threading.Thread(target=lambda: waiter.append(inbox.get()))
        t.start()
        time.sleep(0.2)
        assert t.is_alive()  # nothing to take: it waits
        assert rx.withdraw(inbox.subscription)
        t.join(5)
        assert not t.is_alive() and waiter == [None]
        assert inbox.get_nowait() is None

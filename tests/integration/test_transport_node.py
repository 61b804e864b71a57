"""What roles rely on from common/transport.Node so that they need not import zenoh: a token that
cannot be declared raises the project's TransportError, and withdrawing an entity never raises,
even once the session is gone (a stopping role goes on stopping)."""

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

"""Failover the SDK user does not notice: two ``catalign serve`` replicas sharing one library
behind HAProxy, one killed with SIGKILL while 16 SDK clients register through HAProxy.

HAProxy here resends only requests whose connection was refused (``retry-on conn-failure``),
the ones that never reached a replica; a request that the killed replica held comes back to the
client as a 502, or, on a kept-alive client connection, as that connection closed without an
answer (HAProxy leaves the retry to the client, as browsers do). So the zero failures below are
the SDK's doing: it resends a registration after either (it changes nothing), with jittered
back-off, within its retry budget. The full
configuration in ``docs/deploy-replicas.md`` also lets HAProxy resend those
(``test_replicas.py``); ``bench/failover.py`` runs this scenario longer and reports latencies.
"""

from __future__ import annotations

import shutil
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.deploy._load import Load, chair_view
from tests.deploy._replicas import Deployment, haproxy_binary

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        haproxy_binary() is None,
        reason="haproxy is not installed (Debian: apt-get install haproxy); the failover test "
        "needs a real load balancer in front of the replicas",
    ),
]

CLIENTS = 16


@pytest.fixture
def replicas(model_dir: Path, procedural_library: Path, tmp_path: Path) -> Iterator[Deployment]:
    """Two single-worker read-only replicas, HAProxy resending refused connections only."""
    shutil.copytree(procedural_library, tmp_path / "library")
    with Deployment(
        tmp_path / "library", model_dir, tmp_path / "run", readers=2, writer=False,
        resend="conn-failure",
    ) as running:  # fmt: skip
        yield running


def test_a_replica_killed_under_load_fails_no_sdk_call(replicas: Deployment) -> None:
    victim = replicas.readers[0]
    server = f"readers/{victim.name}"
    with Load(replicas.url, chair_view(1, step=3), CLIENTS, limit_s=90) as load:
        load.wait_for(CLIENTS, since=load.started, timeout=60)  # both replicas busy
        assert int(replicas.proxy.stats()[server]["hrsp_2xx"]) > 0
        killed = time.monotonic()
        victim.stop(signal.SIGKILL)
        replicas.proxy.wait_status(server, "DOWN", timeout=10)
        load.wait_for(CLIENTS, since=killed, timeout=60)  # as many as there are clients
        load.stop()
    calls = load.done()
    assert not load.failures, load.failures[:5]
    after = [c for c in calls if c.started > killed]
    assert len(after) >= CLIENTS and all(c.error is None for c in after)
    # The requests the victim held reached the SDK as failures and were sent again: a 502, or
    # (on a kept-alive connection, as HAProxy does) the connection closed without an answer.
    assert sum(load.retry_reasons.values()) >= 1, load.retry_reasons
    proxy_5xx = int(replicas.proxy.stats()["catalign/FRONTEND"]["hrsp_5xx"])
    assert proxy_5xx == sum(n for r, n in load.retry_reasons.items() if r.startswith("5"))

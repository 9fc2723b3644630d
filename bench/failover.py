"""Failover under load: a replica killed with SIGKILL while SDK clients register through HAProxy.

Starts two ``catalign serve --read-only --workers 1`` replicas (``CATALIGN_THREADS_PER_WORKER=1``)
sharing one library (default ``model_store/library``) behind HAProxy, the set-up of the
deployment tests (``tests/deploy/_replicas.py``: leastconn, 2 requests per replica at once, the
rest queued in HAProxy, health checks on ``/health/ready`` every 250 ms). HAProxy resends only
requests whose connection was refused (``retry-on conn-failure``), so what the killed replica
held reaches the SDK, as a 502 or as a kept-alive connection closed without an answer, and the
SDK's own retries must absorb it; ``--proxy-resends`` lets HAProxy resend those too, as
``docs/deploy-replicas.md`` configures it. ``--clients`` SDK clients (``Client.align``, binary,
the default retry policy) register a view of a library chair back to back for ``--seconds``; at
the middle, reader-1 gets SIGKILL and stays down.

Prints a markdown table and writes it to ``--out`` (default ``bench/results/failover.md``):
calls, failed calls (any exception the SDK raised), throughput and latency (median, p95)
before the kill, of the calls in flight at the kill, and after it; the SDK's retries by reason
(counted from its log); HAProxy's 5xx answers; how long HAProxy took to mark the replica DOWN.

    .venv/bin/python bench/failover.py [--seconds 60] [--clients 16] [--library DIR]
        [--step 2] [--proxy-resends] [--out bench/results/failover.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import signal
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from _report import load_average, publish

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the set-up is the deployment tests' own modules

from tests.deploy._load import Call, Load, chair_view, percentile  # noqa: E402
from tests.deploy._replicas import RESEND, Deployment  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "failover.md"
MODEL_DIR = ROOT / "model_store"
LIBRARY = MODEL_DIR / "library"
VIEW_SEED = 1  # proc-0001, a chair of the default library
TIMEOUT_S = 120.0  # per attempt: after the kill, 16 requests queue for one replica


def row(name: str, calls: Sequence[Call], window: tuple[float, float] | None) -> str:
    """One phase of the table: calls, failures, answers per second (every call that ended in
    ``window``, ``time.monotonic()`` from and to, over its length), median and p95 ms."""
    ms = [c.ms for c in calls]
    rate = "-"
    if window is not None:
        ended = sum(window[0] < c.ended <= window[1] for c in calls)
        rate = f"{ended / (window[1] - window[0]):.2f}"
    failed = sum(c.error is not None for c in calls)
    median, p95 = percentile(ms, 50), percentile(ms, 95)
    return f"| {name} | {len(calls)} | {failed} | {rate} | {median:.0f} | {p95:.0f} |"


def shown(path: Path) -> str:
    """``path`` relative to the repository when it is inside it."""
    path = path.resolve()
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="Length of the load.")
    parser.add_argument("--clients", type=int, default=16, help="SDK clients, one thread each.")
    parser.add_argument("--library", type=Path, default=LIBRARY)
    parser.add_argument("--step", type=int, default=2, help="Keep every step-th view point.")
    parser.add_argument(
        "--proxy-resends",
        action="store_true",
        help=f"HAProxy resends what a dying replica dropped too (retry-on {RESEND}).",
    )
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()

    points = chair_view(VIEW_SEED, step=args.step)
    resend = RESEND if args.proxy_resends else "conn-failure"
    load_before = load_average()
    with (
        tempfile.TemporaryDirectory(prefix="catalign-failover-") as work,
        Deployment(
            args.library,
            MODEL_DIR,
            Path(work),
            readers=2,
            writer=False,
            resend=resend,
            env={"CATALIGN_DEADLINE_S": str(TIMEOUT_S)},
        ) as deployment,
    ):
        victim = deployment.readers[0]
        server = f"readers/{victim.name}"
        with Load(
            deployment.url, points, args.clients, args.seconds + 60, timeout=TIMEOUT_S
        ) as load:
            time.sleep(args.seconds / 2)
            killed = time.monotonic()
            victim.stop(signal.SIGKILL)
            down_s = deployment.proxy.wait_status(server, "DOWN", timeout=30)
            print(
                f"killed {victim.name}: DOWN {down_s * 1e3:.0f} ms after its exit",
                file=sys.stderr,
            )
            load.stop(at_least_s=args.seconds)
            stop_at = load.started + args.seconds  # no call starts after it
        frontend = deployment.proxy.stats()["catalign/FRONTEND"]
        proxy_5xx = int(frontend["hrsp_5xx"])
    calls = load.done()
    before = [c for c in calls if c.ended <= killed]
    held = [c for c in calls if c.started <= killed < c.ended]
    after = [c for c in calls if c.started > killed]
    retries = load.retry_reasons
    closed = sum(n for reason, n in retries.items() if not reason[:1].isdigit())
    answered = sum(retries.values()) - closed
    failures = load.failures
    proxy = f"retry-on {resend}"
    lines = [
        "# Failover: a replica killed under load (SDK through HAProxy, loopback)",
        "",
        f"{platform.machine()}, {os.cpu_count()} CPUs; 2 `catalign serve --read-only "
        "--workers 1` replicas (`CATALIGN_THREADS_PER_WORKER=1`) sharing "
        f"`{shown(args.library)}`"
        f" behind HAProxy (`tests/deploy/_replicas.py`, `{proxy}`); {args.clients} SDK clients "
        f"(`Client.align`, binary, {len(points)} points, up=+Z, seed=0, default retries) for "
        f"{args.seconds:.0f} s; reader-1 killed with SIGKILL after "
        f"{killed - load.started:.0f} s and left down; HAProxy marked it DOWN "
        f"{down_s * 1e3:.0f} ms after the process exited. Load average {load_before:.2f} "
        f"before, {load_average():.2f} after.",
        "",
        "| phase | calls | failed | answers/s | median ms | p95 ms |",
        "|---|---|---|---|---|---|",
        row("before the kill (2 replicas)", before, (load.started, killed)),
        row("in flight at the kill", held, None),
        row("after the kill (1 replica)", after, (killed, stop_at)),
        row("all", calls, (load.started, stop_at)),
        "",
        f"**{len(failures)} failed SDK calls of {len(calls)}.** The SDK retried "
        f"{sum(retries.values())} requests: {closed} whose connection HAProxy closed without an "
        f"answer, {answered} answered with a 5xx; HAProxy answered {proxy_5xx} requests with a "
        "5xx. Retries by reason: "
        + (", ".join(f"{reason} {n}" for reason, n in retries.most_common()) or "none")
        + ".",
    ]
    if failures:
        lines += ["", "First failures: " + "; ".join(failures[:3])]
    publish("\n".join(lines) + "\n", args.out)


if __name__ == "__main__":
    main()

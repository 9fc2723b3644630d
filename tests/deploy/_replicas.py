"""Several ``catalign serve`` replicas sharing one library folder behind HAProxy, on loopback.

One optional *writer* (library changes allowed) and N *readers* (``--read-only``) serve the same
folder; each reloads the library when its manifest changes. HAProxy sends library changes
(``POST``/``DELETE`` under ``/models``) to the writer and everything else to the readers, with
the writer as the readers' backup. It checks ``/health/ready`` every ``check_ms``, so a replica
that dies or restarts leaves the pool and comes back by itself; a request that finds a replica
gone (refused connection, connection closed without an answer) is sent again to another one
(``retry-on``, ``option redispatch``), which is safe because a registration is a pure function.
Library changes are never resent by HAProxy: adding a model twice is not harmless.

Used by ``tests/deploy/test_replicas.py`` and by ``bench/serve.py --replicas``; it needs the
``haproxy`` binary (Debian package ``haproxy``). ``docs/deploy-replicas.md`` explains the set-up.
"""

from __future__ import annotations

import csv
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Self

import httpx

START_TIMEOUT_S = 180.0
LIBRARY_SEEDS = 3  # the tests' library: proc-0000, proc-0001, proc-0002, as tests/api builds it
HAPROXY_BUFFER = 1 << 20  # requests up to this size (about 87,000 binary points) can be resent
RESEND = "conn-failure empty-response junk-response"  # what HAProxy resends to another reader


def haproxy_binary() -> str | None:
    """The ``haproxy`` executable (Debian installs it in /usr/sbin), or None."""
    return shutil.which("haproxy") or shutil.which("haproxy", path="/usr/sbin:/usr/local/sbin")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def wait_until(check: Callable[[], bool], timeout: float, what: str, every: float = 0.1) -> None:
    """Poll ``check`` until it is true; AssertionError naming ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not check():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not after {timeout:.0f} s")
        time.sleep(every)


@dataclass
class Replica:
    """One ``catalign serve`` process on a fixed loopback port (kept across restarts, since
    HAProxy's configuration names it); its output goes to ``log``."""

    name: str
    library: Path
    model_dir: Path
    log: Path
    read_only: bool = True
    workers: int = 1
    threads_per_worker: int = 1
    queue: int = 8
    env: dict[str, str] = field(default_factory=dict)
    port: int = field(default_factory=free_port)
    process: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def start(self) -> None:
        """Start the process (not waiting for it: see :meth:`wait_ready`)."""
        if self.alive:
            raise RuntimeError(f"{self.name} is already running")
        exe = shutil.which("catalign", path=str(Path(sys.executable).parent)) or "catalign"
        command = [
            exe,
            "serve",
            *("--library", str(self.library), "--model-dir", str(self.model_dir)),
            *("--host", "127.0.0.1", "--port", str(self.port), "--grpc-port", "0"),
            *("--workers", str(self.workers), "--queue", str(self.queue)),
            *(["--read-only"] if self.read_only else []),
        ]
        environment = {k: v for k, v in os.environ.items() if not k.startswith("CATALIGN_")}
        environment |= {
            "CATALIGN_THREADS_PER_WORKER": str(self.threads_per_worker),
            "CATALIGN_LOG_LEVEL": "warning",
        }
        with self.log.open("ab") as log:  # appended: a restarted replica keeps its history
            self.process = subprocess.Popen(
                command,
                env=environment | self.env,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
            )

    def wait_ready(self, timeout: float = START_TIMEOUT_S) -> None:
        def ready() -> bool:
            if not self.alive:
                raise RuntimeError(f"{self.name} exited during start-up:\n{self.log_tail()}")
            try:
                return httpx.get(f"{self.url}/health/ready", timeout=5).status_code == 200
            except httpx.TransportError:
                return False

        wait_until(ready, timeout, f"{self.name} ready", every=0.2)

    def stop(self, sig: signal.Signals = signal.SIGTERM, timeout: float = 60.0) -> None:
        """Send ``sig`` (SIGTERM: a graceful stop; SIGKILL: a crash) and wait for the exit."""
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(sig)
        try:
            self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()

    def log_tail(self, chars: int = 4000) -> str:
        return self.log.read_text(errors="replace")[-chars:] if self.log.exists() else ""


def haproxy_config(
    port: int,
    readers: Sequence[Replica],
    writer: Replica | None,
    stats_socket: Path,
    *,
    check_ms: int = 250,
    resend: str = RESEND,
) -> str:
    """An HAProxy configuration for ``readers`` (and ``writer``) on ``127.0.0.1:port``.

    HAProxy hands each replica at most its workers plus one request at once (``maxconn``: the
    worker never idles between two requests); the rest wait in HAProxy's queue and go to
    whichever replica frees up first, and a replica that dies takes only its own few requests
    down with it, which HAProxy then resends to another one (``resend``: the readers'
    ``retry-on`` events; ``"conn-failure"`` alone leaves a request whose replica died under it
    to the client, as a 502).
    """

    def server(replica: Replica, *extra: str) -> str:
        address = f"127.0.0.1:{replica.port}"
        return " ".join(
            ("    server", replica.name, address, f"maxconn {replica.workers + 1}", *extra)
        )

    readiness = [
        "    option httpchk",
        "    http-check send meth GET uri /health/ready",
        "    http-check expect status 200",
        f"    default-server check inter {check_ms}ms fall 2 rise 2",
    ]
    # A refused connection marks a replica down at once, before its next check: else, while
    # the others are at their maxconn, every retry would pick the dead one again.
    passive = "    default-server observe layer4 error-limit 1 on-error mark-down"
    lines = [
        "global",
        "    maxconn 256",
        f"    tune.bufsize {HAPROXY_BUFFER}",
        f"    stats socket {stats_socket} mode 600 level admin",
        "",
        "defaults",
        "    mode http",
        "    option http-buffer-request",  # the whole body before a server is chosen: resendable
        "    timeout connect 1s",
        "    timeout client 120s",
        "    timeout http-request 30s",
        "    timeout server 120s",
        "    timeout queue 60s",
        "    timeout check 2s",
        "    retries 3",
        "    option redispatch 1",  # every retry goes to another replica
        "",
        "frontend catalign",
        f"    bind 127.0.0.1:{port}",
        "    acl library_change path_beg /models",
        "    acl writes method POST PUT PATCH DELETE",
    ]
    if writer is not None:
        lines.append("    use_backend writer if library_change writes")
    lines += [
        "    default_backend readers",
        "",
        "backend readers",
        "    balance leastconn",
        # A registration is a pure function: resend it when its replica died under it.
        f"    retry-on {resend}",
        *readiness,
        passive,
        *(server(r) for r in readers),
    ]
    if writer is not None:
        lines += [
            server(writer, "backup"),
            "",
            "backend writer",  # retries connection failures only: a change is never resent
            *readiness,
            server(writer),
        ]
    return "\n".join(lines) + "\n"


class HAProxy:
    """``haproxy`` in the foreground with a generated configuration, and its stats socket."""

    def __init__(self, config: str, work_dir: Path, port: int, stats_socket: Path) -> None:
        binary = haproxy_binary()
        if binary is None:
            raise RuntimeError("haproxy is not installed (Debian: apt-get install haproxy)")
        self.port = port
        self.stats_socket = stats_socket
        self.config_path = work_dir / "haproxy.cfg"
        self.config_path.write_text(config)
        self.log = work_dir / "haproxy.log"
        subprocess.run([binary, "-c", "-q", "-f", str(self.config_path)], check=True)
        with self.log.open("ab") as log:
            self.process = subprocess.Popen(
                [binary, "-db", "-f", str(self.config_path)],
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        wait_until(self._listening, 10, "haproxy listening")

    def _listening(self) -> bool:
        if self.process.poll() is not None:
            raise RuntimeError(f"haproxy exited: {self.log.read_text(errors='replace')}")
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
            return sock.connect_ex(("127.0.0.1", self.port)) == 0

    def command(self, line: str) -> str:
        """One command on the stats socket (``show stat``, ``set server readers/x state maint``)."""
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(5)
            sock.connect(str(self.stats_socket))
            sock.sendall(line.encode() + b"\n")
            chunks = []
            while chunk := sock.recv(65536):
                chunks.append(chunk)
        return b"".join(chunks).decode()

    def stats(self) -> dict[str, dict[str, str]]:
        """``show stat`` as ``{"backend/server": row}``; ``row["status"]`` is UP, DOWN, MAINT,
        or a transition such as ``UP 1/2``; ``row["hrsp_2xx"]`` counts its 2xx answers."""
        text = self.command("show stat").lstrip("# ")
        return {f"{r['pxname']}/{r['svname']}": r for r in csv.DictReader(text.splitlines())}

    def status(self, server: str) -> str:
        return self.stats()[server]["status"]

    def wait_status(self, server: str, status: str, timeout: float = 30.0) -> float:
        """Wait until ``server`` (``backend/name``) has ``status``; returns the seconds waited."""
        started = time.monotonic()
        wait_until(lambda: self.status(server) == status, timeout, f"{server} {status}", 0.05)
        return time.monotonic() - started

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


class Deployment:
    """A writer (optional), ``readers`` read-only replicas and HAProxy in front, until closed.

    ``with Deployment(library, model_dir, work_dir, readers=2) as deployment:`` starts every
    replica at once, waits until each is ready and HAProxy sees it UP; ``deployment.url`` is
    HAProxy's. ``workers``, ``threads_per_worker``, ``queue`` and ``env`` (extra ``CATALIGN_*``
    variables) apply to every replica; ``resend`` is HAProxy's (see :func:`haproxy_config`).
    """

    def __init__(
        self,
        library: Path,
        model_dir: Path,
        work_dir: Path,
        *,
        readers: int = 2,
        writer: bool = True,
        workers: int = 1,
        threads_per_worker: int = 1,
        queue: int = 8,
        env: dict[str, str] | None = None,
        check_ms: int = 250,
        resend: str = RESEND,
    ) -> None:
        work_dir.mkdir(parents=True, exist_ok=True)

        def replica(name: str, read_only: bool) -> Replica:
            return Replica(
                name,
                library,
                model_dir,
                work_dir / f"{name}.log",
                read_only=read_only,
                workers=workers,
                threads_per_worker=threads_per_worker,
                queue=queue,
                env=dict(env or {}),
            )

        self.readers = [replica(f"reader-{i + 1}", True) for i in range(readers)]
        self.writer = replica("writer", False) if writer else None
        self.replicas = [*self.readers, *([self.writer] if self.writer else [])]
        self.work_dir = work_dir
        self.port = free_port()
        self.config = haproxy_config(
            self.port,
            self.readers,
            self.writer,
            work_dir / "haproxy.sock",
            check_ms=check_ms,
            resend=resend,
        )
        self.haproxy: HAProxy | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> Self:
        try:
            for replica in self.replicas:
                replica.start()
            for replica in self.replicas:
                replica.wait_ready()
            self.haproxy = HAProxy(
                self.config, self.work_dir, self.port, self.work_dir / "haproxy.sock"
            )
            for replica in self.readers:
                self.haproxy.wait_status(f"readers/{replica.name}", "UP")
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        if self.haproxy is not None:
            self.haproxy.stop()
        for replica in self.replicas:
            replica.stop()

    @property
    def proxy(self) -> HAProxy:
        if self.haproxy is None:
            raise RuntimeError("the deployment has not started")
        return self.haproxy

    def restart(self, replica: Replica, sig: signal.Signals = signal.SIGTERM) -> None:
        """Stop ``replica`` with ``sig``, start it again, and wait until HAProxy sees it UP."""
        replica.stop(sig)
        replica.start()
        replica.wait_ready()
        backend = "readers" if replica.read_only else "writer"
        self.proxy.wait_status(f"{backend}/{replica.name}", "UP")

    def ensure_up(self) -> None:
        """Restart any replica that is not running (a test that failed half-way left it so)."""
        for replica in self.replicas:
            if not replica.alive:
                self.restart(replica)

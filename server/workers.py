"""Several server processes over one PostgreSQL database, behind nginx: ``trustlab serve --workers N``.

One trustlab process serves every request on one event loop, so it uses about one core (what that carries:
docs/benchmarks.md; how to run a group: docs/deployment.md). A group runs N workers, each a whole trustlab app
(uvicorn on a unix socket in a private run directory), and nginx in front of them on the public address. This
module writes nginx's configuration, starts the workers and nginx, restarts a worker that exits, and stops them all
on SIGTERM or Ctrl-C.

Routing. A participant's live world (the attempt being played back, the arm under teleoperation, the 3D view's
viser server) is kept in the memory of one process. So every request that names a session token
(``/p/{token}``, ``/api/p/{token}/...`` with the teleoperation websocket, ``/viewer/{token}...``) goes to the
worker that a consistent hash of the token picks: a session sticks to its worker, and when a worker is
added or lost only its own sessions move. The admin API and joins go to worker 0, the primary: it alone runs
the background jobs (the abandonment sweep, model fits) and counts the join rate limits. Everything else
(pages, static files, the API docs) is spread round robin.

A worker that exits is started again; until it is back, nginx sends its sessions to another worker, where
their live world starts afresh, as after a server restart (their data is in the database). Several workers
need PostgreSQL: SQLite takes one writer at a time, and trustlab's SQLite path (turns at the database on the
event loop, group commit) coordinates the requests of one process.

Across several machines. The same group can span machines: each runs ``trustlab worker --index I --host H
--port P`` (the whole app on a TCP address, believing X-Forwarded-For from nginx's address only), and one runs
``trustlab serve --workers-at H:P,H:P,...`` (nginx alone, the same configuration with TCP upstreams; the first
address is the primary). Nothing restarts a worker on another machine: run it under systemd or the like.
"""

from __future__ import annotations

import argparse
import ctypes
import ipaddress
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path

from sqlalchemy.engine import make_url

from server.launch import run_server
from server.settings import Settings

log = logging.getLogger("trustlab.workers")

#: Seconds a worker or nginx may take to start before the group gives up.
START_TIMEOUT_S = 60.0
#: Seconds the processes get to finish on stop (open websockets are closed) before they are killed.
STOP_TIMEOUT_S = 15.0
#: Worker exits restarted within RESTART_WINDOW_S; one more and the group stops (restarting does not mend it).
MAX_RESTARTS = 5
RESTART_WINDOW_S = 60.0
#: Seconds between two looks at the processes.
SUPERVISE_PERIOD_S = 0.2
#: Idle connections nginx keeps open to each worker (a connection per request would cost a handshake each).
UPSTREAM_KEEPALIVE = 64
#: Longest a proxied websocket or response may stay silent (the 3D view and teleoperation stay open for a study).
PROXY_TIMEOUT_S = 3600

#: The session token in a participant URL, for the routing hash (server.routes: participant, teleop, viewer, pages).
SESSION_PATH = r"^/(?:api/p|p|viewer)/(?<token>[^/]+)"
#: Paths served by the primary (worker 0): the admin API (fits, exports, reports) and joins (rate limits).
PRIMARY_PATHS = ("^~ /api/admin/", r"~ ^/api/studies/[^/]+/join$")

_PR_SET_PDEATHSIG = 1


class GroupError(RuntimeError):
    """The group cannot be started or kept running (the message says why and what to do)."""


def check_postgres(settings: Settings) -> None:
    """Refuse a database that several workers cannot share."""
    if make_url(settings.database_url).get_backend_name() != "postgresql":
        raise GroupError("several workers need PostgreSQL (--database-url postgresql+psycopg://...): SQLite takes "
                         "one writer at a time, and its durability path coordinates the requests of one process. "
                         "On SQLite, run one process ('trustlab serve' without --workers).")


def find_nginx() -> str:
    """The nginx executable, or a GroupError that says how to install it."""
    nginx = shutil.which("nginx") or next((p for p in ("/usr/sbin/nginx", "/usr/local/sbin/nginx")
                                           if os.access(p, os.X_OK)), None)
    if nginx is None:
        raise GroupError("several workers need nginx in front of them, to route each participant to one worker; "
                         "install it (Debian/Ubuntu: apt-get install nginx) and try again")
    return nginx


def check_group(settings: Settings, workers: int) -> str:
    """Refuse a group that cannot work; returns the nginx executable."""
    if workers < 2:
        raise GroupError("a group needs at least 2 workers")
    check_postgres(settings)
    return find_nginx()


def _listen_address(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def unix_upstream(path: Path) -> str:
    """nginx's name of a worker on a unix socket."""
    return f"unix:{path}"


def worker_addresses(text: str) -> list[str]:
    """``HOST:PORT,HOST:PORT,...`` (``[IPv6]:PORT`` too) as nginx upstream addresses; the first is the primary."""
    addresses = [part.strip() for part in text.split(",") if part.strip()]
    if len(addresses) < 2:
        raise GroupError(f"--workers-at needs at least 2 workers as HOST:PORT,HOST:PORT (the first is the primary, "
                         f"worker 0), got {text!r}")
    for address in addresses:
        host, _, port = address.rpartition(":")
        if host.startswith("[") and host.endswith("]"):
            try:
                ipaddress.IPv6Address(host[1:-1])
            except ValueError:
                raise GroupError(f"worker address {address!r}: {host[1:-1]!r} is not an IPv6 address") from None
        elif not host or ":" in host:
            port = ""
        if not port.isdigit() or not 0 < int(port) < 65536:
            raise GroupError(f"worker address {address!r} is not HOST:PORT (an IPv6 address in brackets: [::1]:8001)")
    if len(set(addresses)) != len(addresses):
        raise GroupError(f"--workers-at names a worker twice: {text!r}")
    return addresses


def trusted_proxies(host: str, given: Sequence[str]) -> list[str]:
    """The addresses a worker on TCP believes X-Forwarded-For from: nginx's, given with --trusted-proxy.

    The join rate limits count the participant's address, which nginx passes in X-Forwarded-For; a worker that
    believed the header from anyone could be sent forged addresses by whoever reaches its port. Without
    --trusted-proxy, a worker on a loopback address believes the loopback address (nginx on the same machine);
    one on any other address is refused.
    """
    if not given:
        if _is_loopback(host):
            return ["127.0.0.1", "::1"]
        raise GroupError(f"a worker on {host} needs --trusted-proxy NGINX_ADDRESS: it believes the participant's "
                         "address (X-Forwarded-For, counted by the join rate limits) only from nginx, and nginx "
                         "is not on this machine's loopback")
    trusted = []
    for address in (a.strip() for a in given):
        if address == "*":
            raise GroupError("--trusted-proxy '*' would believe X-Forwarded-For from anyone who reaches the worker's "
                             "port, who could then dodge the join rate limits; give nginx's address")
        try:  # uvicorn compares addresses and networks, and silently never matches anything else (a name)
            trusted.append(str(ipaddress.ip_network(address, strict=False) if "/" in address
                               else ipaddress.ip_address(address)))
        except ValueError:
            raise GroupError(f"--trusted-proxy {address!r} is not an IP address or network (e.g. 10.0.0.5 or "
                             "10.0.0.0/24): give the address nginx connects to the workers from") from None
    return trusted


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a name: it may resolve to anything
        return False


def nginx_config(upstreams: Sequence[str], run_dir: Path, host: str, port: int, *, run_as_root: bool) -> str:
    """nginx's configuration for a group: sticky routing by session token, the primary for admin and joins.

    ``upstreams`` are the workers' addresses, ``unix:/path`` or ``host:port``, worker 0 (the primary) first: one
    configuration for a group on one machine and one across machines, with the same consistent hash. (nginx
    places each worker on the hash ring by its address, so which worker a token picks depends on the addresses;
    either way a session sticks to one worker, and a lost worker's sessions alone move.)
    """
    temp = "\n".join(f"    {kind}_temp_path {run_dir / kind};"
                     for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"))
    sessions = "\n".join(f"        server {address};" for address in upstreams)
    proxy = """proxy_http_version 1.1;
            proxy_set_header Host $http_host;
            proxy_set_header X-Forwarded-For $remote_addr;
            proxy_set_header X-Forwarded-Proto $scheme;
            proxy_set_header Upgrade $http_upgrade;
            proxy_set_header Connection $connection_upgrade;"""
    primary = "\n".join(f"""        location {match} {{
            proxy_pass http://trustlab_primary;
            {proxy}
        }}""" for match in PRIMARY_PATHS)
    # As root, nginx's workers run as "nobody"; the run directory lets them reach the sockets (mode 0711, sockets 0666).
    user = "user nobody nogroup;\n" if run_as_root else ""
    return f"""# Written by trustlab serve --workers or --workers-at (server/workers.py); rewritten on every start.
{user}worker_processes 1;
daemon off;
pid {run_dir / 'nginx.pid'};
error_log stderr warn;
worker_shutdown_timeout {int(STOP_TIMEOUT_S) - 5}s;
events {{
    worker_connections 8192;
}}
http {{
    access_log off;
    server_tokens off;
{temp}
    # trustlab refuses bodies over its limit with its own 413; stream bodies and responses (exports) through.
    client_max_body_size 0;
    proxy_request_buffering off;
    proxy_buffering off;
    proxy_read_timeout {PROXY_TIMEOUT_S}s;
    proxy_send_timeout {PROXY_TIMEOUT_S}s;
    map $http_upgrade $connection_upgrade {{
        default upgrade;
        '' '';
    }}
    # The session token of a participant URL; empty for every other path (then nginx goes round robin).
    map $uri $trustlab_session {{
        "~{SESSION_PATH}" $token;
        default '';
    }}
    upstream trustlab_sessions {{
        hash $trustlab_session consistent;
{sessions}
        keepalive {UPSTREAM_KEEPALIVE};
    }}
    upstream trustlab_primary {{
        server {upstreams[0]};
        keepalive {UPSTREAM_KEEPALIVE // 4};
    }}
    server {{
        listen {_listen_address(host, port)};
        location / {{
            proxy_pass http://trustlab_sessions;
            {proxy}
        }}
{primary}
    }}
}}
"""


def _die_with_parent() -> None:
    """(child, before exec) Get SIGTERM when the group's process dies, even by SIGKILL: no orphaned workers.

    Run as ``preexec_fn``, which is unsafe in a process with threads: the group's process has none (it only
    starts and watches processes).
    """
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)


def _accepts(path: Path) -> bool:
    with socket.socket(socket.AF_UNIX) as sock:
        try:
            sock.connect(str(path))
        except OSError:
            return False
        return True


class WorkerGroup:
    """nginx and its workers: ``start()``, then ``supervise()`` until ``stop()`` or a signal.

    ``local=N`` starts N workers here, on unix sockets; ``remote=[HOST:PORT, ...]`` starts nginx alone, in front of
    workers that ``trustlab worker`` runs on other machines (worker 0, the primary, first).
    """

    def __init__(self, settings: Settings, nginx: str, *, local: int = 0, remote: Sequence[str] = (),
                 echo: Callable[[str], None] = print):
        if (local > 0) == bool(remote):
            raise ValueError("a group has either local workers or remote ones")
        self.settings, self.count, self.nginx, self.echo = settings, local, nginx, echo
        self.run_dir = Path(tempfile.mkdtemp(prefix="trustlab-workers-"))
        self.run_dir.chmod(0o711)
        self.sockets = [self.run_dir / f"worker-{i}.sock" for i in range(local)]
        self.upstreams = [unix_upstream(path) for path in self.sockets] or list(remote)
        self.workers: list[subprocess.Popen | None] = [None] * local
        self.proxy: subprocess.Popen | None = None
        self.restarts: deque[float] = deque()
        self.stopping = False

    # -- starting ------------------------------------------------------------------------------
    def start(self) -> None:
        try:
            for index in range(self.count):
                self._start_worker(index)
            for index in range(self.count):
                self._wait_ready(index)
            if not self.count:
                self._check_remote_workers()
            self._start_nginx()
        except BaseException:
            self.stop()
            raise

    def _worker_env(self) -> dict[str, str]:
        s = self.settings
        env = dict(os.environ, TRUSTLAB_DATABASE_URL=s.database_url, TRUSTLAB_HOST=s.host, TRUSTLAB_PORT=str(s.port))
        if s.public_url:
            env["TRUSTLAB_PUBLIC_URL"] = s.public_url
        return env

    def _start_worker(self, index: int) -> None:
        path = self.sockets[index]
        path.unlink(missing_ok=True)
        self.workers[index] = subprocess.Popen([sys.executable, "-m", "server.workers", str(index), str(path)],
                                               env=self._worker_env(), start_new_session=True,
                                               preexec_fn=_die_with_parent)  # noqa: PLW1509 -- this process has no threads

    def _wait_ready(self, index: int) -> None:
        deadline = time.monotonic() + START_TIMEOUT_S
        proc = self.workers[index]
        assert proc is not None
        while not _accepts(self.sockets[index]):
            if proc.poll() is not None:
                raise GroupError(f"worker {index} exited while starting (exit code {proc.returncode}); see its "
                                 "messages above")
            if time.monotonic() > deadline:
                raise GroupError(f"worker {index} did not start within {START_TIMEOUT_S:.0f} s")
            time.sleep(0.05)

    def _check_remote_workers(self) -> None:
        """Say which workers on other machines do not answer yet (they may start after nginx: it waits for them)."""
        for index, address in enumerate(self.upstreams):
            host, _, port = address.rpartition(":")
            try:
                with socket.create_connection((host.strip("[]"), int(port)), timeout=2):
                    continue
            except OSError as exc:
                reason = exc.strerror or type(exc).__name__
            role = "the primary: admin and joins fail" if index == 0 else "nginx sends its sessions to the others"
            self.echo(f"worker {index} at {address} does not answer yet ({reason}); {role} until it does")

    def _start_nginx(self) -> None:
        config = self.run_dir / "nginx.conf"
        config.write_text(nginx_config(self.upstreams, self.run_dir, self.settings.host, self.settings.port,
                                       run_as_root=os.geteuid() == 0))
        self.proxy = subprocess.Popen([self.nginx, "-q", "-p", str(self.run_dir), "-c", str(config)],
                                      start_new_session=True,
                                      preexec_fn=_die_with_parent)  # noqa: PLW1509 -- this process has no threads
        deadline = time.monotonic() + START_TIMEOUT_S
        while not self._listening():
            if self.proxy.poll() is not None:
                raise GroupError(f"nginx exited while starting (exit code {self.proxy.returncode}): is "
                                 f"{_listen_address(self.settings.host, self.settings.port)} free? See nginx's message "
                                 "above")
            if time.monotonic() > deadline:
                raise GroupError(f"nginx did not start listening within {START_TIMEOUT_S:.0f} s")
            time.sleep(0.05)

    def _listening(self) -> bool:
        host = ("127.0.0.1" if self.settings.host in ("0.0.0.0", "")
                else "::1" if self.settings.host == "::" else self.settings.host)
        try:
            with socket.create_connection((host, self.settings.port), timeout=1):
                return True
        except OSError:
            return False

    # -- running -------------------------------------------------------------------------------
    def supervise(self) -> int:
        """Keep the group running until SIGTERM/SIGINT (exit status 0) or a failure it cannot mend (1)."""
        def on_signal(_signum, _frame) -> None:
            self.stopping = True

        previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
        try:
            while not self.stopping:
                if self.proxy is not None and self.proxy.poll() is not None:
                    self.echo(f"nginx exited (exit code {self.proxy.returncode})"
                              + ("; stopping the workers" if self.workers else ""))
                    return 1
                for index, proc in enumerate(self.workers):
                    if proc is not None and proc.poll() is not None and not self.stopping:
                        if not self._may_restart():
                            self.echo(f"worker {index} exited (exit code {proc.returncode}), the group's "
                                      f"{MAX_RESTARTS + 1}th worker exit within {RESTART_WINDOW_S:.0f} s; stopping the "
                                      "group")
                            return 1
                        self.echo(f"worker {index} exited (exit code {proc.returncode}); starting it again")
                        self._start_worker(index)
                time.sleep(SUPERVISE_PERIOD_S)
            return 0
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            self.stop()

    def _may_restart(self) -> bool:
        now = time.monotonic()
        while self.restarts and now - self.restarts[0] > RESTART_WINDOW_S:
            self.restarts.popleft()
        self.restarts.append(now)
        return len(self.restarts) <= MAX_RESTARTS

    def stop(self) -> None:
        """Stop nginx and the workers gracefully (they finish the requests under way), kill what is left, clean up."""
        self.stopping = True
        procs = [p for p in (self.proxy, *self.workers) if p is not None and p.poll() is None]
        for proc in procs:  # nginx shuts down gracefully on SIGQUIT (SIGTERM is its fast shutdown), uvicorn on SIGTERM
            proc.send_signal(signal.SIGQUIT if proc is self.proxy else signal.SIGTERM)
        deadline = time.monotonic() + STOP_TIMEOUT_S
        for proc in procs:
            try:
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        shutil.rmtree(self.run_dir, ignore_errors=True)


def run_worker(index: int, socket_path: str) -> None:
    """One worker of a local group: the whole app on a unix socket, trusting nginx's X-Forwarded-For."""
    from server.main import create_app

    settings = Settings(worker_index=index)
    run_server(create_app(settings), uds=socket_path)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="One worker of 'trustlab serve --workers' (started by it).")
    parser.add_argument("index", type=int)
    parser.add_argument("socket")
    args = parser.parse_args(argv)
    run_worker(args.index, args.socket)


if __name__ == "__main__":
    main()

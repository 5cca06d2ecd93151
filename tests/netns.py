"""Two test hosts on one machine: network namespaces `A` and `B` joined by a veth pair (10.77.0.1/24 on A,
10.77.0.2/24 on B, `lo` up in each), each running its own `ddvs router` (listening on `tcp/0.0.0.0:7447` of its
namespace and on a Unix socket; A's router connects to B's over the veth). Needs root (`ip netns add`).

A process started with `TwoHosts.wrapper(host)` runs on that host; a node there joins as a client of the host's
router at `tcp/127.0.0.1:7447` (its namespace's own loopback). A process of the root namespace (the test driver)
reaches a router through its Unix socket (`unixsock-stream/<path>`): filesystems are shared, networks are not.

Names carry the creating process id (`ddvs-t<pid>-a`); namespaces left behind by a dead test process are deleted
the next time hosts are created.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ADDRESSES = {"a": "10.77.0.1", "b": "10.77.0.2"}
ROUTER_PORT = 7447
ROUTER_READY_S = 30.0
_NAME = re.compile(r"^ddvs-t(\d+)-[ab]$")


def _ip(*args: str) -> None:
    result = subprocess.run(["ip", *args], capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"`ip {' '.join(args)}` failed ({result.returncode}): {result.stderr.strip()}")


def netns_unavailable_reason() -> str | None:
    """None when network namespaces can be created here; otherwise one line saying why not."""
    if shutil.which("ip") is None:
        return "network namespaces unavailable: the `ip` command (iproute2) is not installed"
    probe = f"ddvs-probe{os.getpid()}"
    result = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if result.returncode != 0:
        return f"network namespaces unavailable: `ip netns add` failed: {result.stderr.strip() or result.returncode}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


def delete_stale_namespaces() -> None:
    """Delete `ddvs-t<pid>-*` namespaces whose creating process is gone (a test killed before its clean-up)."""
    listing = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    for line in listing.splitlines():
        name = line.split()[0] if line.split() else ""
        match = _NAME.match(name)
        if match and not Path(f"/proc/{match.group(1)}").exists():
            subprocess.run(["ip", "netns", "del", name], capture_output=True)


@dataclass
class TwoHosts:
    """The namespaces (`ns[host]`), veth ends (`veth[host]`), routers (`routers[host]`, their logs in `log_dir`)
    and Unix sockets (`socket[host]`) of hosts "a" and "b"."""

    ns: dict[str, str]
    veth: dict[str, str]
    socket_dir: Path
    log_dir: Path
    routers: dict[str, subprocess.Popen] = field(default_factory=dict)

    def wrapper(self, host: str) -> tuple[str, ...]:
        """Command words that run a command on `host` (`ip netns exec` execs it: the pid stays the command's)."""
        return ("ip", "netns", "exec", self.ns[host])

    def socket(self, host: str) -> Path:
        return self.socket_dir / f"router-{host}.sock"

    def socket_endpoint(self, host: str) -> str:
        """The Zenoh endpoint of `host`'s router for a process of the root namespace."""
        return f"unixsock-stream/{self.socket(host)}"

    @staticmethod
    def client_flags() -> tuple[str, ...]:
        """Zenoh flags of a node on a host: a client of that host's router."""
        return ("--mode", "client", "--connect", f"tcp/127.0.0.1:{ROUTER_PORT}")

    def set_link(self, up: bool) -> None:
        """Bring host A's end of the veth pair down (the link is cut for both hosts) or up again."""
        _ip("-n", self.ns["a"], "link", "set", self.veth["a"], "up" if up else "down")

    def start_router(self, host: str, connect: str | None) -> None:
        listen = f"tcp/0.0.0.0:{ROUTER_PORT},{self.socket_endpoint(host)}"
        args = ["router", "--listen", listen] + (["--connect", connect] if connect else [])
        with open(self.log_dir / f"router-{host}.log", "w", encoding="utf-8") as log:
            self.routers[host] = subprocess.Popen(
                [*self.wrapper(host), sys.executable, "-m", "ddvs.cli", *args], cwd=ROOT, stdout=log,
                stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        deadline = time.monotonic() + ROUTER_READY_S
        while "listening on" not in (self.log_dir / f"router-{host}.log").read_text(errors="replace"):
            if self.routers[host].poll() is not None or time.monotonic() > deadline:
                tail = (self.log_dir / f"router-{host}.log").read_text(errors="replace")[-2000:]
                raise RuntimeError(f"router of host {host} not ready (exit status {self.routers[host].poll()}):\n"
                                   f"{tail}")
            time.sleep(0.05)

    def close(self) -> None:
        """Stop the routers (SIGTERM, then SIGKILL) and delete both namespaces (which removes the veth pair)."""
        for proc in self.routers.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in self.routers.values():
            try:
                proc.wait(5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for name in self.ns.values():
            subprocess.run(["ip", "netns", "del", name], capture_output=True)
        shutil.rmtree(self.socket_dir, ignore_errors=True)


def create_two_hosts(log_dir: Path) -> TwoHosts:
    """Namespaces, veth pair, addresses and both routers (B's first; A's connects to B's). On any failure what was
    created is removed again before the error propagates."""
    delete_stale_namespaces()
    log_dir.mkdir(parents=True, exist_ok=True)
    pid = os.getpid()
    hosts = TwoHosts(ns={h: f"ddvs-t{pid}-{h}" for h in ADDRESSES}, veth={h: f"dv{pid}{h}" for h in ADDRESSES},
                     socket_dir=Path(tempfile.mkdtemp(prefix="ddvs-net-")), log_dir=log_dir)
    try:
        for host in ADDRESSES:
            _ip("netns", "add", hosts.ns[host])
            _ip("-n", hosts.ns[host], "link", "set", "lo", "up")
        _ip("link", "add", hosts.veth["a"], "netns", hosts.ns["a"], "type", "veth", "peer", "name", hosts.veth["b"],
            "netns", hosts.ns["b"])
        for host, address in ADDRESSES.items():
            _ip("-n", hosts.ns[host], "addr", "add", f"{address}/24", "dev", hosts.veth[host])
            _ip("-n", hosts.ns[host], "link", "set", hosts.veth[host], "up")
        hosts.start_router("b", connect=None)
        hosts.start_router("a", connect=f"tcp/{ADDRESSES['b']}:{ROUTER_PORT}")
    except BaseException:
        hosts.close()
        raise
    return hosts

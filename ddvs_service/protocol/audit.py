"""Audit of a router's access control: every denied message, session without a role and refused handshake, read
from Zenoh's own log, logged as JSON lines at a bounded rate and counted per identity (docs/security.md).

Zenoh reports its access-control decisions only through its Rust `tracing` log (nothing in the Python API): at
TRACE on `zenoh::net::routing::interceptor::access_control` it writes `<zid> on <subject> is unauthorized to <action>
(<flow>) on <key>` for a decision it computes and `Using cached result: <zid> is unauthorized to ...` for one it
reuses, and at INFO `<zid> did not match any configured ACL subject` for a session whose identity has no role.
`zenoh_link_tls` writes a WARN line `<why>. Hint: ...` (1.10; `Can not accept TLS connection: <why>` at DEBUG before)
when a TLS handshake fails, e.g. `invalid peer certificate: certificate does not allow extended key usage for client
authentication`; `zenoh_transport::unicast::establishment::accept` writes at DEBUG `UsrPwd extension - Recv OpenSyn.
Invalid password.` (or `Invalid user.`) when user/password authentication fails. `ZenohLogTap` sends that log
(which Zenoh writes to file descriptor 1) through a pipe to `Audit.feed`, and keeps Python's `sys.stdout` on the
original output.

What is counted as a denial: a message a client *sent* that the router refused (ingress flow). Egress refusals are
the router withholding another node's data or declarations from a client (routine: e.g. it does not tell the plant
about the operator's subscriptions), not something that client attempted. When a key is first used, Zenoh computes the
decisions for every kind of message on it in one burst (after `caching permissions for ...`); those lines are
decisions nobody asked for yet and are skipped. A session without a role is denied everything, but Zenoh logs no line
for its messages: it is reported as a session without a role instead.

Log lines (logger `ddvs.audit`): `access denied` (fields `identity`, `zid`, `action`, `key`, `count` = that identity's
denials so far, and `suppressed` = denials not logged individually since the last line), `session without a role`
(`identity`, `zid`), `TLS handshake refused` (`detail`), `authentication refused` (`detail`: `Invalid password` or
`Invalid user`). At most `rate` lines per second on average (bursts of `burst`); every denial is counted whether
logged or not. `Audit.report(base, others)` is the JSON summary `ddvs router` publishes on `<base>/router/audit`
(`audit_key`) and `ddvs monitor` shows.
"""

from __future__ import annotations

import logging
import os
import re
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

ACL_TARGET = "zenoh::net::routing::interceptor::access_control"
TLS_TARGET = "zenoh_link_tls"
AUTH_TARGET = "zenoh_transport::unicast::establishment::accept"
LOG_DIRECTIVES = f"{ACL_TARGET}=trace,{TLS_TARGET}=debug,{AUTH_TARGET}=debug"
AUDIT_SUFFIX = "router/audit"

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_LINE = re.compile(r"^\S+\s+(TRACE|DEBUG|INFO|WARN|ERROR)\s+(?:\S+\s+)?ThreadId\((\d+)\)\s+([\w:]+):\s(.*)$")
_DECISION = re.compile(r"^(\w+) on (\S+) is (unauthorized|authorized) to (.+) \((ingress|egress)\) on (\S+)$")
_CACHED = re.compile(r"^Using cached result: (\w+) is (unauthorized|authorized) to (.+) \((ingress|egress)\) on (\S+)$")
_CACHING = re.compile(r"^ACL \((ingress|egress)\): caching permissions for `(\S+)` \.\.\.$")
_NO_ROLE = re.compile(r"^(\w+) did not match any configured ACL subject")
_AUTH_REFUSED = re.compile(r"^UsrPwd extension - Recv OpenSyn\. (Invalid \w+)\.")
_TLS_REFUSED = re.compile(r"^(?:Can not accept TLS connection: )?(.*?)(?:\. Hint: .*)?$")
_SUBJECT_NAME = re.compile(r"(?:CertCommonName|Username)\(([^)]*)\)")
_FORWARDED = {"WARN": logging.WARNING, "ERROR": logging.ERROR}

log = logging.getLogger("ddvs.audit")


def audit_key(base: str) -> str:
    """Where the router publishes the audit summary of robot `base` (`<prefix>/<robot>`; JSON, see `Audit.report`)."""
    return f"{base}/{AUDIT_SUFFIX}"


@dataclass(frozen=True)
class Denial:
    """One refused message: who sent it (`identity`: certificate common name or username; `zid`), what (`action`,
    e.g. `Put`, `Query`, `Declare Subscriber`) on which key."""

    zid: str
    identity: str
    action: str
    key: str


def _key_matches(key: str, base: str) -> bool:
    """True when key expression `key` may name a key of robot `base` (`<base>/...`, or a wildcard covering it)."""
    import zenoh

    return zenoh.KeyExpr(f"{base}/**").intersects(zenoh.KeyExpr(key))


class Audit:
    """Counts and logs what Zenoh's log lines (`feed`) say was refused. `resolve(zid)` names a session's identity
    when the line does not (sessions without a role, cached decisions), e.g. from the router's links; `rate`/`burst`
    bound the log lines (token bucket, lines per second); `clock` in seconds."""

    def __init__(
        self,
        resolve: Callable[[str], str | None] = lambda zid: None,
        rate: float = 10.0,
        burst: int = 20,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not (rate > 0 and burst >= 1):
            raise ValueError(f"Audit rate = {rate}, burst = {burst}: expected rate > 0 lines/s and burst ≥ 1")
        self._resolve = resolve
        self.rate, self.burst, self._clock = rate, burst, clock
        self._tokens, self._refilled = float(burst), clock()
        self._lock = threading.Lock()
        self._identities: dict[str, str] = {}
        self._caching: dict[str, tuple[str, str]] = {}  # thread -> (flow, key) of a permission-cache burst
        self.denials: Counter[Denial] = Counter()
        self.by_identity: Counter[str] = Counter()
        self.no_role: Counter[str] = Counter()
        self.refused: Counter[str] = Counter()  # handshakes: `tls_refused`, `auth_refused` (user/password)
        self.suppressed = 0
        self._pending_no_role: dict[str, float] = {}

    # --- input ------------------------------------------------------------------------------------------------------
    def feed(self, raw: str) -> None:
        """One line of Zenoh's log (ANSI colours allowed). Warnings and errors that are not about access are
        forwarded to the `zenoh.<target>` logger; other lines are dropped."""
        match = _LINE.match(_ANSI.sub("", raw).rstrip("\n"))
        if match is None:
            return
        level, thread, target, message = match.groups()
        if target.startswith(ACL_TARGET):
            self._on_acl(thread, message)
        elif target.startswith(TLS_TARGET) and (level == "WARN" or message.startswith("Can not accept")):
            detail = _TLS_REFUSED.match(message).group(1)  # type: ignore[union-attr] # the pattern matches any text
            self._on_refused("tls_refused", "TLS handshake refused", detail)
        elif target.startswith(AUTH_TARGET) and (refused := _AUTH_REFUSED.match(message)):
            self._on_refused("auth_refused", "authentication refused", refused.group(1))
        elif level in _FORWARDED:
            logging.getLogger("zenoh." + target.replace("::", ".")).log(_FORWARDED[level], message)

    def _on_acl(self, thread: str, message: str) -> None:
        if message.startswith("Using cached result: "):
            self._caching.pop(thread, None)
            cached = _CACHED.match(message)
            if cached and cached.group(2) == "unauthorized" and cached.group(4) == "ingress":
                zid, _, action, _, key = cached.groups()
                self._deny(zid, self._identity(zid), action, key)
            return
        if caching := _CACHING.match(message):
            self._caching[thread] = (caching.group(1), caching.group(2))
            return
        if decision := _DECISION.match(message):
            zid, subject, verdict, action, flow, key = decision.groups()
            names = _SUBJECT_NAME.findall(subject)
            identity = "/".join(names) if names else subject
            self._identities.setdefault(zid, identity)
            if self._caching.get(thread) == (flow, key):
                return  # a decision computed for the cache, not a message
            self._caching.pop(thread, None)
            if verdict == "unauthorized" and flow == "ingress":
                self._deny(zid, identity, action, key)
            return
        self._caching.pop(thread, None)
        if no_role := _NO_ROLE.match(message):
            with self._lock:
                self._pending_no_role[no_role.group(1)] = self._clock()

    def _identity(self, zid: str) -> str:
        if zid not in self._identities:
            name = self._resolve(zid)
            if name is None:
                return f"zid:{zid}"
            self._identities[zid] = name
        return self._identities[zid]

    # --- counting and logging ---------------------------------------------------------------------------------------
    def _take_token(self) -> bool:
        now = self._clock()
        self._tokens = min(float(self.burst), self._tokens + (now - self._refilled) * self.rate)
        self._refilled = now
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        return False

    def _deny(self, zid: str, identity: str, action: str, key: str) -> None:
        with self._lock:
            denial = Denial(zid, identity, action, key)
            self.denials[denial] += 1
            self.by_identity[identity] += 1
            if not self._take_token():
                self.suppressed += 1
                return
            suppressed, self.suppressed = self.suppressed, 0
            count = self.by_identity[identity]
        log.warning("access denied", extra={"fields": {"identity": identity, "zid": zid, "action": action,
                                                       "key": key, "count": count, "suppressed": suppressed}})

    def _on_refused(self, kind: str, what: str, detail: str) -> None:
        with self._lock:
            self.refused[kind] += 1
            count, logged = self.refused[kind], self._take_token()
        if logged:
            log.warning(what, extra={"fields": {"detail": detail, "count": count}})

    def flush(self, resolve_within_s: float = 2.0) -> None:
        """Log and count the sessions without a role whose identity is now known (or still unknown after
        `resolve_within_s`), and the denials suppressed since the last line when the rate allows. Call it
        periodically (the router does, every 0.5 s)."""
        now = self._clock()
        with self._lock:
            pending = list(self._pending_no_role.items())
        for zid, seen in pending:
            name = self._resolve(zid)
            if name is None and now - seen < resolve_within_s:
                continue
            identity = name or f"zid:{zid}"
            with self._lock:
                self._pending_no_role.pop(zid, None)
                self._identities.setdefault(zid, identity)
                self.no_role[identity] += 1
            log.warning("session without a role: its identity matches no access-control subject, so everything it "
                        "sends is refused", extra={"fields": {"identity": identity, "zid": zid}})
        with self._lock:
            suppressed = self.suppressed if self.suppressed and self._take_token() else 0
            self.suppressed -= suppressed
        if suppressed:
            log.warning("access denials not logged individually", extra={"fields": {"suppressed": suppressed}})

    def report(self, base: str | None = None, others: Sequence[str] = ()) -> dict[str, Any]:
        """JSON-ready counts: `denied` per identity (when robot `base`, e.g. `ddvs/robot0`, is given: denials on its
        keys and on keys of none of the router's `others` robots — the ROS 2 mode's rmw_zenoh keys, Trigger services
        and graph tokens carry no robot), `no_role` sessions per identity, `tls_refused` and `auth_refused`
        (user/password) handshakes (those three are router-wide)."""
        with self._lock:
            denied: Counter[str] = Counter()
            for denial, n in self.denials.items():
                if (base is None or _key_matches(denial.key, base)
                        or not any(_key_matches(denial.key, other) for other in others)):
                    denied[denial.identity] += n
            return {"denied": dict(denied), "no_role": dict(self.no_role), "tls_refused": self.refused["tls_refused"],
                    "auth_refused": self.refused["auth_refused"]}


class ZenohLogTap:
    """Route Zenoh's log into `on_line` (one call per line, on a reader thread). Zenoh's Rust logger writes to file
    descriptor 1: `start` points that descriptor at a pipe and `sys.stdout` at a copy of the original output, then
    starts Zenoh's logger with `directives` (added to `$RUST_LOG`, default `warn`). Call once per process, before
    opening a session; `on_line` must return quickly (a full pipe would stall Zenoh's threads)."""

    def __init__(self, on_line: Callable[[str], None], directives: str = LOG_DIRECTIVES) -> None:
        self._on_line = on_line
        self.directives = directives
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        import zenoh

        if self._thread is not None:
            raise RuntimeError("ZenohLogTap already started")
        read_fd, write_fd = os.pipe()
        sys.stdout.flush()
        original = os.dup(1)
        os.dup2(write_fd, 1)
        os.close(write_fd)
        sys.stdout = os.fdopen(original, "w", buffering=1, encoding="utf-8")
        self._thread = threading.Thread(target=self._read, args=(read_fd,), name="zenoh-log", daemon=True)
        self._thread.start()
        os.environ["RUST_LOG"] = f"{os.environ.get('RUST_LOG') or 'warn'},{self.directives}"
        zenoh.init_log_from_env_or("warn")

    def _read(self, fd: int) -> None:
        with os.fdopen(fd, "r", encoding="utf-8", errors="replace") as pipe:
            for line in pipe:
                if " is authorized to " in line:  # the bulk of the trace: allowed messages
                    continue
                try:
                    self._on_line(line)
                except Exception:  # one bad line must not stop the audit
                    log.exception("audit: could not handle a Zenoh log line", extra={"fields": {"line": line[:300]}})

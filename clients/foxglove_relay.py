"""The live view's public socket: a TCP relay to the foxglove-sdk server that lets clients of either name of the
Foxglove WebSocket protocol connect.

foxglove-sdk 0.30 names the protocol `foxglove.sdk.v1` and refuses a WebSocket upgrade that does not offer that
subprotocol (HTTP 400), while viewers built on the older `@foxglove/ws-protocol` (Lichtblick, older Foxglove Studio
releases) offer only `foxglove.websocket.v1`, the name of the same protocol before the SDK. The relay reads each
connection's HTTP upgrade request: one that offers `foxglove.websocket.v1` and not `foxglove.sdk.v1` is forwarded
offering `foxglove.sdk.v1`, and the server's answer is handed back naming `foxglove.websocket.v1` (the
`Sec-WebSocket-Accept` key depends on neither); any other request is forwarded unchanged. After the handshake the
bytes flow both ways untouched. The relay runs its own asyncio loop on a daemon thread.
"""

from __future__ import annotations

import asyncio
import re
import threading

SDK_PROTOCOL = "foxglove.sdk.v1"
LEGACY_PROTOCOL = "foxglove.websocket.v1"
MAX_HEAD_BYTES = 16 * 1024
"""The longest HTTP upgrade request relayed (bytes); a longer one closes the connection."""
_PROTOCOL_HEADER = re.compile(rb"^(sec-websocket-protocol:)([^\r\n]*)\r\n", re.IGNORECASE | re.MULTILINE)


def offered(head: bytes) -> list[str]:
    """The subprotocols an HTTP upgrade request `head` offers (every `Sec-WebSocket-Protocol` header, in order)."""
    return [name.strip() for match in _PROTOCOL_HEADER.finditer(head)
            for name in match.group(2).decode("latin-1").split(",") if name.strip()]


def _renamed(head: bytes, old: str, new: str) -> bytes:
    """`head` with every `Sec-WebSocket-Protocol` header naming `new` instead of `old`."""
    def rename(match: re.Match[bytes]) -> bytes:
        names = [n.strip() for n in match.group(2).decode("latin-1").split(",")]
        return match.group(1) + b" " + ", ".join(new if n == old else n for n in names).encode("latin-1") + b"\r\n"

    return _PROTOCOL_HEADER.sub(rename, head)


class SubprotocolRelay:
    """Listens on `host:port` (`port` 0: a free one, `self.port`) and relays each connection to the server on
    `127.0.0.1:upstream_port` (module docstring) until `close()`."""

    def __init__(self, host: str, port: int, upstream_port: int) -> None:
        self._upstream_port = upstream_port
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="foxglove-relay", daemon=True)
        self._thread.start()
        try:
            self._server = asyncio.run_coroutine_threadsafe(
                asyncio.start_server(self._relay, host, port, limit=MAX_HEAD_BYTES), self._loop).result(timeout=10.0)
        except OSError:
            self._loop.call_soon_threadsafe(self._loop.stop)
            raise
        self.port: int = self._server.sockets[0].getsockname()[1]

    async def _relay(self, client_in: asyncio.StreamReader, client_out: asyncio.StreamWriter) -> None:
        try:
            head = await client_in.readuntil(b"\r\n\r\n")
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, ConnectionError):
            client_out.close()
            return
        protocols = offered(head)
        legacy = LEGACY_PROTOCOL in protocols and SDK_PROTOCOL not in protocols
        try:
            server_in, server_out = await asyncio.open_connection("127.0.0.1", self._upstream_port)
        except OSError:
            client_out.close()
            return
        server_out.write(_renamed(head, LEGACY_PROTOCOL, SDK_PROTOCOL) if legacy else head)
        try:
            answer = await server_in.readuntil(b"\r\n\r\n")
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, ConnectionError):
            client_out.close()
            server_out.close()
            return
        client_out.write(_renamed(answer, SDK_PROTOCOL, LEGACY_PROTOCOL) if legacy else answer)
        await asyncio.gather(_pipe(client_in, server_out), _pipe(server_in, client_out))

    def close(self) -> None:
        """Stop listening, end the relayed connections and the loop's thread."""
        async def shut() -> None:
            self._server.close()
            for task in asyncio.all_tasks():
                if task is not asyncio.current_task():
                    task.cancel()

        asyncio.run_coroutine_threadsafe(shut(), self._loop).result(timeout=10.0)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=10.0)


async def _pipe(source: asyncio.StreamReader, sink: asyncio.StreamWriter) -> None:
    """Copy `source` to `sink` until either side closes, then close `sink`."""
    try:
        while data := await source.read(1 << 16):
            sink.write(data)
            await sink.drain()
    except ConnectionError:
        pass
    finally:
        sink.close()

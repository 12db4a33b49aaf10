"""Transport.abort: a connection dropped at once, no close handshake and no flush, for a peer
that would never answer (a blackholed relay). Real sockets on 127.0.0.1."""

from __future__ import annotations

import asyncio
from typing import Any

from shared.transport import TcpTransport, TransportClosed, open_client_transport
from tests.support import scaled


async def test_tcp_abort_drops_the_connection_and_what_it_had_not_sent() -> None:
    """The peer reads nothing for a while: what waits in our buffer is dropped with the
    connection (a graceful close would deliver it all first, for as long as that takes)."""
    received: list[int] = []
    stop = asyncio.Event()
    done = asyncio.Event()

    async def reads_late(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await stop.wait()
        total = 0
        try:
            while data := await reader.read(1 << 20):
                total += len(data)
        except OSError:
            pass  # reset: the abort
        received.append(total)
        writer.close()
        done.set()

    server = await asyncio.start_server(reads_late, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        transport = await open_client_transport("tcp", "127.0.0.1", port, "",
                                                max_message_bytes=1 << 20, open_timeout_s=2.0,
                                                write_buffer_bytes=1 << 16)
        assert isinstance(transport, TcpTransport)
        written = 0
        while transport.ready():  # fill the socket and our buffer: the peer does not read
            transport.write_nowait([b"x" * (1 << 20)])
            written += 1 << 20
            await asyncio.sleep(0)
        transport.abort()
        async with asyncio.timeout(scaled(1.0)):
            await transport.close()  # nothing left to do: returns at once
        stop.set()
        await asyncio.wait_for(done.wait(), scaled(5.0))
        assert received[0] < written
    finally:
        stop.set()
        server.close()
        await server.wait_closed()


async def test_ws_abort_ends_a_connection_whose_peer_never_answers() -> None:
    from websockets.asyncio.server import serve

    release = asyncio.Event()

    async def silent(ws: Any) -> None:
        await release.wait()

    async with serve(silent, "127.0.0.1", 0) as server:
        port = next(iter(server.sockets)).getsockname()[1]
        transport = await open_client_transport(
            "ws", "127.0.0.1", port, f"ws://127.0.0.1:{port}/", max_message_bytes=1 << 20,
            open_timeout_s=2.0, write_buffer_bytes=1 << 16)
        receiving = asyncio.ensure_future(transport.recv())
        try:
            await asyncio.sleep(0.01)
            transport.abort()
            async with asyncio.timeout(scaled(1.0)):
                try:
                    await receiving
                except TransportClosed:
                    pass
                else:  # pragma: no cover - the peer sent nothing
                    raise AssertionError("recv returned data")
        finally:
            release.set()
            receiving.cancel()
            await transport.close()

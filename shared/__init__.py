"""Tele-Touch common package: protocol, clocks, latency ledger, configuration, errors.

Shared by the relay server and both stations. The protocol core here is sans-I/O:
no asyncio and no sockets, only bytes in and events/bytes out.
"""

__version__ = "0.1.0"

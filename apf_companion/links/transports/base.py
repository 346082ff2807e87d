"""The one interface every MAVLink transport implements (UDP in/out, TCP client/server, serial)."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Protocol

from apf_companion.links.endpoint import Endpoint
from apf_companion.links.receiver import Receiver

__all__ = ["MAX_WRITE_BUFFER_B", "Transport", "TransportFactory"]

MAX_WRITE_BUFFER_B = 1 << 20  # stop queueing to a stalled stream peer (TCP, serial) beyond this


class Transport(Protocol):
    """A byte pipe for one endpoint. Received bytes go to the ``Receiver`` it was built with.

    Lifecycle: ``await open()`` binds, listens or opens the device (raises ``OSError``); ``run(tasks)`` is the
    receive loop, run as a task in the link's task group until cancelled (peer tasks it needs go into
    ``tasks``); ``aclose()`` releases everything and is safe to call twice, also after a failed ``open``.
    """

    @property
    def local_address(self) -> tuple[str, int] | None:
        """The bound (host, port) of a socket transport; None for serial and unconnected clients."""
        ...

    @property
    def is_connected(self) -> bool:
        """True while at least one peer can receive what ``send`` writes."""
        ...

    async def open(self) -> None: ...

    async def run(self, tasks: asyncio.TaskGroup) -> None: ...

    def send(self, data: bytes) -> bool:
        """Write ``data`` to every connected peer, never blocking. False: nobody took it (count it as dropped)."""
        ...

    async def aclose(self) -> None: ...


TransportFactory = Callable[[Endpoint, Receiver], Transport]

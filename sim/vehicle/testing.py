"""Helpers for tests that fly the simulator over real loopback sockets (used by tests/test_sim_*.py; others may
use them too).

    async with simulator_with_client(profile="px4", spawn=SpawnConfig(airborne=True)) as (sim, gcs):
        ack = await command_long(gcs, MAV_CMD_COMPONENT_ARM_DISARM, 1)

The client is a ``MavlinkLink`` (pymavlink's parser and encoder) listening on ``udpin:127.0.0.1:<free port>``
as system 255 / component 190 (a ground station); the simulator sends to it with ``udpout`` and the client
replies to the peer it heard from.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math
from collections.abc import AsyncIterator, Callable
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.links import MavlinkLink
from sim.vehicle.simulator import SimConfig, Simulator

__all__ = [
    "angle_close",
    "command_int",
    "command_long",
    "drain",
    "fence_ack",
    "simulator_with_client",
    "upload_fence",
    "wait_for",
    "wait_sim_time",
]


@contextlib.asynccontextmanager
async def simulator_with_client(
    *, source_system: int = 255, source_component: int = 190, speedup: float = 10.0, **cfg: Any
) -> AsyncIterator[tuple[Simulator, MavlinkLink]]:
    """A Simulator (``SimConfig(**cfg)``; its first link goes to the client) and a connected client link.

    Waits for the first HEARTBEAT, so the client can send at once. Unless ``cfg`` says otherwise the vehicle starts
    fast (``fast_start``: EKF origin at boot) and streams unasked (``unasked_streams``): tests of other behaviour
    need not wait out the ArduPilot startup or request each stream; tests of the startup pass ``fast_start=False``
    / ``unasked_streams=None``.
    """
    cfg.setdefault("fast_start", True)
    cfg.setdefault("unasked_streams", True)
    client = await MavlinkLink.open("udpin:127.0.0.1:0", source_system=source_system, source_component=source_component)
    try:
        assert client.local_address is not None
        links = [f"udpout:127.0.0.1:{client.local_address[1]}", *cfg.pop("links", ())]
        sim = await Simulator.start(SimConfig(links=links, speedup=speedup, **cfg))
        try:
            await client.recv_match(type="HEARTBEAT", timeout=5.0)
            yield sim, client
        finally:
            await sim.aclose()
    finally:
        await client.aclose()


async def command_long(
    link: MavlinkLink,
    command: int,
    *params: float,
    target: tuple[int, int] = (1, 1),
    timeout: float = 3.0,
    texts: list[str] | None = None,
) -> Any:
    """Send COMMAND_LONG and return its COMMAND_ACK; STATUSTEXTs seen meanwhile go to ``texts``."""
    p = [float(x) for x in params] + [0.0] * (7 - len(params))
    link.send(link.mav.command_long_encode(target[0], target[1], command, 0, *p))
    return await _ack(link, command, timeout, texts)


async def _ack(link: MavlinkLink, command: int, timeout: float, texts: list[str] | None) -> Any:
    def keep(msg: Any) -> bool:
        if msg.get_type() == "STATUSTEXT":
            if texts is not None:
                texts.append(msg.text)
            return False
        return bool(msg.get_type() == "COMMAND_ACK" and msg.command == command)

    return await link.recv_match(condition=keep, timeout=timeout)


async def command_int(
    link: MavlinkLink,
    command: int,
    *,
    frame: int = 0,
    params: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
    x: int = 0,
    y: int = 0,
    z: float = 0.0,
    target: tuple[int, int] = (1, 1),
    timeout: float = 3.0,
    texts: list[str] | None = None,
) -> Any:
    """Send COMMAND_INT and return its COMMAND_ACK; STATUSTEXTs seen meanwhile go to ``texts``."""
    link.send(link.mav.command_int_encode(target[0], target[1], frame, command, 0, 0, *params, x, y, z))
    return await _ack(link, command, timeout, texts)


async def wait_for(sim: Simulator, predicate: Callable[[Simulator], bool], *, timeout_s: float = 10.0) -> None:
    """Wait (wall clock, polling) until ``predicate(sim)``; AssertionError with the vehicle state if it never is."""
    if not await sim.wait_until(predicate, timeout_s=timeout_s):
        state = dataclasses.asdict(sim.vehicle) if dataclasses.is_dataclass(sim.vehicle) else sim.vehicle
        msg = f"condition not met within {timeout_s} s wall; vehicle {state}"
        raise AssertionError(msg)


async def wait_sim_time(sim: Simulator, t_s: float, *, timeout_s: float = 10.0) -> None:
    """Wait until the simulated clock reaches ``t_s``."""
    await wait_for(sim, lambda s: s.t_s >= t_s - 1e-9, timeout_s=timeout_s)


_FENCE = mavlink.MAV_MISSION_TYPE_FENCE


async def upload_fence(
    gcs: MavlinkLink, items: list[tuple[int, float, int, int]], *, stop_after: int | None = None, timeout: float = 5.0
) -> Any:
    """Upload ``items`` (command, param1, latitude, longitude [1e-7 deg]) as the vehicle's fence, as a ground
    station does: MISSION_COUNT, then each MISSION_ITEM_INT the vehicle asks for (MISSION_REQUEST or
    MISSION_REQUEST_INT). Returns the vehicle's closing MISSION_ACK; with ``stop_after`` = k it returns None after
    sending k items, the upload left open. Messages queued before it (the requests of an upload left open) are
    dropped first."""
    while gcs.recv_nowait() is not None:
        pass
    gcs.send(gcs.mav.mission_count_encode(1, 1, len(items), _FENCE))
    if stop_after == 0 or not items:
        return None if stop_after == 0 else await fence_ack(gcs, timeout)
    sent = 0
    while True:
        msg = await gcs.recv_match(type=("MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"), timeout=timeout)
        if msg.get_type() == "MISSION_ACK":
            return msg
        command, param1, lat, lon = items[msg.seq]
        gcs.send(
            gcs.mav.mission_item_int_encode(
                1, 1, msg.seq, mavlink.MAV_FRAME_GLOBAL, command, 0, 0, param1, 0.0, 0.0, 0.0, lat, lon, 0.0, _FENCE
            )
        )
        sent += 1
        if sent == stop_after:
            return None


async def fence_ack(gcs: MavlinkLink, timeout: float = 5.0) -> Any:
    """The next MISSION_ACK about the fence."""
    return await gcs.recv_match(type="MISSION_ACK", condition=lambda m: m.mission_type == _FENCE, timeout=timeout)


async def drain(link: MavlinkLink) -> list[Any]:
    """Everything queued on ``link`` now."""
    out = []
    while (msg := link.recv_nowait()) is not None:
        out.append(msg)
    await asyncio.sleep(0)
    return out


def angle_close(a: float, b: float, tol: float) -> bool:
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi) <= tol

"""The simulated autopilot's fence uploaded over real loopback MAVLink by a ground station (a pymavlink client), as
ArduPilot's MissionItemProtocol takes it: the items asked for in turn, the new fence kept and served; while one
upload is open, downloads and other uploads are DENIED; an upload left open is cancelled after 8 s."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.links import MavlinkLink
from sim.vehicle.fence import FenceItemRaw
from sim.vehicle.testing import drain, fence_ack, simulator_with_client, upload_fence, wait_sim_time

FENCE = m.MAV_MISSION_TYPE_FENCE
#: A 40 m inclusion circle and a triangular exclusion zone near Canberra's SITL home.
ITEMS: list[FenceItemRaw] = [
    (m.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, 40.0, -353632620, 1491652370),
    (m.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION, 3.0, -353631000, 1491652000),
    (m.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION, 3.0, -353631000, 1491653000),
    (m.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION, 3.0, -353630000, 1491652500),
]


async def _download(gcs: MavlinkLink) -> list[FenceItemRaw]:
    gcs.send(gcs.mav.mission_request_list_encode(1, 1, FENCE))
    count = (await gcs.recv_match(type="MISSION_COUNT", timeout=5.0)).count
    out = []
    for seq in range(count):
        gcs.send(gcs.mav.mission_request_int_encode(1, 1, seq, FENCE))
        it = await gcs.recv_match(type="MISSION_ITEM_INT", timeout=5.0)
        assert it.seq == seq
        out.append((it.command, it.param1, it.x, it.y))
    gcs.send(gcs.mav.mission_ack_encode(1, 1, m.MAV_MISSION_ACCEPTED, FENCE))  # PX4 is busy until this
    return out


@pytest.mark.parametrize(
    ("profile", "request_type"), [("ardupilot", "MISSION_REQUEST"), ("px4", "MISSION_REQUEST_INT")]
)
async def test_an_uploaded_fence_is_kept_and_served(profile: str, request_type: str) -> None:
    async with simulator_with_client(profile=profile) as (sim, gcs):
        gcs.send(gcs.mav.mission_count_encode(1, 1, len(ITEMS), FENCE))
        first = await gcs.recv_match(type=("MISSION_REQUEST", "MISSION_REQUEST_INT"), timeout=5.0)
        assert first.get_type() == request_type and first.seq == 0 and first.mission_type == FENCE
        ack = await upload_fence(gcs, ITEMS)  # starts again: the same ground station may restart its upload
        assert ack.type == m.MAV_MISSION_ACCEPTED and (ack.target_system, ack.target_component) == (255, 190)
        assert sim.engine.fence.items == ITEMS and sim.engine.fence.uploads == 1
        assert await _download(gcs) == ITEMS
        assert (await upload_fence(gcs, [])).type == m.MAV_MISSION_ACCEPTED  # count 0 clears it
        assert sim.engine.fence.items == [] and await _download(gcs) == []
        assert (await upload_fence(gcs, ITEMS)).type == m.MAV_MISSION_ACCEPTED
        gcs.send(gcs.mav.mission_clear_all_encode(1, 1, FENCE))  # and so does MISSION_CLEAR_ALL
        assert (await fence_ack(gcs)).type == m.MAV_MISSION_ACCEPTED and sim.engine.fence.items == []


async def test_while_one_uploads_others_are_denied_and_a_stalled_upload_is_cancelled() -> None:
    other = await MavlinkLink.open("udpin:127.0.0.1:0", source_system=254, source_component=191)
    try:
        assert other.local_address is not None
        links = [f"udpout:127.0.0.1:{other.local_address[1]}"]
        async with simulator_with_client(links=links, speedup=20.0) as (sim, gcs):
            await other.recv_match(type="HEARTBEAT", timeout=5.0)
            assert await upload_fence(gcs, ITEMS, stop_after=2) is None  # two items sent, the upload open
            other.send(other.mav.mission_request_list_encode(1, 1, FENCE))
            assert (await fence_ack(other)).type == m.MAV_MISSION_DENIED  # no download while it uploads
            other.send(other.mav.mission_request_int_encode(1, 1, 0, FENCE))
            assert (await fence_ack(other)).type == m.MAV_MISSION_DENIED
            other.send(other.mav.mission_count_encode(1, 1, 3, FENCE))
            assert (await fence_ack(other)).type == m.MAV_MISSION_DENIED  # nor another upload
            other.send(other.mav.mission_count_encode(1, 1, 1, m.MAV_MISSION_TYPE_MISSION))
            refused = await other.recv_match(type="MISSION_ACK", timeout=5.0)
            assert refused.type == m.MAV_MISSION_UNSUPPORTED  # a mission: this vehicle takes none
            other.send(other.mav.mission_clear_all_encode(1, 1, FENCE))
            assert [(await fence_ack(other)).type for _ in range(2)] == [m.MAV_MISSION_DENIED, m.MAV_MISSION_ERROR]
            assert sim.engine.fence.items == []  # nothing kept from the open upload
            await wait_sim_time(sim, sim.t_s + 8.5)
            other.send(other.mav.mission_request_list_encode(1, 1, FENCE))  # the next fence message cancels it
            assert (await fence_ack(gcs)).type == m.MAV_MISSION_OPERATION_CANCELLED
            assert (await other.recv_match(type="MISSION_COUNT", timeout=5.0)).count == 0
            ack = await upload_fence(other, ITEMS[:1])
            assert ack.type == m.MAV_MISSION_ACCEPTED and sim.engine.fence.items == ITEMS[:1]
    finally:
        await other.aclose()


async def test_px4_keeps_one_transfer_state_for_every_link() -> None:
    """PX4 (mavlink_mission.cpp): while one station downloads, another's upload is refused (ERROR) until the
    download is acked; while one uploads, another's download request is ignored with a STATUSTEXT and its upload
    refused; a transfer left open ends after 5 s."""
    other = await MavlinkLink.open("udpin:127.0.0.1:0", source_system=254, source_component=191)
    try:
        assert other.local_address is not None
        links = [f"udpout:127.0.0.1:{other.local_address[1]}"]
        async with simulator_with_client(profile="px4", links=links, speedup=20.0) as (sim, gcs):
            await other.recv_match(type="HEARTBEAT", timeout=5.0)
            other.send(other.mav.mission_request_list_encode(1, 1, FENCE))
            assert (await other.recv_match(type="MISSION_COUNT", timeout=5.0)).count == 0  # a download, not acked
            assert (await upload_fence(gcs, ITEMS)).type == m.MAV_MISSION_ERROR
            other.send(other.mav.mission_ack_encode(1, 1, m.MAV_MISSION_ACCEPTED, FENCE))  # the download ends
            assert await upload_fence(gcs, ITEMS, stop_after=1) is None  # an upload left open
            other.send(other.mav.mission_request_list_encode(1, 1, FENCE))
            said = await other.recv_match(type="STATUSTEXT", condition=lambda x: "Mission" in x.text, timeout=5.0)
            assert said.text == "Mission download request ignored, already active"
            assert not [x for x in await drain(other) if x.get_type() == "MISSION_COUNT"]
            assert (await upload_fence(other, ITEMS[:1])).type == m.MAV_MISSION_ERROR
            await wait_sim_time(sim, sim.t_s + 5.5)  # PX4's protocol timeout: back to idle
            other.send(other.mav.mission_request_list_encode(1, 1, FENCE))
            assert (await other.recv_match(type="MISSION_COUNT", timeout=5.0)).count == 0  # the open upload dropped
    finally:
        await other.aclose()

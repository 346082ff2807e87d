"""MAVLink 2 signing in the service over real loopback UDP: commands from a ground station signed by pymavlink's
own signer (unsigned, wrong key, replayed: dropped, counted, goal unchanged; signed: used), the key file's mode,
the timestamp across restarts, and flights against the signed simulator (docs/hardening.md#mavlink-2-signing)."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import CopterMode
from apf_companion.cli import main as apf_companion_main
from apf_companion.config import ServiceConfig
from apf_companion.errors import ConfigError
from apf_companion.goal import Route
from apf_companion.links import LinkSigning, MavlinkLink, SigningParams, TimestampFile, Verdict, signing_timestamp
from apf_companion.navigator import State
from apf_companion.service import CompanionService
from apf_companion.status import NVI_REJECTED_SIGNING
from sim.vehicle import SimConfig, Simulator, SpawnConfig
from sim.world import World
from tests.conftest import HANG_S, SimulatorClock, until
from tests.service.test_service_flight import SPEEDUP, running, service_config, wait_state
from tests.service.test_service_mavlink import fast_config, rig

pytestmark = pytest.mark.timeout(120)

KEY = bytes.fromhex("a1" * 16 + "5c" * 16)
OTHER_KEY = bytes(range(32))
MINUTE = 60 * 100_000


def key_file(tmp_path: Path, mode: int = 0o600, key: bytes = KEY) -> Path:
    path = tmp_path / "apf.key"
    path.write_text(key.hex() + "\n")
    os.chmod(path, mode)
    return path


def signed_config(tmp_path: Path, **link: Any) -> ServiceConfig:
    return fast_config(
        link={"signing_key_file": str(key_file(tmp_path)), "signing_timestamp_file": str(tmp_path / "ts")} | link
    )


def frame_timestamp(msg: Any) -> int:
    """The signing timestamp of a received frame (0 when it is unsigned)."""
    buf = bytes(msg.get_msgbuf())
    return int.from_bytes(buf[-12:-6], "little") if buf[2] & mavlink.MAVLINK_IFLAG_SIGNED else 0


class Gcs:
    """A ground station whose frames pymavlink signs (``MAVLink.signing``, as mavutil's ``setup_signing``)."""

    def __init__(self, link: MavlinkLink, key: bytes | None) -> None:
        self.link = link
        self.mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        if key is not None:
            self.mav.signing.secret_key = key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.timestamp = signing_timestamp(time.time())

    def reposition(self, east_m: float) -> bytes:
        """COMMAND_INT DO_REPOSITION to us in LOCAL_NED (x, y in metres * 1e4): (0, east_m, -5)."""
        return self._send(
            self.mav.command_int_encode(
                1, 191, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_CMD_DO_REPOSITION, 0, 0, -1, 1, 0, math.nan, 0,
                int(east_m * 1e4), -5.0,
            )
        )  # fmt: skip

    def param_set(self, name: str, value: float) -> bytes:
        """PARAM_SET of one of our REAL32 parameters."""
        return self._send(self.mav.param_set_encode(1, 191, name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32))

    def param_read(self, name: str) -> bytes:
        """PARAM_REQUEST_READ by name."""
        return self._send(self.mav.param_request_read_encode(1, 191, name.encode(), -1))

    def _send(self, msg: Any) -> bytes:
        buf = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        self.link.send_bytes(buf)
        return buf


def target(svc: CompanionService) -> list[float] | None:
    t = svc.navigator.active_target_ned_m
    return None if t is None else [float(v) for v in t]


async def test_commands_count_only_when_signed_with_our_key(tmp_path: Path) -> None:
    route = Route.point(30.0, 0.0, -5.0, source="test")
    async with rig(signed_config(tmp_path), route) as (svc, ap):
        assert svc.link is not None and svc.link.signing is not None and svc.link.local_address is not None
        stats = svc.link.signing.stats
        await until(lambda: len(ap.setpoints()) > 5, HANG_S, "flying on unsigned telemetry")
        port = svc.link.local_address[1]
        link = await MavlinkLink.open(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        try:
            goal0 = target(svc)
            Gcs(link, None).reposition(5.0)
            await until(lambda: stats.rejected == 1, HANG_S, "unsigned command dropped")
            Gcs(link, OTHER_KEY).reposition(5.0)
            await until(lambda: stats.rejected == 2 and stats.bad_signature == 1, HANG_S, "wrong key dropped")
            assert target(svc) == goal0 and svc.navigator.route is not None and svc.navigator.route.source == "test"
            assert svc.reporter.counters.commands_for_us == 0  # no handler ever saw them

            gcs = Gcs(link, KEY)
            first = gcs.reposition(5.0)
            ack = await link.recv_match(type="COMMAND_ACK", timeout=HANG_S)
            assert ack.result == mavlink.MAV_RESULT_ACCEPTED and frame_timestamp(ack) > 0  # our ACK is signed too
            await until(lambda: target(svc) == pytest.approx([0.0, 5.0, -5.0]), HANG_S, "first signed goal")
            gcs.reposition(8.0)
            await until(lambda: target(svc) == pytest.approx([0.0, 8.0, -5.0]), HANG_S, "second signed goal")
            link.send_bytes(first)  # a replay of the first goal, byte for byte
            await until(lambda: stats.replayed == 1 and stats.rejected == 3, HANG_S, "replay dropped")
            assert target(svc) == pytest.approx([0.0, 8.0, -5.0])
            assert svc.reporter.counters.commands_for_us == 2

            assert svc.reporter.status_dict(svc.clock.now())["rejected"][NVI_REJECTED_SIGNING] == 3
            counters = svc.reporter.counts()
            assert counters["signing_rejected"] == 3 and counters["signing_signed"] == 2

            def nvi() -> list[int]:
                return [m.value for m in ap.of_type("NAMED_VALUE_INT") if m.name == NVI_REJECTED_SIGNING]

            await until(lambda: 3 in nvi(), HANG_S, "APF_RJSIGN = 3 sent")
        finally:
            await link.aclose()
        # Everything the service sent is signed with the key (checked as a peer would).
        checker = LinkSigning(SigningParams(key=KEY, initial_timestamp=0), mavlink.MAVLink(None))
        sps = [m for _, m in ap.setpoints()]
        verdicts = {checker.check(bytes(m.get_msgbuf()), 1, 191) for m in sps}
        assert verdicts == {Verdict.SIGNED}


async def test_a_parameter_changes_only_when_signed_and_reads_stay_open(tmp_path: Path) -> None:
    """PARAM_SET changes the planner's safety parameters: with a key and ``require_signed_commands`` (the default) an
    unsigned one (a review set APF_MARGIN to 0 so) or one signed with another key is dropped, counted in
    ``signing_rejected`` and unanswered, and the value stays; a signed one is applied and answered. An unsigned
    PARAM_REQUEST_READ is answered (telemetry rule: it changes nothing)."""
    async with rig(signed_config(tmp_path)) as (svc, _ap):
        assert svc.link is not None and svc.link.signing is not None and svc.link.local_address is not None
        stats = svc.link.signing.stats
        margin0 = svc.planner.params.safety_margin_m
        assert margin0 > 0.0
        await until(lambda: svc.handlers.heard, HANG_S, "the autopilot heard")
        port = svc.link.local_address[1]
        link = await MavlinkLink.open(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        try:
            Gcs(link, None).param_set("APF_MARGIN", 0.0)
            await until(lambda: stats.rejected == 1, HANG_S, "unsigned PARAM_SET dropped")
            Gcs(link, OTHER_KEY).param_set("APF_MARGIN", 0.0)
            await until(lambda: stats.rejected == 2 and stats.bad_signature == 1, HANG_S, "wrong key dropped")
            assert svc.reporter.counters.param_requests == 0 and svc.params.sets == 0  # no handler saw them
            assert svc.planner.params.safety_margin_m == margin0

            Gcs(link, None).param_read("APF_MARGIN")  # a read: answered unsigned, with the value in force
            value = await link.recv_match(type="PARAM_VALUE", timeout=HANG_S)
            assert (value.param_id, value.param_value) == ("APF_MARGIN", pytest.approx(margin0))
            assert stats.rejected == 2

            Gcs(link, KEY).param_set("APF_MARGIN", 0.2)
            value = await link.recv_match(type="PARAM_VALUE", timeout=HANG_S)
            assert (value.param_id, value.param_value) == ("APF_MARGIN", pytest.approx(0.2))
            assert svc.params.sets == 1
            await until(lambda: svc.planner.params.safety_margin_m == 0.2, HANG_S, "in service at the next cycle")
            assert svc.reporter.counts()["signing_rejected"] == 2
        finally:
            await link.aclose()


async def test_unsigned_telemetry_is_dropped_when_signed_telemetry_is_required(tmp_path: Path) -> None:
    cfg = signed_config(tmp_path, require_signed_telemetry=True)
    async with rig(cfg) as (svc, ap):
        assert svc.link is not None and svc.link.signing is not None
        stats = svc.link.signing.stats
        await until(lambda: stats.rejected >= 20 and len(ap.of_type("HEARTBEAT")) >= 1, HANG_S, "telemetry dropped")
        assert not svc.handlers.heard and svc.navigator.pose is None
        assert stats.unsigned == stats.rejected


async def test_a_key_file_others_can_read_stops_the_start(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = key_file(tmp_path, 0o640)
    cfg = fast_config(link={"signing_key_file": str(path)})
    with pytest.raises(ConfigError, match=f"{path}.*0o640"):
        await CompanionService.open(cfg)
    toml = tmp_path / "apf.toml"
    toml.write_text(f'[link]\nconnect = "udpin:127.0.0.1:0"\nsigning_key_file = "{path.name}"\n')
    assert apf_companion_main(["check-config", str(toml)]) == 2
    assert "0o640" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="require_signed_telemetry"):
        fast_config(link={"require_signed_telemetry": True})


async def test_the_signing_timestamp_persists_across_a_restart(tmp_path: Path) -> None:
    cfg = signed_config(tmp_path)
    store = TimestampFile(tmp_path / "ts")
    seen: list[int] = []
    for run in range(2):
        async with rig(cfg) as (svc, ap):
            assert svc.link is not None and svc.link.signing is not None
            saved_at_start = store.load()
            assert saved_at_start is not None and saved_at_start >= svc.link.signing.timestamp - 1
            await until(lambda: len(ap.of_type("HEARTBEAT")) >= 2, HANG_S, "heartbeats")
            stamps = [frame_timestamp(m) for _, m in ap.received]
        assert min(stamps) > 0
        if run == 1:
            assert min(stamps) > max(seen) + MINUTE - 1  # restarted at persisted + 1 min, never re-using one
        seen += stamps
        saved = store.load()
        assert saved is not None and saved >= max(seen)  # written at exit, after the last frame
    # A clock behind the file (no RTC, clock reset): the file still wins.
    ahead = signing_timestamp(time.time()) + 60 * MINUTE
    store.save(ahead)
    svc = await CompanionService.open(cfg)
    try:
        assert svc.link is not None and svc.link.signing is not None
        assert svc.link.signing.timestamp >= ahead + MINUTE
    finally:
        await svc.aclose()
    assert (store.load() or 0) >= ahead + MINUTE


async def test_with_signed_telemetry_required_forged_poses_never_reach_the_pose_gate(tmp_path: Path) -> None:
    """The autopilot signs; unsigned LOCAL_POSITION_NED frames with its ids, injected on its own socket (each
    stamped 0.95 s after the last and 5 m further east, test_service_pose_time.py's walk), are dropped by the
    signing check before any handler: the pose gate never sees them (docs/hardening.md "Pose plausibility")."""
    cfg = signed_config(tmp_path, require_signed_telemetry=True)
    ap_signing = SigningParams(key=KEY, initial_timestamp=signing_timestamp(time.time()))
    async with rig(cfg, Route.point(30.0, 0.0, -5.0, source="test"), ap_signing=ap_signing) as (svc, ap):
        assert svc.link is not None and svc.link.signing is not None
        stats = svc.link.signing.stats
        await until(lambda: len(ap.setpoints()) > 20, HANG_S, "flying on signed telemetry")
        ap.follow_setpoints = False
        await ap.ticks_pass(3)
        genuine, c = list(ap.pos), svc.perception.counters
        rejected0 = stats.rejected
        counted0 = (c.stale_poses, c.implausible_poses, c.pose_time_leads, c.pose_conflicts, c.pose_resets)
        forger = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)  # the autopilot's ids, no key
        stamp = ap.boot_ms()
        for i in range(1, 11):
            stamp += 950
            forged = forger.local_position_ned_encode(stamp, genuine[0], genuine[1] + 5.0 * i, genuine[2], 0, 0, 0)
            ap.link.send_bytes(bytes(forged.pack(forger)))
            await ap.ticks_pass(1)
        await until(lambda: stats.rejected - rejected0 >= 10, HANG_S, "the forged frames dropped")
        await ap.ticks_pass(5)
        assert stats.unsigned >= 10 and stats.bad_signature == 0
        pose = svc.navigator.pose
        assert pose is not None and math.dist(tuple(pose.pos_ned_m), genuine) < 0.1
        assert (c.stale_poses, c.implausible_poses, c.pose_time_leads, c.pose_conflicts, c.pose_resets) == counted0


# ---- against the bundled simulator ----------------------------------------------------------------------------
async def _sim_flight(
    cfg: ServiceConfig, sim_key: bytes | None, route: Route, *, unasked_streams: bool | None = None
) -> tuple[CompanionService, Simulator]:
    svc = await CompanionService.open(cfg, route=route, clock=SimulatorClock(SPEEDUP))
    assert svc.link is not None and svc.link.local_address is not None
    sim = await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{svc.link.local_address[1]}"],
            world=World.empty(),
            speedup=SPEEDUP,
            spawn=SpawnConfig(pos_ne_m=(3.0, 3.0), airborne=True, alt_m=5.0, mode="LOITER"),
            signing_key=sim_key,
            unasked_streams=unasked_streams,
        )
    )
    return svc, sim


@pytest.mark.slow
async def test_signed_service_takes_over_and_flies_the_signed_simulator(tmp_path: Path) -> None:
    key = key_file(tmp_path)
    cfg = service_config(link={"signing_key_file": str(key), "require_signed_telemetry": True})
    svc, sim = await _sim_flight(cfg, KEY, Route.point(8.0, 3.0, -5.0, source="t"))
    async with running(svc, sim):
        await wait_state(svc, {State.ARRIVED}, 120.0)
        assert sim.vehicle.custom_mode == CopterMode.GUIDED
        res = sim.result()
    assert res["signing"][0]["rejected"] == 0 and res["signing"][0]["signed"] > 50
    assert svc.link is not None and svc.link.signing is not None
    assert svc.link.signing.stats.rejected == 0 and svc.link.signing.stats.unsigned == 0


@pytest.mark.slow
async def test_the_signed_simulator_ignores_an_unsigned_service(tmp_path: Path) -> None:
    """As ArduPilot with a key: the unsigned mode request and setpoints are dropped; the takeover times out."""
    cfg = service_config(autopilot={"mode_timeout_s": 2.0})
    # Streams unasked: the service's (unsigned) stream requests are dropped too, and without a pose it would never
    # get as far as a mode request.
    svc, sim = await _sim_flight(cfg, KEY, Route.point(8.0, 3.0, -5.0, source="t"), unasked_streams=True)
    async with running(svc, sim):
        await until(lambda: svc.counters.goals >= 1, HANG_S, "the goal is set once the autopilot is heard")
        await until(lambda: svc.navigator.route is None, HANG_S, "the goal is dropped when the takeover fails")
        assert svc.navigator.state is State.IDLE
        assert sim.vehicle.mode == "LOITER"
        res = sim.result()
    assert res["signing"][0]["rejected"] > 0 and res["signing"][0]["signed"] == 0
    assert svc.reporter.counters.mode_requests >= 1

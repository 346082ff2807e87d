"""Fuzz harness over the service's real input path: bytes in over loopback UDP, setpoints out.

A real ``CompanionService`` listens on 127.0.0.1; one UDP socket (``FuzzAutopilot``) plays the autopilot: a genuine
stream (HEARTBEAT, ATTITUDE, LOCAL_POSITION_NED at 20 Hz, an all-free OBSTACLE_DISTANCE at 10 Hz; the vehicle
moves towards the last setpoint at a bounded speed) with hostile frames interleaved from the same address. Each
hostile frame comes from one generator in ``GENERATORS`` (random bytes, bad CRCs, truncation, MAVLink 1, payloads
with random bits and a valid CRC, NaN / inf / 1e30 / 3e38 fields, wrong ids, time back / forward / wrapping,
replays of genuine datagrams, abused OBSTACLE_DISTANCE / DISTANCE_SENSOR / OBSTACLE_DISTANCE_3D, 1 km jumps, GCS
commands with hostile values). Every setpoint the service sends is checked against the genuine position when it
arrives (``Verdicts``); the service must stay alive and count what it rejected.

Used by tests/service/test_service_fuzz.py (hypothesis picks the generator sequence and the random stream) and
benchmarks/fuzz_long.py (10^6 frames).
"""

from __future__ import annotations

import asyncio
import collections
import math
import random
import struct
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v10 import ardupilotmega as mavlink1
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from pymavlink.generator.mavcrc import x25crc

from apf_companion.autopilot import MASK_VELOCITY, CopterMode
from apf_companion.config import ServiceConfig, config_from_mapping
from apf_companion.goal import Route
from apf_companion.links import MavlinkLink
from apf_companion.navigator import State
from apf_companion.service import CompanionService

AP_SYS, AP_COMP = 1, 1  # the autopilot the service listens to
GCS_SYS = 255
ALT_DOWN_M = -5.0
VEHICLE_SPEED_M_S = 3.0  # the genuine vehicle flies towards the last setpoint at most this fast
TICK_S = 0.05  # genuine stream period (20 Hz)
SETPOINT_REACH_M = 3.0  # a setpoint further than this from the genuine position came from invalid data
SETPOINT_MAX_SPEED_M_S = 5.0
HOSTILE_FLOATS = (math.nan, math.inf, -math.inf, 1e30, -1e30, 3e38, -3e38, 0.0, -0.0, 1e-45)
GOALS_NE_M = ((30.0, 0.0), (0.0, 0.0), (15.0, 15.0))
UINT32_MAX = 2**32 - 1
BATCH = 32  # hostile frames sent before the harness waits for the service to have read them


def fuzz_config(rate_hz: float = 10.0) -> ServiceConfig:
    """A service on an ephemeral loopback port, GUIDED takeover, reporting counters at 5 Hz."""
    return config_from_mapping(
        {
            "link": {"connect": "udpin:127.0.0.1:0", "heartbeat_timeout_s": 2.0},
            "cycle": {"rate_hz": rate_hz},
            "status": {"named_value_rate_hz": 5.0},
        }
    )


# ---- frames ------------------------------------------------------------------------------------------------------
def frame_v2(msgid: int, payload: bytes, *, seq: int, sys: int = AP_SYS, comp: int = AP_COMP) -> bytes:
    """A MAVLink 2 frame with a valid CRC around any payload (random bits included)."""
    header = struct.pack("<BBBBBBBHB", 0xFD, len(payload), 0, 0, seq & 0xFF, sys, comp, msgid & 0xFFFF, msgid >> 16)
    crc = x25crc(header[1:] + payload)
    entry = mavlink.mavlink_map.get(msgid)
    crc.accumulate(bytes([entry.crc_extra if entry is not None else 0]))
    return header + payload + struct.pack("<H", crc.crc)


class Encoder:
    """Packs pymavlink messages with any source ids, MAVLink 2 or 1, with a running sequence number."""

    def __init__(self) -> None:
        self.v2 = mavlink.MAVLink(None, srcSystem=AP_SYS, srcComponent=AP_COMP)
        self.v1 = mavlink1.MAVLink(None, srcSystem=AP_SYS, srcComponent=AP_COMP)
        self.seq = 0

    def pack(self, msg: Any, *, sys: int = AP_SYS, comp: int = AP_COMP, v1: bool = False) -> bytes:
        mav = self.v1 if v1 else self.v2
        mav.srcSystem, mav.srcComponent, mav.seq = sys, comp, self.seq
        self.seq = (self.seq + 1) % 256
        return bytes(msg.pack(mav))


@dataclass(slots=True)
class Context:
    """What generators may use: the genuine vehicle's position and clock, and recent genuine datagrams."""

    enc: Encoder
    pos: list[float]
    boot_ms: Callable[[], int]
    recent: collections.deque[bytes] = field(default_factory=lambda: collections.deque(maxlen=400))


def _hostile_float(rng: random.Random) -> float:
    return rng.choice(HOSTILE_FLOATS) if rng.random() < 0.7 else rng.uniform(-1e4, 1e4)


def _hostile_time_ms(rng: random.Random, ctx: Context) -> int:
    now = ctx.boot_ms()
    choice = rng.randrange(7)
    if choice == 0:
        return max(0, now - rng.choice((1, 50, 10_500, 60_000)))  # back (reorder, 10 s back, a minute back)
    if choice == 1:
        return min(UINT32_MAX, now + rng.choice((2_000, 9_000, 3_600_000)))  # forward
    if choice == 2:
        return rng.choice((0, UINT32_MAX, UINT32_MAX - 5))  # wrapping
    if choice == 3:
        return rng.randrange(UINT32_MAX + 1)
    return now


def _pose_position(rng: random.Random, ctx: Context) -> tuple[float, float, float]:
    x, y, z = ctx.pos
    choice = rng.randrange(5)
    if choice == 0:  # a 1 km jump
        ang = rng.uniform(0.0, 2.0 * math.pi)
        return x + 1000.0 * math.cos(ang), y + 1000.0 * math.sin(ang), z
    if choice == 1:  # a nearby spoof (5-60 m)
        return x + rng.uniform(5.0, 60.0), y - rng.uniform(5.0, 60.0), z
    if choice == 2:  # at one of the goals
        gn, ge = rng.choice(GOALS_NE_M)
        return gn, ge, ALT_DOWN_M
    return _hostile_float(rng), _hostile_float(rng), _hostile_float(rng) if rng.random() < 0.5 else z


def gen_random_bytes(rng: random.Random, ctx: Context) -> bytes:
    data = rng.randbytes(rng.randrange(1, 300))
    return (b"\xfd" + data) if rng.random() < 0.5 else data


def gen_bad_crc(rng: random.Random, ctx: Context) -> bytes:
    frame = bytearray(gen_hostile_pose(rng, ctx) if rng.random() < 0.5 else gen_free_scan(rng, ctx))
    frame[-1 - rng.randrange(2)] ^= 1 + rng.randrange(255)
    return bytes(frame)


def gen_truncated(rng: random.Random, ctx: Context) -> bytes:
    frame = gen_genuine_like(rng, ctx)
    return frame[: rng.randrange(1, len(frame))]


def gen_mavlink1(rng: random.Random, ctx: Context) -> bytes:
    x, y, z = _pose_position(rng, ctx)
    m = mavlink1
    msgs: list[Any] = [
        m.MAVLink_local_position_ned_message(_hostile_time_ms(rng, ctx), x, y, z, 0.0, 0.0, 0.0),
        m.MAVLink_attitude_message(ctx.boot_ms(), 0.0, 0.0, _hostile_float(rng), 0.0, 0.0, 0.0),
        m.MAVLink_heartbeat_message(2, 3, 1 | 128, int(CopterMode.GUIDED), rng.randrange(9), 3),
        m.MAVLink_distance_sensor_message(ctx.boot_ms(), 20, 800, rng.randrange(65536), 0, 1, rng.randrange(256), 0),
    ]
    return ctx.enc.pack(rng.choice(msgs), v1=True)


def gen_random_payload(rng: random.Random, ctx: Context) -> bytes:
    """A consumed message type (or any known one) with random payload bits and a valid CRC."""
    consumed = (30, 32, 33, 76, 75, 132, 330, 331, 11037)  # HEARTBEAT: gen_heartbeat (a mode change ends a flight)
    msgid = rng.choice(consumed) if rng.random() < 0.8 else rng.choice(list(mavlink.mavlink_map))
    entry = mavlink.mavlink_map[msgid]
    full = int(entry.unpacker.size)
    size = rng.choice((full, rng.randrange(0, full + 1), full + rng.randrange(1, 8)))
    sys, comp = (AP_SYS, AP_COMP) if rng.random() < 0.8 else (GCS_SYS, 190)
    return frame_v2(msgid, rng.randbytes(min(255, size)), seq=rng.randrange(256), sys=sys, comp=comp)


def gen_hostile_pose(rng: random.Random, ctx: Context) -> bytes:
    x, y, z = _pose_position(rng, ctx)
    msg = mavlink.MAVLink_local_position_ned_message(_hostile_time_ms(rng, ctx), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    return _with_floats(ctx, msg, x=x, y=y, z=z, vx=_hostile_float(rng))


def _with_floats(ctx: Context, msg: Any, **floats: float) -> bytes:
    """Pack ``msg`` with float fields set to values pymavlink may refuse (|v| > float32 max): via raw bits."""
    for name, value in floats.items():
        setattr(msg, name, value if not math.isfinite(value) or abs(value) < 3.4e38 else math.copysign(math.inf, value))
    return ctx.enc.pack(msg)


def gen_foreign_ids(rng: random.Random, ctx: Context) -> bytes:
    sys = rng.choice((0, 2, 7, 200, GCS_SYS, AP_SYS))
    comp = rng.choice((0, 2, 100, 191, 250)) if sys == AP_SYS else rng.choice((1, 190, 191))
    x, y, z = ctx.pos
    msgs: list[Any] = [
        mavlink.MAVLink_local_position_ned_message(ctx.boot_ms(), x + 50.0, y + 50.0, z, 0.0, 0.0, 0.0),
        mavlink.MAVLink_heartbeat_message(2, 3, 1, int(CopterMode.LOITER), 4, 3),
        mavlink.MAVLink_obstacle_distance_message(ctx.boot_ms() * 1000, 0, [801] * 72, 0, 20, 800, 5.0, 0.0, 12),
    ]
    return ctx.enc.pack(rng.choice(msgs), sys=sys, comp=comp)


def gen_replay(rng: random.Random, ctx: Context) -> bytes:
    if not ctx.recent:
        return gen_random_bytes(rng, ctx)
    return ctx.recent[rng.randrange(len(ctx.recent))]


def gen_obstacle_distance(rng: random.Random, ctx: Context) -> bytes:
    kind = rng.randrange(4)
    if kind == 0:  # all free, from the autopilot's ids: memory-erasing flood material
        return gen_free_scan(rng, ctx)
    dist = [rng.choice((0, 1, 19, 20, 300, 800, 801, 65534, 65535)) for _ in range(72)]
    if kind == 1:
        dist = [rng.randrange(65536) for _ in range(72)]
    msg = mavlink.MAVLink_obstacle_distance_message(
        rng.choice((0, ctx.boot_ms() * 1000, 2**64 - 1, rng.randrange(2**64))),
        rng.randrange(256),
        dist,
        rng.choice((0, 1, 5, 255)),
        rng.choice((0, 20, 800, 65535)),
        rng.choice((0, 20, 800, 65535)),
        0.0,
        0.0,
        rng.choice((0, 1, 8, 12, 255)),
    )
    return _with_floats(ctx, msg, increment_f=_hostile_float(rng), angle_offset=_hostile_float(rng))


def gen_free_scan(rng: random.Random, ctx: Context) -> bytes:
    return ctx.enc.pack(
        mavlink.MAVLink_obstacle_distance_message(ctx.boot_ms() * 1000, 0, [801] * 72, 0, 20, 800, 5.0, 0.0, 12)
    )


def gen_distance_sensor(rng: random.Random, ctx: Context) -> bytes:
    msg = mavlink.MAVLink_distance_sensor_message(
        _hostile_time_ms(rng, ctx),
        rng.choice((0, 20, 800, 65535)),
        rng.choice((0, 20, 800, 65535)),
        rng.choice((0, 1, 300, 801, 65535, rng.randrange(65536))),
        rng.randrange(256),
        rng.randrange(256),
        rng.choice((0, 1, 24, 25, 100, 255)),
        rng.randrange(256),
    )
    return _with_floats(ctx, msg, horizontal_fov=_hostile_float(rng), vertical_fov=_hostile_float(rng))


def gen_obstacle_distance_3d(rng: random.Random, ctx: Context) -> bytes:
    msg = mavlink.MAVLink_obstacle_distance_3d_message(
        _hostile_time_ms(rng, ctx), rng.randrange(256), rng.randrange(256), rng.randrange(65536), 0, 0, 0, 0, 0
    )
    return _with_floats(
        ctx,
        msg,
        x=_hostile_float(rng),
        y=_hostile_float(rng),
        z=_hostile_float(rng),
        min_distance=_hostile_float(rng),
        max_distance=_hostile_float(rng),
    )


def gen_attitude(rng: random.Random, ctx: Context) -> bytes:
    msg = mavlink.MAVLink_attitude_message(_hostile_time_ms(rng, ctx), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    return _with_floats(ctx, msg, roll=_hostile_float(rng), yaw=_hostile_float(rng))


def gen_global_position(rng: random.Random, ctx: Context) -> bytes:
    i32 = (-(2**31), 2**31 - 1, 0, 900_000_000, 1_800_000_001)
    msg = mavlink.MAVLink_global_position_int_message(
        ctx.boot_ms(), rng.choice(i32), rng.choice(i32), rng.choice(i32), rng.choice(i32), 0, 0, 0, 0
    )
    return ctx.enc.pack(msg)


def gen_gcs_command(rng: random.Random, ctx: Context) -> bytes:
    """DO_REPOSITION (and others) from the ground station with hostile values, addressed to the service."""
    command = mavlink.MAV_CMD_DO_REPOSITION if rng.random() < 0.8 else rng.randrange(65536)
    i32 = (-(2**31), 2**31 - 1, 0, int(ctx.pos[0] * 1e4), 300_000)
    if rng.random() < 0.7:
        msg = mavlink.MAVLink_command_int_message(
            AP_SYS, 191, rng.choice((1, 0, 3, 6, 7, 255)), command, 0, 0, -1, 1, 0, 0.0, rng.choice(i32),
            rng.choice(i32), 0.0,
        )  # fmt: skip
        packed = _with_floats(ctx, msg, param4=_hostile_float(rng), z=_hostile_float(rng))
    else:
        msg = mavlink.MAVLink_command_long_message(AP_SYS, 191, command, 0, 0, 0, 0, 0, 0, 0, 0)
        packed = _with_floats(ctx, msg, param1=_hostile_float(rng), param7=_hostile_float(rng))
    return _resource(packed, GCS_SYS, 190)


def _resource(frame: bytes, sys: int, comp: int) -> bytes:
    """The same MAVLink 2 frame from other source ids (CRC recomputed)."""
    msgid = frame[7] | frame[8] << 8 | frame[9] << 16
    return frame_v2(msgid, frame[10 : 10 + frame[1]], seq=frame[4], sys=sys, comp=comp)


def gen_odometry(rng: random.Random, ctx: Context) -> bytes:
    x, y, z = _pose_position(rng, ctx)
    msg = mavlink.MAVLink_odometry_message(
        ctx.boot_ms() * 1000, 1, 8, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0, 0, 0, 0, [math.nan] * 21, [math.nan] * 21,
        rng.randrange(256), 0, 0,
    )  # fmt: skip
    return _with_floats(ctx, msg, x=x, y=y, z=z)


def gen_heartbeat(rng: random.Random, ctx: Context) -> bytes:
    """From the autopilot's ids: mostly GUIDED with odd status / flags, sometimes another mode or vehicle type."""
    mode = int(CopterMode.GUIDED) if rng.random() < 0.8 else rng.randrange(2**32)
    msg = mavlink.MAVLink_heartbeat_message(rng.choice((2, 2, 6, 18)), 3, rng.randrange(256), mode, 4, 3)
    return ctx.enc.pack(msg)


def gen_genuine_like(rng: random.Random, ctx: Context) -> bytes:
    x, y, z = ctx.pos
    return ctx.enc.pack(mavlink.MAVLink_local_position_ned_message(ctx.boot_ms(), x, y, z, 0.0, 0.0, 0.0))


def gen_flood(rng: random.Random, ctx: Context) -> bytes:
    """Twenty frames in one datagram: all-free scans and "free" forward beams."""
    beam = mavlink.MAVLink_distance_sensor_message(ctx.boot_ms(), 20, 800, 801, 0, 1, 0, 0)
    return b"".join(gen_free_scan(rng, ctx) if k % 2 else ctx.enc.pack(beam) for k in range(20))


def choose_kinds(rng: random.Random, n: int) -> list[str]:
    """``n`` generator names drawn by ``WEIGHTS`` (frames that end a flight, like a mode change, are rarer)."""
    names = sorted(GENERATORS)
    return rng.choices(names, weights=[WEIGHTS.get(k, 1.0) for k in names], k=n)


Generator = Callable[[random.Random, Context], bytes]
GENERATORS: dict[str, Generator] = {
    "random_bytes": gen_random_bytes,
    "bad_crc": gen_bad_crc,
    "truncated": gen_truncated,
    "mavlink1": gen_mavlink1,
    "random_payload": gen_random_payload,
    "hostile_pose": gen_hostile_pose,
    "foreign_ids": gen_foreign_ids,
    "replay": gen_replay,
    "obstacle_distance": gen_obstacle_distance,
    "distance_sensor": gen_distance_sensor,
    "obstacle_distance_3d": gen_obstacle_distance_3d,
    "attitude": gen_attitude,
    "global_position": gen_global_position,
    "gcs_command": gen_gcs_command,
    "odometry": gen_odometry,
    "heartbeat": gen_heartbeat,
    "flood": gen_flood,
}
WEIGHTS = {"heartbeat": 0.02, "gcs_command": 0.05, "odometry": 0.05}  # the rest 1


# ---- the autopilot side ------------------------------------------------------------------------------------------
@dataclass(slots=True)
class Verdicts:
    """What the harness saw the service send."""

    setpoints: int = 0
    bad_setpoints: list[str] = field(default_factory=list)
    named_int: dict[str, int] = field(default_factory=dict)
    heartbeats: int = 0
    brakes: int = 0


class FuzzAutopilot:
    """The genuine autopilot (see the module docstring) on one UDP socket; checks every setpoint it receives."""

    def __init__(self, link: MavlinkLink, ctx: Context, goal_down_m: Callable[[], float | None]) -> None:
        self.link = link
        self.goal_down_m = goal_down_m  # the active goal's altitude: a ground station may command any in bounds
        self.ctx = ctx
        self.t0 = time.monotonic()
        self.target = list(ctx.pos)
        self.custom_mode = int(CopterMode.LOITER)
        self.verdicts = Verdicts()

    def boot_ms(self) -> int:
        return int((time.monotonic() - self.t0) * 1000) + 60_000  # booted a minute ago

    async def run(self) -> None:
        async with asyncio.TaskGroup() as tg:
            tg.create_task(self._rx())
            tg.create_task(self._tx())

    async def _rx(self) -> None:
        async for msg in self.link.messages():
            kind = msg.get_type()
            if kind == "SET_POSITION_TARGET_LOCAL_NED":
                self._check_setpoint(msg)
            elif kind == "COMMAND_LONG" and msg.command == mavlink.MAV_CMD_DO_SET_MODE:
                self.custom_mode = int(msg.param2)
            elif kind == "NAMED_VALUE_INT":
                self.verdicts.named_int[msg.name] = msg.value
            elif kind == "HEARTBEAT":
                self.verdicts.heartbeats += 1

    def _check_setpoint(self, msg: Any) -> None:
        v = self.verdicts
        v.setpoints += 1
        pos, vel = (msg.x, msg.y, msg.z), (msg.vx, msg.vy, msg.vz)
        x, y, z = self.ctx.pos
        if not all(math.isfinite(c) for c in (*pos, *vel)):
            v.bad_setpoints.append(f"non-finite setpoint {pos} {vel}")
        elif msg.type_mask == MASK_VELOCITY:  # a brake: position ignored, velocity must be zero
            v.brakes += 1
            if any(vel):
                v.bad_setpoints.append(f"brake with velocity {vel}")
        elif math.hypot(pos[0] - x, pos[1] - y) > SETPOINT_REACH_M or self._off_altitude(pos[2], z):
            v.bad_setpoints.append(f"setpoint {pos} is {math.dist(pos, (x, y, z)):.1f} m from the vehicle")
        elif math.hypot(*vel) > SETPOINT_MAX_SPEED_M_S:
            v.bad_setpoints.append(f"setpoint velocity {vel}")
        else:
            self.target = list(pos)

    def _off_altitude(self, down_m: float, vehicle_down_m: float) -> bool:
        """Neither near the vehicle's altitude nor the commanded goal's (2D flight climbs by the position part)."""
        goal = self.goal_down_m()
        near_goal = goal is not None and abs(down_m - goal) < 1e-3
        return abs(down_m - vehicle_down_m) > SETPOINT_REACH_M and not near_goal

    async def _tx(self) -> None:
        enc, n = self.ctx.enc, 0
        while True:
            self._move()
            ms = self.boot_ms()
            x, y, z = self.ctx.pos
            frames = [
                mavlink.MAVLink_attitude_message(ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
                mavlink.MAVLink_local_position_ned_message(ms, x, y, z, 0.0, 0.0, 0.0),
            ]
            if n % 20 == 0:
                frames.append(mavlink.MAVLink_heartbeat_message(2, 3, 1 | 128, self.custom_mode, 4, 3))
            if n % 2 == 0:
                frames.append(
                    mavlink.MAVLink_obstacle_distance_message(ms * 1000, 0, [801] * 72, 0, 20, 800, 5.0, 0.0, 12)
                )
            for f in frames:
                data = enc.pack(f)
                self.ctx.recent.append(data)
                self.link.send_bytes(data)
            n += 1
            await asyncio.sleep(TICK_S)

    def _move(self) -> None:
        pos, target = self.ctx.pos, self.target
        gap = math.dist(pos, target)
        step = VEHICLE_SPEED_M_S * TICK_S
        if gap > 0.0:
            f = min(1.0, step / gap)
            self.ctx.pos[:] = [p + f * (t - p) for p, t in zip(pos, target, strict=True)]


# ---- a run -------------------------------------------------------------------------------------------------------
@dataclass(slots=True)
class FuzzReport:
    """One run's outcome (benchmarks/fuzz_long.py prints it)."""

    frames: int = 0
    by_generator: dict[str, int] = field(default_factory=dict)
    wall_s: float = 0.0
    setpoints: int = 0
    brakes: int = 0
    bad_setpoints: list[str] = field(default_factory=list)
    handler_errors: int = 0
    fault_kinds: dict[str, int] = field(default_factory=dict)
    send_errors: int = 0
    alive: bool = True
    counters: dict[str, int] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)
    named_int: dict[str, int] = field(default_factory=dict)
    goals_given: int = 0

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.wall_s if self.wall_s > 0 else 0.0


async def run_fuzz(
    kinds: Sequence[str],
    rng: random.Random,
    *,
    config: ServiceConfig | None = None,
    progress: Callable[[FuzzReport], None] | None = None,
    rate_hz: float | None = None,
) -> FuzzReport:
    """Start a service, fly it between goals, feed it one hostile frame per entry of ``kinds`` (names in
    ``GENERATORS``; at most ``rate_hz`` frames per second, None = as fast as the service reads them), and report
    what it did."""
    svc = await CompanionService.open(config or fuzz_config())
    assert svc.link is not None and svc.link.local_address is not None
    link = await MavlinkLink.open(f"udpout:127.0.0.1:{svc.link.local_address[1]}", source_system=1, source_component=1)
    ctx = Context(enc=Encoder(), pos=[0.0, 0.0, ALT_DOWN_M], boot_ms=lambda: 0)

    def goal_down_m() -> float | None:
        target = svc.navigator.active_target_ned_m
        return None if target is None else float(target[2])

    ap = FuzzAutopilot(link, ctx, goal_down_m)
    ctx.boot_ms = ap.boot_ms
    report = FuzzReport()
    async with asyncio.TaskGroup() as tg:
        svc_task = tg.create_task(svc.run(), name="fuzz.service")
        ap_task = tg.create_task(ap.run(), name="fuzz.autopilot")
        try:
            await _wait(lambda: svc.navigator.pose is not None and svc.handlers.heard, "the autopilot is heard")
            t0 = time.perf_counter()
            await _feed(svc, link, ctx, kinds, rng, report, progress, t0, rate_hz)
            report.wall_s = time.perf_counter() - t0
            hb = ap.verdicts.heartbeats
            await _wait(lambda: ap.verdicts.heartbeats >= hb + 2, "the service still sends heartbeats")
            report.alive = not svc_task.done()
        finally:
            _finish(report, svc, ap)
            svc.stop()
            await svc_task
            ap_task.cancel()
            await link.aclose()
    return report


async def _feed(
    svc: CompanionService,
    link: MavlinkLink,
    ctx: Context,
    kinds: Sequence[str],
    rng: random.Random,
    report: FuzzReport,
    progress: Callable[[FuzzReport], None] | None,
    t0: float,
    rate_hz: float | None,
) -> None:
    assert svc.link is not None
    goal = 0
    for i, kind in enumerate(kinds):
        link.send_bytes(GENERATORS[kind](rng, ctx))
        report.by_generator[kind] = report.by_generator.get(kind, 0) + 1
        report.frames += 1
        if i % BATCH == BATCH - 1:
            # Wait until the service has read what was sent (a kernel buffer overflow would only test the kernel).
            await _wait(_read_up_to(svc, link.stats.bytes_sent), "frames read")
            ahead_s = 0.0 if rate_hz is None else (i + 1) / rate_hz - (time.perf_counter() - t0)
            await asyncio.sleep(max(0.0, ahead_s))
            if svc.navigator.state in (State.IDLE, State.ARRIVED, State.STUCK) and svc.handlers.heard:
                goal += 1  # keep it flying: a fresh goal (a pilot's mode change or an arrival ended the last)
                n, e = GOALS_NE_M[goal % len(GOALS_NE_M)]
                if svc.admission.admit(Route.point(n, e, ALT_DOWN_M, source="fuzz"), svc.clock.now()):
                    report.goals_given += 1
            if progress is not None and i % 10_000 == 10_000 - 1:
                report.wall_s = time.perf_counter() - t0
                progress(report)


def _read_up_to(svc: CompanionService, sent: int) -> Callable[[], bool]:
    return lambda: svc.link is not None and svc.link.stats.bytes_received >= sent


async def _wait(cond: Callable[[], bool], what: str, timeout_s: float = 30.0) -> None:
    try:
        async with asyncio.timeout(timeout_s):
            while not cond():
                await asyncio.sleep(0.005)
    except TimeoutError:
        msg = f"{what}: not within {timeout_s} s"
        raise AssertionError(msg) from None


def _finish(report: FuzzReport, svc: CompanionService, ap: FuzzAutopilot) -> None:
    v = ap.verdicts
    report.setpoints = v.setpoints
    report.brakes = v.brakes
    report.bad_setpoints = list(v.bad_setpoints)
    report.named_int = dict(v.named_int)
    report.handler_errors = svc.counters.handler_errors
    report.fault_kinds = dict(svc.faults.kinds)
    report.send_errors = svc.outbox.send_errors
    result = svc.result()
    report.counters = dict(result.counters)
    report.rejected = svc.reporter.rejected()

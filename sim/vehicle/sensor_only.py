"""Sensor-only mode: the world and the range sensor, following an external autopilot (a real SITL, hardware).

The autopilot's pose comes from its LOCAL_POSITION_NED and ATTITUDE (their rates are requested with
SET_MESSAGE_INTERVAL); the world is in the same local NED frame (north/east metres from the autopilot's EKF
origin). At ``rate_hz`` (wall clock) the sensor sweeps from the latest pose and publishes OBSTACLE_DISTANCE
(and optionally DISTANCE_SENSOR / OBSTACLE_DISTANCE_3D) on the output MAVLink links and/or a zenoh topic, stamped
with the autopilot's ``time_boot_ms`` of that pose so a companion can pick the matching pose. It also tracks the
true clearance along the way (min clearance, first collision) for the result.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.errors import ConfigError
from apf_companion.links import MavlinkLink
from apf_companion.perception import HeadingTrack, euler_yaw_rate_rad_s
from sim.vehicle.sensor import (
    RangeSensorConfig,
    Scan,
    distance_sensor_msgs,
    obstacle_distance_3d_msgs,
    obstacle_distance_msg,
    scan_world,
)
from sim.vehicle.simulator import ZenohOutput, ZenohPublisher, write_result_json
from sim.world.model import World

log = logging.getLogger(__name__)

__all__ = ["SensorOnlyConfig", "SensorSimulator"]

POSE_STALE_S = 1.0  # no scan from a pose older than this (wall clock)
SENSOR_COMPID = int(mavlink.MAV_COMP_ID_PERIPHERAL)  # 158: a peripheral, not the autopilot (1)
AUTOPILOT_COMPID = int(mavlink.MAV_COMP_ID_AUTOPILOT1)


@dataclass(frozen=True, slots=True, kw_only=True)
class SensorOnlyConfig:
    """Sensor-only run.

    Attributes:
        autopilot: MAVLink endpoint of the external autopilot (e.g. ``tcp:127.0.0.1:5760``).
        outputs: MAVLink endpoints the ranges go to (the companion); may be empty with ``zenoh``.
        also_to_autopilot: also send the sensor messages on the autopilot link (e.g. for its proximity
            driver).
        autopilot_sysid: follow this system (None = the first autopilot heard).
        source_system / source_component: our MAVLink identity on every link (default 1/158: the vehicle's
            system, MAV_COMP_ID_PERIPHERAL). Never the autopilot's own 1/1: ArduPilot drops every packet that
            carries its own ids (``MAVLink_routing.cpp``, "loopback of our own messages"), so the stream
            requests would never arrive. The companion must accept ranges from this id (the service:
            ``[sensors] mavlink_sources = ["1/158"]``).
        request_rate_hz: ask the autopilot for LOCAL_POSITION_NED and ATTITUDE at this rate (0 = don't).
        rate_hz, min_range_m, max_range_m, noise_sd_m, dropout_prob: the sensor.
        vehicle_radius_m: for the collision flag in the result.
    """

    autopilot: str
    outputs: Sequence[str] = ()
    also_to_autopilot: bool = False
    world: World = field(default_factory=World.empty)
    sensor: RangeSensorConfig = field(default_factory=RangeSensorConfig)
    autopilot_sysid: int | None = None
    source_system: int = 1
    source_component: int = SENSOR_COMPID
    request_rate_hz: float = 20.0
    rate_hz: float = 10.0
    min_range_m: float = 0.2
    max_range_m: float = 8.0
    noise_sd_m: float = 0.0
    dropout_prob: float = 0.0
    vehicle_radius_m: float = 0.25
    seed: int = 0
    zenoh: ZenohOutput | None = None
    tlog_path: Path | None = None
    result_json: Path | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "outputs", tuple(self.outputs))
        if not 0.1 <= self.rate_hz <= 100.0:
            msg = f"sensor rate_hz must be in [0.1, 100], got {self.rate_hz}"
            raise ConfigError(msg)
        if not 0.0 <= self.min_range_m < self.max_range_m:
            msg = f"need 0 <= min_range_m < max_range_m, got {self.min_range_m}, {self.max_range_m}"
            raise ConfigError(msg)
        if not 0.0 <= self.dropout_prob <= 1.0 or not self.noise_sd_m >= 0.0:
            raise ConfigError("sensor dropout_prob must be in [0, 1] and noise_sd_m >= 0")
        if not self.outputs and self.zenoh is None and not self.also_to_autopilot:
            raise ConfigError("sensor-only mode needs an output: outputs, zenoh, or also_to_autopilot")
        for name in ("source_system", "source_component"):
            value = getattr(self, name)
            if not 1 <= value <= 255:
                msg = f"sensor {name} must be in [1, 255], got {value}"
                raise ConfigError(msg)


class SensorSimulator:
    """A running sensor-only simulator. ``await SensorSimulator.start(cfg)``; ``await aclose()``."""

    def __init__(
        self, cfg: SensorOnlyConfig, autopilot: MavlinkLink, outputs: list[MavlinkLink], zpub: ZenohPublisher | None
    ) -> None:
        self.cfg = cfg
        self.autopilot = autopilot
        self.outputs = outputs
        self._zenoh = zpub
        self.rng = np.random.default_rng(cfg.seed)
        self.sysid: int | None = cfg.autopilot_sysid
        self.pos_ned_m: np.ndarray | None = None
        self.yaw_rad: float | None = None  # the latest ATTITUDE's
        self.heading = HeadingTrack()  # the scan takes the yaw at its position's time, as a real sensor would
        self.time_boot_ms = 0
        self._pose_wall_t = -math.inf
        self.scans = 0
        self.last_scan: Scan | None = None
        self.min_clearance_m = math.inf
        self.collided_at: dict[str, Any] | None = None
        self.trajectory_ned_m: list[list[float]] = []
        self._task: asyncio.Task[None] | None = None
        self._closed = False
        self.error: BaseException | None = None
        self._rates_requested = False
        self.heartbeats = 0  # from the followed autopilot
        self.poses = 0  # LOCAL_POSITION_NED received
        self.attitudes = 0  # ATTITUDE received

    @classmethod
    async def start(cls, cfg: SensorOnlyConfig) -> SensorSimulator:
        opened: list[MavlinkLink] = []
        zpub: ZenohPublisher | None = None
        try:
            ap = await MavlinkLink.open(
                cfg.autopilot,
                source_system=cfg.source_system,
                source_component=cfg.source_component,
                tlog_path=cfg.tlog_path,
            )
            opened.append(ap)
            outs = []
            for ep in cfg.outputs:
                link = await MavlinkLink.open(
                    ep, source_system=cfg.source_system, source_component=cfg.source_component
                )
                opened.append(link)
                outs.append(link)
            if cfg.zenoh is not None:
                zpub = await ZenohPublisher.open(cfg.zenoh)
        except BaseException:
            for link in opened:
                await link.aclose()
            raise
        sim = cls(cfg, ap, outs, zpub)
        sim._task = asyncio.get_running_loop().create_task(sim._main(), name="apf-sensor")
        return sim

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        for link in [self.autopilot, *self.outputs]:
            await link.aclose()
        if self._zenoh is not None:
            await self._zenoh.aclose()
        if self.cfg.result_json is not None:
            await asyncio.to_thread(write_result_json, self.cfg.result_json, self.result())

    async def __aenter__(self) -> SensorSimulator:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.aclose()

    def result(self) -> dict[str, Any]:
        return {
            "schema": "apf.sensor_result/1",
            "scans": self.scans,
            "collided": self.collided_at is not None,
            "crashed_at": self.collided_at,
            "min_clearance_m": self.min_clearance_m if math.isfinite(self.min_clearance_m) else None,
            "trajectory_ned_m": self.trajectory_ned_m,
            "world": self.cfg.world.describe(),
        }

    def waiting_for(self, now: float) -> str | None:
        """Why no scan is being sent at ``now`` (event-loop time; None while scans flow): what is missing from the
        autopilot, and what to check."""
        if self.yaw_rad is not None and now - self._pose_wall_t <= POSE_STALE_S:
            return None
        cfg = self.cfg
        if self.heartbeats == 0:
            return f"no HEARTBEAT from an autopilot on {cfg.autopilot}: check the endpoint and that it sends to us"
        missing = [name for name, n in (("LOCAL_POSITION_NED", self.poses), ("ATTITUDE", self.attitudes)) if n == 0]
        if missing:
            ids = f"{cfg.source_system}/{cfg.source_component}"
            return (
                f"no {' or '.join(missing)} from system {self.sysid}: the autopilot streams nothing unasked and "
                f"ignores requests from its own ids (we are {ids}); an EKF without an origin sends no position"
            )
        return "the pose is older than 1 s"

    async def _main(self) -> None:
        try:
            async with asyncio.TaskGroup() as tg:
                tg.create_task(self._follow())
                tg.create_task(self._sweep())
        except asyncio.CancelledError:
            raise
        except BaseException as err:
            self.error = err
            log.exception("sensor.failed")

    def _request_rates(self, sysid: int, compid: int) -> None:
        if self.cfg.request_rate_hz <= 0:
            return
        interval_us = 1e6 / self.cfg.request_rate_hz
        mav = self.autopilot.mav
        for msg_id in (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ATTITUDE):
            self.autopilot.send(
                mav.command_long_encode(
                    sysid, compid, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, interval_us, 0, 0, 0, 0, 0
                )
            )

    async def _follow(self) -> None:
        loop = asyncio.get_running_loop()
        async for msg in self.autopilot.messages():
            mtype = msg.get_type()
            src = msg.get_srcSystem()
            if mtype == "HEARTBEAT" and msg.get_srcComponent() == AUTOPILOT_COMPID and msg.type != mavlink.MAV_TYPE_GCS:
                if self.sysid is None:
                    self.sysid = src
                if src == self.sysid:
                    self.heartbeats += 1
                    if not self._rates_requested:
                        self._rates_requested = True
                        self._request_rates(src, AUTOPILOT_COMPID)
                continue
            if self.sysid is None or src != self.sysid:
                continue
            if mtype == "LOCAL_POSITION_NED":
                self.poses += 1
                self.pos_ned_m = np.array([msg.x, msg.y, msg.z], dtype=np.float64)
                self.time_boot_ms = int(msg.time_boot_ms)
                self._pose_wall_t = loop.time()
                self._track()
            elif mtype == "ATTITUDE":
                self.attitudes += 1
                self.yaw_rad = float(msg.yaw)
                rate = euler_yaw_rate_rad_s(msg.roll, msg.pitch, msg.pitchspeed, msg.yawspeed)
                self.heading.update(self.yaw_rad, int(msg.time_boot_ms), rate)

    def _track(self) -> None:
        assert self.pos_ned_m is not None
        p = self.pos_ned_m
        if not self.trajectory_ned_m or np.hypot(*(np.asarray(self.trajectory_ned_m[-1][:2]) - p[:2])) > 0.05:
            self.trajectory_ned_m.append([round(float(x), 4) for x in p])
        w = self.cfg.world
        if w.n_obstacles == 0:
            return
        i, d = w.nearest_obstacle(p[:2], -float(p[2]))
        self.min_clearance_m = min(self.min_clearance_m, d)
        if d < self.cfg.vehicle_radius_m and self.collided_at is None:
            self.collided_at = {"time_boot_ms": self.time_boot_ms, "pos_ned_m": p.tolist(), "obstacle_id": i}
            log.warning("sensor.collision", extra=self.collided_at)

    async def _sweep(self) -> None:
        loop = asyncio.get_running_loop()
        period = 1.0 / self.cfg.rate_hz
        next_t = loop.time()
        while True:
            next_t += period
            await asyncio.sleep(max(0.0, next_t - loop.time()))
            if self.pos_ned_m is None or self.yaw_rad is None or loop.time() - self._pose_wall_t > POSE_STALE_S:
                continue
            self._publish(self._scan())

    def _scan(self) -> Scan:
        assert self.pos_ned_m is not None and self.yaw_rad is not None
        yaw = self.heading.at(self.time_boot_ms)
        return scan_world(
            self.cfg.world,
            self.cfg.sensor,
            t_s=self.time_boot_ms / 1000.0,
            pos_ned_m=self.pos_ned_m,
            yaw_rad=self.yaw_rad if yaw is None else yaw,
            min_range_m=self.cfg.min_range_m,
            max_range_m=self.cfg.max_range_m,
            noise_sd_m=self.cfg.noise_sd_m,
            dropout_prob=self.cfg.dropout_prob,
            rng=self.rng,
            octants="distance_sensor" in self.cfg.sensor.messages,
            points="obstacle_distance_3d" in self.cfg.sensor.messages,
        )

    def _publish(self, scan: Scan) -> None:
        self.scans += 1
        self.last_scan = scan
        kinds = self.cfg.sensor.messages
        mav = self.autopilot.mav
        msgs: list[Any] = []
        if "obstacle_distance" in kinds:
            msgs.append(obstacle_distance_msg(mav, scan, self.cfg.sensor))
        if "distance_sensor" in kinds:
            msgs.extend(distance_sensor_msgs(mav, scan))
        if "obstacle_distance_3d" in kinds:
            msgs.extend(obstacle_distance_3d_msgs(mav, scan))
        targets = list(self.outputs) + ([self.autopilot] if self.cfg.also_to_autopilot else [])
        for m in msgs:
            for link in targets:
                link.send(m)
        if self._zenoh is not None:
            self._zenoh.publish(scan)

"""The simulator on real sockets: the pure ``VehicleEngine`` driven in (scaled) real time over MAVLink links.

Usage (in-process, one event loop)::

    sim = await Simulator.start(SimConfig(links=["udpout:127.0.0.1:14550"], profile="ardupilot",
                                          world=load_world("forest"), speedup=5, seed=1,
                                          spawn=SpawnConfig(airborne=True, alt_m=5)))
    print(sim.vehicle.pos_ned_m, sim.vehicle.mode)
    result = sim.result()
    await sim.aclose()               # or: async with await Simulator.start(...) as sim:

Every link speaks MAVLink 2 as system 1 / component 1 (``apf_companion.links.MavlinkLink``); telemetry and
STATUSTEXT go to every link, replies to the link that asked. Simulated time advances in fixed physics steps,
``speedup`` simulated seconds per wall second (``math.inf`` = as fast as the CPU allows); if the machine falls
behind by more than 0.5 s of simulated time the simulator stops catching up and runs slower instead.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import math
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

from apf_companion.autopilot import Autopilot
from apf_companion.errors import ApfCompanionError, ConfigError, LinkError
from apf_companion.links import MavlinkLink, SigningParams, accept_unsigned_only, signing_timestamp
from apf_companion.planning import FlyingArea, KeepOuts
from sim.vehicle.config import AUTO_DYNAMICS, Dynamics, EngineConfig, HomeConfig, SpawnConfig, VehicleSnapshot
from sim.vehicle.engine import VehicleEngine
from sim.vehicle.sensor import RangeSensorConfig, Scan
from sim.world.model import World

log = logging.getLogger(__name__)

__all__ = ["SimConfig", "Simulator", "ZenohOutput", "scan_to_range_scan", "write_result_json"]

#: With a signing key, the only messages taken unsigned or wrongly signed on a non-USB link: ArduPilot's
#: ``accept_list`` (libraries/GCS_MAVLink/GCS_Signing.cpp ``accept_unsigned_callback``) and PX4's
#: ``unsigned_messages`` (src/modules/mavlink/mavlink_sign_control.cpp ``accept_unsigned``, MAV_SIGN_CFG >= 1).
UNSIGNED_ACCEPTED: dict[Autopilot, tuple[str, ...]] = {
    Autopilot.ARDUPILOT: ("RADIO_STATUS", "RADIO"),
    Autopilot.PX4: ("RADIO_STATUS", "ADSB_VEHICLE", "COLLISION"),
}
STEPS_PER_YIELD = 25  # as-fast-as-possible mode (speedup inf) only: let the readers run this often
MAX_LAG_S = 0.5  # simulated seconds behind schedule before the clock is re-based


@dataclass(frozen=True, slots=True, kw_only=True)
class ZenohOutput:
    """Publish each range scan on a zenoh key (the project's JSON schema or a ROS 2 LaserScan in CDR).

    Attributes:
        connect / listen: explicit ``tcp/127.0.0.1:PORT`` endpoints (multicast scouting is always off).
        mode: zenoh session mode (peer, client, router).
        key: the sensor topic (default ``apf/sensors/range0/ranges``).
        encoding: ``json`` (apf.range_scan/1) or ``cdr`` (sensor_msgs/LaserScan).
    """

    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    mode: str = "peer"
    key: str = "apf/sensors/range0/ranges"
    encoding: str = "json"

    def __post_init__(self) -> None:
        if self.encoding not in ("json", "cdr"):
            msg = f"zenoh encoding must be 'json' or 'cdr', got {self.encoding!r}"
            raise ConfigError(msg)


@dataclass(frozen=True, slots=True, kw_only=True)
class SimConfig:
    """A simulator run.

    Attributes:
        links: MAVLink endpoints (``udpout:127.0.0.1:14550``, ``udpin:...``, ``tcpin:...``, ``tcp:...``).
        profile: ``ardupilot`` or ``px4`` (or an ``Autopilot``).
        dynamics: ``simple`` or ``arducopter`` (or a ``Dynamics``; arducopter needs the ardupilot profile), or
            ``auto``: arducopter for the ardupilot profile, simple for px4 (the CLI's default).
        world: the obstacles (``sim.world``).
        speedup: simulated seconds per wall second (``math.inf`` = as fast as possible).
        seed: seeds actuation noise and sensor noise/dropout (separate streams).
        spawn: start pose and state (on the ground, or airborne in GUIDED / Hold for fast tests).
        params: parameter overrides by name (``GUID_TIMEOUT``, ``COM_OF_LOSS_T``, ``SIM_POS_NOISE``, ...).
        sensor: range sensor geometry and which messages it emits.
        home: geodetic home (= EKF origin = world origin).
        physics_rate_hz: physics steps per simulated second.
        rates_hz: default telemetry rates by message name (SET_MESSAGE_INTERVAL still changes them).
        tlog_path: record every frame in and out; link ``i > 0`` records to ``<stem>.link<i>.tlog``.
        zenoh: also publish scans over zenoh.
        result_json: write the flight result here on close and on a crash.
        fast_start: the EKF origin is set at boot (the ArduPilot profile otherwise waits SIM_EKF_ORIGIN_S, 20 s,
            with no position, no arming in GUIDED; see sim/vehicle/startup.py). For tests that do not test startup.
        unasked_streams: stream telemetry without being asked (the old behaviour); None = the profile's habit
            (ArduPilot: HEARTBEAT only until SET_MESSAGE_INTERVAL / REQUEST_DATA_STREAM; PX4: its default streams).
        fence: the autopilot's fence, served over the mission protocol as one inclusion polygon (sim.vehicle.fence);
            None: no inclusion zone. fence_keepouts: its exclusion polygons. Neither: no fence (count 0). The
            ArduPilot profile serves FENCE_ENABLE 1 with a fence (unless ``params`` says otherwise); FENCE_* and
            PX4's GF_* parameters are stored, served and enforced (sim.vehicle.fencebreach).
        signing_key: MAVLink 2 signing key (32 bytes, ``apf_companion.links.load_signing_key``): every link signs
            its frames (link id = link index, timestamp from the wall clock, as ArduPilot with a GPS fix) and
            drops frames not signed with it, except the profile's ``UNSIGNED_ACCEPTED``; None = signing off.
        duration_s: stop the physics at the first step at or after this many simulated seconds since boot and set
            ``Simulator.finished`` (the links stay open until ``aclose``); None = run until ``aclose`` [s].
    """

    links: Sequence[str] = ()
    profile: Autopilot | str = Autopilot.ARDUPILOT
    dynamics: Dynamics | str = Dynamics.SIMPLE
    world: World = field(default_factory=World.empty)
    speedup: float = 1.0
    seed: int = 0
    spawn: SpawnConfig = field(default_factory=SpawnConfig)
    params: Mapping[str, float] = field(default_factory=dict)
    sensor: RangeSensorConfig = field(default_factory=RangeSensorConfig)
    home: HomeConfig = field(default_factory=HomeConfig)
    physics_rate_hz: float = 100.0
    rates_hz: Mapping[str, float] = field(default_factory=dict)
    tlog_path: Path | None = None
    zenoh: ZenohOutput | None = None
    result_json: Path | None = None
    fast_start: bool = False
    unasked_streams: bool | None = None
    signing_key: bytes | None = None
    fence: FlyingArea | None = None
    fence_keepouts: KeepOuts = ()
    duration_s: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "links", tuple(self.links))
        if self.signing_key is not None and len(self.signing_key) != 32:
            msg = f"signing_key must be 32 bytes, got {len(self.signing_key)}"
            raise ConfigError(msg)
        if isinstance(self.profile, str):
            try:
                object.__setattr__(self, "profile", Autopilot(self.profile.lower()))
            except ValueError as err:
                msg = f"profile must be 'ardupilot' or 'px4', got {self.profile!r}"
                raise ConfigError(msg) from err
        if isinstance(self.dynamics, str) and self.dynamics.lower() == AUTO_DYNAMICS:
            # The profile's own vehicle: ArduCopter's controller shape for ArduPilot (what flies here flies there,
            # issue 8); PX4 keeps the simple response with its takeoff/land ramps.
            auto = Dynamics.ARDUCOPTER if self.profile is Autopilot.ARDUPILOT else Dynamics.SIMPLE
            object.__setattr__(self, "dynamics", auto)
        if isinstance(self.dynamics, str):
            try:
                object.__setattr__(self, "dynamics", Dynamics(self.dynamics.lower()))
            except ValueError as err:
                msg = f"dynamics must be 'auto', 'simple' or 'arducopter', got {self.dynamics!r}"
                raise ConfigError(msg) from err
        if not (self.speedup > 0):
            msg = f"speedup must be > 0 (inf = as fast as possible), got {self.speedup}"
            raise ConfigError(msg)
        if self.duration_s is not None and not (0.0 < self.duration_s < math.inf):
            msg = f"duration must be a finite number of simulated seconds > 0, got {self.duration_s}"
            raise ConfigError(msg)

    def _params(self) -> dict[str, float]:
        """The overrides, with ArduPilot's fence switched on when one is served (FENCE_ENABLE, unless given)."""
        served = self.fence is not None or bool(self.fence_keepouts)
        on = {"FENCE_ENABLE": 1.0} if served and self.profile is Autopilot.ARDUPILOT else {}
        return on | dict(self.params)

    def engine_config(self) -> EngineConfig:
        assert isinstance(self.profile, Autopilot)
        assert isinstance(self.dynamics, Dynamics)
        return EngineConfig(
            profile=self.profile,
            dynamics=self.dynamics,
            world=self.world,
            seed=self.seed,
            params=self._params(),
            sensor=self.sensor,
            spawn=self.spawn,
            home=self.home,
            physics_rate_hz=self.physics_rate_hz,
            rates_hz=dict(self.rates_hz),
            fast_start=self.fast_start,
            unasked_streams=self.unasked_streams,
            fence=self.fence,
            fence_keepouts=self.fence_keepouts,
        )


def tlog_path_for(base: Path, index: int) -> Path:
    """Link 0 records to ``base``; link ``i`` to ``<stem>.link<i><suffix>`` beside it."""
    return base if index == 0 else base.with_name(f"{base.stem}.link{index}{base.suffix or '.tlog'}")


def write_result_json(path: Path, result: Mapping[str, Any]) -> None:
    """Write atomically (temp file + rename), so a reader never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(result, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def scan_to_range_scan(scan: Scan) -> Any:
    """A sensor scan as ``apf_companion.perception.RangeScan`` (BODY_FRD), for the zenoh encoders."""
    from apf_companion.perception import RangeScan, ScanFrame

    return RangeScan(
        t_s=scan.t_s,
        frame=ScanFrame.BODY_FRD,
        bearings_rad=scan.bearings_body_rad,
        ranges_m=scan.ranges_m,
        range_min_m=scan.min_range_m,
        range_max_m=scan.max_range_m,
        time_boot_ms=int(scan.t_s * 1000),
        source="sim",
    )


class ZenohPublisher:
    """Publishes scans on zenoh (opened in a worker thread; ``publish`` never blocks the loop)."""

    def __init__(self, link: Any, cfg: ZenohOutput) -> None:
        self._link = link
        self.cfg = cfg
        self.errors = 0

    @classmethod
    async def open(cls, cfg: ZenohOutput) -> ZenohPublisher:
        from apf_companion.links.zenoh import ZenohConfig, ZenohLink

        link = await ZenohLink.open(ZenohConfig(mode=cfg.mode, connect=cfg.connect, listen=cfg.listen))
        return cls(link, cfg)

    def publish(self, scan: Scan) -> None:
        from apf_companion.perception import encode_laserscan_cdr, encode_scan_json

        rs = scan_to_range_scan(scan)
        try:
            if self.cfg.encoding == "json":
                self._link.publish(self.cfg.key, encode_scan_json(rs), encoding="application/json")
            else:
                sec = int(scan.t_s)
                payload = encode_laserscan_cdr(rs, stamp_sec=sec, stamp_nanosec=int((scan.t_s - sec) * 1e9))
                self._link.publish(self.cfg.key, payload, encoding="application/cdr")
        except (LinkError, ConfigError):
            self.errors += 1
            log.debug("sim.zenoh_publish_failed", exc_info=True)

    async def aclose(self) -> None:
        await self._link.aclose()


def _signing(cfg: SimConfig, link_index: int) -> SigningParams | None:
    if cfg.signing_key is None:
        return None
    assert isinstance(cfg.profile, Autopilot)
    return SigningParams(
        key=cfg.signing_key,
        initial_timestamp=signing_timestamp(time.time()),  # GCS_Signing.cpp update_signing_timestamp (GPS time)
        accept_unsigned=accept_unsigned_only(UNSIGNED_ACCEPTED[cfg.profile]),
        link_id=link_index % 256,
    )


class Simulator:
    """A running simulator. Create with ``await Simulator.start(cfg)``; stop with ``await sim.aclose()``."""

    def __init__(self, cfg: SimConfig, links: list[MavlinkLink], zenoh_pub: ZenohPublisher | None) -> None:
        self.cfg = cfg
        self.links = links
        self._zenoh = zenoh_pub
        self.engine = VehicleEngine(cfg.engine_config(), n_links=len(links), emit=self._emit)
        if zenoh_pub is not None:
            self.engine.scan_listeners.append(zenoh_pub.publish)
        if cfg.result_json is not None:
            self.engine.crash_listeners.append(self._write_result_soon)
        self._supervisor: asyncio.Task[None] | None = None
        self._closed = False
        self.error: BaseException | None = None
        self.wall_time_s = 0.0
        self.lag_resets = 0
        #: Set when the simulated time reached ``cfg.duration_s`` (the physics stopped there).
        self.finished = asyncio.Event()

    # ------------------------------------------------------------------------------------------- lifecycle
    @classmethod
    async def start(cls, cfg: SimConfig) -> Simulator:
        """Open every link (and zenoh), then run the simulation in the background.

        Raises:
            LinkError: an endpoint cannot be opened.
            ConfigError: invalid configuration.
        """
        links: list[MavlinkLink] = []
        zenoh_pub: ZenohPublisher | None = None
        try:
            for i, ep in enumerate(cfg.links):
                tlog = tlog_path_for(cfg.tlog_path, i) if cfg.tlog_path is not None else None
                signing = _signing(cfg, i)
                links.append(
                    await MavlinkLink.open(ep, source_system=1, source_component=1, tlog_path=tlog, signing=signing)
                )
            if cfg.zenoh is not None:
                zenoh_pub = await ZenohPublisher.open(cfg.zenoh)
            sim = cls(cfg, links, zenoh_pub)
        except BaseException:
            for link in links:
                await link.aclose()
            if zenoh_pub is not None:
                await zenoh_pub.aclose()
            raise
        sim._supervisor = asyncio.get_running_loop().create_task(sim._main(), name="apf-sim")
        log.info(
            "sim.started",
            extra={"profile": sim.engine.profile.value, "links": list(cfg.links), "world": cfg.world.name},
        )
        return sim

    async def aclose(self) -> None:
        """Stop the simulation, close every link, write the result JSON (if configured). Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._supervisor is not None:
            self._supervisor.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._supervisor
        for link in self.links:
            await link.aclose()
        if self._zenoh is not None:
            await self._zenoh.aclose()
        if self.cfg.result_json is not None:
            await asyncio.to_thread(self._write_result, self.result())

    async def __aenter__(self) -> Simulator:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.aclose()

    async def wait_closed(self) -> None:
        """Wait until the simulation task ends (after ``aclose``, or when it fails: see ``error``)."""
        if self._supervisor is not None:
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.shield(self._supervisor)

    # ------------------------------------------------------------------------------------------- views
    @property
    def vehicle(self) -> VehicleSnapshot:
        """The vehicle now: position, velocity, yaw, mode, armed, crashed, on_ground (a copy)."""
        return self.engine.snapshot()

    @property
    def t_s(self) -> float:
        """Simulated seconds since boot."""
        return self.engine.t_s

    def result(self) -> dict[str, Any]:
        """The flight result (documented in docs/simulator-usage.md)."""
        out = self.engine.result()
        out["wall_time_s"] = round(self.wall_time_s, 6)
        out["speedup"] = self.cfg.speedup if math.isfinite(self.cfg.speedup) else None
        out["links"] = [str(link.endpoint) for link in self.links]
        out["lag_resets"] = self.lag_resets  # times the host could not keep up with the speed-up
        if self.cfg.signing_key is not None:  # per link: frames signed / unsigned / ... / rejected
            out["signing"] = [dataclasses.asdict(lk.signing.stats) for lk in self.links if lk.signing is not None]
        return out

    async def wait_until(self, predicate: Any, *, timeout_s: float, poll_s: float = 0.005) -> bool:
        """Poll ``predicate(sim)`` until true or ``timeout_s`` wall seconds pass; returns the last value.

        Raises:
            ApfCompanionError: the simulation task failed (its error is chained).
        """
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while True:
            if self.error is not None:
                msg = f"simulator failed: {self.error!r}"
                raise ApfCompanionError(msg) from self.error
            if predicate(self):
                return True
            if loop.time() >= deadline:
                return False
            await asyncio.sleep(poll_s)

    # ------------------------------------------------------------------------------------------- internals
    def _emit(self, link: int | None, msg: Any) -> None:
        if link is None:
            for lk in self.links:
                lk.send(msg)
        else:
            self.links[link].send(msg)

    def _write_result(self, result: Mapping[str, Any]) -> None:
        if self.cfg.result_json is not None:
            try:
                write_result_json(self.cfg.result_json, result)
            except OSError:
                log.exception("sim.result_write_failed")

    def _write_result_soon(self) -> None:
        # on a crash: snapshot now, write in a worker thread (file I/O stays off the loop)
        asyncio.get_running_loop().run_in_executor(None, self._write_result, self.result())

    async def _main(self) -> None:
        try:
            async with asyncio.TaskGroup() as tg:
                for i in range(len(self.links)):
                    tg.create_task(self._reader(i), name=f"apf-sim-link{i}")
                tg.create_task(self._clock(), name="apf-sim-clock")
        except asyncio.CancelledError:
            raise
        except BaseException as err:  # a task failed: keep the error for the owner, log it
            self.error = err
            log.exception("sim.failed")

    async def _reader(self, index: int) -> None:
        link = self.links[index]
        async for msg in link.messages():
            self.engine.handle(msg, index)

    async def _clock(self) -> None:
        loop = asyncio.get_running_loop()
        engine = self.engine
        dt = engine.dt
        speedup = self.cfg.speedup
        wall0 = loop.time()
        sim0 = engine.t_s
        started = wall0
        # The physics stops at the first step at or after duration_s (t_s is steps * dt; the tolerance only
        # absorbs its rounding), so the duration is honoured within one step at any speed-up; the owner, which
        # polls ``finished``, may notice it later in wall time but no further simulated time passes.
        end_s = math.inf if self.cfg.duration_s is None else self.cfg.duration_s - 1e-9 * dt
        try:
            if math.isinf(speedup):
                while engine.t_s < end_s:
                    for _ in range(STEPS_PER_YIELD):
                        engine.step()
                        if engine.t_s >= end_s:
                            break
                    self.wall_time_s = loop.time() - started
                    await asyncio.sleep(0)
            while engine.t_s < end_s:
                now = loop.time()
                due = sim0 + (now - wall0) * speedup
                behind = due - engine.t_s
                if behind > MAX_LAG_S:
                    # too slow for this speed-up: re-base the clock instead of bursting to catch up
                    wall0, sim0 = now, engine.t_s
                    self.lag_resets += 1
                    behind = 0.0
                steps = int(behind / dt + 1e-9)
                if steps > 0:
                    engine.step()
                self.wall_time_s = loop.time() - started
                if steps > 1:
                    # Behind schedule: one step per event-loop pass while catching up, so readers in this loop
                    # (its own links; an in-process service or test) see every step's messages in step; a burst
                    # of steps between yields would leave them ever further behind the vehicle on a loaded host.
                    await asyncio.sleep(0)
                    continue
                next_wall = wall0 + (engine.t_s + dt - sim0) / speedup
                await asyncio.sleep(max(0.0, next_wall - loop.time()))
            self.finished.set()
        finally:
            self.wall_time_s = loop.time() - started

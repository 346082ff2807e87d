"""The SITL recipe of docs/sitl.md, run as written, with the bundled simulator standing in for ArduCopter SITL.

There is no ArduPilot SITL build on this machine, so the autopilot end is `Simulator` with the ArduPilot profile's
real start-up (EKF origin after 20 s, nothing streamed until asked) and SITL's two serial ports as TCP servers.
Everything else is the recipe: MAVProxy on the first port forwarding to the service's UDP port, `apf-sim sensor`
(as 1/158) following the autopilot on the second port with the forest world, and the service configured with the
``sitl.toml`` printed in the doc (read from the doc, so the doc cannot drift from what is tested), plus the
``[autopilot] arm`` / ``takeoff_alt_m`` the doc names. The simulated autopilot has no obstacles of its own (SITL
has none): clearance and collisions are the sensor's view of the forest.
"""

from __future__ import annotations

import asyncio
import re
import shutil
import socket
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest

from apf_companion.config import config_from_mapping
from apf_companion.navigator import State
from apf_companion.service import CompanionService
from sim.vehicle import RangeSensorConfig, SimConfig, Simulator
from sim.vehicle.sensor_only import SensorOnlyConfig, SensorSimulator
from sim.world import load_world
from tests.conftest import HANG_S, SimulatorClock, free_port, until

pytestmark = [pytest.mark.slow, pytest.mark.interop, pytest.mark.timeout(600)]

DOC = Path(__file__).resolve().parents[2] / "docs" / "sitl.md"
SPEEDUP = 4.0  # MAVProxy relays in wall time; a higher speed-up would stretch its latency in simulated time
DOC_PORT = 14540  # the recipe's service port, replaced by a free one


def _mavproxy() -> str | None:
    beside = Path(sys.executable).parent / "mavproxy.py"
    return str(beside) if beside.is_file() else shutil.which("mavproxy.py")


def recipe_config() -> dict[str, Any]:
    """The ``sitl.toml`` block of docs/sitl.md."""
    text = DOC.read_text()
    found = re.search(r"`sitl\.toml`:\s*```toml\n(.*?)```", text, re.S)
    assert found, "docs/sitl.md lost its sitl.toml block"
    return tomllib.loads(found.group(1))


def test_the_recipe_config_is_valid_and_wired_as_the_doc_draws_it() -> None:
    raw = recipe_config()
    cfg = config_from_mapping(raw)
    assert cfg.link.connect == f"udpin:127.0.0.1:{DOC_PORT}"
    assert "1/158" in raw["sensors"]["mavlink_sources"]
    text = DOC.read_text()
    # the three commands use the same ports as the config and the wiring table
    assert f"--out udp:127.0.0.1:{DOC_PORT}" in text
    assert f"--output udpout:127.0.0.1:{DOC_PORT}" in text
    assert "--autopilot tcp:127.0.0.1:5762" in text


@pytest.mark.skipif(_mavproxy() is None, reason="MAVProxy not installed (pip install --no-deps MAVProxy)")
async def test_the_recipe_flies_through_mavproxy_with_the_sensor_on_its_own_port(tmp_path: Path) -> None:
    serial0, serial1 = free_port(), free_port()
    service_port = free_port(socket.SOCK_DGRAM)
    raw = recipe_config()
    raw["link"]["connect"] = raw["link"]["connect"].replace(str(DOC_PORT), str(service_port))
    raw["autopilot"] |= {"arm": True, "takeoff_alt_m": 5.0}
    raw["cycle"] = {"time_scale": SPEEDUP}
    cfg = config_from_mapping(raw)

    autopilot = await Simulator.start(
        SimConfig(
            links=[f"tcpin:127.0.0.1:{serial0}", f"tcpin:127.0.0.1:{serial1}"],
            profile="ardupilot",
            sensor=RangeSensorConfig(messages=frozenset()),  # SITL has no obstacles and no range sensor
            speedup=SPEEDUP,
        )
    )
    mavproxy = _mavproxy()
    assert mavproxy is not None
    proxy = await asyncio.create_subprocess_exec(
        sys.executable, "-u", mavproxy, f"--master=tcp:127.0.0.1:{serial0}", f"--out=udp:127.0.0.1:{service_port}",
        "--daemon", "--non-interactive", f"--state-basedir={tmp_path}",
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL, cwd=tmp_path,
    )  # fmt: skip
    sensor = await SensorSimulator.start(
        SensorOnlyConfig(
            autopilot=f"tcp:127.0.0.1:{serial1}",
            outputs=(f"udpout:127.0.0.1:{service_port}",),
            world=load_world("forest"),
        )
    )
    svc = await CompanionService.open(cfg, clock=SimulatorClock(SPEEDUP))
    assert isinstance(svc.clock, SimulatorClock)
    svc.clock.follow(autopilot)
    try:
        async with asyncio.TaskGroup() as tg:
            task = tg.create_task(svc.run())
            try:
                await until(
                    lambda: svc.navigator.state is State.ARRIVED or autopilot.error is not None,
                    12 * HANG_S,
                    "arrived at 22, 22",
                )
                assert autopilot.error is None, f"the simulated autopilot failed: {autopilot.error!r}"
            finally:
                svc.stop()
                await task
        assert svc.counters.rejected_ranges == 0 and svc.result().steps > 0
        result = sensor.result()
        assert result["scans"] > 0
        assert not result["collided"]
        assert result["min_clearance_m"] >= 0.35  # vehicle radius 0.25 m + the default 0.1 m margin
        assert autopilot.engine.startup.origin_t_s is not None  # it waited for the EKF origin
        assert autopilot.engine.own_id_drops == 0
    finally:
        await sensor.aclose()
        if proxy.returncode is None:
            proxy.terminate()
            await proxy.wait()
        await autopilot.aclose()

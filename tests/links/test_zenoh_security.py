"""Zenoh mutual TLS and access control with the example configs in deploy/, on loopback, with certificates made
here by deploy/zenoh-certs.sh (openssl): a router with TLS + ACL, a sensor that may publish ranges, an operator that
may publish goals, an intruder (same CA, other CN) whose publications are denied, and the real service connecting
over TLS with ``[zenoh] config_file``."""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from apf_companion.config import config_from_mapping
from apf_companion.errors import ConfigError, LinkError
from apf_companion.links.zenoh import Overflow, ZenohConfig, ZenohLink, ZenohSubscription
from apf_companion.perception import GoalCommand, encode_goal_json
from apf_companion.service import CompanionService
from tests.conftest import HANG_S, free_port, until

pytestmark = [
    pytest.mark.timeout(90),
    pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl CLI to make certificates"),
]

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
PKI_IN_EXAMPLES = "/etc/apf-companion/zenoh/"
RANGES = "apf/sensors/range0/ranges"
GOAL = "apf/cmd/goal"
STATUS = "apf/status"


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("pki")
    subprocess.run(
        [str(DEPLOY / "zenoh-certs.sh"), str(out), "companion", "sensor", "operator", "intruder"],
        check=True,
        capture_output=True,
        timeout=60,
    )
    return out


@pytest.fixture(scope="module")
def other_pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A second, unrelated CA with a client called "sensor"."""
    out = tmp_path_factory.mktemp("other-pki")
    subprocess.run([str(DEPLOY / "zenoh-certs.sh"), str(out), "sensor"], check=True, capture_output=True, timeout=60)
    return out


def example(name: str, pki: Path, port: int, dest: Path, *, cert: str | None = None) -> Path:
    """deploy/NAME with the PKI paths pointing at ``pki``, port 7447 replaced, and (client files) ``cert`` as the
    client certificate."""
    text = (DEPLOY / name).read_text().replace(PKI_IN_EXAMPLES, f"{pki}/").replace(":7447", f":{port}")
    if cert is not None:
        text = text.replace(f"{pki}/sensor.pem", f"{pki}/{cert}.pem").replace(
            f"{pki}/sensor-key.pem", f"{pki}/{cert}-key.pem"
        )
    path = dest / f"{cert or 'x'}-{name}"
    path.write_text(text)
    return path


async def _open_raw(path: Path) -> zenoh.Session:
    return await asyncio.to_thread(zenoh.open, zenoh.Config.from_file(str(path)))


async def _close_raw(session: zenoh.Session) -> None:
    await asyncio.to_thread(session.close)


@pytest.fixture
async def router(pki: Path, tmp_path: Path) -> AsyncIterator[int]:
    port = free_port()
    session = await _open_raw(example("zenoh-router-tls-acl.json5", pki, port, tmp_path))
    try:
        yield port
    finally:
        await _close_raw(session)


def _companion_cfg(pki: Path, port: int, dest: Path) -> ZenohConfig:
    return ZenohConfig(
        mode="client",
        connect=(f"tls/127.0.0.1:{port}",),
        config_file=str(example("zenoh-companion-tls.json5", pki, port, dest)),
    )


def test_example_configs_parse_with_multicast_off(pki: Path, tmp_path: Path) -> None:
    for name in ("zenoh-router-tls-acl.json5", "zenoh-client-tls.json5", "zenoh-companion-tls.json5"):
        conf = zenoh.Config.from_file(str(example(name, pki, 7447, tmp_path)))  # zenoh rejects unknown keys
        enabled = json.loads(conf.get_json("scouting/multicast/enabled"))
        assert enabled is False or name == "zenoh-companion-tls.json5"  # the service forces it off itself
        for key in ("listen/endpoints", "connect/endpoints"):
            endpoints = json.loads(conf.get_json(key))
            if isinstance(endpoints, list):
                assert all(ep.startswith("tls/127.0.0.1:") for ep in endpoints), endpoints
    acl = json.loads(
        zenoh.Config.from_file(str(example("zenoh-router-tls-acl.json5", pki, 1, tmp_path))).get_json("access_control")
    )
    assert acl["enabled"] is True
    assert acl["default_permission"] == "deny"


async def _collect(sub: ZenohSubscription, into: list[tuple[str, str]]) -> None:
    async for sample in sub:
        into.append((sample.key_expr, sample.payload.decode()))


REPEAT_S = 0.05  # how often ``_until`` repeats its action: a rate, not a wait


async def _until(cond: Callable[[], bool], action: Callable[[], None], timeout_s: float = HANG_S) -> None:
    """Repeat ``action`` every ``REPEAT_S`` until ``cond()`` (samples of a best-effort put may be lost, so the
    put is repeated); the wait is on the condition, ``timeout_s`` only bounds a hang."""
    async with asyncio.timeout(timeout_s):
        while not cond():
            action()
            await asyncio.sleep(REPEAT_S)  # pacing of the repeated action


async def test_acl_only_sensor_publishes_ranges_only_operator_publishes_goals(
    pki: Path, router: int, tmp_path: Path
) -> None:
    got: list[tuple[str, str]] = []
    clients = {
        name: await _open_raw(example("zenoh-client-tls.json5", pki, router, tmp_path, cert=name))
        for name in ("sensor", "operator", "intruder")
    }
    try:
        async with await ZenohLink.open(_companion_cfg(pki, router, tmp_path)) as companion:
            subs = [
                await companion.subscribe(RANGES, overflow=Overflow.FIFO, capacity=10_000),
                await companion.subscribe(GOAL, overflow=Overflow.FIFO, capacity=10_000),
            ]
            readers = [asyncio.create_task(_collect(s, got)) for s in subs]

            def publish_round() -> None:
                # Every client tries both topics each round; the allowed samples come last in the round.
                for name, session in clients.items():
                    for key in (RANGES, GOAL):
                        session.put(key, f"{name}")

            def allowed_seen() -> bool:
                return sum(g == (RANGES, "sensor") for g in got) >= 5 and sum(g == (GOAL, "operator") for g in got) >= 5

            await _until(allowed_seen, publish_round)
            for task in readers:
                task.cancel()
    finally:
        for session in clients.values():
            await _close_raw(session)
    assert set(got) == {(RANGES, "sensor"), (GOAL, "operator")}, set(got)


async def test_clients_without_a_certificate_of_the_ca_cannot_connect(
    pki: Path, other_pki: Path, router: int, tmp_path: Path
) -> None:
    # No client certificate at all.
    no_cert = tmp_path / "no-cert.json5"
    text = example("zenoh-client-tls.json5", pki, router, tmp_path).read_text()
    no_cert.write_text("\n".join(line for line in text.splitlines() if "connect_" not in line))
    # A certificate called "sensor", signed by another CA (the client trusts our router's CA).
    foreign = tmp_path / "foreign.json5"
    foreign.write_text(text.replace(f"{pki}/sensor", f"{other_pki}/sensor"))
    for path in (no_cert, foreign):
        conf = zenoh.Config.from_file(str(path))
        conf.insert_json5("connect/timeout_ms", "2000")
        with pytest.raises(zenoh.ZError):
            session = await asyncio.to_thread(zenoh.open, conf)
            await _close_raw(session)
    # And the companion's link, with a foreign certificate, reports a LinkError.
    companion_foreign = tmp_path / "companion-foreign.json5"
    companion_foreign.write_text(
        example("zenoh-companion-tls.json5", pki, router, tmp_path)
        .read_text()
        .replace(f"{pki}/companion", f"{other_pki}/sensor")
    )
    bad = ZenohConfig(mode="client", connect=(f"tls/127.0.0.1:{router}",), config_file=str(companion_foreign))
    with pytest.raises(LinkError):
        await ZenohLink.open(bad, timeout=20.0)


async def test_service_connects_over_tls_and_acl_filters_its_inputs(pki: Path, router: int, tmp_path: Path) -> None:
    companion_file = example("zenoh-companion-tls.json5", pki, router, tmp_path)
    (tmp_path / "svc").mkdir()
    (tmp_path / "svc" / "zenoh.json5").write_text(companion_file.read_text())
    config = config_from_mapping(
        {
            "link": {"connect": "udpin:127.0.0.1:0"},  # no autopilot: goals are refused, but counted
            "zenoh": {
                "enabled": True,
                "mode": "client",
                "connect": [f"tls/127.0.0.1:{router}"],
                "config_file": "zenoh.json5",  # relative to the config's directory
                "status_rate_hz": 20.0,
            },
        },
        base_dir=tmp_path / "svc",
    )
    svc = await CompanionService.open(config)
    operator = await _open_raw(example("zenoh-client-tls.json5", pki, router, tmp_path, cert="operator"))
    intruder = await _open_raw(example("zenoh-client-tls.json5", pki, router, tmp_path, cert="intruder"))
    statuses: list[dict[str, Any]] = []
    intruder_statuses: list[bytes] = []
    operator.declare_subscriber(STATUS, lambda s: statuses.append(json.loads(s.payload.to_bytes())))
    intruder.declare_subscriber(STATUS, lambda s: intruder_statuses.append(s.payload.to_bytes()))
    goal = encode_goal_json(GoalCommand(pos_ned_m=np.array([5.0, 5.0, -5.0])))

    def goals_heard() -> int:
        return svc.counters.goals + svc.counters.bad_goals

    try:
        async with asyncio.TaskGroup() as tg:
            run = tg.create_task(svc.run())
            try:
                # The status reaches the operator through the TLS router: the service is connected.
                await _until(lambda: len(statuses) >= 3, lambda: None)
                assert statuses[-1]["schema"] == "apf.status/1"
                # The operator's goals reach the service (refused there without an autopilot, but counted) ...
                await _until(lambda: goals_heard() >= 1, lambda: operator.put(GOAL, goal))
                h0 = await _lockstep(operator, goal, goals_heard)
                # ... the intruder's 20 do not: the operator's next two, sent after them, are all that arrives.
                for _ in range(20):
                    intruder.put(GOAL, goal)
                    intruder.put(STATUS, b'{"state": "spoofed"}')
                h1 = await _lockstep(operator, goal, goals_heard, rounds=2)
                assert h1 == h0 + 2
                assert statuses
                assert all(s.get("state") != "spoofed" for s in statuses)
            finally:
                svc.stop()
                await run
    finally:
        await _close_raw(operator)
        await _close_raw(intruder)
    # The intruder may not read the service's status either (zenoh hands a session its own puts locally).
    assert statuses
    assert [s for s in intruder_statuses if b"spoofed" not in s] == []


async def _counted_after(heard: Callable[[], int], before: int) -> None:
    await until(lambda: heard() != before, HANG_S, "the service counted the goal")


async def _lockstep(session: zenoh.Session, goal: bytes, heard: Callable[[], int], rounds: int = 3) -> int:
    """Put one goal at a time and wait until the service has counted it (``rounds`` in a row each counted
    exactly once, so nothing else is in flight); returns the count."""
    exact = 0
    while exact < rounds:
        before = heard()
        session.put(GOAL, goal)
        await _counted_after(heard, before)
        exact = exact + 1 if heard() == before + 1 else 0
    return heard()


@pytest.mark.parametrize(
    ("content", "fragment"),
    [
        ('{ mode: "router" }', "sets 'mode'"),
        ('{ listen: { endpoints: ["tcp/127.0.0.1:7447"] } }', "sets 'listen/endpoints'"),
        ('{ connect: { endpoints: ["tcp/10.0.0.1:7447"] } }', "sets 'connect/endpoints'"),
        ("{ scouting: { multicast: { enabled: true } } }", "multicast"),
        ("{ transprt: {} }", "unknown field"),
        ("{ transport: ", "config_file"),
    ],
)
def test_config_file_is_validated(tmp_path: Path, content: str, fragment: str) -> None:
    path = tmp_path / "z.json5"
    path.write_text(content)
    with pytest.raises(ConfigError, match="config_file") as info:
        ZenohConfig(mode="client", connect=("tls/127.0.0.1:7447",), config_file=str(path))
    assert fragment in str(info.value)
    with pytest.raises(ConfigError, match="config_file"):
        ZenohConfig(mode="client", connect=("tls/127.0.0.1:7447",), config_file=str(tmp_path / "missing.json5"))


def test_config_file_keeps_scouting_off_and_endpoints(tmp_path: Path) -> None:
    path = tmp_path / "z.json5"
    path.write_text("{ scouting: { multicast: { enabled: false } }, transport: { link: { tx: { lease: 5000 } } } }")
    conf = ZenohConfig(mode="client", connect=("tls/127.0.0.1:7447",), config_file=str(path)).to_zenoh()
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("connect/endpoints")) == ["tls/127.0.0.1:7447"]
    assert json.loads(conf.get_json("transport/link/tx/lease")) == 5000
    assert json.loads(conf.get_json("mode")) == "client"


def test_service_config_takes_tls_endpoints_and_config_file() -> None:
    cfg = config_from_mapping(
        {"zenoh": {"enabled": True, "mode": "client", "connect": ["tls/127.0.0.1:7447"], "config_file": "z.json5"}}
    )
    assert cfg.zenoh.config_file == "z.json5"
    with pytest.raises(ConfigError, match=r"zenoh\.connect"):
        config_from_mapping({"zenoh": {"enabled": True, "connect": ["quic/127.0.0.1:7447"]}})
    with pytest.raises(ConfigError, match="config_file"):
        config_from_mapping({"zenoh": {"config_file": 3}})

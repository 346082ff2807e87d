"""Which streams the service asks for, and when it asks again (apf_companion/streams.py), without sockets."""

from __future__ import annotations

import itertools
import logging

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.autopilot import Autopilot
from apf_companion.config import config_from_mapping
from apf_companion.links.messages import Heartbeat, LocalPositionNed, Source
from apf_companion.service import CompanionService
from apf_companion.streams import STREAM_RETRY_S, STREAM_STALE_S, StreamKeeper, wanted_streams

LPOS = m.MAVLINK_MSG_ID_LOCAL_POSITION_NED
ATT = m.MAVLINK_MSG_ID_ATTITUDE
AP = Source(1, 1)


def test_wanted_streams_per_profile() -> None:
    ardupilot = wanted_streams(Autopilot.ARDUPILOT, 20.0)
    assert ardupilot[LPOS] == ardupilot[ATT] == 20.0
    assert m.MAVLINK_MSG_ID_GLOBAL_POSITION_INT in ardupilot and m.MAVLINK_MSG_ID_EKF_STATUS_REPORT in ardupilot
    assert m.MAVLINK_MSG_ID_EKF_STATUS_REPORT not in wanted_streams(Autopilot.PX4, 20.0)


def test_asks_once_then_again_only_for_a_missing_stream_and_after_a_restart() -> None:
    keeper = StreamKeeper({LPOS: 10.0, ATT: 10.0})
    assert keeper.due(0.0) == {LPOS: 10.0, ATT: 10.0}
    t = 0.0
    while t < 20.0:  # both arrive: never asked again
        t += 0.1
        keeper.heard(LPOS, t)
        keeper.heard(ATT, t)
        assert keeper.due(t) == {}
    # LOCAL_POSITION_NED stops (ArduCopter before its EKF origin, or a stream dropped): asked again, not too often
    asked = []
    while t < 40.0:
        t += 0.1
        keeper.heard(ATT, t)
        if keeper.due(t):
            asked.append(t)
    assert asked and asked[0] - 20.0 <= STREAM_STALE_S + 0.2
    assert all(b - a >= STREAM_RETRY_S - 1e-9 for a, b in itertools.pairwise(asked))
    # a reboot: asked at once, whatever the retry timer says
    keeper.restart()
    assert keeper.due(t + 0.1) == {LPOS: 10.0, ATT: 10.0}
    assert keeper.requests == len(asked) + 2


def test_a_rebooting_autopilot_is_asked_again() -> None:
    """HEARTBEAT.system_status BOOT (a reboot forgets every stream request): the handler asks again at once."""
    svc = CompanionService(config_from_mapping({"link": {"connect": "udpin:127.0.0.1:0"}}))
    handlers = svc.handlers

    def heartbeat(t: float, status: int) -> None:
        hb = Heartbeat(src=AP, type=m.MAV_TYPE_QUADROTOR, autopilot=3, base_mode=1, custom_mode=0, system_status=status)
        handlers.handle(hb, t)

    heartbeat(0.0, m.MAV_STATE_STANDBY)
    assert handlers.streams.requests == 1
    for k in range(1, 4):
        handlers.handle(LocalPositionNed(src=AP, time_boot_ms=1000 * k, x=0.0, y=0.0, z=0.0, vx=0, vy=0, vz=0), k)
        heartbeat(float(k), m.MAV_STATE_STANDBY)
    assert handlers.streams.requests == 1  # nothing new to ask (the other streams are missing, but not for long)
    heartbeat(3.5, m.MAV_STATE_BOOT)
    assert handlers.streams.requests == 2


def _feed(keeper: StreamKeeper, t0: float, t1: float, rates_hz: dict[int, float]) -> list[float]:
    """Messages at ``rates_hz`` from ``t0`` to ``t1`` (steps of 10 ms), ``due`` once a second: when it asked."""
    asked: list[float] = []
    step = 0
    next_at = dict.fromkeys(rates_hz, t0)
    while True:
        t = t0 + step * 0.01
        if t > t1:
            return asked
        for msg_id, hz in rates_hz.items():
            if t >= next_at[msg_id] - 1e-9:
                keeper.heard(msg_id, t)
                next_at[msg_id] += 1.0 / hz
        if step % 100 == 0 and keeper.due(t):
            asked.append(t)
        step += 1


def test_a_stream_slowed_by_someone_else_is_asked_for_again_at_most_every_retry() -> None:
    """A ground station on the same link sends REQUEST_DATA_STREAM (MAVProxy: 4 Hz, at start and every 15 s) and
    ArduPilot sends our 20 Hz pose at 4 Hz: it arrives, so it is not missing, and nothing asked again before."""
    keeper = StreamKeeper({LPOS: 20.0, ATT: 20.0})
    assert keeper.due(0.0)
    assert _feed(keeper, 0.0, 30.0, {LPOS: 20.0, ATT: 20.0}) == []  # at the rate asked: never again
    assert keeper.slow() == {} and keeper.measured_hz[LPOS] > 19.0
    asked = _feed(keeper, 30.0, 60.0, {LPOS: 4.0, ATT: 20.0})  # the pose slowed down
    assert asked and asked[0] <= 30.0 + 2 * 5.0 + 1.0  # within two rate windows
    assert all(b - a >= STREAM_RETRY_S - 1e-9 for a, b in itertools.pairwise(asked))
    assert set(keeper.last_slow) == {LPOS} and 3.0 < keeper.last_slow[LPOS] < 5.0
    assert keeper.slow_requests == len(asked) and keeper.requests == len(asked) + 1
    assert _feed(keeper, 60.0, 90.0, {LPOS: 20.0, ATT: 20.0}) == []  # the request took: quiet again
    assert _feed(keeper, 90.0, 120.0, {ATT: 20.0}) != []  # missing (not slow) is the old rule
    assert keeper.slow_requests == len(asked)


def test_slowed_streams_are_counted_and_said_in_one_warning_a_minute(caplog: pytest.LogCaptureFixture) -> None:
    svc = CompanionService(config_from_mapping({"link": {"connect": "udpin:127.0.0.1:0"}}))
    handlers, t = svc.handlers, 0.0
    for k in range(130):  # 130 s: a heartbeat a second, the pose at 4 Hz of the 20 Hz asked, the rest on time
        t = float(k)
        hb = Heartbeat(src=AP, type=m.MAV_TYPE_QUADROTOR, autopilot=3, base_mode=1, custom_mode=0, system_status=4)
        with caplog.at_level(logging.INFO, logger="apf_companion.handlers"):
            handlers.handle(hb, t)
        for j in range(20):
            tj = t + j * 0.05
            if j % 5 == 0:
                pose = LocalPositionNed(src=AP, time_boot_ms=int(tj * 1000), x=0.0, y=0.0, z=0.0, vx=0, vy=0, vz=0)
                handlers.handle(pose, tj)
            for msg_id in handlers.streams.rates_hz:
                if msg_id != LPOS and j % max(1, round(20 / handlers.streams.rates_hz[msg_id])) == 0:
                    handlers.streams.heard(msg_id, tj)
    slow = [r for r in caplog.records if r.getMessage() == "streams.slow"]
    assert svc.counters.slow_streams >= 10  # asked again every STREAM_RETRY_S
    assert len(slow) == 3 and all(r.levelno == logging.WARNING for r in slow)  # at once, then once a minute
    assert slow[0].__dict__["streams"] == {"LOCAL_POSITION_NED": "4.0 of 20 Hz"}
    assert "REQUEST_DATA_STREAM" in slow[0].__dict__["hint"]
    assert svc.reporter.counts()["slow_streams"] == svc.counters.slow_streams

"""Which streams the service asks for, and when it asks again (apf_companion/streams.py), without sockets."""

from __future__ import annotations

import itertools

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

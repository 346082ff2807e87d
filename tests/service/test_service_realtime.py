"""SCHED_FIFO for the service process, best effort (apf_companion/realtime.py). Each case runs in a child process:
the test process's own scheduling stays as it was."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys

import pytest

from apf_companion.config import config_from_mapping
from apf_companion.errors import ConfigError
from apf_companion.realtime import Scheduling, request_realtime

pytestmark = pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="Linux scheduling")

_CHILD = """
import json, os, resource, sys
from apf_companion.realtime import request_realtime
limit, drop = int(sys.argv[1]), sys.argv[2] == "drop"
if drop and os.geteuid() == 0:
    os.setgid(65534)
    os.setuid(65534)  # nobody: no CAP_SYS_NICE, so RLIMIT_RTPRIO decides
hard = resource.getrlimit(resource.RLIMIT_RTPRIO)[1]
try:  # as LimitRTPRIO= does (raising the hard limit needs root)
    resource.setrlimit(resource.RLIMIT_RTPRIO, (limit, hard if hard == resource.RLIM_INFINITY else max(hard, limit)))
except (ValueError, OSError):
    pass
s = request_realtime(5)
print(json.dumps({"fifo": s.fifo_priority, "refused": s.refused, "describe": s.describe(),
                  "policy": os.sched_getscheduler(0), "priority": os.sched_getparam(0).sched_priority}))
"""


def _child(limit: int, *, drop: bool) -> dict[str, object]:
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, str(limit), "drop" if drop else "keep"],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    result: dict[str, object] = json.loads(out.stdout)
    return result


def test_without_an_rtprio_allowance_the_request_is_refused_and_the_process_stays_normal() -> None:
    got = _child(0, drop=True)
    assert got["fifo"] == 0 and got["policy"] == os.SCHED_OTHER
    assert "RLIMIT_RTPRIO" in str(got["refused"]) and str(got["describe"]).startswith("normal (SCHED_FIFO refused")


def test_with_the_deploy_units_allowance_the_process_runs_sched_fifo() -> None:
    hard = resource.getrlimit(resource.RLIMIT_RTPRIO)[1]
    if hard != resource.RLIM_INFINITY and hard < 5 and os.geteuid() != 0:
        pytest.skip("this machine's hard RLIMIT_RTPRIO is below 5 (the unit's LimitRTPRIO=5 grants it)")
    got = _child(5, drop=False)
    if got["fifo"] == 0:  # a container without real-time scheduling for anyone: the refusal is reported
        assert got["refused"] and got["policy"] == os.SCHED_OTHER
        pytest.skip(f"real-time scheduling refused here: {got['refused']}")
    assert got["policy"] == os.SCHED_FIFO and got["priority"] == 5
    assert got["describe"] == "SCHED_FIFO priority 5"


def test_priority_zero_asks_nothing() -> None:
    assert request_realtime(0) == Scheduling(0)
    assert Scheduling(0).describe() == "normal"


@pytest.mark.parametrize("bad", [-1, 100, 2.5, True, "5"])
def test_the_config_key_is_an_integer_in_0_to_99(bad: object) -> None:
    with pytest.raises(ConfigError, match=r"cycle\.realtime_priority"):
        config_from_mapping({"cycle": {"realtime_priority": bad}})
    assert config_from_mapping({"cycle": {"realtime_priority": 0}}).cycle.realtime_priority == 0

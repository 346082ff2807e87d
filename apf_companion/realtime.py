"""The service process's CPU scheduling: SCHED_FIFO at a low real-time priority, when the system allows it.

The planning cycle is short (about 1 ms) and rare (20 Hz: 2-5 % of a core), but under the normal scheduler it
waits behind every other runnable process: with two busy processes on a 2-core companion computer, the in-service
sensor-to-setpoint p99 was 10-15 ms at Nice=-5, and 1.1-1.2 ms at SCHED_FIFO priority 10
(``benchmarks/bench_service_latency.py --fifo``; docs/benchmarks.md). A SCHED_FIFO process runs as soon as it is
woken, ahead of every normal process.

The default priority, 5, stays below every thread of ArduPilot's own Linux HAL but its Lua scripting thread
(libraries/AP_HAL_Linux/Scheduler.cpp: APM_LINUX_MAIN_PRIORITY 12, APM_LINUX_IO_PRIORITY 10, timers 15, UART 14,
RC input 13, APM_LINUX_SCRIPTING_PRIORITY 1), so on a board that also runs the autopilot (Navio2, BBBmini) the
autopilot still comes first. A runaway real-time loop cannot take the whole machine: the kernel leaves normal
processes 5 % of each second by default (``/proc/sys/kernel/sched_rt_runtime_us`` = 950000), and systemd's
watchdog ends a service whose cycles stop.

The request is best effort. An unprivileged process may use SCHED_FIFO up to its RLIMIT_RTPRIO
(deploy/apf-companion.service grants 5 with ``LimitRTPRIO=5``, no capability needed); where that is 0, or the
kernel's real-time group scheduling gives the service's cgroup no budget, the kernel refuses (EPERM) and the
service runs under the normal scheduler, saying so in its start log line.
"""

from __future__ import annotations

import errno
import os
from dataclasses import dataclass

__all__ = ["Scheduling", "request_realtime"]


@dataclass(frozen=True, slots=True)
class Scheduling:
    """What the process runs under after ``request_realtime``: the SCHED_FIFO priority (0: the normal scheduler)
    and, where the request was refused, why."""

    fifo_priority: int
    refused: str | None = None

    def describe(self) -> str:
        if self.fifo_priority > 0:
            return f"SCHED_FIFO priority {self.fifo_priority}"
        return "normal" if self.refused is None else f"normal (SCHED_FIFO refused: {self.refused})"


def request_realtime(priority: int) -> Scheduling:
    """Ask for SCHED_FIFO at ``priority`` (1-99) for this process; 0 asks nothing. Never raises: a refusal is
    returned (``Scheduling.refused``) and the process keeps the normal scheduler."""
    if priority <= 0:
        return Scheduling(0)
    setter = getattr(os, "sched_setscheduler", None)
    if setter is None:  # not Linux
        return Scheduling(0, "not supported on this system")
    try:
        setter(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as err:
        hint = " (RLIMIT_RTPRIO; the deploy unit sets LimitRTPRIO)" if err.errno == errno.EPERM else ""
        return Scheduling(0, f"{os.strerror(err.errno or 0)}{hint}")
    return Scheduling(priority)

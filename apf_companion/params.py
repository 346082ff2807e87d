"""Planner and safety parameters over MAVLink: PARAM_REQUEST_LIST / PARAM_REQUEST_READ / PARAM_SET -> PARAM_VALUE.

``PARAMS`` is the one table from MAVLink parameter names (at most 16 characters) to config keys. A PARAM_SET is
validated exactly as the TOML file is: the section's frozen dataclass is rebuilt with the new value (its
``__post_init__`` range checks) and the planner's parameters are rebuilt from the new config (``planner_params``:
the planner's own checks). Refused: PARAM_VALUE carries the old value, every time (the ground station waits for it
and sends the PARAM_SET again without it), and a STATUSTEXT and a WARNING ``param.refused`` say why: the first at
once, then at most one each per ``REFUSED_INTERVAL_S`` of the service clock, saying how many refusals in between
went unsaid. A review sent 300 refused PARAM_SETs in 0.65 s: 900 STATUSTEXT chunks went towards the autopilot
(seconds of a 57600-baud link, queued in front of the setpoints) and 300 WARNING lines.

Accepted: PARAM_VALUE carries the new value at once, and the change goes into service before the next planning
cycle (``apply_pending``, which the service calls before every cycle): one planner build for every change accepted
since the last cycle. A value equal to the one in force changes nothing. Each accepted one is logged (INFO
``param.set`` with the old and the new value) as the refused ones are: the first at once, then at most one line per
``SET_LOG_INTERVAL_S`` carrying how many went unlogged (those at DEBUG). Before, every accepted PARAM_SET built the
planner (bapf-nav: about 1.2 ms, its maps) and logged a line, so a flood of them cost a core and flooded the log.
ArduPilot's own PARAM_SET also sets the value at once and defers the costly part: ``AP_Param::save``
(libraries/AP_Param/AP_Param.cpp) queues the storage write for the IO thread and drops a repeat of the parameter at
the queue's head ("flooding the save queue with one parameter").

Nothing is written to the config file: a restart returns to the TOML values.

The protocol follows ArduPilot's ``libraries/GCS_MAVLink/GCS_Param.cpp``:

- PARAM_REQUEST_LIST: every parameter, ``param_index`` 0..count-1 and ``param_count``, paced (a few per tick:
  ``queued_param_send`` caps a burst at 5 without flow control);
- PARAM_REQUEST_READ: by ``param_index`` when it is not -1, else by name; an unknown one gets no answer;
- PARAM_SET: an unknown name gets no answer; the reply is PARAM_VALUE with ``param_index`` -1
  (``GCS::send_parameter_value``); a refused one gets the old value in it (``handle_param_set``: "send the readonly
  value" after its STATUSTEXT "Param write denied");
- integers travel as the float value of the integer (ArduPilot's cast encoding, not PX4's byte-wise one).
"""

from __future__ import annotations

import asyncio
import collections
import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.builders import build_planner, planner_params
from apf_companion.config import ServiceConfig
from apf_companion.errors import ConfigError
from apf_companion.links.messages import ParamRequestList, ParamRequestRead, ParamSet
from apf_companion.outbox import Outbox
from apf_companion.perception.ratelog import RateLimitedLog, Throttle
from apf_companion.planning import PlannerParams
from apf_companion.reporter import ServiceCounters

__all__ = ["PARAMS", "ParamServer", "ParamSpec", "config_with", "param_value"]

log = logging.getLogger(__name__)

REAL32 = mavlink.MAV_PARAM_TYPE_REAL32
INT32 = mavlink.MAV_PARAM_TYPE_INT32
NAME_MAX = 16  # PARAM_*.param_id: char[16], not NUL-terminated when full
INT32_MAX = 2**31 - 1
PLANNER_PARAMS = "planner.params."
LIST_BURST = 5  # PARAM_VALUEs of a list per burst (GCS_Param.cpp queued_param_send: 5 without flow control)
LIST_PERIOD_S = 0.02  # between bursts [wall s]: 250 PARAM_VALUE/s, a 24-parameter list in about 0.1 s
# A refused PARAM_SET's STATUSTEXT and WARNING: at most one each per this long [service s]. A STATUSTEXT is up to
# 4 chunks (~260 bytes): under 5 % of a 57600-baud link at the most, and a person setting values by hand gets
# every refusal said.
REFUSED_INTERVAL_S = 1.0
SET_LOG_INTERVAL_S = 1.0  # an accepted PARAM_SET's INFO line: at most one per this long [service s]


@dataclass(frozen=True, slots=True)
class ParamSpec:
    """One MAVLink parameter: its name, the config key it stands for and its MAV_PARAM_TYPE."""

    name: str
    key: str  # "cycle.cruise_speed_m_s", or "planner.params.rho_l_m" (a PlannerParams field)
    mav_type: int  # MAV_PARAM_TYPE_REAL32 or MAV_PARAM_TYPE_INT32 (booleans: 0 / 1)

    def __post_init__(self) -> None:
        if not 0 < len(self.name) <= NAME_MAX or not self.name.isascii():
            msg = f"internal: MAVLink parameter name {self.name!r} is not 1-16 ASCII characters"
            raise AssertionError(msg)


PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("APF_RHO_L", "planner.params.rho_l_m", REAL32),
    ParamSpec("APF_RHO_U", "planner.params.rho_u_m", REAL32),
    ParamSpec("APF_STEP", "planner.params.step_m", REAL32),
    ParamSpec("APF_N_BACT", "planner.params.n_bacteria", INT32),
    ParamSpec("APF_MU_MIN", "planner.params.mu_min", INT32),
    ParamSpec("APF_MU_MAX", "planner.params.mu_max", INT32),
    ParamSpec("APF_ALPHA_T", "planner.params.alpha_t", REAL32),
    ParamSpec("APF_ALPHA_O", "planner.params.alpha_o", REAL32),
    ParamSpec("APF_VEH_RADIUS", "planner.params.vehicle_radius_m", REAL32),
    ParamSpec("APF_MARGIN", "planner.params.safety_margin_m", REAL32),
    ParamSpec("APF_NOISE_STD", "planner.params.noise_std_m", REAL32),
    ParamSpec("APF_NOISE_K", "planner.params.noise_k", REAL32),
    ParamSpec("APF_RW_BUDGET", "planner.random_walk_budget", INT32),
    ParamSpec("APF_PROG_TMO", "planner.progress_timeout_s", REAL32),
    ParamSpec("APF_FENCE_POLL", "planner.fence_poll_s", REAL32),
    ParamSpec("APF_CRUISE_SPD", "cycle.cruise_speed_m_s", REAL32),
    ParamSpec("APF_ARRIVE_RAD", "cycle.arrival_radius_m", REAL32),
    ParamSpec("APF_REPLAN_RAD", "cycle.replan_radius_m", REAL32),
    ParamSpec("APF_POSE_AGE", "cycle.pose_max_age_s", REAL32),
    ParamSpec("APF_RANGE_AGE", "cycle.ranges_max_age_s", REAL32),
    ParamSpec("APF_GUID_TMO", "safety.guid_timeout_s", REAL32),
    ParamSpec("APF_SILENT_DRIFT", "safety.silent_drift_m", REAL32),
    ParamSpec("APF_RESET_HOLD", "safety.reset_hold_s", REAL32),
    ParamSpec("APF_RESUME_LINK", "safety.resume_after_link_lost", INT32),
)
"""Every parameter the companion answers for, in ``param_index`` order. Only keys the navigator and planner read
(``apf_companion.builders.navigator_params``, ``build_planner``) are here: they can change between two cycles.
Perception and link keys need a restart."""

_BY_NAME = {p.name: p for p in PARAMS}


def _current(config: ServiceConfig, planner: PlannerParams, spec: ParamSpec) -> Any:
    if spec.key.startswith(PLANNER_PARAMS):
        return getattr(planner, spec.key.removeprefix(PLANNER_PARAMS))
    section, name = spec.key.split(".")
    return getattr(getattr(config, section), name)


def param_value(config: ServiceConfig, planner: PlannerParams, spec: ParamSpec) -> float:
    """The value of ``spec`` as PARAM_VALUE carries it (a float; integers and booleans cast); ``planner``: the
    planner's parameters (``planner_params(config)``)."""
    return float(_current(config, planner, spec))


def _typed(spec: ParamSpec, old: Any, value: float) -> Any:
    """The wire value as the config field's type; ConfigError naming the key when it cannot be."""
    if not math.isfinite(value):
        msg = f"{spec.key} must be finite, got {value!r}"
        raise ConfigError(msg)
    if isinstance(old, bool):
        if value not in (0.0, 1.0):
            msg = f"{spec.key} must be 0 or 1 (false / true), got {value!r}"
            raise ConfigError(msg)
        return value == 1.0
    if isinstance(old, int):
        if not value.is_integer() or abs(value) > INT32_MAX:
            msg = f"{spec.key} must be an integer, got {value!r}"
            raise ConfigError(msg)
        return int(value)
    return float(str(np.float32(value)))  # the float32 the GCS meant: 0.4, not 0.4000000059604645


def config_with(
    config: ServiceConfig, planner: PlannerParams, spec: ParamSpec, value: float
) -> tuple[ServiceConfig, PlannerParams]:
    """``config`` with ``spec`` set to ``value``, and the planner's parameters from it, validated as the TOML file is
    (``planner``: the planner's parameters now). The planner itself is not built (``build_planner``).

    Raises:
        ConfigError: the value is refused (the message names the key and the allowed range).
    """
    typed = _typed(spec, _current(config, planner, spec), value)
    if spec.key.startswith(PLANNER_PARAMS):
        field = spec.key.removeprefix(PLANNER_PARAMS)
        section = dataclasses.replace(config.planner, params={**config.planner.params, field: typed})
        new = dataclasses.replace(config, planner=section)
    else:
        name, field = spec.key.split(".")
        new = dataclasses.replace(config, **{name: dataclasses.replace(getattr(config, name), **{field: typed})})
    return new, planner_params(new)


class ParamServer:
    """Answers the parameter protocol for the companion component, and puts accepted changes into service.

    Args:
        config: The running configuration.
        planner: The running planner's parameters (``planner_params(config)``).
        outbox: Where PARAM_VALUE goes.
        apply: Puts a config and its planner into service (the service's; between cycles).
        statustext: Sends a STATUSTEXT (the reporter's), for refused values.
        counters: The service's counters (``param_sets_coalesced``).
        build: Builds the planner of a config (``build_planner``).

    ``config`` and ``planner_params`` are the accepted values, those PARAM_VALUE says; they are in service from the
    next cycle on (``apply_pending``).
    """

    def __init__(
        self,
        config: ServiceConfig,
        planner: PlannerParams,
        *,
        outbox: Outbox,
        apply: Callable[[ServiceConfig, Any], None],
        statustext: Callable[[int, str], None],
        counters: ServiceCounters,
        build: Callable[[ServiceConfig], Any] = build_planner,
    ) -> None:
        self.config = config
        self.planner_params = planner
        self.outbox = outbox
        self.counters = counters
        self._apply = apply
        self._build = build
        self._statustext = statustext
        self._in_service = (config, planner)
        self.pending: dict[str, ParamSpec] = {}  # changed by PARAM_SETs accepted since the last ``apply_pending``
        self._pending_sets = 0  # those PARAM_SETs
        self.queue: collections.deque[int] = collections.deque()  # indices of a list request still to send
        self.sets = 0
        self.refused = 0
        self.builds = 0  # planners built for accepted PARAM_SETs
        self._set_log = RateLimitedLog(log, "param.set", SET_LOG_INTERVAL_S, level=logging.INFO)
        self._refused_log = RateLimitedLog(log, "param.refused", REFUSED_INTERVAL_S)
        self._refused_text = Throttle(REFUSED_INTERVAL_S)
        self._wake = asyncio.Event()

    async def run(self) -> None:
        """Send the PARAM_VALUEs of list requests, ``LIST_BURST`` every ``LIST_PERIOD_S`` (the ``apf.params`` task)."""
        while True:
            await self._wake.wait()
            self._wake.clear()
            while self.send_queued(LIST_BURST):
                await asyncio.sleep(LIST_PERIOD_S)

    def handle(self, rec: ParamRequestList | ParamRequestRead | ParamSet, now_s: float) -> None:
        """One request addressed to us, at ``now_s`` on the service clock [s]."""
        if isinstance(rec, ParamRequestList):
            self.queue.clear()  # a new list restarts from index 0 (ArduPilot restarts its queued parameter)
            self.queue.extend(range(len(PARAMS)))
            self._wake.set()
        elif isinstance(rec, ParamRequestRead):
            self._read(rec)
        else:
            self._set(rec, now_s)

    def apply_pending(self) -> bool:
        """Put the changes of the PARAM_SETs accepted since the last call into service, with one planner build for
        all of them (the service calls this before every cycle). Returns whether there were any."""
        if not self.pending:
            return False
        try:
            planner = self._build(self.config)
        except ConfigError as err:  # not expected: planner_params checked each value, and the planners no more
            self._undo(err)
            return False
        self.builds += 1
        self.counters.param_sets_coalesced += self._pending_sets - 1
        self._into_service(self.config, planner)
        return True

    def taken(self, config: ServiceConfig, planner: Any) -> None:
        """``config`` (built from ``self.config``: the pending changes are in it) and its planner go into service now,
        e.g. with the fence's zones; later PARAM_SETs start from it."""
        self.counters.param_sets_coalesced += self._pending_sets  # in service with this build
        self.config, self.planner_params = config, planner.params
        self._into_service(config, planner)

    def send_queued(self, budget: int) -> int:
        """Send up to ``budget`` PARAM_VALUEs of a list request; how many are left."""
        for _ in range(min(budget, len(self.queue))):
            i = self.queue.popleft()
            self._send(PARAMS[i], i)
        return len(self.queue)

    def _into_service(self, config: ServiceConfig, planner: Any) -> None:
        self.pending.clear()
        self._pending_sets = 0
        self._in_service = (config, planner.params)
        self._apply(config, planner)

    def _undo(self, err: ConfigError) -> None:
        """The pending changes could not be built: the values in service stay, and the ground station is told so
        (PARAM_VALUE with the value in force for each changed parameter, and a STATUSTEXT)."""
        changed = list(self.pending.values())
        self.config, self.planner_params = self._in_service
        self.pending.clear()
        self._pending_sets = 0
        log.error("param.not_applied", extra={"params": [s.name for s in changed], "error": str(err)})
        self._statustext(mavlink.MAV_SEVERITY_WARNING, f"params not applied: {err}")
        for spec in changed:
            self._send(spec, -1)

    def _send(self, spec: ParamSpec, index: int) -> None:
        value = param_value(self.config, self.planner_params, spec)
        self.outbox.param_value(spec.name, value, spec.mav_type, len(PARAMS), index)

    def _read(self, rec: ParamRequestRead) -> None:
        if rec.param_index != -1:
            if 0 <= rec.param_index < len(PARAMS):
                self._send(PARAMS[rec.param_index], rec.param_index)
            return
        spec = _BY_NAME.get(rec.param_id)
        if spec is not None:
            self._send(spec, PARAMS.index(spec))

    def _set(self, rec: ParamSet, now_s: float) -> None:
        spec = _BY_NAME.get(rec.param_id)
        if spec is None:
            return  # ArduPilot and PX4 stay silent about a parameter they do not have
        old = param_value(self.config, self.planner_params, spec)
        try:
            config, planner = config_with(self.config, self.planner_params, spec, rec.param_value)
        except ConfigError as err:
            self.refused += 1
            self._refused_log.note(now_s, param=spec.name, value=rec.param_value, error=str(err))
            unsaid = self._refused_text.allow(now_s)
            if unsaid is not None:
                more = f" ({unsaid} more refused, not said)" if unsaid else ""  # before the reason: never cut
                self._statustext(mavlink.MAV_SEVERITY_WARNING, f"{spec.name} refused{more}: {err}")
        else:
            self.sets += 1
            new = param_value(config, planner, spec)
            if new == old:
                self.counters.param_sets_coalesced += 1  # in force already: nothing to build
            else:
                self.config, self.planner_params = config, planner
                self.pending[spec.name] = spec
                self._pending_sets += 1
            self._set_log.note(now_s, param=spec.name, key=spec.key, old=old, new=new)
        self._send(spec, -1)  # the value now in force: the new one, or the old one when refused

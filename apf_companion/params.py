"""Planner and safety parameters over MAVLink: PARAM_REQUEST_LIST / PARAM_REQUEST_READ / PARAM_SET -> PARAM_VALUE.

``PARAMS`` is the one table from MAVLink parameter names (at most 16 characters) to config keys. A PARAM_SET is
validated exactly as the TOML file is: the section's frozen dataclass is rebuilt with the new value (its
``__post_init__`` range checks) and the planner is rebuilt from the new config (``build_planner``: the planner's
own checks). Accepted: the new config and planner replace the running ones (between cycles, ``apply``), the change
is logged and PARAM_VALUE carries the new value. Refused: PARAM_VALUE carries the old value, every time (the ground
station waits for it and sends the PARAM_SET again without it), and a STATUSTEXT and a WARNING ``param.refused``
say why: the first at once, then at most one each per ``REFUSED_INTERVAL_S`` of the service clock, saying how many
refusals in between went unsaid. A review sent 300 refused PARAM_SETs in 0.65 s: 900 STATUSTEXT chunks went
towards the autopilot (seconds of a 57600-baud link, queued in front of the setpoints) and 300 WARNING lines.
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

from apf_companion.builders import build_planner
from apf_companion.config import ServiceConfig
from apf_companion.errors import ConfigError
from apf_companion.links.messages import ParamRequestList, ParamRequestRead, ParamSet
from apf_companion.outbox import Outbox
from apf_companion.perception.ratelog import RateLimitedWarning, Throttle

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


def _current(config: ServiceConfig, planner: Any, spec: ParamSpec) -> Any:
    if spec.key.startswith(PLANNER_PARAMS):
        return getattr(planner.params, spec.key.removeprefix(PLANNER_PARAMS))
    section, name = spec.key.split(".")
    return getattr(getattr(config, section), name)


def param_value(config: ServiceConfig, planner: Any, spec: ParamSpec) -> float:
    """The value of ``spec`` as PARAM_VALUE carries it (a float; integers and booleans cast)."""
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


def config_with(config: ServiceConfig, planner: Any, spec: ParamSpec, value: float) -> tuple[ServiceConfig, Any]:
    """``config`` with ``spec`` set to ``value``, and the planner built from it, validated as the TOML file is.

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
    return new, build_planner(new)


class ParamServer:
    """Answers the parameter protocol for the companion component.

    Args:
        config: The running configuration (replaced on every accepted PARAM_SET).
        planner: The running planner.
        outbox: Where PARAM_VALUE goes.
        apply: Puts an accepted config and its planner into service (the service's; between cycles).
        statustext: Sends a STATUSTEXT (the reporter's), for refused values.
    """

    def __init__(
        self,
        config: ServiceConfig,
        planner: Any,
        *,
        outbox: Outbox,
        apply: Callable[[ServiceConfig, Any], None],
        statustext: Callable[[int, str], None],
    ) -> None:
        self.config = config
        self.planner = planner
        self.outbox = outbox
        self._apply = apply
        self._statustext = statustext
        self.queue: collections.deque[int] = collections.deque()  # indices of a list request still to send
        self.sets = 0
        self.refused = 0
        self._refused_log = RateLimitedWarning(log, "param.refused", REFUSED_INTERVAL_S)
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

    def send_queued(self, budget: int) -> int:
        """Send up to ``budget`` PARAM_VALUEs of a list request; how many are left."""
        for _ in range(min(budget, len(self.queue))):
            i = self.queue.popleft()
            self._send(PARAMS[i], i)
        return len(self.queue)

    def _send(self, spec: ParamSpec, index: int) -> None:
        value = param_value(self.config, self.planner, spec)
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
        old = param_value(self.config, self.planner, spec)
        try:
            config, planner = config_with(self.config, self.planner, spec, rec.param_value)
        except ConfigError as err:
            self.refused += 1
            self._refused_log.note(now_s, param=spec.name, value=rec.param_value, error=str(err))
            unsaid = self._refused_text.allow(now_s)
            if unsaid is not None:
                more = f" ({unsaid} more refused, not said)" if unsaid else ""  # before the reason: never cut
                self._statustext(mavlink.MAV_SEVERITY_WARNING, f"{spec.name} refused{more}: {err}")
        else:
            self.sets += 1
            self.config, self.planner = config, planner
            self._apply(config, planner)
            new = param_value(config, planner, spec)
            log.info("param.set", extra={"param": spec.name, "key": spec.key, "old": old, "new": new})
        self._send(spec, -1)  # the value now in force: the new one, or the old one when refused

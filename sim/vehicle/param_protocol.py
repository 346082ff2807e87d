"""The parameter protocol (PARAM_REQUEST_LIST / PARAM_REQUEST_READ / PARAM_SET -> PARAM_VALUE).

As ArduPilot's ``GCS_Param.cpp`` and PX4's ``mavlink_parameters.cpp``: a list answers on the asking link, a set
is echoed on every link, and an unknown name gets no answer at all.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

if TYPE_CHECKING:
    from sim.vehicle.engine import VehicleEngine

__all__ = ["PARAM_HANDLERS", "param_id"]


def param_id(raw: Any) -> str:
    """A PARAM_* param_id field (bytes or str, NUL-padded) as a name."""
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).rstrip("\x00")


def param_value(v: VehicleEngine, name: str) -> Any:
    params = v.params
    return v.mav.param_value_encode(
        name.encode(), params[name], mavlink.MAV_PARAM_TYPE_REAL32, len(params), params.index(name)
    )


def _on_param_request_list(v: VehicleEngine, msg: Any, link: int) -> None:
    for name, _ in v.params.items():
        v.emit(link, param_value(v, name))


def _on_param_request_read(v: VehicleEngine, msg: Any, link: int) -> None:
    name = v.params.name_at(msg.param_index) if msg.param_index >= 0 else param_id(msg.param_id)
    if name is not None and name in v.params:
        v.emit(link, param_value(v, name))


def _on_param_set(v: VehicleEngine, msg: Any, link: int) -> None:
    name = param_id(msg.param_id)
    if name not in v.params:
        return  # ArduPilot and PX4 stay silent about unknown parameters
    err = v.params.set(name, float(msg.param_value))
    if err is not None:
        v.statustext(mavlink.MAV_SEVERITY_WARNING, err)  # sent in chunks when longer than one STATUSTEXT
    v.emit(None, param_value(v, name))


# handlers for messages addressed to this vehicle (the caller checks target_system / target_component)
PARAM_HANDLERS: dict[int, Callable[[VehicleEngine, Any, int], None]] = {
    mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_LIST: _on_param_request_list,
    mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_READ: _on_param_request_read,
    mavlink.MAVLINK_MSG_ID_PARAM_SET: _on_param_set,
}

"""Goals that come as MAVLink: a ground station's DO_REPOSITION addressed to us (COMMAND_INT; answered with a
COMMAND_ACK) and the autopilot's own guided target (POSITION_TARGET_*), adopted as the goal when it is new
(apf_companion.adopt)."""

from __future__ import annotations

import logging
from collections.abc import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.adopt import ECHO_WINDOW_S, is_new_target
from apf_companion.goal import RepositionError, Route
from apf_companion.handling.globalref import GlobalPlacement
from apf_companion.handling.params import BROADCAST, HandlerParams
from apf_companion.handling.vehicle import AutopilotState
from apf_companion.links.messages import CommandInt, CommandLong, PositionTargetGlobalInt, PositionTargetLocalNed
from apf_companion.navigator import Navigator
from apf_companion.outbox import Outbox
from apf_companion.reporter import ServiceCounters

__all__ = ["GoalCommands"]

log = logging.getLogger("apf_companion.handlers")  # the logger its lines had before the handlers' split


class GoalCommands:
    """DO_REPOSITION and goal adoption (see the module docstring); owns nothing.

    Args:
        set_route: Offers a goal to goal admission (``GoalAdmission.admit``; False: refused).
    """

    def __init__(
        self,
        params: HandlerParams,
        *,
        autopilot: AutopilotState,
        global_ref: GlobalPlacement,
        navigator: Navigator,
        outbox: Outbox,
        counters: ServiceCounters,
        set_route: Callable[[Route, float], bool],
    ) -> None:
        self.params = params
        self._autopilot = autopilot
        self._global_ref = global_ref
        self._navigator = navigator
        self._outbox = outbox
        self._counters = counters
        self._set_route = set_route

    def on_command(self, rec: CommandInt | CommandLong, now_s: float) -> None:
        """A command addressed to us (the dispatcher checked): DO_REPOSITION is a goal, the others unsupported."""
        self._counters.commands_for_us += 1
        src, outbox = rec.src, self._outbox
        if rec.command != mavlink.MAV_CMD_DO_REPOSITION:
            if rec.target_component != BROADCAST:
                # To all components, the command is the autopilot's to answer: an UNSUPPORTED from us beside
                # its ACCEPTED would read as a refusal.
                outbox.ack(rec.command, mavlink.MAV_RESULT_UNSUPPORTED, src.system, src.component)
            return
        if isinstance(rec, CommandLong):
            outbox.ack(rec.command, mavlink.MAV_RESULT_COMMAND_INT_ONLY, src.system, src.component)
            return
        try:
            route = self._global_ref.goal(
                frame=rec.frame, x=rec.x, y=rec.y, z=rec.z, source=f"mavlink:{src.system}/{src.component}"
            )
        except RepositionError as err:
            self._counters.bad_goals += 1
            outbox.ack(rec.command, err.result, src.system, src.component)
            log.info("goal.rejected", extra={"source": "mavlink", "error": str(err)})
            return
        accepted = self._set_route(route, now_s)
        result = mavlink.MAV_RESULT_ACCEPTED if accepted else mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        outbox.ack(rec.command, result, src.system, src.component)

    def on_position_target_local(self, rec: PositionTargetLocalNed, now_s: float) -> None:
        if self.params.adopt.enabled and rec.coordinate_frame == mavlink.MAV_FRAME_LOCAL_NED:
            self._adopt((rec.x, rec.y, rec.z), rec.type_mask, now_s)

    def on_position_target_global(self, rec: PositionTargetGlobalInt, now_s: float) -> None:
        if not self.params.adopt.enabled:
            return
        try:  # the frames and the flat-earth placement of DO_REPOSITION (apf_companion.goal)
            route = self._global_ref.goal(
                frame=rec.coordinate_frame, x=rec.lat_int, y=rec.lon_int, z=rec.alt, source=""
            )
        except RepositionError:
            return  # no global reference yet, or a frame we cannot place (terrain): not a goal we can fly
        n, e, d = (float(v) for v in route.waypoints_ned_m[-1])
        self._adopt((n, e, d), rec.type_mask, now_s)

    def _adopt(self, target: tuple[float, float, float], type_mask: int, now_s: float) -> None:
        nav = self._navigator
        if not self._autopilot.mode_ok:
            return
        new = is_new_target(
            target,
            type_mask,
            sent=self._outbox.sent.since(now_s - ECHO_WINDOW_S),
            goal_ned_m=None if nav.route is None else nav.route.waypoints_ned_m[-1].tolist(),
            pose_ned_m=None if nav.pose is None else nav.pose.pos_ned_m.tolist(),
            tolerance_m=self.params.adopt.tolerance_m,
        )
        if new:
            log.info("goal.adopted", extra={"source": "autopilot", "target_ned_m": list(target)})
            self._set_route(Route.point(*target, source="autopilot-target"), now_s)

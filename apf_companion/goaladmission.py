"""Goal admission: every goal (the goal at start, zenoh, DO_REPOSITION, an adopted autopilot target) is checked here
before the navigator flies it.

A goal is refused when it lies outside the limits (``goal.max_altitude_m`` / ``goal.min_altitude_m`` above home,
the autopilot's fence, bapf-nav's flying area and keep-out zones, ``goal.max_distance_m`` from the vehicle:
``goal.route_outside_limits``). A goal whose distance check needs the vehicle's position before any pose came
(``goal.route_check_waits``) is held, not flown, and checked at the first pose; a goal taken before the fence's
bounds were known is checked again when they come (``recheck``). With ``exit_when_done`` a refused goal at start
ends the run with outcome "error" (nothing else will come). Pure of I/O: the service wires it
(docs/architecture-service.md).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.flightend import FlightEnd, Outcome
from apf_companion.goal import FenceBounds, Route, route_check_waits, route_outside_limits
from apf_companion.navigator import Navigator
from apf_companion.planning.area import FlyingArea, KeepOuts
from apf_companion.reporter import ServiceCounters

__all__ = ["AdmissionParams", "GoalAdmission", "GoalBounds"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True, kw_only=True)
class AdmissionParams:
    """What goal admission reads of the configuration (fixed for the run).

    Attributes:
        max_altitude_m: ``goal.max_altitude_m``: no waypoint higher above home [m]; 0 = no limit.
        min_altitude_m: ``goal.min_altitude_m``: no waypoint lower above home [m] (negative: below home); the
            fence's floor, where it has one, counts too (the higher wins).
        max_distance_m: ``goal.max_distance_m``: no waypoint horizontally farther from the vehicle [m]; 0 = none.
        exit_when_done: A refused goal at start ends the run (outcome "error").
    """

    max_altitude_m: float = 120.0
    min_altitude_m: float = 1.0
    max_distance_m: float = 2000.0
    exit_when_done: bool = False


@dataclass(frozen=True, slots=True, kw_only=True)
class GoalBounds:
    """The bounds that change at run time (the fence is read, a PARAM_SET builds a new planner).

    Attributes:
        fence: The autopilot fence's bounds; None when no fence is read (``planner.fence_area`` off).
        area_ne_m: bapf-nav's flying area (None: none, or another planner).
        keepouts_ne_m: bapf-nav's keep-out zones.
    """

    fence: FenceBounds | None = None
    area_ne_m: FlyingArea | None = None
    keepouts_ne_m: KeepOuts = ()


class GoalAdmission:
    """Checks each goal and hands it to the navigator (flown), holds it for its check, or refuses it.

    Args:
        params: Its configuration (``AdmissionParams``).
        navigator: Flies an admitted goal; its pose is the position the distance check uses.
        bounds: The bounds in effect now (called at each check).
        counters: ``goals`` (flown) and ``bad_goals`` (refused) are counted here.
        flight: Told when a goal is flown; its outcome is "error" when a refused goal at start ends the run.
        statustext: Sends a STATUSTEXT (severity, text).
        end_run: Ends the run (``exit_when_done`` and the goal at start was refused).
        start_route: The goal at start (flown once the autopilot is first heard), or None.
    """

    def __init__(
        self,
        params: AdmissionParams,
        *,
        navigator: Navigator,
        bounds: Callable[[], GoalBounds],
        counters: ServiceCounters,
        flight: FlightEnd,
        statustext: Callable[[int, str], None],
        end_run: Callable[[], None],
        start_route: Route | None,
    ) -> None:
        self.params = params
        self.navigator = navigator
        self.bounds = bounds
        self.counters = counters
        self.flight = flight
        self.statustext = statustext
        self.end_run = end_run
        self.start_route = start_route
        self.error: str | None = None  # exit_when_done: why the goal at start was refused

    def admit(self, route: Route, now: float) -> bool:
        """Fly ``route`` (replacing the current goal); False when it is refused or while the link is lost. A goal
        whose check needs the vehicle's position (``goal.max_distance_m``) before any pose is held, not flown
        (True: taken; the navigator keeps it, ``Navigator.held``, and a lost link keeps or drops it as a flown
        goal), and checked at the first pose (``pose_arrived``): flown then, or refused."""
        pose = self.navigator.pose
        pos = None if pose is None else pose.pos_ned_m
        p, b = self.params, self.bounds()
        why = route_outside_limits(
            route,
            pos,
            max_altitude_m=p.max_altitude_m,
            min_altitude_m=p.min_altitude_m,
            fence=FenceBounds() if b.fence is None else b.fence,
            max_distance_m=p.max_distance_m,
            area_ne_m=b.area_ne_m,  # bapf-nav's: goals outside it are refused
            keepouts_ne_m=b.keepouts_ne_m,
        )
        if why is not None:
            self._refuse(route, why, now)
            return False
        wait = route_check_waits(pos, max_distance_m=p.max_distance_m)
        if wait is not None:
            if not self.navigator.hold_goal(route, now):  # HOLDING, silent, saying why there is no position
                self.counters.bad_goals += 1  # the link is lost: refused, as the navigator refuses a goal then
                return False
            log.info("goal.held", extra={"source": route.source, "reason": wait})
            self.statustext(mavlink.MAV_SEVERITY_NOTICE, wait)
            return True
        accepted = self.navigator.set_route(route, now)  # replaces a held goal too
        if accepted:
            self.counters.goals += 1
            self.flight.goal_set(now)
            # Its state change is reported by the next cycle (<= one period), to the status and the observers alike.
            log.info("goal.set", extra={"source": route.source, "waypoints_ned_m": route.to_json_list()})
        else:
            self.counters.bad_goals += 1
        return accepted

    def pose_arrived(self, now: float) -> None:
        """A new pose: a held goal's check can be made now (flown or refused). Not while the link is lost: the
        navigator keeps or drops the held goal then (``resume_after_link_lost``), and the first pose after the
        link is back checks a kept one."""
        held = self.navigator.held
        if held is not None and self.navigator.accepts_goals(now):
            self.admit(held, now)

    def recheck(self, now: float) -> None:
        """The fence's bounds came (or changed): a goal taken before them (flown or held) that lies outside them
        (above the ceiling, below the floor, outside the circle round home) is refused and dropped (IDLE)."""
        route = self.navigator.goal.taken
        fence = self.bounds().fence
        if route is None or fence is None:
            return
        why = route_outside_limits(route, None, max_altitude_m=0.0, max_distance_m=0.0, fence=fence)
        if why is None:
            return
        self._refuse(route, why, now, told=True)
        if route is self.navigator.route:
            self.navigator.clear_route(now, f"goal refused: {why}")

    def _refuse(self, route: Route, why: str, now: float, *, told: bool = False) -> None:
        """``route`` is refused: counted and logged. A goal nobody is waiting on an answer for (the goal at start,
        a held goal, ``told``) is said in a STATUSTEXT; with ``exit_when_done`` a refused goal at start ends the
        run with outcome "error" (nothing else will come)."""
        self.counters.bad_goals += 1
        log.warning("goal.refused", extra={"source": route.source, "reason": why})
        held = route is self.navigator.held
        if told or route is self.start_route or held:
            self.statustext(mavlink.MAV_SEVERITY_WARNING, f"goal refused: {why}")
        if held:
            self.navigator.clear_route(now, f"goal refused: {why}")  # IDLE, said by the next cycle
        if route is self.start_route and self.params.exit_when_done:
            self.error = f"the goal at start was refused: {why}"
            self.flight.outcome = Outcome.ERROR
            self.end_run()

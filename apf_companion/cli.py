"""apf-companion: the obstacle-avoiding path-planning service for a MAVLink drone's companion computer.

Commands:
  run           run the service (``apf-companion run --config /etc/apf-companion/apf-companion.toml``)
  check-config  validate a config file and print the effective settings; exit 2 on an error
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import errno
import importlib.metadata
import json
import logging
import os
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from apf_companion import __version__
from apf_companion.config import ServiceConfig, VisualisationConfig, load_config
from apf_companion.errors import ApfCompanionError, ConfigError
from apf_companion.goal import Route, load_route, parse_goal_text
from apf_companion.planning import ALL_PLANNER_NAMES, DEFAULT_PLANNER

__all__ = ["LOG_LEVELS", "add_log_level_option", "build_parser", "log_level", "main"]

log = logging.getLogger(__name__)

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_CONFIG = 2
EXIT_STUCK = 3


class _JsonFormatter(logging.Formatter):
    """One JSON object per line: time, level, logger, event and the record's ``extra`` fields."""

    _SKIP = frozenset(vars(logging.makeLogRecord({})).keys()) | {"message", "asctime"}

    def format(self, record: logging.LogRecord) -> str:
        obj: dict[str, Any] = {
            "t": round(record.created, 6),
            "level": record.levelname,
            "logger": record.name,
            "event": record.getMessage(),
        }
        for key, value in vars(record).items():
            if key not in self._SKIP:
                obj[key] = value
        if record.exc_info:
            obj["exc"] = self.formatException(record.exc_info)
        return json.dumps(obj, default=str)


class _TextFormatter(logging.Formatter):
    """``time level logger: event key=value ...`` (the ``extra`` fields appended)."""

    _SKIP = _JsonFormatter._SKIP

    def format(self, record: logging.LogRecord) -> str:
        base = super().format(record)
        extras = " ".join(f"{k}={v}" for k, v in vars(record).items() if k not in self._SKIP)
        return f"{base} {extras}" if extras else base


def _setup_logging(level: str, fmt: str) -> None:
    handler = logging.StreamHandler(sys.stderr)
    if fmt == "json":
        handler.setFormatter(_JsonFormatter())
    else:
        handler.setFormatter(_TextFormatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    handler.set_name("apf-companion")
    root = logging.getLogger()
    # Replace only our own handler (a second main() call in one process must not log twice).
    root.handlers[:] = [h for h in root.handlers if h.get_name() != "apf-companion"] + [handler]
    root.setLevel(level.upper())


LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
LOG_FORMATS = ("text", "json")


def log_level(text: str) -> str:
    """``--log-level`` / $APF_LOG_LEVEL, any case, as its upper-case name; argparse reports a bad one (exit 2),
    not a traceback."""
    if text.upper() not in LOG_LEVELS:
        msg = f"invalid log level {text!r} (choose from {', '.join(LOG_LEVELS)}; also $APF_LOG_LEVEL)"
        raise argparse.ArgumentTypeError(msg)
    return text.upper()


def _env(name: str, default: str) -> str:
    """An environment variable's value; unset or empty (``APF_LOG_LEVEL=``) gives ``default``."""
    return os.environ.get(name) or default


def add_log_level_option(parser: argparse.ArgumentParser, *, default: str) -> None:
    """Add ``--log-level`` (checked by ``log_level``, default $APF_LOG_LEVEL, else ``default``) to ``parser``: the
    same option for ``apf-companion`` and ``apf-sim``."""
    parser.add_argument(
        "--log-level",
        type=log_level,
        metavar="LEVEL",
        default=_env("APF_LOG_LEVEL", default),
        help=f"{', '.join(LOG_LEVELS)} (default: $APF_LOG_LEVEL or {default})",
    )


def _log_format(text: str) -> str:
    """``--log-format`` / $APF_LOG_FORMAT: checked even when it comes from the environment (argparse's
    ``choices`` would not check a default)."""
    if text.lower() not in LOG_FORMATS:
        msg = f"invalid log format {text!r} (choose from {', '.join(LOG_FORMATS)}; also $APF_LOG_FORMAT)"
        raise argparse.ArgumentTypeError(msg)
    return text.lower()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="apf-companion",
        description=__doc__.splitlines()[0] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    # The installed distribution's metadata (what pip/pipx installed), falling back to the source's version.
    try:
        version = importlib.metadata.version("apf-companion")
    except importlib.metadata.PackageNotFoundError:
        version = __version__
    parser.add_argument("--version", action="version", version=f"%(prog)s {version}")
    add_log_level_option(parser, default="INFO")
    parser.add_argument(
        "--log-format",
        type=_log_format,
        default=_env("APF_LOG_FORMAT", "text"),
        help="log lines as text or one JSON object per line (default: $APF_LOG_FORMAT or text)",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser("run", help="run the service", description=_cmd_run.__doc__)
    run.add_argument("--config", type=Path, help="TOML config file (default: built-in defaults)")
    run.add_argument("--connect", metavar="ENDPOINT", help="override link.connect (e.g. udpin:127.0.0.1:14540)")
    run.add_argument(
        "--planner",
        metavar="NAME",
        help=f"override planner.name (default {DEFAULT_PLANNER}; one of {', '.join(ALL_PLANNER_NAMES)})",
    )
    run.add_argument("--goal", metavar="N,E[,D]", help="goal in local NED metres (overrides [goal])")
    run.add_argument("--route", type=Path, metavar="FILE", help="route file (overrides [goal])")
    run.add_argument("--dry-run", action="store_true", help="plan and log, send nothing")
    run.add_argument("--tlog", metavar="PATH", help="override link.tlog")
    run.add_argument("--result-json", type=Path, metavar="PATH", help="write the outcome (ServiceResult) here on exit")
    run.add_argument(
        "--foxglove",
        nargs="?",
        type=int,
        const=-1,
        metavar="PORT",
        help="serve a Foxglove WebSocket on 127.0.0.1 (PORT, default visualisation.foxglove_port; 0 = any free)",
    )
    run.add_argument("--mcap-dir", metavar="DIR", help="record one .mcap per run into DIR (visualisation.mcap_dir)")
    run.set_defaults(func=_cmd_run)

    check = sub.add_parser("check-config", help="validate a config file", description=_cmd_check.__doc__)
    check.add_argument("config", type=Path, help="TOML config file")
    check.set_defaults(func=_cmd_check)
    return parser


def _visualisation(cfg: ServiceConfig, args: argparse.Namespace) -> VisualisationConfig:
    """``[visualisation]`` with ``--foxglove [PORT]`` and ``--mcap-dir`` applied (validated again)."""
    vc = cfg.visualisation
    if args.foxglove is not None:
        port = vc.foxglove_port if args.foxglove == -1 else args.foxglove
        vc = dataclasses.replace(vc, foxglove=True, foxglove_port=port)
    if args.mcap_dir:
        vc = dataclasses.replace(vc, mcap_dir=str(Path(args.mcap_dir).resolve()))
    return vc


def _effective_config(args: argparse.Namespace) -> tuple[ServiceConfig, Route | None]:
    cfg = load_config(args.config) if args.config is not None else ServiceConfig()
    link = cfg.link
    if args.connect:
        link = dataclasses.replace(link, connect=args.connect)
    if args.tlog:
        link = dataclasses.replace(link, tlog=str(Path(args.tlog).resolve()))
    planner = dataclasses.replace(cfg.planner, name=args.planner) if args.planner else cfg.planner
    cfg = dataclasses.replace(cfg, link=link, planner=planner, dry_run=cfg.dry_run or args.dry_run)
    cfg = dataclasses.replace(cfg, visualisation=_visualisation(cfg, args))
    route: Route | None = None
    if args.goal and args.route:
        msg = "--goal and --route exclude each other"
        raise ConfigError(msg)
    if args.goal:
        route = parse_goal_text(args.goal, source="cli")
    elif args.route:
        route = load_route(args.route, source="cli:route")
    return cfg, route


def _result_path(path: Path) -> Path:
    """``--result-json``'s path, absolute, its directory created as ``--tlog``'s is; OSError when the result could
    not be written there (said at start, not after the flight, when the result would be lost)."""
    path = path.resolve()
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, "is a directory")
    if not os.access(path.parent, os.W_OK | os.X_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise PermissionError(errno.EACCES, "permission denied")
    return path


def _cmd_run(args: argparse.Namespace) -> int:
    """Run the service: connect to the autopilot, fly goals around obstacles, report status.

    Exit codes: 0 = stopped or arrived (SIGINT / SIGTERM, any number of them), 1 = error (also a --result-json
    path that cannot be written, said at start; with exit_when_done also a goal given at start that was refused,
    e.g. beyond goal.max_altitude_m or goal.max_distance_m), 2 = configuration error, 3 (only with exit_when_done) =
    stuck, timeout (max_flight_s) or link lost (no autopilot HEARTBEAT for max_link_lost_s, 60 s by default, also
    from the start when none ever came, or the goal dropped at LINK_LOST with resume_after_link_lost = false),
    130 = interrupted before the event loop ran (imports, reading the config).
    """
    from apf_companion.builders import signing_setup
    from apf_companion.service import build_planner, initial_route

    try:
        cfg, route = _effective_config(args)
        planner = build_planner(cfg)  # validate planner parameters before opening anything
        # The config's goal or route file too, as check-config does: a configuration error is exit 2, which the
        # systemd unit does not restart (RestartPreventExitStatus=2); found later, in CompanionService.open, it
        # was exit 1 and restarted until the start limit.
        route = route if route is not None else initial_route(cfg, planner)
        signing_setup(cfg)  # a key file others can read is refused here (exit 2)
    except ConfigError as err:
        print(f"apf-companion: config error: {err}", file=sys.stderr)
        return EXIT_CONFIG

    try:
        result_path = None if args.result_json is None else _result_path(args.result_json)
    except OSError as err:
        why = f"{args.result_json}: cannot write the result there ({err.strerror or err})"
        print(f"apf-companion: --result-json {why}", file=sys.stderr)
        return EXIT_ERROR

    code: list[int] = []  # the run's exit code once it has ended
    try:
        return asyncio.run(_serve(cfg, route, result_path, code))
    except KeyboardInterrupt:
        # A Ctrl-C while asyncio starts the loop or tears it down (before or after the handlers above): the same
        # stop request, not exit 130; the run's own code when it had ended.
        return code[-1] if code else EXIT_OK


async def _serve(cfg: ServiceConfig, route: Route | None, result_path: Path | None, code: list[int]) -> int:
    """Open the service, run it to its end, and return (and append to ``code``) the exit code. SIGINT / SIGTERM ask
    it to stop, however many arrive and whenever: while it opens, the opening is abandoned (exit 0: stopped); a
    second Ctrl-C is no KeyboardInterrupt (exit 130) but the same request."""
    from apf_companion.service import CompanionService

    service: list[CompanionService] = []
    opening = asyncio.create_task(CompanionService.open(cfg, route=route, result_path=result_path))

    def request_stop() -> None:
        opening.cancel()  # no-op once it is open
        for s in service:
            s.stop()

    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, request_stop)
    try:
        svc = await opening
    except asyncio.CancelledError:
        _write_unopened(result_path, "stopped", None)
        return EXIT_OK
    except ApfCompanionError as err:
        # Said once, on stderr (journald keeps it too); the log line only for --log-level DEBUG.
        log.debug("service.open_failed", extra={"error": str(err)})
        print(f"apf-companion: {err}", file=sys.stderr)
        _write_unopened(result_path, "error", str(err))
        return EXIT_ERROR
    service.append(svc)
    _log_start(cfg)
    result = await svc.run()
    log.info("service.end", extra={"outcome": result.outcome, "steps": result.steps})
    code.append(_exit_code(result.outcome))
    return code[-1]


def _write_unopened(path: Path | None, outcome: str, error: str | None) -> None:
    """``--result-json`` of a run that ended while the service was opening (stopped, or an error such as a zenoh
    router that was never reached): written too, so a script reading it learns why."""
    from apf_companion.service import ServiceResult

    if path is not None:
        path.write_text(ServiceResult.unopened(outcome, error=error).to_json() + "\n", encoding="utf-8")


def _log_start(cfg: ServiceConfig) -> None:
    """Best-effort real-time scheduling and the frozen startup heap, then the ``service.start`` line."""
    from apf_companion.heap import freeze_startup_heap
    from apf_companion.realtime import request_realtime

    scheduling = request_realtime(cfg.cycle.realtime_priority)  # best effort (apf_companion/realtime.py)
    frozen = freeze_startup_heap()  # no full collection of the startup heap mid-flight (apf_companion/heap.py)
    log.info(
        "service.start",
        extra={
            "connect": cfg.link.connect,
            "planner": cfg.planner.name,
            "profile": cfg.autopilot.profile.value,
            "rate_hz": cfg.cycle.rate_hz,
            "dry_run": cfg.dry_run,
            "scheduling": scheduling.describe(),
            "gc_frozen": frozen,
        },
    )


def _exit_code(outcome: str) -> int:
    """A run's outcome as the process's exit code (``_cmd_run``'s docstring)."""
    if outcome == "error":
        return EXIT_ERROR
    return EXIT_OK if outcome in ("arrived", "stopped") else EXIT_STUCK


def _cmd_check(args: argparse.Namespace) -> int:
    """Validate a config file (keys, types, ranges, planner parameters, route file); print the effective
    configuration as JSON, with ``not_used``: the settings it does not read, and why. Exit 0 if valid, 2 with the
    offending key otherwise."""
    from apf_companion.builders import settings_not_used, signing_setup
    from apf_companion.service import build_planner, initial_route

    try:
        cfg = load_config(args.config)
        planner = build_planner(cfg)
        route = initial_route(cfg, planner)
        signing_setup(cfg)  # the key file's mode and contents, the timestamp file
    except ConfigError as err:
        print(f"{args.config}: {err}", file=sys.stderr)
        return EXIT_CONFIG

    def plain(value: Any) -> Any:
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
        if isinstance(value, tuple | list):
            return [plain(v) for v in value]
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, Path):
            return str(value)
        if hasattr(value, "value"):
            return value.value
        return value

    out = plain(cfg)
    # The planner's parameters in effect (preset, then [planner.params], then dim), not only the overrides.
    out["planner"]["params"] = plain(planner.params)
    out["route_waypoints_ned_m"] = None if route is None else route.to_json_list()
    # Printed in full as above, but not read with this planner (or config): said, with why.
    out["not_used"] = settings_not_used(cfg, planner)
    print(json.dumps(out, indent=2))
    print(f"{args.config}: OK", file=sys.stderr)
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``apf-companion`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.log_level, args.log_format)
    try:
        code = int(args.func(args))
    except KeyboardInterrupt:
        return 130
    if argv is None:  # the process's own command line: it ends now
        # A Ctrl-C after the run's loop has closed (a quick second one) would kill it by SIGINT (status -2 / 130)
        # during the interpreter's exit, and the run's exit code would be lost.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    return code


if __name__ == "__main__":
    sys.exit(main())

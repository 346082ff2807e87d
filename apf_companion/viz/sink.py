"""``FoxgloveSink``: the cycle on a Foxglove WebSocket (127.0.0.1) and/or in an MCAP file, via foxglove-sdk.

The sink has its own ``foxglove.Context``, so two services in one process (tests) never share channels. The SDK
encodes (protobuf, the well-known schemas) and writes in Rust; the WebSocket server runs on the SDK's own threads
and drops the oldest messages for a slow client, so a viewer cannot hold up the cycle.
"""

from __future__ import annotations

import datetime
import logging
import time
from pathlib import Path
from typing import Any

from apf_companion.errors import ConfigError
from apf_companion.observe import CycleSnapshot
from apf_companion.viz import scene
from apf_companion.viz.frames import Topic

__all__ = ["FoxgloveSink", "mcap_path_in"]

log = logging.getLogger(__name__)
#: The service has no clock of its own here: the log time is the wall time at start + the cycle's service time.
_NS = 1_000_000_000


def mcap_path_in(directory: Path, now: datetime.datetime | None = None) -> Path:
    """A new file name for this run's recording: ``apf-YYYYmmddTHHMMSSZ.mcap`` (``-1``, ``-2``... if taken)."""
    now = now or datetime.datetime.now(datetime.UTC)
    stem = f"apf-{now:%Y%m%dT%H%M%SZ}"
    path = directory / f"{stem}.mcap"
    n = 0
    while path.exists():
        n += 1
        path = directory / f"{stem}-{n}.mcap"
    return path


def _sdk() -> Any:
    try:
        import foxglove
    except ImportError as err:  # the optional extra is missing
        msg = "visualisation needs foxglove-sdk: pip install 'apf-companion[viz]'"
        raise ConfigError(msg) from err
    return foxglove


class FoxgloveSink:
    """Publishes every cycle (``CycleObserver``). Open with at least one of ``mcap_path`` and ``port``.

    Args:
        mcap_path: Write an MCAP file here (must not exist), or None.
        port: Serve a Foxglove WebSocket on 127.0.0.1:port (0 = a free port, see ``port``), or None.
        t0_s: Service time now (the log time of a cycle at ``t_s`` is the wall time now + ``t_s - t0_s``).
    """

    def __init__(self, *, mcap_path: Path | None = None, port: int | None = None, t0_s: float = 0.0) -> None:
        if mcap_path is None and port is None:
            raise ConfigError("FoxgloveSink needs an MCAP path or a port")
        fg = _sdk()
        from foxglove import channels as ch

        self.ctx = fg.Context()
        self._epoch_ns = time.time_ns() - int(t0_s * _NS)
        self.mcap_path = mcap_path
        self.writer = None
        self.server = None
        self.cycles = 0
        self._decision: str | None = None
        self.tf = ch.FrameTransformChannel(Topic.TF, context=self.ctx)
        self.pose = ch.PoseInFrameChannel(Topic.POSE, context=self.ctx)
        self.obstacles = ch.PointCloudChannel(Topic.OBSTACLES, context=self.ctx)
        self.scan = ch.PointCloudChannel(Topic.SCAN, context=self.ctx)
        self.candidates = ch.PointCloudChannel(Topic.CANDIDATES, context=self.ctx)
        self.entities = ch.SceneUpdateChannel(Topic.SCENE, context=self.ctx)
        self.log = ch.LogChannel(Topic.LOG, context=self.ctx)
        self.cycle = fg.Channel(Topic.CYCLE, context=self.ctx)
        try:
            if mcap_path is not None:
                mcap_path.parent.mkdir(parents=True, exist_ok=True)
                self.writer = fg.open_mcap(mcap_path, context=self.ctx)
            if port is not None:
                self.server = fg.start_server(name="apf-companion", host="127.0.0.1", port=port, context=self.ctx)
        except Exception as err:
            self.close()
            where = f"MCAP {mcap_path}" if self.writer is None and mcap_path is not None else f"127.0.0.1:{port}"
            msg = f"cannot open the Foxglove output ({where}): {err}"
            raise ConfigError(msg) from err
        log.info("viz.open", extra={"mcap": str(mcap_path) if mcap_path else None, "port": self.port})

    @property
    def port(self) -> int | None:
        """The WebSocket's port (the real one when 0 was asked), or None without a server."""
        return None if self.server is None else int(self.server.port)

    def on_cycle(self, snap: CycleSnapshot) -> None:
        ns = self._epoch_ns + int(snap.out.t_s * _NS)
        self.cycles += 1
        self.tf.log(scene.frame_transform(ns), log_time=ns)
        pose = scene.pose(snap, ns)
        if pose is not None:
            self.pose.log(pose, log_time=ns)
        self.obstacles.log(scene.point_cloud(ns, snap.obstacles_ned_m), log_time=ns)
        self.scan.log(scene.point_cloud(ns, snap.scan_ned_m), log_time=ns)
        candidates = scene.candidate_cloud(snap, ns)
        if candidates is not None:
            self.candidates.log(candidates, log_time=ns)
        self.entities.log(scene.scene(snap, ns), log_time=ns)
        for msg in scene.log_messages(snap, self._decision, ns):
            self.log.log(msg, log_time=ns)
        if snap.out.decision not in (None, "TRACKING"):  # the planner's own decisions, not flying on to a point
            self._decision = snap.out.decision
        self.cycle.log(scene.cycle_record(snap), log_time=ns)

    def close(self) -> None:
        """Finish the MCAP file and stop the server (safe to call twice)."""
        writer, self.writer = self.writer, None
        server, self.server = self.server, None
        try:
            if writer is not None:
                writer.close()
                log.info("viz.mcap_written", extra={"mcap": str(self.mcap_path), "cycles": self.cycles})
        finally:
            if server is not None:
                server.stop()

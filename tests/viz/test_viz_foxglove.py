"""The Foxglove output of a real flight: the service flies the bundled simulator over loopback MAVLink, records an
MCAP (read back with the ``mcap`` reader and protobuf decoding) and serves a WebSocket that a real client
(``websockets``, Foxglove's WebSocket protocol) subscribes to."""

from __future__ import annotations

import asyncio
import base64
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from websockets.asyncio.client import connect

from apf_companion.goal import Route
from apf_companion.observe import CycleSnapshot
from apf_companion.viz import NED_IN_ENU_XYZW, Topic
from apf_companion.viz.sink import FoxgloveSink
from sim.world.files import example_world_path, load_world
from sim.world.geometry import clearance_many_m
from tests.conftest import HANG_S, until
from tests.service.test_service_flight import GOAL, flight, service_config

pytestmark = [pytest.mark.timeout(240), pytest.mark.slow]

STEPS = 25  # planner steps to record: enough to pass the first wall of the world


class _JsonDecoders(McapDecoderFactory):
    """The cycle record is JSON; the rest is protobuf (``mcap_protobuf``)."""

    def decoder_for(self, message_encoding: str, schema: Any) -> Callable[[bytes], Any] | None:
        return json.loads if message_encoding == "json" else None


def _read(path: Path) -> dict[str, list[Any]]:
    """Every message of the recording by topic, decoded (protobuf messages, JSON dicts), in log-time order."""
    out: dict[str, list[Any]] = {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory(), _JsonDecoders()])
        for _, channel, _, decoded in reader.iter_decoded_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append(decoded)
    return out


def _cloud_xyz(cloud: Any) -> np.ndarray[Any, np.dtype[np.float32]]:
    names = [f.name for f in cloud.fields]
    arr = np.frombuffer(cloud.data, dtype=np.float32).reshape(-1, cloud.point_stride // 4)
    return arr[:, [names.index(n) for n in ("x", "y", "z")]]


async def test_a_flight_is_recorded_to_mcap_with_every_topic(tmp_path: Path) -> None:
    world = load_world(example_world_path("u-trap"))
    cfg = service_config(planner="bapf-nav", visualisation={"mcap_dir": str(tmp_path)})
    async with flight(world, cfg, route=Route.point(*GOAL, source="test"), spawn_mode="LOITER") as (svc, sim):
        await until(lambda: svc.navigator.counters.planner_steps >= STEPS, HANG_S * 4, f"{STEPS} planner steps")
        trajectory = np.array(sim.result()["trajectory_ned_m"])
    assert svc.observers.errors == 0
    (path,) = tmp_path.glob("apf-*.mcap")
    msgs = _read(path)
    assert set(msgs) == {str(t) for t in Topic}

    # Poses: local NED as the simulator flew it (each recorded pose lies on the simulator's trajectory).
    poses = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for m in msgs[Topic.POSE]])
    gaps = np.min(np.linalg.norm(poses[:, None, :] - trajectory[None, :, :], axis=2), axis=1)
    assert len(poses) >= STEPS and float(gaps.max()) < 0.3, gaps.max()
    assert msgs[Topic.POSE][0].frame_id == "ned"
    tf = msgs[Topic.TF][0]
    assert (tf.parent_frame_id, tf.child_frame_id) == ("enu", "ned")
    assert [tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w] == pytest.approx(NED_IN_ENU_XYZW)

    # Obstacles were remembered, and they are where the world's walls are (within the sensor's noise).
    last_obstacles = _cloud_xyz(msgs[Topic.OBSTACLES][-1])
    assert last_obstacles.shape[0] > 0
    to_walls = clearance_many_m(world, last_obstacles[:, :2].astype(np.float64))
    assert float(np.abs(to_walls).max()) < 0.3

    # Every planner step recorded its candidates, scored (1 = the best passing point), and a chosen point.
    cycles = msgs[Topic.CYCLE]
    planned = [c for c in cycles if c["decision"] not in (None, "TRACKING")]
    assert len(planned) >= STEPS - 1
    assert all(c["chosen_ned_m"] is not None for c in planned if c["decision"] == "GREEDY")
    cands = msgs[Topic.CANDIDATES][-1]
    names = [f.name for f in cands.fields]
    assert names == ["x", "y", "z", "score", "cost_m"]
    table = np.frombuffer(cands.data, dtype=np.float32).reshape(-1, 5)
    assert table.shape[0] == svc.planner.params.n_bacteria
    assert float(table[:, 3].max()) == pytest.approx(1.0)
    # Scene and log: the chosen point and the setpoint are entities; the state changes are logged with reasons.
    ids = {e.id for e in msgs[Topic.SCENE][-1].entities}
    assert ids == {"route", "chosen", "setpoint"}
    logs = [m.message for m in msgs[Topic.LOG]]
    assert any(text.startswith(("IDLE -> NAVIGATING", "HOLDING -> NAVIGATING")) for text in logs), logs
    assert any(text.startswith("decision - -> GREEDY") for text in logs), logs


async def test_a_foxglove_client_receives_the_live_flight() -> None:
    """A WebSocket client on loopback speaks Foxglove's protocol to the service's server (a free port), subscribes
    to the pose and the cycle record and receives them while the service flies the simulator."""
    world = load_world(example_world_path("u-trap"))
    cfg = service_config(planner="bapf-nav", visualisation={"foxglove": True, "foxglove_port": 0})
    async with flight(world, cfg, route=Route.point(*GOAL, source="test"), spawn_mode="LOITER") as (svc, sim):
        (sink,) = svc.observers.observers
        assert isinstance(sink, FoxgloveSink) and sink.port
        protocols = ["foxglove.sdk.v1", "foxglove.websocket.v1"]  # the SDK's current name, and the older one
        async with connect(f"ws://127.0.0.1:{sink.port}", subprotocols=protocols) as ws:  # type: ignore[arg-type]
            assert ws.subprotocol in protocols
            channels: dict[str, dict[str, Any]] = {}
            while not {Topic.POSE, Topic.CYCLE} <= channels.keys():
                op = json.loads(await ws.recv())
                if op["op"] == "advertise":
                    channels |= {c["topic"]: c for c in op["channels"]}
            subs = {1: Topic.POSE, 2: Topic.CYCLE}
            request = [{"id": sid, "channelId": channels[t]["id"]} for sid, t in subs.items()]
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": request}))
            got: dict[str, bytes] = {}
            async with asyncio.timeout(HANG_S):
                while len(got) < 2:
                    frame = await ws.recv()
                    if isinstance(frame, bytes) and frame[0] == 1:  # messageData: op, subscription id, log time
                        got[subs[int.from_bytes(frame[1:5], "little")]] = frame[13:]
        trajectory = np.array(sim.result()["trajectory_ned_m"])
    record = json.loads(got[Topic.CYCLE])
    assert record["state"] in {"NAVIGATING", "HOLDING", "IDLE"}
    pose = _decode(channels[Topic.POSE], got[Topic.POSE])
    assert pose.frame_id == "ned"
    # The pose the client received is one the simulator flew through (local NED, unchanged).
    p = np.array([pose.pose.position.x, pose.pose.position.y, pose.pose.position.z])
    assert float(np.min(np.linalg.norm(trajectory - p, axis=1))) < 0.3


def _decode(channel: dict[str, Any], data: bytes) -> Any:
    """A protobuf message from the schema the server advertised (a base64 FileDescriptorSet)."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))
    return cls.FromString(data)


def test_a_failing_observer_is_counted_and_the_cycle_goes_on(tmp_path: Path) -> None:
    """A sink that raises never reaches the cycle: counted in handler_errors, the setpoint still goes out."""
    from apf_companion.service import CompanionService

    class Broken:
        def on_cycle(self, snap: CycleSnapshot) -> None:
            raise RuntimeError("viewer fell over")

        def close(self) -> None:
            raise OSError("disk full")

    svc = CompanionService(service_config(), observers=[Broken()])
    svc.run_cycle(0.0)
    svc.run_cycle(0.1)
    assert svc.observers.errors == 2
    assert svc.counters.handler_errors == 2
    svc.observers.close()
    assert svc.observers.errors == 3

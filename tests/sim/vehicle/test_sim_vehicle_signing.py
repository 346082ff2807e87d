"""The simulated autopilot with a signing key, over real loopback UDP: it signs every frame and, as ArduPilot
(GCS_Signing.cpp ``accept_unsigned_callback``), takes unsigned or wrongly signed frames only for RADIO_STATUS and
RADIO; ``apf-sim vehicle --signing-key`` refuses a key file others can read."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.autopilot import CopterMode
from apf_companion.errors import LinkTimeout
from apf_companion.links import LinkSigning, SigningParams, Verdict, signing_timestamp
from sim.vehicle import SpawnConfig
from sim.vehicle.cli import main as vehicle_main
from sim.vehicle.testing import simulator_with_client
from tests.conftest import HANG_S, until

pytestmark = [pytest.mark.timeout(60)]

KEY = bytes(range(7, 39))


def set_mode(mav: m.MAVLink, mode: int) -> bytes:
    msg = mav.command_long_encode(1, 1, m.MAV_CMD_DO_SET_MODE, 0, 1, mode, 0, 0, 0, 0, 0)
    buf = bytes(msg.pack(mav))
    mav.seq = (mav.seq + 1) % 256
    return buf


async def test_the_signed_simulator_obeys_signed_commands_only() -> None:
    async with simulator_with_client(signing_key=KEY, spawn=SpawnConfig(airborne=True, mode="LOITER")) as (sim, gcs):
        stats = sim.links[0].signing.stats if sim.links[0].signing is not None else None
        assert stats is not None
        hb = await gcs.recv_match(type="HEARTBEAT", timeout=HANG_S)
        checker = LinkSigning(SigningParams(key=KEY, initial_timestamp=0), m.MAVLink(None))
        assert checker.check(bytes(hb.get_msgbuf()), 1, 1) is Verdict.SIGNED  # what it sends is signed

        unsigned = m.MAVLink(None, srcSystem=255, srcComponent=190)
        gcs.send_bytes(set_mode(unsigned, CopterMode.GUIDED))
        with pytest.raises(LinkTimeout):
            await gcs.recv_match(type="COMMAND_ACK", timeout=1.0)
        assert stats.rejected >= 1 and sim.vehicle.mode == "LOITER"

        gcs.send_bytes(bytes(unsigned.radio_status_encode(200, 190, 100, 10, 10, 0, 0).pack(unsigned)))
        await until(lambda: stats.unsigned >= 2 and stats.rejected == stats.unsigned - 1, HANG_S, "RADIO_STATUS")

        signed = m.MAVLink(None, srcSystem=255, srcComponent=190)
        signed.signing.secret_key = KEY
        signed.signing.sign_outgoing = True
        signed.signing.timestamp = signing_timestamp(time.time())
        gcs.send_bytes(set_mode(signed, CopterMode.GUIDED))
        ack = await gcs.recv_match(type="COMMAND_ACK", timeout=HANG_S)
        assert ack.result == m.MAV_RESULT_ACCEPTED
        await until(lambda: sim.vehicle.mode == "GUIDED", HANG_S, "GUIDED")
        assert stats.signed == 1
        assert sim.result()["signing"] == [
            {"signed": 1, "unsigned": stats.unsigned, "bad_signature": 0, "replayed": 0, "stale": 0, "rejected": 1}
        ]


def test_vehicle_cli_refuses_a_key_file_others_can_read(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "sim.key"
    path.write_bytes(KEY)
    os.chmod(path, 0o644)
    assert vehicle_main(["vehicle", "--signing-key", str(path), "--link", "udpout:127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and "0o644" in err

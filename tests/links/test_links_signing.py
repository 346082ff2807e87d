"""MAVLink 2 signing on MavlinkLink over real loopback UDP: the key file, the timestamp file, and the check of every
frame (signed, unsigned, wrong key, replayed, stale, forged timestamps), cross-checked against pymavlink's own
signer and verifier."""

from __future__ import annotations

import os
import secrets
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.errors import ConfigError
from apf_companion.links import (
    LinkSigning,
    MavlinkLink,
    SigningParams,
    TimestampFile,
    Verdict,
    accept_unsigned_only,
    load_signing_key,
    signing_timestamp,
    start_timestamp,
)
from tests.conftest import HANG_S, until

pytestmark = pytest.mark.timeout(60)

KEY = bytes(range(1, 33))
OTHER_KEY = bytes(range(101, 133))
MINUTE = 60 * 100_000  # signing timestamp units (10 us)


def write_key(path: Path, data: bytes, mode: int = 0o600) -> Path:
    path.write_bytes(data)
    os.chmod(path, mode)
    return path


def params(key: bytes = KEY, *, unsigned: tuple[str, ...] = (), timestamp: int | None = None) -> SigningParams:
    ts = signing_timestamp(time.time()) if timestamp is None else timestamp
    return SigningParams(key=key, initial_timestamp=ts, accept_unsigned=accept_unsigned_only(unsigned))


def heartbeat(mav: Any) -> Any:
    return mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE)


def signed_frame(key: bytes, timestamp: int, *, sysid: int = 255, link_id: int = 0) -> bytes:
    """A HEARTBEAT signed by pymavlink's own signer (not ours)."""
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=190)
    mav.signing.secret_key = key
    mav.signing.sign_outgoing = True
    mav.signing.timestamp = timestamp
    mav.signing.link_id = link_id
    return bytes(heartbeat(mav).pack(mav))


# ---- key and timestamp files ----------------------------------------------------------------------------------
def test_key_file_forms_and_refusals(tmp_path: Path) -> None:
    assert load_signing_key(write_key(tmp_path / "raw", KEY)) == KEY
    assert load_signing_key(write_key(tmp_path / "hex", KEY.hex().encode() + b"\n")) == KEY
    for name, data, words in (
        ("short", b"x" * 31, "32 raw bytes or 64 hex digits"),
        ("nothex", b"z" * 64, "32 raw bytes or 64 hex digits"),
        ("zero", bytes(32), "all-zero"),
    ):
        with pytest.raises(ConfigError, match=words):
            load_signing_key(write_key(tmp_path / name, data))
    with pytest.raises(ConfigError, match="cannot read signing key file"):
        load_signing_key(tmp_path / "missing")


@pytest.mark.parametrize("mode", [0o640, 0o604, 0o620, 0o644])
def test_a_key_file_others_can_read_is_refused_naming_file_and_mode(tmp_path: Path, mode: int) -> None:
    path = write_key(tmp_path / "apf.key", KEY, mode)
    with pytest.raises(ConfigError) as err:
        load_signing_key(path)
    assert str(path) in str(err.value) and f"{mode:#o}" in str(err.value) and "chmod 600" in str(err.value)


def test_timestamp_file_round_trip_is_atomic_and_private(tmp_path: Path) -> None:
    store = TimestampFile(tmp_path / "ts")
    assert store.load() is None
    store.save(123456789)
    assert store.load() == 123456789
    assert os.stat(store.path).st_mode & 0o777 == 0o600
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ts"]  # the temporary file was renamed, not left
    store.path.write_text("12x\n")
    with pytest.raises(ConfigError, match="must hold one integer"):
        store.load()


def test_start_timestamp_is_the_later_of_now_and_persisted_plus_a_minute() -> None:
    now_unix = 1_700_000_000.0
    now = signing_timestamp(now_unix)
    assert now == (1_700_000_000 - 1_420_070_400) * 100_000
    assert start_timestamp(None, now_unix) == now
    assert start_timestamp(now - 10 * MINUTE, now_unix) == now  # an old file: the clock wins
    assert start_timestamp(now + 5, now_unix) == now + 5 + MINUTE  # a clock behind the file: file + 1 min


# ---- the check, over loopback ---------------------------------------------------------------------------------
class Pair:
    def __init__(self, rx: MavlinkLink, port: int) -> None:
        self.rx = rx
        self.port = port

    async def sender(self, signing: SigningParams | None, sysid: int = 255) -> MavlinkLink:
        return await MavlinkLink.open(
            f"udpout:127.0.0.1:{self.port}", source_system=sysid, source_component=190, signing=signing
        )

    def verdicts(self) -> dict[str, int]:
        assert self.rx.signing is not None
        return {k: getattr(self.rx.signing.stats, k) for k in ("signed", "unsigned", "bad_signature", "replayed")}


@pytest.fixture
async def pair() -> AsyncIterator[Pair]:
    rx = await MavlinkLink.open("udpin:127.0.0.1:0", source_system=1, source_component=1, signing=params())
    assert rx.local_address is not None
    try:
        yield Pair(rx, rx.local_address[1])
    finally:
        await rx.aclose()


async def test_signed_frames_pass_and_unsigned_or_wrong_key_are_dropped_and_counted(pair: Pair) -> None:
    good = await pair.sender(params())
    unsigned = await pair.sender(None, sysid=254)
    wrong = await pair.sender(params(OTHER_KEY), sysid=253)
    try:
        for link in (unsigned, wrong, good):
            link.send(heartbeat(link.mav))
        msg = await pair.rx.recv(timeout=HANG_S)
        assert msg.get_srcSystem() == 255  # only the signed one came through
        await until(lambda: pair.rx.signing is not None and pair.rx.signing.stats.rejected == 2, what="2 rejected")
        assert pair.verdicts() == {"signed": 1, "unsigned": 1, "bad_signature": 1, "replayed": 0}
        assert pair.rx.recv_nowait() is None
    finally:
        for link in (good, unsigned, wrong):
            await link.aclose()


async def test_a_replayed_frame_is_dropped_and_a_newer_one_passes(pair: Pair) -> None:
    sender = await pair.sender(None)  # sends raw bytes: the frames are signed by pymavlink itself
    try:
        ts = signing_timestamp(time.time())
        first = signed_frame(KEY, ts)
        sender.send_bytes(first)
        await pair.rx.recv(timeout=HANG_S)
        sender.send_bytes(first)  # the same frame again
        sender.send_bytes(signed_frame(KEY, ts))  # re-signed, same timestamp
        await until(lambda: pair.verdicts()["replayed"] == 2, what="2 replays")
        sender.send_bytes(signed_frame(KEY, ts + 1))
        await pair.rx.recv(timeout=HANG_S)
        assert pair.verdicts() == {"signed": 2, "unsigned": 0, "bad_signature": 0, "replayed": 2}
    finally:
        await sender.aclose()


async def test_a_forged_high_timestamp_does_not_lock_out_the_real_sender(pair: Pair) -> None:
    """pymavlink's check_signature records a stream's timestamp before comparing signatures; ours does not."""
    sender = await pair.sender(None)
    try:
        ts = signing_timestamp(time.time())
        sender.send_bytes(signed_frame(OTHER_KEY, (1 << 48) - 2))  # same stream (255/190, link 0), wrong key
        sender.send_bytes(signed_frame(KEY, ts))
        msg = await pair.rx.recv(timeout=HANG_S)
        assert msg.get_srcSystem() == 255
        assert pair.verdicts()["bad_signature"] == 1 and pair.verdicts()["signed"] == 1
    finally:
        await sender.aclose()


async def test_a_new_stream_more_than_a_minute_old_is_stale(pair: Pair) -> None:
    sender = await pair.sender(None)
    try:
        ts = signing_timestamp(time.time())
        sender.send_bytes(signed_frame(KEY, ts - 2 * MINUTE, sysid=200))
        sender.send_bytes(signed_frame(KEY, ts - MINUTE // 2, sysid=201))  # within the minute: accepted
        msg = await pair.rx.recv(timeout=HANG_S)
        assert msg.get_srcSystem() == 201
        assert pair.rx.signing is not None and pair.rx.signing.stats.stale == 1
    finally:
        await sender.aclose()


async def test_unsigned_types_on_the_accept_list_pass(pair: Pair) -> None:
    rx = await MavlinkLink.open(
        "udpin:127.0.0.1:0", source_system=1, source_component=1, signing=params(unsigned=("RADIO_STATUS",))
    )
    assert rx.local_address is not None
    tx = await MavlinkLink.open(f"udpout:127.0.0.1:{rx.local_address[1]}", source_system=255, source_component=190)
    try:
        tx.send(heartbeat(tx.mav))
        tx.send(tx.mav.radio_status_encode(200, 190, 100, 10, 10, 0, 0))
        msg = await rx.recv(timeout=HANG_S)
        assert msg.get_type() == "RADIO_STATUS"
        assert rx.signing is not None and rx.signing.stats.unsigned == 2 and rx.signing.stats.rejected == 1
    finally:
        await tx.aclose()
        await rx.aclose()


async def test_our_frames_verify_with_pymavlink_and_raise_our_timestamp(pair: Pair) -> None:
    """What we sign, pymavlink's own verifier accepts; a peer's newer timestamp becomes our floor."""
    sender = await pair.sender(params())
    try:
        sender.send(heartbeat(sender.mav))
        msg = await pair.rx.recv(timeout=HANG_S)
        verifier = mavlink.MAVLink(None)
        verifier.signing.secret_key = KEY
        verifier.signing.timestamp = 0
        (again,) = verifier.parse_buffer(bytes(msg.get_msgbuf())) or []
        assert again.get_signed() and verifier.signing.goodsig_count == 1
        assert pair.rx.signing is not None
        ahead = pair.rx.signing.timestamp + 10 * MINUTE
        sender.send_bytes(signed_frame(KEY, ahead))
        await pair.rx.recv(timeout=HANG_S)
        assert pair.rx.signing.timestamp >= ahead
        before = pair.rx.signing.timestamp
        pair.rx.send(heartbeat(pair.rx.mav))
        assert pair.rx.signing.timestamp == before + 1  # pymavlink's signer advances it one per frame
    finally:
        await sender.aclose()


def test_random_keys_sign_and_verify() -> None:
    key = secrets.token_bytes(32)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    ours = LinkSigning(params(key), mav)
    ts = ours.timestamp
    assert ours.check(signed_frame(key, ts + 1), 255, 190) is Verdict.SIGNED
    assert ours.check(signed_frame(key, ts + 1), 255, 190) is Verdict.REPLAYED
    altered = bytearray(signed_frame(key, ts + 2))
    altered[-1] ^= 0xFF
    assert ours.check(bytes(altered), 255, 190) is Verdict.BAD_SIGNATURE
    assert ours.check(bytes(heartbeat(mav).pack(mavlink.MAVLink(None))), 1, 1) is Verdict.UNSIGNED

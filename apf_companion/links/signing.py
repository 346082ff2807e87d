"""MAVLink 2 message signing: the key file, the persisted timestamp, and the check of every incoming frame.

Outgoing frames are signed by pymavlink itself: ``LinkSigning`` sets the link's ``MAVLink.signing`` state
(``secret_key``, ``link_id``, ``timestamp``, ``sign_outgoing``) and ``MAVLink_message.pack`` appends the 13-byte
signature block (link id, 48-bit timestamp, first 6 bytes of SHA-256(key + frame)), advancing the timestamp by one
per frame.

Incoming frames are parsed by key-less pymavlink parsers (``Receiver``) and checked here, in the order of the
MAVLink C library (``mavlink_signature_check`` in mavlink_helpers.h, which ArduPilot runs): the signature first,
then the timestamp against the last one of its stream (link id, sysid, compid): a frame not newer than the last is
a replay; a new stream more than one minute behind our own timestamp is stale. A stream's timestamp is recorded
only once the signature is good. pymavlink's own ``check_signature`` records it before comparing signatures, so
one forged frame with a high timestamp would lock its claimed sender out; that is why it is not used for input.

Frames that fail the check (unsigned, wrongly signed, replayed, stale) go to an ``accept_unsigned`` rule by
message type, as the C library's ``accept_unsigned_callback``: ArduPilot accepts RADIO_STATUS and RADIO only
(libraries/GCS_MAVLink/GCS_Signing.cpp); the companion accepts unsigned telemetry unless told otherwise, never
unsigned commands (docs/hardening.md#mavlink-2-signing). Every verdict is counted (``SigningStats``).

Timestamps are 10 us units since 2015-01-01 00:00 UTC. At start a link uses max(now, persisted + 60 s) and the
owner saves the timestamp every 30 s and at exit (ArduPilot's ``load_signing_key`` / ``save_signing_timestamp``
use the same minute and half minute), so a restart never re-uses a timestamp a peer has already seen.
"""

from __future__ import annotations

import asyncio
import enum
import hashlib
import hmac
import logging
import os
import stat
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.errors import ConfigError

__all__ = [
    "KEY_BYTES",
    "LinkSigning",
    "SigningParams",
    "SigningStats",
    "TimestampFile",
    "TimestampKeeper",
    "Verdict",
    "accept_unsigned_only",
    "accept_unsigned_telemetry",
    "load_signing_key",
    "signing_timestamp",
    "start_timestamp",
]

log = logging.getLogger(__name__)

KEY_BYTES = 32
TICKS_PER_S = 100_000  # signing timestamp units: 10 us
EPOCH_2015_UNIX_S = 1_420_070_400  # 2015-01-01 00:00 UTC
NEW_STREAM_MAX_LAG = 60 * TICKS_PER_S  # mavlink_helpers.h: a new stream's timestamp may be 1 min behind ours
RESTART_MARGIN = 60 * TICKS_PER_S  # GCS_Signing.cpp load_signing_key: persisted + 1 min
SAVE_PERIOD_S = 30.0  # GCS_Signing.cpp save_signing_timestamp: every 30 s
MAX_STREAMS = 256  # only good signatures create streams; a bound all the same (the C library keeps 16)
TIMESTAMP_MAX = (1 << 48) - 1
_SIG_LEN = mavlink.MAVLINK_SIGNATURE_BLOCK_LEN  # 13: link id (1), timestamp (6), signature (6)
_HEADER_CRC_LEN = mavlink.HEADER_LEN_V2 + 2
_PRIVATE_BITS = stat.S_IRWXG | stat.S_IRWXO


class Verdict(enum.StrEnum):
    """What the signature check says about one frame."""

    SIGNED = "signed"  # good signature, newer than its stream's last
    UNSIGNED = "unsigned"  # no signature (or MAVLink 1)
    BAD_SIGNATURE = "bad_signature"  # signed with another key, or altered
    REPLAYED = "replayed"  # timestamp not newer than the last of its stream
    STALE = "stale"  # a new stream more than a minute behind our timestamp, or too many streams


@dataclass(slots=True)
class SigningStats:
    """Frames per verdict, and how many were dropped (a verdict other than SIGNED the rule did not accept)."""

    signed: int = 0
    unsigned: int = 0
    bad_signature: int = 0
    replayed: int = 0
    stale: int = 0
    rejected: int = 0


def accept_unsigned_only(types: Iterable[str]) -> Callable[[str], bool]:
    """A rule accepting only these message types without a good signature (ArduPilot: RADIO_STATUS, RADIO)."""
    allowed = frozenset(types)
    return lambda msg_type: msg_type in allowed


def accept_unsigned_telemetry(
    commands: Iterable[str], *, commands_ok: bool, telemetry_ok: bool
) -> Callable[[str], bool]:
    """A rule accepting unsigned ``commands`` when ``commands_ok`` and every other type when ``telemetry_ok``."""
    cmd = frozenset(commands)
    return lambda msg_type: commands_ok if msg_type in cmd else telemetry_ok


def signing_timestamp(unix_s: float) -> int:
    """A wall-clock time as a signing timestamp (10 us units since 2015-01-01)."""
    return max(0, min(TIMESTAMP_MAX, int((unix_s - EPOCH_2015_UNIX_S) * TICKS_PER_S)))


def start_timestamp(persisted: int | None, unix_s: float) -> int:
    """The first timestamp after a start: max(now, persisted + 1 min)."""
    now = signing_timestamp(unix_s)
    return now if persisted is None else min(TIMESTAMP_MAX, max(now, persisted + RESTART_MARGIN))


def load_signing_key(path: Path | str) -> bytes:
    """Read a 32-byte signing key: the raw bytes, or 64 hexadecimal digits (a trailing newline is fine).

    Raises:
        ConfigError: the file is missing, readable or writable by group or others (it must be ``chmod 600``),
            not 32 bytes / 64 hex digits, or all zero (which means "signing off" to ArduPilot).
    """
    p = Path(path)
    try:
        with p.open("rb") as f:
            mode = os.fstat(f.fileno()).st_mode
            if mode & _PRIVATE_BITS:
                msg = (
                    f"signing key file {p} has mode {stat.S_IMODE(mode):#o}: it must not be accessible by group or "
                    f"others (chmod 600 {p})"
                )
                raise ConfigError(msg)
            data = f.read(4 * KEY_BYTES)
    except OSError as err:
        msg = f"cannot read signing key file {p}: {err.strerror}"
        raise ConfigError(msg) from err
    key = data if len(data) == KEY_BYTES else _hex_key(data)
    if key is None:
        msg = (
            f"signing key file {p} must hold {KEY_BYTES} raw bytes or {2 * KEY_BYTES} hex digits, got {len(data)} bytes"
        )
        raise ConfigError(msg)
    if not any(key):
        msg = f"signing key file {p} holds an all-zero key (that means 'signing off' to ArduPilot)"
        raise ConfigError(msg)
    return key


def _hex_key(data: bytes) -> bytes | None:
    text = data.strip()
    if len(text) != 2 * KEY_BYTES:
        return None
    try:
        return bytes.fromhex(text.decode("ascii"))
    except (UnicodeDecodeError, ValueError):
        return None


class TimestampFile:
    """The persisted signing timestamp: one decimal integer, replaced atomically (write, fsync, rename)."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)

    def load(self) -> int | None:
        """The saved timestamp, None when there is no file yet.

        Raises:
            ConfigError: the file exists but does not hold a timestamp.
        """
        try:
            text = self.path.read_text(encoding="ascii").strip()
        except FileNotFoundError:
            return None
        except (OSError, UnicodeDecodeError) as err:
            msg = f"cannot read signing timestamp file {self.path}: {err}"
            raise ConfigError(msg) from err
        if not text.isdigit() or int(text) > TIMESTAMP_MAX:
            msg = f"signing timestamp file {self.path} must hold one integer in [0, 2^48), got {text[:40]!r}"
            raise ConfigError(msg)
        return int(text)

    def save(self, timestamp: int) -> None:
        """Write ``timestamp`` (only ever larger than what is there; raises OSError when the disk refuses)."""
        tmp = self.path.with_name(f".{self.path.name}.tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.write(fd, f"{timestamp}\n".encode("ascii"))
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, self.path)


@dataclass(frozen=True, slots=True, kw_only=True)
class SigningParams:
    """Signing on one link.

    Attributes:
        key: The 32-byte secret key (``load_signing_key``).
        initial_timestamp: The first outgoing timestamp (``start_timestamp``).
        accept_unsigned: Message types accepted without a good signature (``accept_unsigned_only`` /
            ``accept_unsigned_telemetry``); default none.
        link_id: Our link id in the signature block (ArduPilot uses its channel number).
    """

    key: bytes
    initial_timestamp: int
    accept_unsigned: Callable[[str], bool] = lambda msg_type: False
    link_id: int = 0

    def __post_init__(self) -> None:
        if len(self.key) != KEY_BYTES:
            msg = f"signing key must be {KEY_BYTES} bytes, got {len(self.key)}"
            raise ConfigError(msg)
        if not 0 <= self.initial_timestamp <= TIMESTAMP_MAX or not 0 <= self.link_id <= 255:
            msg = f"signing timestamp / link id out of range: {self.initial_timestamp}, {self.link_id}"
            raise ConfigError(msg)


class LinkSigning:
    """A link's signing: signs through pymavlink's ``MAVLink.signing`` state and checks incoming frames."""

    def __init__(self, params: SigningParams, mav: Any) -> None:
        self.params = params
        self.state = mav.signing  # pymavlink's MAVLinkSigning: the outgoing timestamp lives here
        self.state.secret_key = params.key
        self.state.link_id = params.link_id
        self.state.timestamp = params.initial_timestamp
        self.state.sign_outgoing = True
        self.state.allow_unsigned_callback = None
        self.stats = SigningStats()
        self._streams: dict[tuple[int, int, int], int] = {}

    @property
    def timestamp(self) -> int:
        """The next outgoing timestamp."""
        return int(self.state.timestamp)

    def advance(self, unix_s: float | None = None) -> int:
        """Move the outgoing timestamp up to the wall clock (never back); the new value."""
        now = signing_timestamp(time.time() if unix_s is None else unix_s)
        self.state.timestamp = max(self.timestamp, now)
        return self.timestamp

    def accept(self, msg: Any) -> bool:
        """Check ``msg``'s frame, count its verdict, and say whether it may be used."""
        verdict = self.check(bytes(msg.get_msgbuf()), msg.get_srcSystem(), msg.get_srcComponent())
        stats = self.stats
        setattr(stats, verdict.value, getattr(stats, verdict.value) + 1)
        if verdict is Verdict.SIGNED or self.params.accept_unsigned(msg.get_type()):
            return True
        stats.rejected += 1
        return False

    def check(self, frame: bytes, sysid: int, compid: int) -> Verdict:
        """The verdict on one complete frame (mavlink_helpers.h ``mavlink_signature_check``, in its order)."""
        signed = (
            len(frame) >= _HEADER_CRC_LEN + _SIG_LEN
            and frame[0] == mavlink.PROTOCOL_MARKER_V2
            and frame[2] & mavlink.MAVLINK_IFLAG_SIGNED
        )
        if not signed:
            return Verdict.UNSIGNED
        digest = hashlib.sha256(self.params.key + frame[:-6]).digest()[:6]
        if not hmac.compare_digest(digest, frame[-6:]):
            return Verdict.BAD_SIGNATURE
        link_id = frame[-_SIG_LEN]
        ts = int.from_bytes(frame[-12:-6], "little")
        stream = (link_id, sysid, compid)
        last = self._streams.get(stream)
        if last is None:
            if len(self._streams) >= MAX_STREAMS or ts + NEW_STREAM_MAX_LAG < self.timestamp:
                return Verdict.STALE
        elif ts <= last:
            return Verdict.REPLAYED
        self._streams[stream] = ts
        self.state.timestamp = max(self.timestamp, ts)  # our next timestamp is at least the newest seen
        return Verdict.SIGNED


class TimestampKeeper:
    """Keeps a link's signing timestamp on disk: ``save`` now, ``run`` every 30 s (wall clock), ``close`` at exit.
    Each save first moves the timestamp up to the wall clock, so the saved value never lags real time."""

    def __init__(self, signing: LinkSigning, store: TimestampFile) -> None:
        self.signing = signing
        self.store = store
        self.saves = 0

    def save(self) -> None:
        """Save now (raises OSError when the file cannot be written)."""
        self.store.save(self.signing.advance())
        self.saves += 1

    async def run(self, on_error: Callable[[Exception], None]) -> None:
        """Save every ``SAVE_PERIOD_S`` until cancelled; a failed save goes to ``on_error`` and the loop goes on."""
        while True:
            await asyncio.sleep(SAVE_PERIOD_S)
            timestamp = self.signing.advance()
            try:
                await asyncio.to_thread(self.store.save, timestamp)
                self.saves += 1
            except OSError as err:
                on_error(err)

    def close(self) -> None:
        """The last save (at exit): logged, never raised."""
        try:
            self.save()
        except OSError as err:
            log.error("signing.timestamp_not_saved", extra={"path": str(self.store.path), "error": str(err)})

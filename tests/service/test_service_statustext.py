"""STATUSTEXT longer than one message goes in MAVLink 2 chunks (common.xml STATUSTEXT ``id`` / ``chunk_seq``)."""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.navigator import State
from apf_companion.outbox import STATUSTEXT_BYTES, statustext_chunks
from apf_companion.status import statustext_for


def _reassemble(chunks: list[tuple[int, int, bytes]]) -> bytes:
    return b"".join(part for _, _, part in sorted(chunks, key=lambda c: c[1]))


def test_short_text_is_one_message_with_id_0() -> None:
    assert statustext_chunks("APF: arrived", 7) == [(0, 0, b"APF: arrived")]
    assert statustext_chunks("x" * STATUSTEXT_BYTES, 7) == [(0, 0, b"x" * STATUSTEXT_BYTES)]


def test_long_text_shares_a_new_nonzero_id_and_numbers_its_chunks() -> None:
    text = "APF_CRUISE_SPD refused: cycle.cruise_speed_m_s must be in (0.0, 20.0], got -1.0"
    chunks = statustext_chunks(text, 7)
    assert [c[0] for c in chunks] == [8, 8] and [c[1] for c in chunks] == [0, 1]
    assert _reassemble(chunks) == text.encode()
    assert statustext_chunks(text, 0xFFFF)[0][0] == 1  # wraps past 0 (0 means a single chunk)


def test_a_text_filling_its_last_chunk_ends_with_an_empty_one() -> None:
    chunks = statustext_chunks("y" * (2 * STATUSTEXT_BYTES), 0)
    assert [len(p) for _, _, p in chunks] == [50, 50, 0]


def test_chunks_are_capped_and_non_ascii_is_replaced() -> None:
    chunks = statustext_chunks("é" + "z" * 1000, 0)
    assert len(chunks) == 4 and chunks[0][2].startswith(b"?z")
    assert [len(p) for _, _, p in chunks] == [50, 50, 50, 49]  # the last still ends the text (ArduPilot's cut)
    assert len(statustext_chunks("v" * 150, 0)) == 4  # 3 full chunks and the empty one: never more than 4


def test_chunks_pack_as_mavlink2_statustext() -> None:
    tx = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    rx = mavlink.MAVLink(None)
    got = []
    for chunk_id, seq, part in statustext_chunks("w" * 120, 41):
        buf = tx.statustext_encode(mavlink.MAV_SEVERITY_WARNING, part, chunk_id, seq).pack(tx)
        msgs = rx.parse_buffer(buf)
        assert msgs is not None
        got.extend(msgs)
    assert [(m.id, m.chunk_seq) for m in got] == [(42, 0), (42, 1), (42, 2)]
    assert "".join(m.text for m in got) == "w" * 120


def test_a_state_change_text_is_not_cut_at_50_characters() -> None:
    """Seen on the wire before: 'APF HOLDING: started with the vehicle flying in gu' (the advice lost)."""
    reason = "started with the vehicle flying in guided control: holding, send a fresh goal"
    text = statustext_for(State.HOLDING, reason)
    assert text == f"APF HOLDING: {reason}"
    chunks = statustext_chunks(text, 0)
    assert [(c[0], c[1]) for c in chunks] == [(1, 0), (1, 1)]
    assert _reassemble(chunks) == text.encode()

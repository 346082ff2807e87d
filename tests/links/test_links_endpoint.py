from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from apf_companion.errors import ConfigError
from apf_companion.links import Endpoint, EndpointKind, parse_endpoint

# MAVSDK's empty host means all interfaces; only parsed here, never bound.
ANY_IPV4 = ".".join("0" * 4)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("udpin:127.0.0.1:14550", Endpoint(EndpointKind.UDPIN, "127.0.0.1", 14550)),
        ("udp:127.0.0.1:14550", Endpoint(EndpointKind.UDPIN, "127.0.0.1", 14550)),
        ("udpout:127.0.0.1:14551", Endpoint(EndpointKind.UDPOUT, "127.0.0.1", 14551)),
        ("tcp:127.0.0.1:5760", Endpoint(EndpointKind.TCP, "127.0.0.1", 5760)),
        ("tcpin:127.0.0.1:5760", Endpoint(EndpointKind.TCPIN, "127.0.0.1", 5760)),
        ("udpin://127.0.0.1:14540", Endpoint(EndpointKind.UDPIN, "127.0.0.1", 14540)),
        ("udp://:14540", Endpoint(EndpointKind.UDPIN, ANY_IPV4, 14540)),
        ("tcpout://127.0.0.1:5760", Endpoint(EndpointKind.TCP, "127.0.0.1", 5760)),
        ("/dev/ttyACM0", Endpoint(EndpointKind.SERIAL, device="/dev/ttyACM0", baud=57600)),
        ("/dev/ttyACM0:921600", Endpoint(EndpointKind.SERIAL, device="/dev/ttyACM0", baud=921600)),
        ("/dev/serial0,115200", Endpoint(EndpointKind.SERIAL, device="/dev/serial0", baud=115200)),
        ("serial:///dev/ttyUSB0:57600", Endpoint(EndpointKind.SERIAL, device="/dev/ttyUSB0", baud=57600)),
        ("udpin:127.0.0.1:0", Endpoint(EndpointKind.UDPIN, "127.0.0.1", 0)),
    ],
)
def test_parse_accepted_forms(text: str, expected: Endpoint) -> None:
    assert parse_endpoint(text) == expected


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("", "empty"),
        ("udpout:127.0.0.1", "HOST:PORT"),
        ("udpot:127.0.0.1:14550", "unknown scheme"),
        ("udpout:127.0.0.1:0", "outside 1..65535"),
        ("tcp:127.0.0.1:70000", "outside"),
        ("tcp:127.0.0.1:abc", "not an integer"),
        ("udpout::14550", "needs a host"),
        ("serial:ttyACM0:57600", "absolute path"),
        ("/dev/ttyACM0:12", "baud"),
    ],
)
def test_parse_rejects_with_a_clear_message(text: str, fragment: str) -> None:
    with pytest.raises(ConfigError, match=fragment):
        parse_endpoint(text)


@pytest.mark.parametrize("kind", [*EndpointKind])
def test_str_round_trips_for_every_kind(kind: EndpointKind) -> None:
    text = "serial:/dev/ttyACM0:57600" if kind is EndpointKind.SERIAL else f"{kind.value}:127.0.0.1:5760"
    ep = parse_endpoint(text)
    assert ep.kind is kind
    assert parse_endpoint(str(ep)) == ep


@pytest.mark.parametrize("kind", [*EndpointKind])
def test_only_listening_kinds_take_port_zero_and_an_empty_host(kind: EndpointKind) -> None:
    assert kind.listens == (kind in (EndpointKind.UDPIN, EndpointKind.TCPIN))
    if kind is EndpointKind.SERIAL:
        return
    assert parse_endpoint(f"{kind.value}:127.0.0.1:5760").listens == kind.listens
    if kind.listens:
        assert parse_endpoint(f"{kind.value}:127.0.0.1:0").port == 0
        assert parse_endpoint(f"{kind.value}://:5760").host == ANY_IPV4
    else:
        with pytest.raises(ConfigError, match=r"outside 1\.\.65535"):
            parse_endpoint(f"{kind.value}:127.0.0.1:0")
        with pytest.raises(ConfigError, match="needs a host"):
            parse_endpoint(f"{kind.value}://:5760")


@given(st.text(max_size=40))
def test_random_text_parses_or_raises_config_error(text: str) -> None:
    try:
        ep = parse_endpoint(text)
    except ConfigError:
        return
    assert isinstance(ep, Endpoint)

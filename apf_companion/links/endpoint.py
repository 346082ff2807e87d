"""Connection strings in the forms MAVLink users already type, parsed into one frozen ``Endpoint``.

Accepted (pymavlink ``mavutil`` style, then MAVSDK URL style):

=============================  ============================================================
``udpin:HOST:PORT``            listen for UDP; reply to every peer heard from
``udp:HOST:PORT``              same as ``udpin`` (pymavlink's default direction)
``udpout:HOST:PORT``           send UDP to HOST:PORT (and read its replies)
``tcp:HOST:PORT``              connect to a TCP server; reconnect with backoff
``tcpin:HOST:PORT``            listen for TCP clients
``/dev/ttyACM0[:BAUD]``        serial port (also ``/dev/ttyACM0,BAUD``, MAVProxy's form)
``serial:/dev/ttyACM0[:BAUD]``
``udpin://HOST:PORT``          MAVSDK forms; ``udp://`` = ``udpin://``, ``tcpout://`` = ``tcp://`` = ``tcp:``,
``serial:///dev/ttyACM0:BAUD``  an empty host (``udpin://:14540``) means all interfaces
=============================  ============================================================
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from apf_companion.errors import ConfigError

__all__ = ["DEFAULT_BAUD", "Endpoint", "EndpointKind", "connection_hint", "parse_endpoint"]

DEFAULT_BAUD = 57600


class EndpointKind(enum.Enum):
    """The five kinds of link; each has one transport class (``apf_companion.links.transports.TRANSPORTS``)."""

    UDPIN = "udpin"
    UDPOUT = "udpout"
    TCP = "tcp"
    TCPIN = "tcpin"
    SERIAL = "serial"

    @property
    def listens(self) -> bool:
        """Waits for peers (udpin, tcpin): may bind port 0 (any free port) and an empty host (all interfaces)."""
        return self in (EndpointKind.UDPIN, EndpointKind.TCPIN)


_SCHEMES: dict[str, EndpointKind] = {
    "udpin": EndpointKind.UDPIN,
    "udp": EndpointKind.UDPIN,
    "udpout": EndpointKind.UDPOUT,
    "tcp": EndpointKind.TCP,
    "tcpout": EndpointKind.TCP,
    "tcpin": EndpointKind.TCPIN,
    "serial": EndpointKind.SERIAL,
}


@dataclass(frozen=True, slots=True)
class Endpoint:
    """Where a MAVLink link goes. ``host``/``port`` for network kinds, ``device``/``baud`` for serial."""

    kind: EndpointKind
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = DEFAULT_BAUD

    def __str__(self) -> str:
        if self.kind is EndpointKind.SERIAL:
            return f"serial:{self.device}:{self.baud}"
        return f"{self.kind.value}:{self.host}:{self.port}"

    @property
    def listens(self) -> bool:
        """True for the kinds that wait for peers (udpin, tcpin)."""
        return self.kind.listens


def _parse_baud(text: str, original: str) -> int:
    try:
        baud = int(text)
    except ValueError as err:
        msg = f"endpoint {original!r}: baud rate {text!r} is not an integer"
        raise ConfigError(msg) from err
    if not 50 <= baud <= 20_000_000:
        msg = f"endpoint {original!r}: baud rate {baud} outside 50..20000000"
        raise ConfigError(msg)
    return baud


def _parse_serial(rest: str, original: str) -> Endpoint:
    device, baud = rest, DEFAULT_BAUD
    for sep in (",", ":"):
        head, found, tail = rest.rpartition(sep)
        if found and tail.isdigit():
            device, baud = head, _parse_baud(tail, original)
            break
    if not device.startswith("/"):
        msg = f"endpoint {original!r}: serial device must be an absolute path such as /dev/ttyACM0"
        raise ConfigError(msg)
    return Endpoint(EndpointKind.SERIAL, device=device, baud=baud)


def _parse_host_port(kind: EndpointKind, rest: str, original: str) -> Endpoint:
    host, found, port_text = rest.rpartition(":")
    if not found:
        msg = f"endpoint {original!r}: expected HOST:PORT after '{kind.value}:'"
        raise ConfigError(msg)
    host = host.strip("[]")
    if not host:
        if not kind.listens:
            msg = f"endpoint {original!r}: {kind.value} needs a host to send to"
            raise ConfigError(msg)
        host = "0.0.0.0"  # MAVSDK's "udpin://:14540" means every interface
    try:
        port = int(port_text)
    except ValueError as err:
        msg = f"endpoint {original!r}: port {port_text!r} is not an integer"
        raise ConfigError(msg) from err
    # Port 0 = "any free port" is only meaningful when we listen.
    low = 0 if kind.listens else 1
    if not low <= port <= 65535:
        msg = f"endpoint {original!r}: port {port} outside {low}..65535"
        raise ConfigError(msg)
    return Endpoint(kind, host=host, port=port)


def connection_hint(endpoint: Endpoint) -> str:
    """What to check when nothing is heard on ``endpoint`` (logged with the no-heartbeat warning)."""
    if endpoint.kind is EndpointKind.SERIAL:
        return (
            f"check the wiring (TX to RX), the baud rate ({endpoint.baud}; ArduPilot SERIALn_BAUD, PX4 SER_TELn_BAUD) "
            "and that the port speaks MAVLink 2 (ArduPilot SERIALn_PROTOCOL = 2; PX4 MAV_n_CONFIG / MAV_n_MODE = "
            "Onboard); the device must be readable by this user (group dialout)"
        )
    where = f"{endpoint.host or '*'}:{endpoint.port}"
    if endpoint.kind is EndpointKind.UDPIN:
        return (
            f"nothing sends to {where}: the autopilot, SITL or mavlink-router must send UDP to this port "
            "(e.g. mavlink-router's UdpEndpoint Mode=Normal Address=<this host> Port=" + str(endpoint.port) + ")"
        )
    if endpoint.kind is EndpointKind.TCPIN:
        return f"no autopilot has connected to {where}: point its TCP client (or mavlink-router) at this port"
    return (
        f"is the autopilot, SITL or mavlink-router listening at {where}? check the host, the port "
        "(SITL: tcp:127.0.0.1:5760, udp 14550/14540) and a firewall"
    )


def parse_endpoint(text: str) -> Endpoint:
    """Parse a connection string (see the module docstring) into an ``Endpoint``.

    Raises:
        ConfigError: the string is not one of the accepted forms; the message says which part is wrong.
    """
    original = text
    text = text.strip()
    if not text:
        msg = "endpoint is empty; expected e.g. udpin:127.0.0.1:14550, tcp:127.0.0.1:5760 or /dev/ttyACM0:57600"
        raise ConfigError(msg)
    if text.startswith("/"):
        return _parse_serial(text, original)
    scheme, found, rest = text.partition(":")
    kind = _SCHEMES.get(scheme.lower())
    if not found or kind is None:
        msg = (
            f"endpoint {original!r}: unknown scheme {scheme!r}; "
            f"expected one of {', '.join(sorted(_SCHEMES))} or a /dev/... serial path"
        )
        raise ConfigError(msg)
    if rest.startswith("//"):  # MAVSDK URL form
        rest = rest[2:]
    if kind is EndpointKind.SERIAL:
        return _parse_serial(rest, original)
    return _parse_host_port(kind, rest, original)

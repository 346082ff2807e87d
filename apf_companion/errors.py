"""The one error tree of apf-companion: every error the package raises derives from ApfCompanionError."""

from __future__ import annotations

__all__ = ["ApfCompanionError", "CommandRejected", "ConfigError", "LinkError", "LinkTimeout", "ProtocolError"]


class ApfCompanionError(Exception):
    """Root of all apf-companion errors."""


class ConfigError(ApfCompanionError, ValueError):
    """A configuration or parameter value is invalid; the message names the key and the allowed range."""


class LinkError(ApfCompanionError):
    """A transport (UDP, TCP, serial, zenoh) failed or could not be opened."""


class LinkTimeout(LinkError, TimeoutError):
    """A wait on a link passed its deadline."""


class ProtocolError(ApfCompanionError):
    """A peer sent something that breaks the protocol (malformed frame, impossible field)."""


class CommandRejected(ApfCompanionError):
    """The autopilot answered a command with a COMMAND_ACK result other than ACCEPTED."""

    def __init__(self, command: int, result: int, message: str | None = None) -> None:
        self.command = command
        self.result = result
        super().__init__(message or f"command {command} rejected with MAV_RESULT {result}")

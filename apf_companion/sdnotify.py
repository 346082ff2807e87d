"""systemd's service notification protocol (sd_notify), in-house: READY, WATCHDOG, STATUS, STOPPING.

The protocol is one datagram of ``KEY=value`` lines to the AF_UNIX socket named by ``NOTIFY_SOCKET`` (a path, or
an abstract name starting with ``@``), see sd_notify(3). It is a dozen lines, so it is written here instead of
depending on ``python-systemd`` (a C extension that needs libsystemd headers to build) or the ``sdnotify`` package
(unmaintained since 2017). Only active when systemd set ``NOTIFY_SOCKET`` (``Type=notify`` units); otherwise
``SystemdNotifier.from_env`` gives None and the service sends nothing.

The watchdog: with ``WatchdogSec=`` systemd sets ``WATCHDOG_USEC`` (and ``WATCHDOG_PID``); the service must send
``WATCHDOG=1`` more often than that or it is killed and restarted (``Restart=on-failure``). ``Watchdog.pet`` is
called after every completed planning cycle and sends at most one ``WATCHDOG=1`` per half period, so a hung or
failing cycle stops the petting (docs/deployment.md).

Sending never raises: a failed send is counted (``errors``) and logged once.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from collections.abc import Callable, Mapping

__all__ = ["SystemdNotifier", "Watchdog"]

log = logging.getLogger(__name__)

US = 1e-6


class SystemdNotifier:
    """Sends notifications to ``NOTIFY_SOCKET``. Create with ``from_env`` (None outside a notify unit).

    Args:
        address: The socket path, or an abstract name starting with ``@``.
        watchdog_usec: ``WATCHDOG_USEC`` when the watchdog is on (for this process), else None.
    """

    def __init__(self, address: str, *, watchdog_usec: int | None = None) -> None:
        self.address = "\0" + address[1:] if address.startswith("@") else address
        self.watchdog_usec = watchdog_usec
        self.sent = 0
        self.errors = 0
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        self._sock.setblocking(False)

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None) -> SystemdNotifier | None:
        """From ``NOTIFY_SOCKET`` / ``WATCHDOG_USEC`` / ``WATCHDOG_PID`` (the watchdog only if it is ours)."""
        env = os.environ if env is None else env
        address = env.get("NOTIFY_SOCKET", "")
        if not address:
            return None
        usec: int | None = None
        try:
            usec = int(env.get("WATCHDOG_USEC", "0")) or None
            pid = env.get("WATCHDOG_PID")
            if pid and int(pid) != os.getpid():
                usec = None  # the watchdog is for another process (sd_watchdog_enabled(3))
        except ValueError:
            log.warning("sdnotify.bad_env", extra={"WATCHDOG_USEC": env.get("WATCHDOG_USEC")})
            usec = None
        return cls(address, watchdog_usec=usec)

    def notify(self, **fields: str | int) -> bool:
        """Send one notification (``notify(READY=1, STATUS="...")``); False if it could not be sent."""
        text = "\n".join(f"{k}={v}" for k, v in fields.items())
        try:
            self._sock.sendto(text.encode("utf-8", errors="replace"), self.address)
        except OSError as err:
            self.errors += 1
            if self.errors == 1:
                log.warning("sdnotify.send_failed", extra={"error": f"{type(err).__name__}: {err}"})
            return False
        self.sent += 1
        return True

    def close(self) -> None:
        self._sock.close()


class Watchdog:
    """``WATCHDOG=1`` at most once per half ``WATCHDOG_USEC``, and ``STATUS=`` when the status text changes.

    Args:
        notifier: Where to send.
        monotonic: Wall clock in seconds (injectable for tests).
    """

    def __init__(self, notifier: SystemdNotifier, *, monotonic: Callable[[], float] = time.monotonic) -> None:
        self.notifier = notifier
        self.monotonic = monotonic
        usec = notifier.watchdog_usec
        self.interval_s = None if usec is None else 0.5 * usec * US
        self.pets = 0
        self._last_pet_s: float | None = None
        self._status = ""

    def pet(self, status: str) -> None:
        """A planning cycle completed: pet the watchdog when half its period has passed; report a new status."""
        fields: dict[str, str | int] = {}
        now = self.monotonic()
        if self.interval_s is not None and (self._last_pet_s is None or now - self._last_pet_s >= self.interval_s):
            fields["WATCHDOG"] = 1
        if status != self._status:
            fields["STATUS"] = status
        if fields and self.notifier.notify(**fields):
            self._status = status
            if "WATCHDOG" in fields:
                self._last_pet_s = now
                self.pets += 1

#!/usr/bin/env bash
# Install apf-companion as a systemd service on a companion computer (Raspberry Pi OS / Ubuntu on Jetson).
#
#   sudo ./deploy/install.sh            # from a checkout of the repository
#
# What it does: creates the system user "apf", a virtualenv in /opt/apf-companion/venv with this checkout
# installed, /etc/apf-companion/apf-companion.toml (kept if it exists), the systemd unit, and enables it.
# The first start runs with the config as installed: review it (autopilot profile, link, dry_run) before
# flying. Set dry_run = true for a first flight to see the plan in the log without commanding the vehicle.
set -euo pipefail

if [[ $EUID -ne 0 ]]; then
    echo "run as root (sudo $0)" >&2
    exit 1
fi
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/.." && pwd)"
prefix=/opt/apf-companion
python="${PYTHON:-python3}"

"$python" - <<'PY'
import sys
if sys.version_info < (3, 11):
    sys.exit("apf-companion needs Python >= 3.11")
PY

id -u apf >/dev/null 2>&1 || useradd --system --home-dir /var/lib/apf-companion --shell /usr/sbin/nologin apf
getent group dialout >/dev/null && usermod -a -G dialout apf

install -d -m 0755 "$prefix"
if [[ ! -x "$prefix/venv/bin/python" ]]; then
    "$python" -m venv "$prefix/venv"
fi
"$prefix/venv/bin/pip" install --upgrade pip wheel
"$prefix/venv/bin/pip" install "$repo"

install -d -m 0755 /etc/apf-companion
if [[ ! -f /etc/apf-companion/apf-companion.toml ]]; then
    # Record the link in the state directory by default.
    sed -e 's|^tlog = ""|tlog = "/var/lib/apf-companion/companion.tlog"|' \
        "$here/apf-companion.toml" > /etc/apf-companion/apf-companion.toml
    echo "installed /etc/apf-companion/apf-companion.toml (review it)"
else
    echo "kept existing /etc/apf-companion/apf-companion.toml"
fi
"$prefix/venv/bin/apf-companion" check-config /etc/apf-companion/apf-companion.toml >/dev/null

install -m 0644 "$here/apf-companion.service" /etc/systemd/system/apf-companion.service
systemctl daemon-reload
systemctl enable apf-companion.service
echo "enabled apf-companion.service; start it with: systemctl start apf-companion"
if ! command -v mavlink-routerd >/dev/null 2>&1; then
    echo "note: mavlink-router not found; see deploy/mavlink-router.conf for the UART -> UDP setup"
fi

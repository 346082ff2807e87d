#!/usr/bin/env bash
# Install apf-companion as a sandboxed systemd service on a companion computer (Raspberry Pi OS, Ubuntu on Jetson).
#
#   sudo ./deploy/install.sh                  # from a checkout of the repository
#   ./deploy/install.sh --dry-run             # print what it would do, change nothing
#   sudo ./deploy/install.sh --with-mavproxy  # also MAVProxy as the UART -> UDP router (apf-mavproxy.service)
#   sudo ./deploy/install.sh --uninstall [--purge]
#
# What it does: creates the system user "apf", a virtualenv in PREFIX/venv (default /opt/apf-companion) with this
# checkout (or --wheel FILE) installed, /etc/apf-companion/apf-companion.toml (kept if it exists), the systemd
# unit, and enables it. The first start runs with the config as installed: review it (autopilot profile, link,
# dry_run) before flying. Set dry_run = true for a first flight to see the plan in the log without commanding the
# vehicle.
#
# Options:
#   --dry-run          print every step, change nothing (no root needed)
#   --uninstall        stop and disable the units, remove them and the venv; keep config, state and user
#   --purge            with --uninstall: also remove /etc/apf-companion, /var/lib/apf-companion and the user
#   --with-mavproxy    install MAVProxy into the venv and apf-mavproxy.service (mavlink-router alternative)
#   --wheel FILE       install this wheel instead of the checkout
#   --prefix DIR       install root of the venv (default /opt/apf-companion); the unit's paths follow it
#   --destdir DIR      stage everything under DIR (packaging, tests): no user, no systemctl, no root needed
#                      (also $DESTDIR)
#   --no-venv          leave PREFIX/venv alone (you manage it); write config and units only
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/.." && pwd)"
prefix=/opt/apf-companion
destdir="${DESTDIR:-}"
python="${PYTHON:-python3}"
dry_run=0 uninstall=0 purge=0 with_mavproxy=0 no_venv=0 wheel=""

# The comment block after the shebang, up to the first line that is not a comment.
usage() { awk 'NR == 1 { next } !/^#/ { exit } { sub(/^# ?/, ""); print }' "$0"; exit "${1:-0}"; }
while [[ $# -gt 0 ]]; do
    case $1 in
        --dry-run) dry_run=1 ;;
        --uninstall) uninstall=1 ;;
        --purge) purge=1 ;;
        --with-mavproxy) with_mavproxy=1 ;;
        --no-venv) no_venv=1 ;;
        --wheel) wheel="$(cd "$(dirname "$2")" && pwd)/$(basename "$2")"; shift ;;
        --prefix) prefix="$2"; shift ;;
        --destdir) destdir="$2"; shift ;;
        -h|--help) usage 0 ;;
        *) echo "install.sh: unknown option $1" >&2; usage 2 ;;
    esac
    shift
done
if [[ $purge -eq 1 && $uninstall -eq 0 ]]; then
    echo "install.sh: --purge goes with --uninstall" >&2; exit 2
fi
if [[ $prefix != /* ]]; then
    echo "install.sh: --prefix must be an absolute path, got $prefix" >&2; exit 2
fi

etc="$destdir/etc/apf-companion"
units="$destdir/etc/systemd/system"
state="$destdir/var/lib/apf-companion"
venv="$destdir$prefix/venv"

# run CMD...: do it, or print it with --dry-run. host CMD...: the same, but only on the real system (no DESTDIR).
run() {
    if [[ $dry_run -eq 1 ]]; then printf 'would run:'; printf ' %q' "$@"; printf '\n'; else "$@"; fi
}
host() {
    if [[ -n $destdir ]]; then printf 'skipped (--destdir):'; printf ' %q' "$@"; printf '\n'; else run "$@"; fi
}
# render SRC DEST: a unit with the venv's path under --prefix.
render() {
    if [[ $dry_run -eq 1 ]]; then echo "would write: $2 (from $1, venv $prefix/venv)"; return; fi
    sed -e "s|/opt/apf-companion/venv|$prefix/venv|g" "$1" > "$2"
    chmod 0644 "$2"
}

if [[ $dry_run -eq 0 && -z $destdir && $EUID -ne 0 ]]; then
    echo "run as root (sudo $0), or try --dry-run" >&2
    exit 1
fi

if [[ $uninstall -eq 1 ]]; then
    for unit in apf-companion.service apf-mavproxy.service; do
        if [[ -f $units/$unit ]]; then
            host systemctl disable --now "$unit"
            run rm -f "$units/$unit"
        fi
    done
    host systemctl daemon-reload
    run rm -rf "$venv"
    [[ -d $destdir$prefix ]] && run rmdir --ignore-fail-on-non-empty "$destdir$prefix"
    if [[ $purge -eq 1 ]]; then
        run rm -rf "$etc" "$state" "$destdir/var/lib/apf-mavproxy"
        if [[ -z $destdir ]] && id -u apf >/dev/null 2>&1; then run userdel apf; fi
    else
        echo "kept $etc, $state and the user apf (--purge removes them)"
    fi
    echo "uninstalled apf-companion"
    exit 0
fi

"$python" - <<'PY'
import sys
if sys.version_info < (3, 11):
    sys.exit("apf-companion needs Python >= 3.11")
PY

if ! id -u apf >/dev/null 2>&1; then
    host useradd --system --home-dir /var/lib/apf-companion --shell /usr/sbin/nologin apf
fi
if getent group dialout >/dev/null; then host usermod -a -G dialout apf; fi

if [[ $no_venv -eq 0 ]]; then
    run install -d -m 0755 "$destdir$prefix"
    [[ -x $venv/bin/python ]] || run "$python" -m venv "$venv"
    run "$venv/bin/pip" install --upgrade pip
    run "$venv/bin/pip" install "${wheel:-$repo}"
    # MAVProxy without its ~1 GB of GUI dependencies (pymavlink and pyserial come with apf-companion).
    [[ $with_mavproxy -eq 1 ]] && run "$venv/bin/pip" install --no-deps MAVProxy
fi

run install -d -m 0755 "$etc" "$units"
if [[ ! -f $etc/apf-companion.toml ]]; then
    # Record the link in the state directory by default.
    if [[ $dry_run -eq 1 ]]; then
        echo "would write: $etc/apf-companion.toml (from $here/apf-companion.toml, tlog in the state directory)"
    else
        sed -e 's|^tlog = ""|tlog = "/var/lib/apf-companion/companion.tlog"|' \
            "$here/apf-companion.toml" > "$etc/apf-companion.toml"
        chmod 0644 "$etc/apf-companion.toml"
        echo "installed $etc/apf-companion.toml (review it)"
    fi
else
    echo "kept existing $etc/apf-companion.toml"
fi
if [[ $no_venv -eq 0 ]]; then
    run "$venv/bin/apf-companion" check-config "$etc/apf-companion.toml"
fi
render "$here/apf-companion.service" "$units/apf-companion.service"
if [[ $with_mavproxy -eq 1 ]]; then
    render "$here/apf-mavproxy.service" "$units/apf-mavproxy.service"
    [[ -f $etc/mavproxy.env ]] || run install -m 0644 "$here/mavproxy.env" "$etc/mavproxy.env"
fi
host systemctl daemon-reload
host systemctl enable apf-companion.service
[[ $with_mavproxy -eq 1 ]] && host systemctl enable apf-mavproxy.service
echo "apf-companion.service installed; start it with: systemctl start apf-companion"
if [[ $with_mavproxy -eq 0 ]] && ! command -v mavlink-routerd >/dev/null 2>&1; then
    echo "note: no MAVLink router found: --with-mavproxy installs MAVProxy as one; docs/ecosystem.md shows how to"
    echo "      build mavlink-router (deploy/mavlink-router.conf)"
fi
exit 0

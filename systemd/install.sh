#!/usr/bin/env bash
# Install (or --uninstall) the treetraits onboard service from this checkout.
#
#   sudo systemd/install.sh               # or: sudo make install
#   sudo systemd/install.sh --uninstall   # or: sudo make uninstall
#   DESTDIR=/tmp/root systemd/install.sh --no-venv   # stage into a tree, no root needed
#
# Installs: the venv PREFIX/venv (default /opt/treetraits, `pip install .` of this checkout
# with the first Python >= 3.10), the unit /etc/systemd/system/treetraits.service, the udev
# rules /etc/udev/rules.d/99-treetraits.rules, the sysctl file
# /etc/sysctl.d/60-treetraits.conf, and the default config /etc/treetraits/config.toml
# (only when there is none: a user's config is never overwritten). Creates the system
# user `treetraits` (groups dialout, video). Then applies the sysctl, reloads udev when
# udevd runs, and daemon-reloads and enables (does not start) the unit when systemd is
# PID 1. Running it again installs only what changed (the venv is always re-installed).
#
# With DESTDIR set, files go under DESTDIR and nothing touches the running system (no
# user, no sysctl, no udev, no systemctl). Environment: DESTDIR, PREFIX, PYTHON.
# A live install with the venv also compiles the kernels as the user into the unit's cache
# (/var/cache/treetraits/numba), so that the first start does not.
# --uninstall removes the unit, rules, sysctl file, venv and that cache; it keeps the
# config, the data in /var/lib/treetraits and the user.
set -euo pipefail

SRC="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
DESTDIR="${DESTDIR:-}"
DESTDIR="${DESTDIR%/}"
PREFIX="${PREFIX:-/opt/treetraits}"
PREFIX="${PREFIX%/}"
SERVICE_USER=treetraits
UNIT=treetraits.service

usage() {
    sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'
}

mode=install
venv=yes
for arg in "$@"; do
    case "$arg" in
        --uninstall) mode=uninstall ;;
        --no-venv) venv=no ;;
        -h | --help) usage; exit 0 ;;
        *) echo "install.sh: unknown option $arg (see --help)" >&2; exit 2 ;;
    esac
done

say() { echo "treetraits install: $*"; }
warn() { echo "treetraits install: warning: $*" >&2; }
die() { echo "treetraits install: error: $*" >&2; exit 1; }

live=no # acting on the running system (not staging into DESTDIR)
if [ -z "$DESTDIR" ]; then
    live=yes
    [ "$(id -u)" = 0 ] || die "run as root (sudo make $mode), or stage with DESTDIR=/some/dir"
fi
systemd_running() { [ "$live" = yes ] && [ -d /run/systemd/system ]; }
udevd_running() { [ "$live" = yes ] && [ -S /run/udev/control ] && command -v udevadm >/dev/null; }

# install_file SRC DST MODE: copy when absent or different; says what it did.
install_file() {
    local src=$1 dst=$2 mode=$3
    if [ -f "$dst" ] && cmp -s "$src" "$dst"; then
        say "unchanged $dst"
        return 1
    fi
    install -D -m "$mode" "$src" "$dst"
    say "installed $dst"
}

remove_file() {
    if [ -e "$1" ]; then
        rm -f "$1"
        say "removed $1"
    fi
}

find_python() {
    local p
    if [ -n "${PYTHON:-}" ]; then
        "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 10))' 2>/dev/null \
            || die "PYTHON=$PYTHON is not Python >= 3.10"
        echo "$PYTHON"
        return
    fi
    for p in python3.13 python3.12 python3.11 python3.10 python3; do
        if command -v "$p" >/dev/null 2>&1 \
            && "$p" -c 'import sys; sys.exit(sys.version_info < (3, 10))' 2>/dev/null; then
            command -v "$p"
            return
        fi
    done
    die "treetraits needs Python >= 3.10 (on Ubuntu 20.04 / the Xavier: deadsnakes python3.10 or a uv-managed Python; docs/deployment.md), or set PYTHON="
}

ensure_user() {
    local group
    for group in dialout video; do
        getent group "$group" >/dev/null || { groupadd --system "$group"; say "created group $group"; }
    done
    if ! getent passwd "$SERVICE_USER" >/dev/null; then
        useradd --system --user-group --no-create-home --home-dir /var/lib/treetraits \
            --shell /usr/sbin/nologin --groups dialout,video "$SERVICE_USER"
        say "created system user $SERVICE_USER (groups dialout, video)"
        return
    fi
    local have
    have=" $(id -nG "$SERVICE_USER") "
    for group in dialout video; do
        if [[ "$have" != *" $group "* ]]; then
            usermod -aG "$group" "$SERVICE_USER"
            say "added $SERVICE_USER to group $group"
        fi
    done
}

make_venv() {
    local python venv_dir="$DESTDIR$PREFIX/venv"
    python=$(find_python)
    if [ ! -x "$venv_dir/bin/python" ]; then
        "$python" -m venv "$venv_dir" \
            || die "$python -m venv failed (Debian/Ubuntu: apt install python3-venv, or python3.X-venv)"
        say "created $venv_dir with $("$venv_dir/bin/python" --version)"
    fi
    # Not editable: the service must not depend on this checkout staying where it is.
    # shellcheck disable=SC2086 # PIP_INSTALL_ARGS is a list of options
    "$venv_dir/bin/python" -m pip install --quiet ${PIP_INSTALL_ARGS:-} "$SRC"
    say "installed treetraits $("$venv_dir/bin/python" -c 'import treetraits; print(treetraits.__version__)') into $venv_dir"
}

# The unit's NUMBA_CACHE_DIR (CacheDirectory=treetraits), filled now as the service's user:
# its first start then loads the compiled kernels (~0.4 s) instead of compiling them before
# READY (28-30 s on the development machine, several times that on a Xavier).
CACHE_DIR=/var/cache/treetraits

compile_kernels() {
    local python="$PREFIX/venv/bin/python"
    install -d -m 0750 -o "$SERVICE_USER" -g "$SERVICE_USER" "$CACHE_DIR" "$CACHE_DIR/numba"
    if (cd / && runuser -u "$SERVICE_USER" -- env NUMBA_CACHE_DIR="$CACHE_DIR/numba" \
        "$python" -c 'from treetraits.service.runtime import load_pipeline; load_pipeline()'); then
        say "compiled the kernels into $CACHE_DIR/numba"
    else
        warn "could not compile the kernels into $CACHE_DIR/numba: the service compiles them at its first start"
    fi
}

do_install() {
    local etc="$DESTDIR/etc" unit_tmp changed_rules=no changed_sysctl=no
    [ -f "$SRC/systemd/config.toml" ] || die "$SRC/systemd/config.toml is missing: the default config comes from the checkout"
    [ "$live" = yes ] && ensure_user
    [ "$venv" = yes ] && make_venv
    [ "$live" = yes ] && [ "$venv" = yes ] && compile_kernels

    # The unit names the venv's entry point: follow PREFIX.
    unit_tmp=$(mktemp)
    sed "s#/opt/treetraits/#$PREFIX/#g" "$SRC/systemd/$UNIT" >"$unit_tmp"
    install_file "$unit_tmp" "$etc/systemd/system/$UNIT" 0644 || true
    rm -f "$unit_tmp"
    install_file "$SRC/systemd/99-treetraits.rules" "$etc/udev/rules.d/99-treetraits.rules" 0644 \
        && changed_rules=yes
    install_file "$SRC/systemd/60-treetraits.conf" "$etc/sysctl.d/60-treetraits.conf" 0644 \
        && changed_sysctl=yes
    if [ -e "$etc/treetraits/config.toml" ]; then
        say "kept existing $etc/treetraits/config.toml (the default is $SRC/systemd/config.toml)"
    else
        install_file "$SRC/systemd/config.toml" "$etc/treetraits/config.toml" 0644 || true
    fi

    if [ "$live" = yes ]; then
        if [ "$changed_sysctl" = yes ] || [ "$(sysctl -n net.core.rmem_max 2>/dev/null || echo 0)" -lt 16777216 ]; then
            sysctl -q -p "$etc/sysctl.d/60-treetraits.conf" \
                || warn "could not apply $etc/sysctl.d/60-treetraits.conf (a container?); it applies at the next boot"
        fi
        if udevd_running; then
            if [ "$changed_rules" = yes ]; then
                udevadm control --reload-rules && udevadm trigger
                say "udev rules reloaded"
            fi
        else
            say "udevd is not running: the rules apply when it starts"
        fi
        if systemd_running; then
            systemctl daemon-reload
            systemctl enable "$UNIT"
            say "enabled $UNIT (start it: sudo systemctl start treetraits; check: treetraits doctor)"
        else
            say "systemd is not PID 1 here: not enabling $UNIT"
        fi
    else
        say "staged into $DESTDIR (no user, sysctl, udev or systemctl changes)"
    fi
}

do_uninstall() {
    local etc="$DESTDIR/etc"
    if systemd_running && systemctl list-unit-files "$UNIT" >/dev/null 2>&1; then
        systemctl disable --now "$UNIT" || true
    fi
    remove_file "$etc/systemd/system/$UNIT"
    remove_file "$etc/udev/rules.d/99-treetraits.rules"
    remove_file "$etc/sysctl.d/60-treetraits.conf"
    if [ -d "$DESTDIR$PREFIX/venv" ]; then
        rm -rf "$DESTDIR$PREFIX/venv"
        say "removed $DESTDIR$PREFIX/venv"
        rmdir "$DESTDIR$PREFIX" 2>/dev/null || true
    fi
    if [ -z "$DESTDIR" ] && [ -d "$CACHE_DIR" ]; then
        rm -rf "$CACHE_DIR"
        say "removed $CACHE_DIR (the compiled kernels)"
    fi
    systemd_running && systemctl daemon-reload
    udevd_running && udevadm control --reload-rules
    say "kept $etc/treetraits/ (config), /var/lib/treetraits (data) and the user $SERVICE_USER"
}

"do_$mode"

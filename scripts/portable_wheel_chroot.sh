#!/bin/bash
# The portable wheel on another distribution: a minimal Debian chroot (debootstrap minbase:
# no OpenCV, no compiler, only python3 and its venv) installs the wheel from
# `cargo xtask wheel --portable` with numpy from PyPI and runs scripts/portable_wheel_check.py
# on the fountain (every camera estimated, every relative rotation within 1° of the truth, no
# OpenCV library loaded).
#
# Usage (as root, Debian's and PyPI's registries reachable):
#   bash scripts/portable_wheel_chroot.sh RELEASE [WHEEL] [SHARED]
#   RELEASE: a Debian release debootstrap knows (bookworm: glibc 2.36, Python 3.11;
#            trixie: glibc 2.41, Python 3.13)
#   WHEEL:   default target/portable-wheel/wheels/posediff-*-manylinux_*.whl
#   SHARED:  default ../shared (its data/strecha_fountainP11 is mounted read-only)
# The chroot is made under target/chroot/RELEASE once and reused; the host's CA certificates
# and pip.conf are copied in so that pip reaches PyPI through the same proxy.
set -euo pipefail
release=${1:?usage: portable_wheel_chroot.sh RELEASE [WHEEL] [SHARED]}
root=$(cd "$(dirname "$0")/.." && pwd)
wheel=${2:-$(ls "$root"/target/portable-wheel/wheels/posediff-*-manylinux_*.whl 2>/dev/null | head -1)}
shared=$(cd "${3:-$root/../shared}" && pwd)
[ -f "$wheel" ] || { echo "no portable wheel: run cargo xtask wheel --portable first" >&2; exit 1; }
[ -d "$shared/data/strecha_fountainP11/images" ] || { echo "$shared has no data/strecha_fountainP11" >&2; exit 1; }
command -v debootstrap > /dev/null || { echo "debootstrap is missing: apt-get install debootstrap" >&2; exit 1; }
chroot_dir=$root/target/chroot/$release
if [ ! -x "$chroot_dir/usr/bin/python3" ]; then
  debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates \
    "$release" "$chroot_dir" http://deb.debian.org/debian
fi
cp /etc/resolv.conf "$chroot_dir/etc/resolv.conf"
if ls /usr/local/share/ca-certificates/*.crt > /dev/null 2>&1; then
  cp /usr/local/share/ca-certificates/*.crt "$chroot_dir/usr/local/share/ca-certificates/"
  chroot "$chroot_dir" update-ca-certificates > /dev/null 2>&1
fi
[ -f /etc/pip.conf ] && cp /etc/pip.conf "$chroot_dir/etc/pip.conf"
mkdir -p "$chroot_dir/shared" "$chroot_dir/work"
cp "$wheel" "$root/scripts/portable_wheel_check.py" "$chroot_dir/work/"
cleanup() {
  for m in shared dev proc; do
    mountpoint -q "$chroot_dir/$m" && umount "$chroot_dir/$m"
  done
}
trap cleanup EXIT
mount -t proc proc "$chroot_dir/proc"
mount --bind /dev "$chroot_dir/dev"
mount --bind "$shared" "$chroot_dir/shared"
mount -o remount,bind,ro "$chroot_dir/shared"
if ls "$chroot_dir"/usr/lib/x86_64-linux-gnu/libopencv_* > /dev/null 2>&1; then
  echo "the chroot has OpenCV: not a check of the portable wheel" >&2
  exit 1
fi
chroot "$chroot_dir" /usr/bin/env -i PATH=/usr/bin:/bin HOME=/root PIP_DISABLE_PIP_VERSION_CHECK=1 \
  /bin/bash -c "set -e
    echo \"\$(ldd --version | head -1), \$(python3 --version)\"
    rm -rf /venv && python3 -m venv /venv
    /venv/bin/pip install -q /work/$(basename "$wheel")
    /venv/bin/pip list 2>/dev/null | grep -E '^(numpy|posediff) '
    /venv/bin/python /work/portable_wheel_check.py /shared/data/strecha_fountainP11"

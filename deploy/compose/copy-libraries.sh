#!/bin/sh
# Copies into DIR the shared libraries that BINARY... load (directly or
# through another library) and that belong to one of the Debian packages
# named in COPIED_PACKAGES below, as their real files under their sonames.
# The Dockerfile's build stage runs it; the runtime stage installs every
# other library from packages (scripts/install-deps.sh --runtime) and checks
# with ldd that nothing is missing. Why OpenCV's libraries are copied rather
# than installed: docs/decisions/0038-a-lean-runtime-image.md.
#
#   deploy/compose/copy-libraries.sh DIR BINARY...
set -eu

# OpenCV's libraries (libopencv-contrib406 holds wechat_qrcode), and the GL
# dispatch libraries that libopencv_core names but never calls without a
# display. tests/deploy/runtime_packages_test.py reads this line.
COPIED_PACKAGES="libopencv-core406 libopencv-imgproc406 libopencv-calib3d406 \
  libopencv-features2d406 libopencv-flann406 libopencv-objdetect406 libopencv-dnn406 \
  libopencv-contrib406 libglx0 libglvnd0"

if [ $# -lt 2 ]; then
  echo "usage: $0 DIR BINARY..." >&2
  exit 2
fi
dir="$1"
shift
mkdir -p "$dir"

# Every file each copied package installs, by its base name.
owned="$(mktemp)"
trap 'rm -f "$owned"' EXIT
# shellcheck disable=SC2086
dpkg -L $COPIED_PACKAGES | sed 's|.*/||' | sort -u > "$owned"

copied=0
for lib in $(ldd "$@" | awk '$2 == "=>" && $3 ~ /^\// { print $3 }' | sort -u); do
  name="${lib##*/}"
  if grep -qxF "$name" "$owned"; then
    cp -L "$lib" "$dir/$name"
    copied=$((copied + 1))
  fi
done
if [ "$copied" -eq 0 ]; then
  echo "copy-libraries: no library of $COPIED_PACKAGES is loaded by $*" >&2
  exit 1
fi
echo "copy-libraries: $copied libraries into $dir"

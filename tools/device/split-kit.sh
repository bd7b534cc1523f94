#!/usr/bin/env bash
# Splits the Warp kit (.device/warp-1.19.0, from ../shared/device/make-warp-kit.sh) into two carries that each fit
# one device call beside the work tree: .device/kit1 (the first 30 MB of warp.so.xz) and .device/kit2 (the rest,
# the Python files and the installer). tools/device/install-kit.sh joins them on the GPU machine.
set -euo pipefail
kit=${1:-.device/warp-1.19.0}
rm -rf .device/kit1 .device/kit2 && mkdir -p .device/kit1 .device/kit2
head -c 30000000 "$kit/warp.so.xz" > .device/kit1/warp.so.xz.part_a
tail -c +30000001 "$kit/warp.so.xz" > .device/kit2/warp.so.xz.part_b
cp "$kit/install.sh" "$kit/warp-py.tar.xz" .device/kit2/
cat .device/kit1/warp.so.xz.part_a .device/kit2/warp.so.xz.part_b | cmp - "$kit/warp.so.xz"
du -sh .device/kit1 .device/kit2

#!/usr/bin/env bash
# The protocol's checks on one GPU, for tools/device/background.sh (start it after the kit's install, with
# .device/camvid copied to /tmp/camvid): the CamVid camera study's positive control (clean sRGB), A/A check (the fixed
# ISP twice) and co-design against the fixed ISP on block fold 1, then the photon map's contested pair (f/1.4 30 ms
# against the preset's f/2 10 ms) on the same fold; 3 seeds each, the presets' 150 epochs, three cells at once under
# MPS. Each study directory is under /tmp/studies; `background.sh poll SECONDS /tmp/studies` brings them back.
# Usage: bash tools/device/protocol.sh [FOLD]   (default block1)
# Measured with it: docs/results.md, the protocol (block1, 18 cells, 881 + 458 s on one H200).
set -u
fold=${1:-block1}
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
git log -1 --format='commit %h %s' 2>/dev/null || true
mkdir -p /tmp/studies
python -m warpsense study run camvid_cameras --out /tmp/studies/camvid_cameras --gpus 0 --per-gpu 3 --mps on \
  --set data.root=/tmp/camvid \
  --cells "fixed_isp/night/$fold/*" --cells "fixed_isp_twin/night/$fold/*" --cells "clean_srgb/night/$fold/*" \
  --cells "codesign/night/$fold/*"
python -m warpsense study run camvid_photon_map --out /tmp/studies/camvid_photon_map --gpus 0 --per-gpu 3 --mps on \
  --set data.root=/tmp/camvid --cells "map_f2_t10/night/$fold/*" --cells "map_f1p4_t30/night/$fold/*"

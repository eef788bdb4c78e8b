#!/usr/bin/env bash
# The main job of `make demo` on the embedded default (see README).
set -euo pipefail
cd "$(dirname "$0")/.."
LM=.venv/bin/loopmodel
OUT=results/demo
SRC=../shared/data/kitti_clip
if [ ! -d "$SRC" ]; then
  echo "../shared is absent: using the bundled tiny sequence datasets/tiny_kitti"
  SRC=datasets/tiny_kitti
fi
mkdir -p "$OUT"
$LM info "$SRC"
$LM convert "$SRC" "$OUT/sequence.mcap"
$LM info "$OUT/sequence.mcap"
echo
echo "demo results: $(pwd)/$OUT"

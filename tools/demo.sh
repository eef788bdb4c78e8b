#!/usr/bin/env bash
# The main job of `make demo` on the embedded default (see README): generate the bundled
# synthetic scan once, run the whole pipeline on it, mesh its laser stripes, evaluate it.
set -euo pipefail
cd "$(dirname "$0")/.."
LM=.venv/bin/loopmodel
SAMPLE=datasets/sample/scan.mcap
OUT=results
NAME=demo
if [ ! -f "$SAMPLE" ]; then
  echo "generating the bundled sample $SAMPLE (orbit preset, 600 frames; about a minute on 2 cores)"
  $LM simulate scan --config configs/sim.yaml --out "$SAMPLE"
fi
$LM info "$SAMPLE"
$LM run "$SAMPLE" --config configs/sim.yaml --out "$OUT" --name "$NAME" --rerun "$OUT/$NAME.rrd"
mv -f "$OUT/$NAME.rrd" "$OUT/$NAME/run.rrd"  # open it with: .venv/bin/rerun results/demo/run.rrd
[ -f "$OUT/$NAME/mesh.ply" ] || $LM mesh "$OUT/$NAME" --out "$OUT/$NAME/mesh.ply"
$LM eval "$OUT/$NAME" --gt "$SAMPLE"
echo
echo "demo results: $(pwd)/$OUT/$NAME"

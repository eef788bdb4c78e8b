#!/usr/bin/env bash
# The main job of `make demo` on the embedded default (see README): generate the bundled
# synthetic scan (realistic sensor, lens, laser and motion: issue 17) once, run the whole pipeline on it, mesh its laser stripes, evaluate it.
set -euo pipefail
cd "$(dirname "$0")/.."
LM=.venv/bin/loopmodel
SAMPLE=datasets/sample/scan.mcap
OUT=results
NAME=demo
# the sample is the realistic world (issue 17); an older clean sample is regenerated
level() {
  .venv/bin/python -c "import json,sys; from loopmodel.io.mcap_io import McapSequence; \
print(json.loads(McapSequence(sys.argv[1]).metadata['simulation']['config_json']).get('realism',{}).get('level','clean'))" "$1" 2>/dev/null || echo none
}
if [ -f "$SAMPLE" ] && [ "$(level "$SAMPLE")" != realistic ]; then
  echo "$SAMPLE is not the realistic world: regenerating it"
  rm -f "$SAMPLE" "${SAMPLE%.mcap}.scene.ply"
fi
if [ ! -f "$SAMPLE" ]; then
  echo "generating the bundled sample $SAMPLE (orbit preset, realistic world, 600 frames; a few minutes on 2 cores)"
  $LM simulate scan --config configs/sim.yaml --out "$SAMPLE"
fi
$LM info "$SAMPLE"
# results/demo is the demo's own folder: a second `make demo` replaces it (--overwrite)
mkdir -p "$OUT"  # a fresh clone has no results folder (--rerun wants an existing one)
rm -f "$OUT/$NAME.rrd"  # a recording an interrupted demo left behind
$LM run "$SAMPLE" --config configs/sim.yaml --out "$OUT" --name "$NAME" --rerun "$OUT/$NAME.rrd" --overwrite
mv -f "$OUT/$NAME.rrd" "$OUT/$NAME/run.rrd"  # open it with: .venv/bin/rerun results/demo/run.rrd
[ -f "$OUT/$NAME/mesh.ply" ] || $LM mesh "$OUT/$NAME" --out "$OUT/$NAME/mesh.ply"
$LM eval "$OUT/$NAME" --gt "$SAMPLE"
echo
echo "demo results: $(pwd)/$OUT/$NAME"

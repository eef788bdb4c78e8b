#!/usr/bin/env bash
# A rerun recording (.rrd) to a PNG, headless:  tools/screenshot_rerun.sh RUN.rrd [OUT.png]
# Runs the rerun viewer in a virtual X server (Debian's xvfb) on the CPU (mesa-vulkan-drivers:
# llvmpipe); installs both when they are missing and we are root (`make viewer-libs` does the same).
set -euo pipefail
rrd=${1:?usage: tools/screenshot_rerun.sh RUN.rrd [OUT.png]}
out=${2:-${rrd%.rrd}.png}
[ -f "$rrd" ] || { echo "error: $rrd: no such recording" >&2; exit 2; }
here=$(cd "$(dirname "$0")/.." && pwd)
rerun=${RERUN:-$(command -v rerun || echo "$here/.venv/bin/rerun")}
[ -x "$rerun" ] || { echo "error: the rerun viewer is not installed: pip install 'loopmodel[viz]'" >&2; exit 1; }
if ! command -v xvfb-run >/dev/null || ! ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    echo "installing Debian's xvfb and mesa-vulkan-drivers (headless rerun screenshots)" >&2
    apt-get install -y -q xvfb mesa-vulkan-drivers >/dev/null 2>&1 || \
      { apt-get update -q >/dev/null && apt-get install -y -q xvfb mesa-vulkan-drivers >/dev/null; }
  else
    echo "error: xvfb-run or a Vulkan driver is missing: sudo apt-get install xvfb mesa-vulkan-drivers" >&2; exit 1
  fi
fi
timeout "${TIMEOUT:-180}" xvfb-run -a -s "-screen 0 ${SIZE:-1280x800}x24" \
  "$rerun" "$rrd" --screenshot-to "$(realpath -m "$out")" --window-size "${SIZE:-1280x800}" >/dev/null 2>&1
[ -s "$out" ] || { echo "error: rerun wrote no screenshot to $out" >&2; exit 1; }
echo "wrote $out"

#!/usr/bin/env bash
# Render an evaluation report (report.html) to a PNG in headless Chromium, to check how the
# page looks in a real browser:  tools/screenshot_report.sh results/demo_eval/report.html [out.png]
# Installs Debian's chromium when it is missing and we are root.
set -euo pipefail
html=${1:?usage: tools/screenshot_report.sh REPORT.html [OUT.png]}
out=${2:-${html%.html}.png}
[ -f "$html" ] || { echo "error: $html: no such report" >&2; exit 2; }
if ! command -v chromium >/dev/null; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    echo "installing Debian's chromium (headless screenshots)" >&2
    apt-get install -y -q chromium >/dev/null 2>&1 || { apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null; }
  else
    echo "error: chromium is not installed: sudo apt-get install chromium" >&2; exit 1
  fi
fi
profile=$(mktemp -d)
trap 'rm -rf "$profile"' EXIT
# the flags keep a closed network quiet (no background connections, no first-run work)
chromium --headless --no-sandbox --disable-gpu --disable-quic --no-first-run \
  --disable-background-networking --disable-component-update --disable-sync \
  --user-data-dir="$profile" --hide-scrollbars --window-size=1200,${HEIGHT:-4000} \
  --screenshot="$(realpath -m "$out")" "file://$(realpath "$html")" >/dev/null 2>&1
echo "wrote $out"

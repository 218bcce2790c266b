#!/usr/bin/env bash
# Open a recording in the Rerun web viewer in Chromium under Xvfb (no GPU needed) and save a
# screenshot of the view it opens on. A tool for looking at the designed view, not a CI test.
#
#   scripts/screenshot_recording.sh RUN.rrd OUT.png [WIDTH HEIGHT WAIT_S]
#
# Needs (Debian/Ubuntu):  apt-get update && apt-get install -y chromium xvfb xauth
# and the project's .venv (./run tests tests/unit/test_layering.py -q builds it; its Pillow, a
# rerun-sdk dependency, grabs the screen).
# Chromium renders WebGL with SwiftShader (software) and the viewer is asked for its WebGL
# renderer (&renderer=webgl): its default WebGPU renderer fails on a machine without a GPU. The
# GPU watchdog is off: software rendering on a busy machine is slow enough for it to kill the
# GPU process (the page then goes black).
# Everything binds to 127.0.0.1; the viewer is stopped by its own pid on exit. CHROMIUM_LOG=FILE
# keeps the browser's log.
set -euo pipefail
cd "$(dirname "$0")/.."
rrd=${1:?usage: scripts/screenshot_recording.sh RUN.rrd OUT.png [WIDTH HEIGHT WAIT_S]}
out=${2:?usage: scripts/screenshot_recording.sh RUN.rrd OUT.png [WIDTH HEIGHT WAIT_S]}
width=${3:-1600}
height=${4:-1000}
wait_s=${5:-25}
for tool in chromium xvfb-run; do
  command -v "$tool" >/dev/null || { echo "error: $tool is not installed; apt-get install -y chromium xvfb xauth" >&2; exit 2; }
done
[ -f "$rrd" ] || { echo "error: $rrd: no such recording" >&2; exit 2; }
export RERUN_ANALYTICS=0
rerun=$(.venv/bin/python -c 'from autopower.recording.merge import rerun_binary; print(rerun_binary())')
free_port() { .venv/bin/python -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
rm -f "$out"
web=$(free_port)
grpc=$(free_port)
"$rerun" --serve-web --bind 127.0.0.1 --web-viewer-port "$web" --port "$grpc" "$rrd" >/dev/null 2>&1 &
viewer=$!
profile=$(mktemp -d)
trap 'kill "$viewer" 2>/dev/null || true; wait "$viewer" 2>/dev/null || true; rm -rf "$profile"' EXIT
for _ in $(seq 100); do
  (exec 3<>"/dev/tcp/127.0.0.1/$web") 2>/dev/null && break
  sleep 0.2
done
url="http://127.0.0.1:$web/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A$grpc%2Fproxy&renderer=webgl"
echo "viewer: $url" >&2
# Chromium runs in a real (virtual) X display, not --headless: the headless screenshot is taken
# before the wasm viewer has drawn anything. The display is grabbed (Pillow) every 15 s until
# WAIT_S; the last grab that shows more than a blank page is kept (software WebGL on a busy
# machine can take minutes to load a recording).
export CHROMIUM_FLAGS="--no-sandbox --test-type --user-data-dir=$profile --no-first-run --disable-infobars \
  --use-angle=swiftshader --enable-unsafe-swiftshader --ignore-gpu-blocklist --disable-gpu-watchdog \
  --disable-backgrounding-occluded-windows --disable-renderer-backgrounding --disable-background-timer-throttling \
  --window-position=0,0 --window-size=$width,$height --app=$url"
export OUT=$(realpath -m "$out") WAIT_S=$wait_s PY=$PWD/.venv/bin/python LOG=${CHROMIUM_LOG:-/dev/null}
timeout $((wait_s + 60)) xvfb-run -a -s "-screen 0 ${width}x${height}x24 -nolisten tcp" bash -c '
  chromium $CHROMIUM_FLAGS >"$LOG" 2>&1 &
  browser=$!
  "$PY" - <<"PY"
import os, time
from PIL import ImageGrab
end = time.monotonic() + float(os.environ["WAIT_S"])
while True:
    time.sleep(max(0.0, min(15.0, end - time.monotonic())))
    shot = ImageGrab.grab(xdisplay=os.environ["DISPLAY"])
    colours = shot.convert("RGB").resize((400, 250)).getcolors(maxcolors=1 << 16)
    if colours is None or len(colours) > 200:  # a drawn view, not a blank or loading page
        shot.save(os.environ["OUT"], optimize=True)
    if time.monotonic() >= end:
        break
PY
  kill $browser; wait $browser 2>/dev/null || true'
[ -s "$out" ] || { echo "error: the viewer showed nothing in ${wait_s} s; try a longer WAIT_S" >&2; exit 1; }
echo "$out"

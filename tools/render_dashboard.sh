#!/usr/bin/env bash
# Render the Rerun dashboard headless and take screenshots, to look at it as a user would.
#
#   tools/render_dashboard.sh [OUT_DIR] [RRD]
#
# Without RRD it first runs `feedmon demo` (12 s milling trial replayed at 10×) into OUT_DIR/demo and
# renders OUT_DIR/demo/monitor.rrd. Writes OUT_DIR/dashboard.png (the viewer as it opens: time cursor
# at the end) and, with xdotool, OUT_DIR/dashboard-mid.png (time bar clicked at CURSOR of the run).
# Needs Debian's packages:
#   apt-get install -y xvfb mesa-vulkan-drivers imagemagick x11-utils xdotool
# Environment: PYTHON (default python), WAIT (s for the software renderer, default 25),
# SIZE (default 1920x1080), CURSOR (default 0.5), DURATION and RATE of the demo.
# Not run by CI. Starts its own Xvfb on a free display and its own viewer on a free port, and stops
# both (by their process ids) on exit.
set -euo pipefail

OUT=${1:-dashboard-shots}
RRD=${2:-}
WAIT=${WAIT:-25}          # seconds for the software renderer to load and draw the recording
SIZE=${SIZE:-1920x1080}
PY=${PYTHON:-python}
mkdir -p "$OUT"

for tool in Xvfb import xwininfo; do
    command -v "$tool" >/dev/null || { echo "render_dashboard: $tool missing (apt-get install -y xvfb imagemagick x11-utils)" >&2; exit 2; }
done

if [[ -z "$RRD" ]]; then
    "$PY" -m feedmon demo --out "$OUT/demo" --duration "${DURATION:-12}" --rate "${RATE:-10}" >/dev/null
    RRD="$OUT/demo/monitor.rrd"
fi

# the viewer binary itself (the `rerun` script would hand the file to a viewer already running)
VIEWER=$("$PY" -c 'import os, rerun_cli; print(os.path.join(os.path.dirname(rerun_cli.__file__), "rerun"))')
PORT=$("$PY" -c 'from feedio.transport import free_tcp_port; print(free_tcp_port())')
DISP=99
while [[ -e /tmp/.X11-unix/X$DISP || -e /tmp/.X$DISP-lock ]]; do DISP=$((DISP + 1)); done

XPID=""; VPID=""
cleanup() {
    [[ -n "$VPID" ]] && { kill "$VPID" 2>/dev/null; wait "$VPID" 2>/dev/null; } || true
    [[ -n "$XPID" ]] && { kill "$XPID" 2>/dev/null; wait "$XPID" 2>/dev/null; } || true
}
trap cleanup EXIT

Xvfb ":$DISP" -screen 0 "${SIZE}x24" -extension Composite >"$OUT/xvfb.log" 2>&1 &
XPID=$!
for _ in $(seq 50); do [[ -e /tmp/.X11-unix/X$DISP ]] && break; sleep 0.1; done

DISPLAY=":$DISP" "$VIEWER" --port "$PORT" --window-size "$SIZE" --hide-welcome-screen "$RRD" >"$OUT/viewer.log" 2>&1 &
VPID=$!
# wait until the window exists, then give the software renderer time to load and draw
for _ in $(seq 100); do
    DISPLAY=":$DISP" xwininfo -root -tree 2>/dev/null | grep -q '"Rerun"' && break
    sleep 0.2
done
sleep "$WAIT"
if command -v xdotool >/dev/null; then  # the pointer starts mid-screen: move it off the plots (no tooltip)
    DISPLAY=":$DISP" xdotool mousemove $((${SIZE%x*} / 2)) 14
    sleep 3
fi
DISPLAY=":$DISP" import -window root "$OUT/dashboard.png"
echo "render_dashboard: $OUT/dashboard.png (the viewer as it opens: time cursor at the end)"
# with xdotool: click the time bar at CURSOR (fraction of the run, default 0.5) for a mid-run view
if command -v xdotool >/dev/null; then
    W=${SIZE%x*}; H=${SIZE#*x}
    X=$("$PY" -c "print(int(0.1375 * $W + ${CURSOR:-0.5} * 0.753 * $W))")
    DISPLAY=":$DISP" xdotool mousemove "$X" $((H - 16)) click 1
    sleep 8
    DISPLAY=":$DISP" xdotool mousemove $((W / 2)) 14  # out of the plots: no tooltip
    sleep 4
    DISPLAY=":$DISP" import -window root "$OUT/dashboard-mid.png"
    echo "render_dashboard: $OUT/dashboard-mid.png (time cursor at ${CURSOR:-0.5} of the run)"
fi

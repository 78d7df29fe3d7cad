#!/usr/bin/env bash
# Screenshot of a run.rrd in rerun's web viewer, taken with headless Chromium (no display needed).
#   scripts/screenshot_viewer.sh RUN_DIR|FILE.rrd OUT.png [BUDGET_MS]
# Installs Debian's chromium when missing (needs root), serves the .rrd with `rerun --serve-web` on localhost,
# renders with SwiftShader (software WebGL) and stops the server again.
set -euo pipefail

src=${1:?usage: $0 RUN_DIR|FILE.rrd OUT.png [BUDGET_MS]}
out=${2:?usage: $0 RUN_DIR|FILE.rrd OUT.png [BUDGET_MS]}
budget=${3:-15000}
rrd=$src
[[ -d $src ]] && rrd=$src/run.rrd
[[ -f $rrd ]] || { echo "$rrd: missing; pass a run directory with run.rrd or an .rrd file" >&2; exit 2; }

here=$(cd "$(dirname "$0")/.." && pwd)
rerun_bin=$here/.venv/bin/rerun
[[ -x $rerun_bin ]] || rerun_bin=$(command -v rerun || true)
[[ -n $rerun_bin ]] || { echo "rerun binary not found; run 'uv sync' first" >&2; exit 2; }

chrome=$(command -v chromium || command -v chromium-browser || command -v google-chrome || true)
if [[ -z $chrome ]]; then
    export DEBIAN_FRONTEND=noninteractive
    apt-get install -y chromium >/dev/null 2>&1 || { apt-get update >/dev/null && apt-get install -y chromium >/dev/null; }
    chrome=$(command -v chromium)
fi

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
web_port=$(free_port)
grpc_port=$(free_port)
tmp=$(mktemp -d)
server_pid=
cleanup() {
    [[ -n $server_pid ]] && kill -- "-$server_pid" 2>/dev/null || true
    rm -rf "$tmp"
}
trap cleanup EXIT

# own process group: .venv/bin/rerun is a wrapper that starts the real binary as a child
setsid "$rerun_bin" "$rrd" --serve-web --bind 127.0.0.1 --web-viewer-port "$web_port" --port "$grpc_port" \
    >"$tmp/rerun.log" 2>&1 &
server_pid=$!
for _ in $(seq 50); do
    curl -sf -o /dev/null "http://127.0.0.1:$web_port/" && break
    sleep 0.2
done
url="http://127.0.0.1:$web_port/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A$grpc_port%2Fproxy"

mkdir -p "$(dirname "$out")"
# --screenshot fires at the page's load event, before the wasm viewer has fetched and drawn the recording, and
# --virtual-time-budget does not wait for wasm compilation: so drive Chromium over the DevTools protocol and
# capture after a real-time wait instead.
cdp_port=$(free_port)
"$chrome" --headless --no-sandbox --disable-gpu-sandbox --use-gl=angle --use-angle=swiftshader \
    --enable-unsafe-swiftshader --ignore-gpu-blocklist --enable-webgl --disable-quic --no-first-run \
    --disable-background-networking --disable-component-update --disable-sync \
    --user-data-dir="$tmp/profile" --window-size=1600,1000 --remote-debugging-port="$cdp_port" \
    "$url" >"$tmp/chromium.log" 2>&1 &
chrome_pid=$!
cleanup() {
    kill "$chrome_pid" 2>/dev/null || true
    [[ -n $server_pid ]] && kill -- "-$server_pid" 2>/dev/null || true
    wait 2>/dev/null || true
    rm -rf "$tmp"
}
python=$here/.venv/bin/python
[[ -x $python ]] || python=python3
"$python" - "$cdp_port" "$budget" "$out" <<'PY'
import asyncio, base64, json, sys, time, urllib.request
from tornado.ioloop import IOLoop
from tornado.websocket import websocket_connect

port, budget_ms, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
for _ in range(100):
    try:
        targets = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=1))
        pages = [t for t in targets if t.get("type") == "page"]
        if pages:
            break
    except OSError:
        pass
    time.sleep(0.2)
else:
    sys.exit("chromium DevTools endpoint did not come up")

async def capture() -> bytes:
    ws = await websocket_connect(pages[0]["webSocketDebuggerUrl"], max_message_size=1 << 28)
    # The recording streams in over gRPC and is drawn by a software rasteriser: wait the budget, then capture
    # until two consecutive frames agree (the data finished loading) or 60 s more have passed.
    await asyncio.sleep(budget_ms / 1000)
    prev, n = b"", 0
    for n in range(1, 16):
        await ws.write_message(json.dumps({"id": n, "method": "Page.captureScreenshot", "params": {"format": "png"}}))
        while True:
            msg = json.loads(await ws.read_message())
            if msg.get("id") == n:
                png = base64.b64decode(msg["result"]["data"])
                break
        if png == prev:
            break
        prev = png
        await asyncio.sleep(4)
    print(f"captured after {n} frame(s)", file=sys.stderr)
    return png

with open(out, "wb") as f:
    f.write(IOLoop.current().run_sync(capture, timeout=budget_ms / 1000 + 120))
PY
echo "$out ($url)"

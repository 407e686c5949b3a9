#!/usr/bin/env bash
# Takes docs/foxglove-studio.png: `muster up` on the built-in default, watched live through
# `muster view` by Foxglove Studio 1.48 in Debian's Chromium (headless).
#
# Needs node and npm (the packages in package.json come from the npm registry), Debian's
# chromium (`apt-get install chromium`) and cargo. Usage: docs/foxglove/take.sh [SECONDS]
# (how long into the run the picture is taken, default 25).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
at=${1:-25}
command -v chromium >/dev/null || { apt-get update -qq && apt-get install -y -qq chromium; }
npm ci --prefix "$here" --no-audit --no-fund --loglevel=error
cargo build --release --manifest-path "$root/Cargo.toml"
muster=$root/target/release/muster
inst=foxglove-shot-$$
logs=$(mktemp -d)
pids=()
stop() {
  # Only what this script started; muster cleans its shared memory on SIGTERM.
  for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
  wait 2>/dev/null || true
  rm -rf "$logs"
}
trap stop EXIT

# The first line of $1 that matches, within 30 s.
first_line() {
  for _ in $(seq 300); do
    if line=$(grep -m1 "$2" "$1" 2>/dev/null); then echo "$line"; return 0; fi
    sleep 0.1
  done
  echo "take.sh: nothing from $1" >&2; cat "$1" >&2; return 1
}

"$muster" --instance "$inst" view --listen 127.0.0.1:0 --duration "$((at + 60))s" \
  >"$logs/view" 2>"$logs/view.err" &
pids+=($!)
view=$(first_line "$logs/view" '"listen"' | sed 's/.*"listen":"\([^"]*\)".*/\1/')
node "$here/proxy.mjs" 0 "ws://$view" >"$logs/proxy" 2>&1 &
pids+=($!)
proxy=$(first_line "$logs/proxy" '"listen"' | sed 's/.*"listen":\([0-9]*\).*/\1/')
python3 -u -m http.server 0 --bind 127.0.0.1 --directory "$here" >"$logs/http" 2>&1 &
pids+=($!)
http=$(first_line "$logs/http" 'Serving HTTP' | sed 's/.* port \([0-9]*\).*/\1/')

# Studio connects first, so that its event panel sees the run from its first event.
node "$here/shoot.mjs" \
  "http://127.0.0.1:$http/index.html?ds=foxglove-websocket&ds.url=ws://127.0.0.1:$proxy" \
  "$root/docs/foxglove-studio.png" "$((at + 8))" &
shoot=$!
sleep 8
"$muster" --instance "$inst" up --no-udp --duration "$((at + 30))s" >"$logs/up" 2>&1 &
pids+=($!)
wait "$shoot"
echo "take.sh: wrote docs/foxglove-studio.png (view at $view, Studio through the proxy at $proxy)"

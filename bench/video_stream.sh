#!/usr/bin/env bash
# Video input benchmark: a 1080p 30 fps stream of two minutes, read in real time
# (`--realtime`: ffmpeg -re, frames dropped and counted when the service is behind), as a
# camera would send it. Prints frames read, kept, dropped, results and update latency.
#
#   bench/video_stream.sh [SECONDS] [WORKDIR]
#
# The video is made here with FFmpeg: a 1920x1080 window panning back and forth (up to
# 117 px/s, and a little up and down) over a rendered 4800x1400 facade
# (examples/render_facade.rs). The mask is a 320x280 box in the keyframe (the first sharp
# frame).
set -euo pipefail
cd "$(dirname "$0")/.."
secs="${1:-120}"
work="${2:-/tmp/clearview-video-bench}"
mkdir -p "$work"
command -v ffmpeg >/dev/null || { echo "ffmpeg is needed (apt-get install ffmpeg)" >&2; exit 1; }
cargo build --release --quiet --bin clearview --example render_facade
[ -f "$work/facade.png" ] || target/release/examples/render_facade "$work/facade.png" 4800 1400
video="$work/walk-1080p30-${secs}s.mp4"
if [ ! -f "$video" ]; then
  echo "encoding $video ..."
  # The image is decoded once and looped in memory (loop filter), then cropped per frame.
  ffmpeg -v error -y -i "$work/facade.png" -r 30 -t "$secs" \
    -vf "loop=loop=-1:size=1:start=0,setpts=N/30/TB,crop=1920:1080:x='740+700*sin(t/6)':y='160+40*sin(t/4)',format=yuv420p" \
    -c:v libx264 -preset ultrafast -crf 20 -g 60 "$video"
fi
[ -f "$work/mask.png" ] || ffmpeg -v error -y -f lavfi -i color=black:s=1920x1080 \
  -vf "drawbox=x=800:y=400:w=320:h=280:color=white:t=fill,format=gray" -frames:v 1 "$work/mask.png"
rm -rf "$work/out"
start=$(date +%s.%N)
/usr/bin/time -v target/release/clearview run --video "$video" --realtime --mask "$work/mask.png" \
  --out "$work/out" 2> "$work/run.log" || { tail -20 "$work/run.log"; exit 1; }
end=$(date +%s.%N)
echo "wall: $(echo "$end - $start" | bc) s for ${secs} s of video"
grep -E "Maximum resident set size" "$work/run.log" || true
python3 - "$work/out/events.jsonl" <<'PY'
import json, sys
ev = [json.loads(l) for l in open(sys.argv[1])]
end = [e for e in ev if e["event"] == "video_ended"][-1]
upd = [e for e in ev if e["event"] == "result_updated"]
acc = [e for e in ev if e["event"] == "view_accepted"]
keys = ["frames_read", "warmup", "blurred", "still", "rate_capped", "kept", "dropped", "aligned",
        "mean_update_latency_ms"]
print({k: end[k] for k in keys})
rej = [e for e in ev if e["event"] == "view_rejected"]
print("results:", len(upd), " accepted frames:", len(acc), " rejected:", len(rej))
reasons = {}
for e in rej:
    reasons[e.get("reason", "?")] = reasons.get(e.get("reason", "?"), 0) + 1
for r, n in sorted(reasons.items(), key=lambda kv: -kv[1]):
    print("  rejected %d: %s" % (n, r))
# Every aligned frame, accepted or not: the service keeps up only if these do.
aligns = sorted(e["align_ms"] for e in acc + rej if "align_ms" in e)
fills = sorted(e["fill_ms"] for e in upd)
if aligns: print("align ms median:", aligns[len(aligns) // 2])
if fills: print("fill ms median:", fills[len(fills) // 2])
ts = [e["t"] for e in acc if "t" in e]
if ts: print("accepted frames span stream time %.1f .. %.1f s" % (min(ts), max(ts)))
PY

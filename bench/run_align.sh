#!/usr/bin/env bash
# Reproduces every alignment figure in BENCHMARKS.md in one session and writes them, with
# the date and the machine's conditions, to bench/results/align.md (also printed).
#
#   bench/run_align.sh            # everything (about 10 minutes on 2 busy cores)
#   SKIP_ACCURACY=1 bench/run_align.sh   # speed and memory only
#   NICE=-10 bench/run_align.sh   # timed runs at a raised priority (root only): on a machine
#                                 # shared with busy neighbours, closer to an idle one
#
# Needs the peer's venv: python3.11 -m venv bench/.venv &&
#   bench/.venv/bin/pip install -r bench/requirements.txt
set -euo pipefail
cd "$(dirname "$0")/.."
PY=bench/.venv/bin/python
[ -x "$PY" ] || { echo "missing $PY: see the header of $0" >&2; exit 1; }
PAIRS=${PAIRS_DIR:-/tmp/clearview-bench-pairs}
OUT=${OUT:-bench/results/align.md}
mkdir -p bench/results "$PAIRS"

conditions() {
    echo "- $(date -u '+%Y-%m-%d %H:%M UTC'), $1: load average $(cut -d' ' -f1-3 /proc/loadavg)"
}

cargo build --release --bins --examples 2>&1 | tail -1
cargo bench --bench align --no-run 2>&1 | tail -1
RUN=(nice -n "${NICE:-0}")
target/release/examples/bench_pair 1155 866 "$PAIRS/1mp"
target/release/examples/bench_pair 4000 3000 "$PAIRS/12mp"

{
    echo "## Run of $(date -u '+%Y-%m-%d %H:%M UTC')"
    echo
    echo "Machine: $(nproc) cores ($(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ //')), $(free -g | awk '/Mem:/ {print $2}') GB;"
    echo "$(rustc --version); commit $(git rev-parse --short HEAD)$(git diff --quiet || echo ' (dirty)')."
    echo
    echo "Conditions (other agents were compiling on the same 2 cores; load average = runnable processes;"
    echo "timed runs at nice ${NICE:-0}):"
    echo
    conditions "start"
} > "$OUT.tmp"

# Speed: criterion, then the peer on the same pixels, back to back.
"${RUN[@]}" cargo bench --bench align 2>&1 | grep -E "time:|Warning" || true
conditions "after criterion" >> "$OUT.tmp"
$PY - >> "$OUT.tmp.crit" <<'EOF'
import json, glob, os
rows = []
for est in sorted(glob.glob("target/criterion/*/new/estimates.json")):
    d = os.path.dirname(est)
    name = json.load(open(os.path.join(d, "benchmark.json")))["full_id"]
    if not name.startswith("align "):
        continue
    e = json.load(open(est))
    s = json.load(open(os.path.join(d, "sample.json")))
    per_iter = sorted(t / n / 1e6 for t, n in zip(s["times"], s["iters"]))
    ci = e["median"]["confidence_interval"]
    rows.append(f"| {name} | {e['median']['point_estimate'] / 1e6:.1f} | "
                f"{ci['lower_bound'] / 1e6:.1f}–{ci['upper_bound'] / 1e6:.1f} | "
                f"{per_iter[0]:.1f}–{per_iter[-1]:.1f} | {len(per_iter)} |")
print("| criterion benchmark | median ms | 95 % CI of the median | sample range ms | samples |")
print("|---|---:|---|---|---:|")
print("\n".join(rows))
EOF
SPEED=$("${RUN[@]}" $PY bench/align_peer.py speed "$PAIRS/1mp" "$PAIRS/12mp" --runs 5)
conditions "after the OpenCV peer" >> "$OUT.tmp"
CPU=$("${RUN[@]}" target/release/examples/align_cpu 1155 866 40
      RAYON_NUM_THREADS=1 "${RUN[@]}" target/release/examples/align_cpu 1155 866 40 | sed 's/$/ (one thread)/'
      "${RUN[@]}" target/release/examples/align_cpu 4000 3000 8)
conditions "after the CPU-time run" >> "$OUT.tmp"
MEM=$( { /usr/bin/time -v target/release/examples/align_12mp 2>&1; } | grep -E "^4000x3000|Maximum resident"
      echo "clearview align on the PNGs (decoding included, whole process):"
      { /usr/bin/time -v target/release/clearview align --json "$PAIRS/12mp/key.png" "$PAIRS/12mp/view.png" 2>&1 >/dev/null; } | grep -E "Maximum resident" )
conditions "after the memory run" >> "$OUT.tmp"

{
    echo
    echo "### Speed (\`cargo bench --bench align\`, then \`bench/align_peer.py speed\` on the same pixels)"
    echo
    cat "$OUT.tmp.crit"
    echo
    echo "$SPEED"
    echo
    echo "### Wall and CPU time per pair (\`target/release/examples/align_cpu\`, same work as the criterion loop)"
    echo
    echo '```'
    echo "$CPU"
    echo '```'
    echo
    echo "### Peak memory, 12 MP pair (\`/usr/bin/time -v\` on \`target/release/examples/align_12mp\` and on the command)"
    echo
    echo '```'
    echo "$MEM"
    echo '```'
} >> "$OUT.tmp"
rm -f "$OUT.tmp.crit"

if [ -z "${SKIP_ACCURACY:-}" ]; then
    {
        echo
        echo "### Accuracy (\`bench/align_peer.py accuracy\`)"
        echo
        $PY bench/align_peer.py accuracy
        echo
        conditions "after the accuracy run"
    } >> "$OUT.tmp"
fi
mv "$OUT.tmp" "$OUT"
cat "$OUT"

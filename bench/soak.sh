#!/usr/bin/env bash
# Soak test of the capture service: the real release binary `clearview run` on a temporary
# folder for MINUTES (default 30), 4 sessions of 800x600 rendered facades (keyframe with a
# tree, its mask, views with people), one file every 2.5 s spread over the sessions, every
# fifth one bad (zero bytes, truncated JPEG, random bytes, a wrong-size mask that is put
# right two files later, a view of another scene). Samples VmRSS, open descriptors and
# threads of the service every minute (every 10 s under 5 minutes) into a CSV, and fails
# (exit 1) when the service died or did not stop cleanly, a good file got no event saying
# it was used or why not, a session has no result, or memory, descriptors or threads grew
# (last third against middle third; see examples/soak.rs for the tolerances).
#
#   bench/soak.sh [MINUTES] [extra examples/soak.rs flags, e.g. --keep DIR --size 1024x768]
#
# The CSV goes to bench/results/soak-<MINUTES>min.csv.
set -euo pipefail
cd "$(dirname "$0")/.."
minutes="${1:-30}"
shift || true
cargo build --release --quiet --bin clearview --example soak
mkdir -p bench/results
exec target/release/examples/soak --bin target/release/clearview --minutes "$minutes" \
  --csv "bench/results/soak-${minutes}min.csv" "$@"

#!/usr/bin/env bash
# Run the benchmark at size small, then at size large, and write both reports to docs/benchmarks.md.
#   benchmarks/run.sh [more bench options, e.g. --param subdomain_size=1000]
# Needs ../shared/datasets beside the checkout. The large size takes hours on 2 cores;
# LARGE_TIMEOUT (seconds, default 3600) is its limit per solver run.
set -euo pipefail
cd "$(dirname "$0")/.."

bench=(python -m gtsam_schwarz.apps.cli bench)  # = gtsam-schwarz bench, from this checkout

mkdir -p docs
tmp=$(mktemp -d docs/.benchmarks.XXXXXX)  # beside the target, so the final mv is atomic
trap 'rm -rf "$tmp"' EXIT

"${bench[@]}" --size small --out "$tmp/small.md" "$@" >/dev/null
"${bench[@]}" --size large --timeout "${LARGE_TIMEOUT:-3600}" --out "$tmp/large.md" "$@" >/dev/null

cat "$tmp/small.md" <(printf '\n') "$tmp/large.md" > "$tmp/benchmarks.md"
mv "$tmp/benchmarks.md" docs/benchmarks.md
echo "wrote docs/benchmarks.md"

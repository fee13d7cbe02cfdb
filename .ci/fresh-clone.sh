#!/usr/bin/env bash
# A newcomer's first test run: clone this checkout (its HEAD) into an empty temporary
# directory, so that no ../shared/seed-data is beside it, and run the suites that read the
# seed data with CI and PHOTOSTEREO_SEED_DATA unset. They must pass, and every test that
# takes seed data (calls `seed!` or `real!`) must print its skip line: a silent pass would hide a test
# that never ran. The full run in .ci/run covers the other suites.
#
# The clone builds in its own target directory beside CARGO_TARGET_DIR: cargo's
# fingerprints do not depend on where the crate lies, so a clone building into the
# caller's target directory leaves test binaries there that cargo then takes as fresh
# for the checkout, with the clone's (deleted) CARGO_MANIFEST_DIR compiled in.
set -euo pipefail
cd "$(dirname "$0")/.."

# The test programs: tests/<program>/main.rs, with one module file per subject beside it.
files=()
for main in tests/*/main.rs; do
  files+=("$(dirname "$main")"/*.rs)
done
# "tests/http/api.rs api::limits_get_413": each test that calls seed! or real!, named as
# libtest names it (module::fn, the module being its file's name), after the file it is in.
needs_seed="$(awk '
  FNR == 1 { m = FILENAME; sub(/.*\//, "", m); sub(/\.rs$/, "", m); prefix = (m == "main") ? "" : m "::" }
  match($0, /fn [a-z0-9_]+\(/) { name = substr($0, RSTART + 3, RLENGTH - 4) }
  /(seed|real)!\(/ { print FILENAME, prefix name }' "${files[@]}" | sort -u)"
# Their programs, and their modules as test filters ("api::"): each module that reads seed
# data runs whole, as it did when it was a program of its own.
mapfile -t programs < <(cut -d' ' -f1 <<<"$needs_seed" | xargs -n1 dirname | sort -u | xargs -n1 basename)
mapfile -t modules < <(cut -d' ' -f2 <<<"$needs_seed" | sed -E 's/[^:]+$//' | sort -u)

work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
git clone --quiet --no-hardlinks . "$work/photostereo"

args=()
for p in "${programs[@]}"; do
  args+=(--test "$p")
done
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$PWD/target}-fresh-clone"
(
  cd "$work/photostereo"
  env -u CI -u PHOTOSTEREO_SEED_DATA -u PHOTOSTEREO_REAL_DATA cargo test --release --locked "${args[@]}" -- "${modules[@]}"
) 2>&1 | tee "$work/log"

missing=0
while read -r file name; do
  if ! grep -q "SKIPPED $name: " "$work/log"; then
    echo "fresh clone: $file $name did not say it skipped" >&2
    missing=$((missing + 1))
  fi
done <<<"$needs_seed"
if [ "$missing" -gt 0 ]; then
  exit 1
fi
echo "fresh clone: $(wc -l <<<"$needs_seed") seed-data tests skipped, saying so; the rest passed"

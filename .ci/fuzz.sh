#!/usr/bin/env bash
# Coverage-guided fuzzing (cargo-fuzz / libFuzzer, AddressSanitizer) of the code that reads
# client bytes first. The targets live in fuzz/fuzz_targets/:
#
#   lights         core::lights::parse_bytes    the light table, CSV or JSON
#   options        JSON -> core::Options        and the stored round trip a job makes
#   intake_decode  core::intake::decode         every image format, under pixel limits
#   archive        service::unpack_archive      the zip reader of the `archive` part
#
# Set up once:   rustup toolchain install nightly && cargo install cargo-fuzz
# This script:   .ci/fuzz.sh            every target for FUZZ_SECONDS (default 20) seconds
#                .ci/fuzz.sh archive    one target
# By hand:       cd fuzz && cargo +nightly fuzz run -O archive corpus/archive seeds/archive -- -max_total_time=600
# A crash:       libFuzzer saves the input as fuzz/artifacts/<target>/crash-<sha1>; replay it with
#                cd fuzz && cargo +nightly fuzz run -O <target> artifacts/<target>/crash-<sha1>
#                and shrink it with  cargo +nightly fuzz tmin -O <target> artifacts/<target>/crash-<sha1>
#
# intake_decode passes when a third-party decoder panics and intake::decode turns that
# into an error (what the service relies on); PHOTOSTEREO_FUZZ_STRICT=1 fails on those too.
#
# The corpus grows in fuzz/corpus/<target>/ (not committed) from the small hand-made inputs
# in fuzz/seeds/<target>/. The build goes to $CARGO_TARGET_DIR/fuzz when CARGO_TARGET_DIR is
# set (else fuzz/target); the first build takes several minutes. The script exits non-zero
# when a target crashes, and skips (exit 0, saying why) without nightly or cargo-fuzz.
set -euo pipefail
cd "$(dirname "$0")/../fuzz"

seconds="${FUZZ_SECONDS:-20}"
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
  targets=(lights options intake_decode archive)
fi

if ! command -v rustup >/dev/null 2>&1 || ! rustup run nightly rustc --version >/dev/null 2>&1; then
  echo "fuzz: skipped: no nightly toolchain (rustup toolchain install nightly)"
  exit 0
fi
if ! cargo +nightly fuzz --version >/dev/null 2>&1; then
  echo "fuzz: skipped: cargo-fuzz is not installed (cargo install cargo-fuzz)"
  exit 0
fi

target_dir=()
if [ -n "${CARGO_TARGET_DIR:-}" ]; then
  target_dir=(--target-dir "$CARGO_TARGET_DIR/fuzz")
  unset CARGO_TARGET_DIR
fi

echo "== fuzz: build"
cargo +nightly fuzz build -O "${target_dir[@]}"

status=0
for t in "${targets[@]}"; do
  echo "== fuzz: $t for ${seconds}s"
  mkdir -p "corpus/$t"
  if ! cargo +nightly fuzz run -O "${target_dir[@]}" "$t" "corpus/$t" "seeds/$t" -- \
    -max_total_time="$seconds" -timeout=10 -rss_limit_mb=2048 -max_len=65536 \
    -print_final_stats=1 2>"corpus/$t.log"; then
    status=1
    echo "fuzz: $t FAILED; the panic, then the end of its log:"
    grep -m 3 -A 2 "panicked at" "corpus/$t.log" || true
    tail -n 60 "corpus/$t.log"
  else
    grep -E '^(stat::number_of_executed_units|stat::peak_rss_mb|#[0-9]+ +DONE)' "corpus/$t.log" || true
    echo "fuzz: $t: no crash; corpus $(find "corpus/$t" -type f | wc -l) inputs"
  fi
done
exit "$status"

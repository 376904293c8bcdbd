#!/usr/bin/env bash
# Runs every libFuzzer target of a fuzz build for a while: scripts/fuzz.sh BUILD_DIR [SECONDS].
#
# A target NAME_fuzzer starts from fuzz/corpus/NAME, with fuzz/NAME.dict if there is one. It works on a copy under
# BUILD_DIR/fuzz-work/NAME/corpus, so what it finds stays out of the repository until someone
# picks the interesting inputs by hand; the copy persists, so runs build on each other. Crashes,
# leaks and timeouts land in BUILD_DIR/fuzz-work/NAME/artifacts/. Exits non-zero if any target
# failed.
set -euo pipefail

if (($# < 1 || $# > 2)); then
    echo "usage: $0 BUILD_DIR [SECONDS]" >&2
    exit 2
fi
build=$1
seconds=${2:-60}
if ! [[ $seconds =~ ^[1-9][0-9]*$ ]]; then
    echo "fuzz: SECONDS must be a positive whole number, not '$seconds'" >&2
    exit 2
fi
repo=$(cd "$(dirname "$0")/.." && pwd)

fuzzers=()
for f in "$build"/fuzz/*_fuzzer; do
    [[ -f $f && -x $f ]] && fuzzers+=("$f")
done
if ((${#fuzzers[@]} == 0)); then
    echo "fuzz: no *_fuzzer executables in $build/fuzz; build with 'cmake --preset fuzz' first" >&2
    exit 1
fi

failed=()
for fuzzer in "${fuzzers[@]}"; do
    name=$(basename "$fuzzer" _fuzzer)
    work=$build/fuzz-work/$name
    mkdir -p "$work/corpus" "$work/artifacts"
    seeds=$repo/fuzz/corpus/$name
    if [[ -d $seeds ]]; then
        cp -n "$seeds"/* "$work/corpus/" 2>/dev/null || true
    fi
    dict=()
    [[ -f $repo/fuzz/$name.dict ]] && dict=(-dict="$repo/fuzz/$name.dict")
    echo "fuzz: $name for ${seconds}s on $work/corpus"
    # A hang counts as a failure after 10 s per input; the memory cap keeps an unbounded
    # allocation from taking the machine down before libFuzzer reports it.
    if "$fuzzer" -max_total_time="$seconds" -timeout=10 -rss_limit_mb=2048 \
        -artifact_prefix="$work/artifacts/" -print_final_stats=1 "${dict[@]}" \
        "$work/corpus" >"$work/log.txt" 2>&1; then
        tail -n 12 "$work/log.txt" | grep -E '^(stat::|Done)' || true
    else
        echo "fuzz: $name FAILED; last lines of $work/log.txt:" >&2
        tail -n 40 "$work/log.txt" >&2
        failed+=("$name")
    fi
done

if ((${#failed[@]} > 0)); then
    echo "fuzz: failures in: ${failed[*]} (reproducers in $build/fuzz-work/*/artifacts/)" >&2
    exit 1
fi
echo "fuzz: ${#fuzzers[@]} target(s) ran ${seconds}s each without a failure"

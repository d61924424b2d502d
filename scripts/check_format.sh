#!/usr/bin/env bash
# Checks that every C++ file of the project is formatted by .clang-format (STYLE: applied to every
# file). Prints each file that differs with the first lines of the difference; exit 1 if any does,
# 77 (skipped) when clang-format is not installed.
set -uo pipefail
cd "$(dirname "$0")/.."
CLANG_FORMAT=${CLANG_FORMAT:-clang-format}
if ! command -v "$CLANG_FORMAT" >/dev/null; then
  echo "check_format: $CLANG_FORMAT not found (Debian package clang-format); skipped"
  exit 77
fi
bad=0
checked=0
while IFS= read -r -d '' f; do
  checked=$((checked + 1))
  if ! diff -q "$f" <("$CLANG_FORMAT" --style=file "$f") >/dev/null; then
    echo "not formatted: $f (fix: $CLANG_FORMAT -i $f)"
    diff "$f" <("$CLANG_FORMAT" --style=file "$f") | head -8
    bad=$((bad + 1))
  fi
done < <(find client-sdk core fuzz proto server tests tools -type f \( -name '*.cc' -o -name '*.h' \) -print0)
echo "check_format: $checked files, $bad not formatted"
[ "$bad" -eq 0 ]

#!/usr/bin/env bash
# Installs the development tools and runs every check and test of dhptam.
#
# This is the README's second quick-start command, and CI's `.ci/run` calls it unchanged.
# Order: cheap checks first, so a formatting slip fails in seconds rather than after a build.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}

step() { printf '\n==> %s\n' "$*"; }

for tool in cargo rustc; do
    command -v "$tool" >/dev/null || { echo "error: '$tool' not found; install Rust (rustup) first" >&2; exit 2; }
done
for sub in fmt clippy; do
    cargo "$sub" --version >/dev/null 2>&1 || {
        echo "error: 'cargo $sub' not found; run 'rustup component add ${sub/fmt/rustfmt}'" >&2
        exit 2
    }
done

step "install dhptam (editable, release build of the Rust extension) with the dev tools"
"$PYTHON" -m pip install --quiet --disable-pip-version-check -e ".[dev]"

step "the core stays pure Rust (no pyo3 in its dependency tree)"
if cargo tree -p dhptam-core -e normal,build --prefix none | grep -q '^pyo3'; then
    echo "error: dhptam-core depends on pyo3; keep Python in crates/dhptam-python" >&2
    exit 1
fi

step "cargo fmt --check"
cargo fmt --all --check

step "cargo clippy (all targets, warnings are errors)"
cargo clippy --workspace --all-targets --quiet -- -D warnings

step "cargo test (the pure-Rust core; no Python needed)"
cargo test --quiet

step "ruff"
"$PYTHON" -m ruff check .
"$PYTHON" -m ruff format --check .

step "pytest (warnings are errors)"
"$PYTHON" -m pytest -W error

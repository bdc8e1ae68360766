#!/usr/bin/env bash
# Compiles a workspace crate with Clippy's lints, denied (-D warnings), in the same pass that
# generates its code: scripts/test.sh sets this as RUSTC_WORKSPACE_WRAPPER for its `ci` builds,
# so the tests' build is also the lint check (a separate `cargo clippy` type-checked every crate
# a second time: 158 s of the suite). `cargo clippy` itself runs clippy-driver the same way,
# as the wrapper of the workspace's crates only (their dependencies build with rustc), but stops
# before code generation. Cargo calls this with rustc's path and its arguments.
# Bash, not sh: dash drops environment variables whose names are not shell identifiers, such as
# the CARGO_BIN_EXE_mecanum-runner that Cargo sets for integration tests.
exec clippy-driver "$@" -D warnings

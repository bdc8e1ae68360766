"""Shared fixtures: the `mecanum-codec` binary (built on demand) and the project's DBC files."""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
from collections.abc import Callable, Iterable

import cantools
import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
DBC_DIR = ROOT / "dbc"
DBC_FILES = {
    "robot": "mecanum_robot.dbc",
    "dji": "dji_c620.dbc",
    "odrive": "odrive_cansimple.dbc",
}


def _target_dir() -> pathlib.Path:
    env = os.environ.get("CARGO_TARGET_DIR")
    if not env:
        return ROOT / "target"
    path = pathlib.Path(env)
    return path if path.is_absolute() else ROOT / path


@pytest.fixture(scope="session")
def codec_bin() -> pathlib.Path:
    """Path of `mecanum-codec`: $MECANUM_CODEC if set, else built with cargo (debug profile)."""
    prebuilt = os.environ.get("MECANUM_CODEC")
    if prebuilt:
        path = pathlib.Path(prebuilt)
        assert path.is_file(), f"MECANUM_CODEC={prebuilt} does not exist"
        return path
    subprocess.run(
        ["cargo", "build", "--quiet", "-p", "firmware", "--features", "std", "--bin", "mecanum-codec"],
        cwd=ROOT,
        check=True,
        timeout=900,
    )
    path = _target_dir() / "debug" / ("mecanum-codec" + (".exe" if os.name == "nt" else ""))
    assert path.is_file(), f"cargo build did not produce {path}"
    return path


@pytest.fixture(scope="session")
def run_codec(codec_bin: pathlib.Path) -> Callable[..., list[dict]]:
    """Runs `mecanum-codec <args>` with the given stdin lines; returns the JSON output lines."""

    def run(*args: str, lines: Iterable[str] = ()) -> list[dict]:
        stdin = "".join(line + "\n" for line in lines)
        proc = subprocess.run(
            [str(codec_bin), *args],
            input=stdin,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert proc.returncode == 0, f"mecanum-codec {args} failed: {proc.stderr}"
        return [json.loads(line) for line in proc.stdout.splitlines()]

    return run


@pytest.fixture(scope="session")
def dbs() -> dict[str, cantools.database.can.Database]:
    """The three DBC files, loaded strictly, by protocol name."""
    return {
        name: cantools.database.load_file(str(DBC_DIR / file), strict=True)
        for name, file in DBC_FILES.items()
    }


@pytest.fixture(scope="session")
def hostsim_bin() -> pathlib.Path:
    """Path of `hostsim`: $HOSTSIM if set, else built with cargo (release: runs are long)."""
    prebuilt = os.environ.get("HOSTSIM")
    if prebuilt:
        path = pathlib.Path(prebuilt)
        assert path.is_file(), f"HOSTSIM={prebuilt} does not exist"
        return path
    subprocess.run(
        ["cargo", "build", "--quiet", "--release", "-p", "hostsim", "--bin", "hostsim"],
        cwd=ROOT,
        check=True,
        timeout=1800,
    )
    path = _target_dir() / "release" / ("hostsim" + (".exe" if os.name == "nt" else ""))
    assert path.is_file(), f"cargo build did not produce {path}"
    return path

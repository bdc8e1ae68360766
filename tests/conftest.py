"""Shared fixtures: the `mecanum-codec` binary (built on demand), the project's DBC files, and
the vcan lane's (vcan0, can-utils, the runner and the plant as processes)."""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any, NoReturn

import cantools
import pytest
import vcan_robot

if TYPE_CHECKING:
    import vcan_cia402  # imported by the fixture that needs it (it checks its configuration)

ROOT = pathlib.Path(__file__).resolve().parent.parent
DBC_DIR = ROOT / "dbc"
DBC_FILES = {
    "robot": "mecanum_robot.dbc",
    "dji": "dji_c620.dbc",
    "odrive": "odrive_cansimple.dbc",
    # CANopen CiA 301/402, nodes 1 and 2 (its ids overlap DJI's and ODrive's: `decode --canopen`).
    "canopen": "cia402.dbc",
}


def _target_dir() -> pathlib.Path:
    env = os.environ.get("CARGO_TARGET_DIR")
    if not env:
        return ROOT / "target"
    path = pathlib.Path(env)
    return path if path.is_absolute() else ROOT / path


def _prebuilt_or_cargo(env: str, name: str, cargo_args: list[str], timeout: float) -> pathlib.Path:
    """Path of the binary `name`: $`env` if set (it must exist), else built with
    `cargo build --quiet --locked CARGO_ARGS` (debug profile) within `timeout` seconds."""
    prebuilt = os.environ.get(env)
    if prebuilt:
        path = pathlib.Path(prebuilt)
        assert path.is_file(), f"{env}={prebuilt} does not exist"
        return path
    subprocess.run(["cargo", "build", "--quiet", "--locked", *cargo_args], cwd=ROOT, check=True, timeout=timeout)
    path = _target_dir() / "debug" / (name + (".exe" if os.name == "nt" else ""))
    assert path.is_file(), f"cargo build did not produce {path}"
    return path


@pytest.fixture(scope="session")
def codec_bin() -> pathlib.Path:
    """Path of `mecanum-codec`: $MECANUM_CODEC if set, else built with cargo (debug profile)."""
    return _prebuilt_or_cargo("MECANUM_CODEC", "mecanum-codec", ["-p", "mecanum-codec"], timeout=900)


@pytest.fixture(scope="session")
def config_id(codec_bin: pathlib.Path) -> Callable[[pathlib.Path], str]:
    """The id of a configuration file as `mecanum-codec config-id` prints it (`0x1a2b`)."""

    def run(path: pathlib.Path) -> str:
        proc = subprocess.run([str(codec_bin), "config-id", str(path)], capture_output=True, text=True,
                              timeout=60, check=False)
        assert proc.returncode == 0, f"mecanum-codec config-id {path} failed: {proc.stderr}"
        return proc.stdout.split()[0]

    return run


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
    """The DBC files (robot, dji, odrive, canopen), loaded strictly, by protocol name."""
    out = {}
    for name, file in DBC_FILES.items():
        db = cantools.database.load_file(str(DBC_DIR / file), strict=True)
        assert isinstance(db, cantools.database.can.Database), file
        out[name] = db
    return out


@pytest.fixture(scope="session")
def hostsim_bin() -> pathlib.Path:
    """Path of `hostsim`: $HOSTSIM if set, else built with cargo (debug: `cargo test` has built
    it already, so this costs nothing after the Rust tests, and the runs here are short)."""
    return _prebuilt_or_cargo("HOSTSIM", "hostsim", ["-p", "hostsim", "--bin", "hostsim"], timeout=1800)


# --- vcan: a real SocketCAN interface ------------------------------------------------------
# Tests that need a real SocketCAN interface are marked `vcan` (registered below, so
# --strict-markers accepts it) and take the `vcan` fixture, or just carry the marker: the
# autouse gate below gives every `vcan`-marked test the same check. scripts/vcan.sh brings
# vcan0 up (natively where the kernel has vcan, else in a micro-VM) and sets
# MECANUM_VCAN_REQUIRED=1, which turns a missing interface from a skip into a failure.

VCAN_CHANNEL = "vcan0"
VCAN_SKIP_REASON = "vcan0 not present (run via scripts/vcan.sh)"
_ARPHRD_CAN = 280  # /sys/class/net/<if>/type of a CAN interface (linux/if_arp.h)


def pytest_configure(config: pytest.Config) -> None:
    """Registers the project's markers (one hook per conftest: add further markers here) and
    the vcan lane's hooks (lane.py: progress, the guest's state on a failure)."""
    import lane

    if not config.pluginmanager.is_registered(lane):
        config.pluginmanager.register(lane, "mecanum-lane")
    config.addinivalue_line(
        "markers",
        "vcan: needs a real SocketCAN interface vcan0; skipped without it, a failure without it "
        "when MECANUM_VCAN_REQUIRED=1 (scripts/vcan.sh runs these natively or in a micro-VM)",
    )


def vcan_required() -> bool:
    """True if a missing vcan0 must fail the test (scripts/vcan.sh sets MECANUM_VCAN_REQUIRED=1)."""
    return os.environ.get("MECANUM_VCAN_REQUIRED", "") == "1"


def _vcan_problem(name: str = VCAN_CHANNEL) -> str | None:
    """None if `name` is an up CAN interface, else what is wrong with it."""
    sys_dir = pathlib.Path("/sys/class/net") / name
    if not sys_dir.is_dir():
        return f"{name} does not exist"
    try:
        if int((sys_dir / "type").read_text().strip()) != _ARPHRD_CAN:
            return f"{name} exists but is not a CAN interface"
        flags = int((sys_dir / "flags").read_text().strip(), 16)
    except (OSError, ValueError) as err:
        return f"{name}: cannot read its state ({err})"
    if not flags & 0x1:  # IFF_UP
        return f"{name} exists but is down (ip link set up {name})"
    return None


def vcan_unavailable(what: str, detail: str) -> NoReturn:
    """Skips the test for a missing vcan prerequisite, or fails it when vcan is required."""
    if vcan_required():
        pytest.fail(f"{detail}; MECANUM_VCAN_REQUIRED=1, so this is a failure, not a skip")
    pytest.skip(what)


@pytest.fixture(scope="session")
def vcan() -> str:
    """Name of an up SocketCAN interface (vcan0). Skips when it is missing, fails if required."""
    problem = _vcan_problem(VCAN_CHANNEL)
    if problem is not None:
        vcan_unavailable(VCAN_SKIP_REASON, problem)
    return VCAN_CHANNEL


@pytest.fixture(autouse=True)
def _vcan_marker_gate(request: pytest.FixtureRequest) -> None:
    """Every test marked `vcan` gets the `vcan` fixture's check, even if it does not name it."""
    if request.node.get_closest_marker("vcan") is not None:
        request.getfixturevalue("vcan")


@pytest.fixture(scope="session")
def can_utils() -> Callable[[str], str]:
    """Path of a can-utils program (cansend, candump, ...): skips if missing, fails if required."""

    import shutil

    def find(name: str) -> str:
        path = shutil.which(name)
        if path is None:
            vcan_unavailable(
                f"{name} not found (Debian package can-utils)", f"{name} (can-utils) not on PATH"
            )
        return path

    return find


# --- vcan: the runner and the plant as processes (tests/vcan_robot.py) ----------------------
# (or the runner and two CiA 402 drives: tests/vcan_cia402.py, `cia402_factory`).
# Module-scoped, as each module's sessions are: a module gets its own configurations and
# temporary directories.


@pytest.fixture(scope="module")
def runner_bin() -> pathlib.Path:
    """`mecanum-runner`: $MECANUM_RUNNER, else the release build (vcan_robot.binary)."""
    return vcan_robot.binary("MECANUM_RUNNER", ROOT / "target" / "release" / "mecanum-runner")


@pytest.fixture(scope="module")
def plant_bin() -> pathlib.Path:
    """`hostsim` (its `plant` subcommand): $HOSTSIM, else the release build."""
    return vcan_robot.binary("HOSTSIM", ROOT / "target" / "release" / "hostsim")


@pytest.fixture(scope="module")
def configs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, pathlib.Path]:
    """The example configurations, by protocol, but stopping at once when the watchdog
    expires (no deceleration ramp), so the stop budget is the timeout plus two periods."""
    work = tmp_path_factory.mktemp("config")
    return {
        protocol: vcan_robot.write_config(
            work / f"{protocol}.toml",
            ROOT / "config" / example,
            stop_linear_decel="inf",
            stop_angular_decel="inf",
            **vcan_robot.VM_TIMING,
        )
        for protocol, example in (("dji", "dji_m3508.toml"), ("odrive", "odrive.toml"))
    }


@pytest.fixture(scope="module")
def config(configs: dict[str, pathlib.Path]) -> pathlib.Path:
    """The DJI configuration of `configs`: what a `robot_factory` session runs by default."""
    return configs["dji"]


@pytest.fixture(scope="module")
def robot_factory(runner_bin: pathlib.Path, plant_bin: pathlib.Path, can_utils: Callable[[str], str],
                  vcan: str, config: pathlib.Path,
                  tmp_path_factory: pytest.TempPathFactory) -> Callable[..., vcan_robot.Robot]:
    """`make(name, **kw)`: a `vcan_robot.Robot` on vcan0 with `config` (or `config=`), its
    files in a fresh directory `name`; `kw` as `Robot` takes them."""

    def make(name: str, **kw: Any) -> vcan_robot.Robot:
        return vcan_robot.Robot(
            runner=runner_bin,
            hostsim=plant_bin,
            candump=can_utils("candump"),
            iface=vcan,
            config=kw.pop("config", config),
            workdir=tmp_path_factory.mktemp(name),
            **kw,
        )

    return make


@pytest.fixture(scope="module")
def cia402_factory(runner_bin: pathlib.Path, can_utils: Callable[[str], str], vcan: str,
                   tmp_path_factory: pytest.TempPathFactory) -> Callable[..., vcan_cia402.Cia402Robot]:
    """`make(name, **kw)`: a `vcan_cia402.Cia402Robot` on vcan0 running `vcan_cia402.CONFIG`
    (tests/test_vcan_cia402.py, tests/test_vcan_cia402_outages.py), its files in a fresh
    directory `name`; `kw` as `Cia402Robot` takes them."""
    import vcan_cia402

    def make(name: str, **kw: Any) -> vcan_cia402.Cia402Robot:
        return vcan_cia402.Cia402Robot(runner=runner_bin, candump=can_utils("candump"), iface=vcan,
                                       config=vcan_cia402.CONFIG, workdir=tmp_path_factory.mktemp(name), **kw)

    return make


def pytest_terminal_summary(terminalreporter: Any) -> None:
    """The bad-input corpus's count, when it ran (tests/test_bad_input.py)."""
    outcomes: dict[str, int] = {}
    for outcome in ("passed", "failed", "skipped", "error"):
        for report in terminalreporter.stats.get(outcome, []):
            if getattr(report, "nodeid", "").startswith("tests/test_bad_input.py::test_bad_input[") \
                    and report.when in ("call", "setup") and not (outcome == "passed" and report.when == "setup"):
                outcomes[outcome] = outcomes.get(outcome, 0) + 1
    if outcomes:
        terminalreporter.write_line("bad-input corpus: " + ", ".join(f"{n} {o}" for o, n in sorted(outcomes.items()))
                                    + f" of {sum(outcomes.values())} cases")

"""`mecanum-drive sweep --ray local`: a hostsim sweep shared out over a real Ray cluster of
this machine (the package's ray extra), with one `hostsim sweep` as the oracle: the merged
table is the single-machine table byte for byte (CSV, JSON lines, PNG); a worker killed
mid-shard has its shard run again; a shard that fails stops the sweep with the finished
shards kept, and `--resume` runs only the rest (another sweep's parts refused); Ctrl-C keeps
the finished shards (exit 130) and `--resume` runs only the one that was cut off; bad input
fails at once with hostsim's own message, before Ray starts.

The scenario is a file (its configuration shipped beside it): the straight pods leg, 13 s
simulated, a handful of seeds.
"""

from __future__ import annotations

import importlib.util
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from typing import Any, Iterator

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
SCENARIO = str(ROOT / "scenarios" / "straight_pods.toml")
SWEEP = ["--seeds", "1..5", "--set", "pods.radius_error=-0.01..0.01", "--set", "gains.kp=1.0,1.4"]


@pytest.fixture(scope="module", autouse=True)
def ray_installed() -> None:
    """The package's ray extra (scripts/test.sh installs it): looked up, not imported, so
    that collecting this module (the vcan lane collects every module) costs nothing; in CI a
    missing extra is a failure, not a skip."""
    if importlib.util.find_spec("ray") is None:
        why = "Ray is not installed: pip install './python[ray]'"
        if os.environ.get("CI"):
            pytest.fail(why)
        pytest.skip(why)


@pytest.fixture(scope="module", autouse=True)
def ray_temp() -> Iterator[None]:
    """Ray's session folders and the shards' work folders in a folder of this module's,
    removed at its end: a worker killed mid-shard cannot remove its own. Short, under the
    system's temporary folder, as Ray's sockets there must fit a Unix socket's 107 bytes."""
    folder = tempfile.mkdtemp(prefix="ray-test-")
    before = os.environ.get("TMPDIR")
    os.environ["TMPDIR"] = folder
    yield
    if before is None:
        del os.environ["TMPDIR"]
    else:
        os.environ["TMPDIR"] = before
    shutil.rmtree(folder, ignore_errors=True)


def drive_cmd(tmp: pathlib.Path, hostsim: pathlib.Path, *args: str, nodes: pathlib.Path | None = None,
              sweep: list[str] = SWEEP) -> list[str]:
    """`mecanum-drive sweep SCENARIO SWEEP --ray local` into tmp/ray, on two CPUs."""
    cmd = [sys.executable, "-m", "mecanum_drive", "sweep", SCENARIO, *sweep, "--ray", "local", "--cpus", "2",
           "--shard-size", "3", "--out", str(tmp / "ray"), "--hostsim", str(hostsim), *args]
    return cmd + ["--hostsim-on-nodes", str(nodes)] if nodes is not None else cmd


def drive(tmp: pathlib.Path, hostsim: pathlib.Path, *args: str, nodes: pathlib.Path | None = None,
          **popen: Any) -> subprocess.CompletedProcess[str]:
    return subprocess.run(drive_cmd(tmp, hostsim, *args, nodes=nodes), capture_output=True, text=True,
                          timeout=300, check=False, **popen)


@pytest.fixture(scope="module")
def oracle(hostsim_bin: pathlib.Path, tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    """The same sweep by one hostsim on this machine."""
    out = tmp_path_factory.mktemp("oracle")
    proc = subprocess.run([str(hostsim_bin), "sweep", SCENARIO, *SWEEP, "--out", str(out)],
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    return out


def assert_same_tables(got: pathlib.Path, oracle: pathlib.Path) -> None:
    for name in ("sweep.csv", "sweep.jsonl", "sweep.png"):
        assert (got / name).read_bytes() == (oracle / name).read_bytes(), name


def wrapper(tmp: pathlib.Path, hostsim: pathlib.Path, on_rows: str, act: str) -> pathlib.Path:
    """A hostsim on the nodes that does `act` (shell) the first time it is given `--runs
    on_rows`, and is hostsim otherwise; each call is logged in tmp/calls."""
    script = tmp / "hostsim-node"
    script.write_text(f"""#!/bin/sh
echo "$@" >> {tmp}/calls
case " $* " in
  *" --runs {on_rows} "*) if [ ! -e {tmp}/acted ]; then touch {tmp}/acted; {act}; fi ;;
esac
exec {hostsim} "$@"
""")
    script.chmod(0o755)
    return script


def test_the_merged_table_is_one_hostsims_byte_for_byte(hostsim_bin: pathlib.Path, tmp_path: pathlib.Path,
                                                         oracle: pathlib.Path) -> None:
    proc = drive(tmp_path, hostsim_bin)
    assert proc.returncode == 0, proc.stderr
    # 10 runs in shards of 3: four parts, each written as it came, with its progress line.
    parts = sorted(p.name for p in (tmp_path / "ray" / "parts").iterdir() if p.is_dir())
    assert parts == ["rows-0-2", "rows-3-5", "rows-6-8", "rows-9-9"], parts
    assert "sweep: 4 of 4 shards, 10 of 10 runs here" in proc.stderr, proc.stderr
    assert_same_tables(tmp_path / "ray", oracle)


def test_a_shard_whose_worker_was_killed_runs_again(hostsim_bin: pathlib.Path, tmp_path: pathlib.Path,
                                                     oracle: pathlib.Path) -> None:
    # The first hostsim of rows 3..5 kills the Ray worker that runs it (its parent), as a node
    # lost mid-shard: Ray runs the task again, and the table is whole.
    nodes = wrapper(tmp_path, hostsim_bin, "3..5", "kill -9 $PPID; exit 1")
    proc = drive(tmp_path, hostsim_bin, nodes=nodes)
    assert proc.returncode == 0, proc.stderr
    calls = (tmp_path / "calls").read_text().splitlines()
    assert sum(" --runs 3..5 " in f" {c} " for c in calls) == 2, calls
    assert_same_tables(tmp_path / "ray", oracle)


def test_a_failed_shard_stops_the_sweep_and_resume_runs_only_the_rest(
        hostsim_bin: pathlib.Path, tmp_path: pathlib.Path, oracle: pathlib.Path) -> None:
    nodes = wrapper(tmp_path, hostsim_bin, "9..9", "echo 'disk full' >&2; exit 3")
    proc = drive(tmp_path, hostsim_bin, nodes=nodes)
    assert proc.returncode == 1, proc.stderr
    assert "rows-9-9 failed" in proc.stderr and "disk full" in proc.stderr, proc.stderr
    assert "--resume runs the rest" in proc.stderr
    assert not (tmp_path / "ray" / "sweep.csv").exists()
    # Without --resume the parts are not overwritten; with it only rows 9..9 run again.
    again = drive(tmp_path, hostsim_bin, nodes=nodes)
    assert again.returncode == 2 and "--resume to go on with it" in again.stderr, again.stderr
    # The shards that finished before the failure was seen are kept (the rest were cancelled).
    kept = {p.name for p in (tmp_path / "ray" / "parts").iterdir() if p.is_dir()}
    shards = {"rows-0-2": "0..2", "rows-3-5": "3..5", "rows-6-8": "6..8", "rows-9-9": "9..9"}
    assert kept <= set(shards) - {"rows-9-9"}, kept
    # Another sweep's --resume is refused before anything runs: the same count of runs and
    # the same header, other values.
    other_values = [*SWEEP[:-1], "gains.kp=1.0,1.2"]
    other = subprocess.run([*drive_cmd(tmp_path, hostsim_bin, "--resume", nodes=nodes, sweep=other_values)],
                           capture_output=True, text=True, timeout=300, check=False)
    assert other.returncode == 2 and "holds parts of another sweep (hostsim's arguments differ" in other.stderr, \
        other.stderr
    # A request file that is JSON but not a sweep's is refused with its name, and kept.
    request = tmp_path / "ray" / "parts" / "request.json"
    good = request.read_text()
    for bad in ("[1]\n", '{"argv": 3}\n'):
        request.write_text(bad)
        proc = drive(tmp_path, hostsim_bin, "--resume", nodes=nodes)
        assert proc.returncode == 2 and f"{request}: not a sweep's request" in proc.stderr, (bad, proc.stderr)
        assert request.read_text() == bad
    request.write_text(good)
    before = len((tmp_path / "calls").read_text().splitlines())
    resumed = drive(tmp_path, hostsim_bin, "--resume", nodes=nodes)
    assert resumed.returncode == 0, resumed.stderr
    assert f"{len(kept)} done already" in resumed.stderr, resumed.stderr
    ran = sorted(c.split(" --runs ")[1].split()[0] for c in (tmp_path / "calls").read_text().splitlines()[before:])
    assert ran == sorted(rows for name, rows in shards.items() if name not in kept), (ran, kept)
    assert_same_tables(tmp_path / "ray", oracle)


def test_ctrl_c_keeps_the_finished_shards_and_resume_runs_the_rest(
        hostsim_bin: pathlib.Path, tmp_path: pathlib.Path, oracle: pathlib.Path) -> None:
    # Rows 9..9 hang (their program's pid kept) until their worker is gone; the other three
    # shards finish, and Ctrl-C comes once they are in.
    hung = tmp_path / "hung.pid"
    nodes = wrapper(tmp_path, hostsim_bin, "9..9",
                    f"echo $$ > {hung}; while kill -0 $PPID 2>/dev/null; do sleep 0.1; done; exit 1")
    # stderr to a file, not a pipe: Ray's own processes inherit it and may outlive the driver.
    log = tmp_path / "stderr"
    with open(log, "w") as err:
        proc = subprocess.Popen(drive_cmd(tmp_path, hostsim_bin, nodes=nodes), stderr=err,
                                stdout=subprocess.DEVNULL)
    try:
        # The same bound as every other sweep of this module, Ray's start included.
        deadline = time.monotonic() + 300
        while "sweep: 3 of 4 shards" not in log.read_text():
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.1)
        proc.send_signal(signal.SIGINT)
        sent = time.monotonic()
        proc.wait(timeout=max(deadline - sent, 60))
        print(f"Ctrl-C: the driver exited {time.monotonic() - sent:.1f} s after it", file=sys.stderr)
    finally:
        # A driver that did not stop is ended as a job's time limit ends it (SIGTERM: the same
        # clean-up, its local Ray with it), then killed.
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    text = log.read_text()
    assert proc.returncode == 130, text
    assert "INTERRUPTED: 3 of 4 shards kept" in text and "with --resume runs the rest" in text, text
    parts = tmp_path / "ray" / "parts"
    assert sorted(p.name for p in parts.iterdir() if p.is_dir()) == ["rows-0-2", "rows-3-5", "rows-6-8"]
    assert not (tmp_path / "ray" / "sweep.csv").exists()
    # The cut-off shard's program ended with its worker (killed with it: PR_SET_PDEATHSIG).
    pid = int(hung.read_text())
    deadline = time.monotonic() + 60
    while pathlib.Path(f"/proc/{pid}").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not pathlib.Path(f"/proc/{pid}").exists(), f"the cut-off shard's program {pid} outlived its worker"
    # --resume runs rows 9..9 alone (the wrapper hangs only once), and the table is whole.
    before = len((tmp_path / "calls").read_text().splitlines())
    resumed = drive(tmp_path, hostsim_bin, "--resume", nodes=nodes)
    assert resumed.returncode == 0, resumed.stderr
    assert "3 done already" in resumed.stderr, resumed.stderr
    ran = [c.split(" --runs ")[1].split()[0] for c in (tmp_path / "calls").read_text().splitlines()[before:]]
    assert ran == ["9..9"], ran
    assert_same_tables(tmp_path / "ray", oracle)


def test_bad_input_fails_at_once_with_hostsims_message(hostsim_bin: pathlib.Path, tmp_path: pathlib.Path) -> None:
    cmd = [sys.executable, "-m", "mecanum_drive", "sweep", SCENARIO, "--set", "gains.kq=1", "--ray", "local",
           "--out", str(tmp_path), "--hostsim", str(hostsim_bin)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 2, proc.stderr
    assert "gains.kq: no such field; [gains] has: " in proc.stderr, proc.stderr
    assert "Ray" not in proc.stderr, "before Ray starts"
    for bad, says in [(["--shard-size", "0"], "--shard-size 0: expected 1 to 1000000"),
                      (["--hostsim", str(tmp_path / "none")], "no hostsim binary at")]:
        proc = subprocess.run([*cmd[:5], "--ray", "local", "--out", str(tmp_path), "--hostsim", str(hostsim_bin),
                               *bad], capture_output=True, text=True, timeout=60, check=False)
        assert proc.returncode == 2 and says in proc.stderr, (bad, proc.stderr)

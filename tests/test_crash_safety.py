"""Crash-safe logs: `hostsim run` killed with SIGKILL at random moments, and damaged logs given
to `hostsim summary` and `hostsim replay`.

What the writer promises (docs/logs.md, "Crash safety"): a run that dies
leaves `NAME.mcap.part` cut short, every complete chunk readable, at most the last half second
of log time lost (the log is renamed to `NAME.mcap` only when the run finishes). What the reader
promises (crates/drivelog/src/read.rs): every complete, intact chunk before the damage is
used, the damage is named with its byte offset, and `summary`/`replay` exit with status 3
("damaged") rather than crash.
"""

from __future__ import annotations

import concurrent.futures
import pathlib
import random
import re
import signal
import struct
import subprocess
import threading
import time

import pytest
from mcap.reader import NonSeekingReader

ROOT = pathlib.Path(__file__).resolve().parent.parent

#: Runs killed, how many at once, and when. Most are killed at a moment of the run's own log
#: time: once its progress line says it has logged `target` seconds of the 60 s square, uniform
#: in [0, KILL_AT_MAX_S], the kill follows at once, with 60 - KILL_AT_MAX_S s of the run still to
#: go (tens of milliseconds at the fastest): no run can end before its kill, however fast or
#: loaded the machine (a kill timed in wall-clock seconds from a calibration let 16 of 104 runs
#: end first when the load changed between the two). One in EARLY is killed before its first
#: progress line instead, EARLY_S of wall time after its start at most, so that runs that die
#: before their file or its header exists are covered too.
KILLS = 104
PARALLEL = 4
KILL_AT_MAX_S = 10.0
EARLY = 8
EARLY_S = 0.02
SEED = 20261122

#: How the Python reader's errors for a file that ends inside a record begin.
TRUNCATED = ("EndOfFile", "error: unpack requires a buffer")

#: Exit status of `summary` and `replay` for a damaged log whose complete part was used.
EXIT_DAMAGED = 3

#: A line of `hostsim run --progress-lines`.
PROGRESS_LINE = re.compile(r"progress (\d+\.\d{3})\n")

#: A topic line of `hostsim summary`: "  /can/rx      33460 messages".
TOPIC_LINE = re.compile(r"^\s+(/\S+)\s+(\d+) messages$", re.MULTILINE)


def python_read(path: pathlib.Path) -> tuple[int, int | None, str | None]:
    """Messages the Python reader reads, the last log time (ns), and the error it stopped on.

    The linear reader (NonSeekingReader, what `make_reader` gives for a stream) is the one that
    reads a file cut short: the seeking one starts from the Footer, which a killed run never
    wrote. It reads chunk by chunk (checking their CRCs) and raises at the incomplete tail.
    """
    count, last, error = 0, None, None
    with open(path, "rb") as f:
        try:
            for _, _, message in NonSeekingReader(f, validate_crcs=True).iter_messages(log_time_order=False):
                count += 1
                last = message.log_time if last is None else max(last, message.log_time)
        except Exception as err:  # noqa: BLE001 - the cut-off tail is expected to raise
            error = f"{type(err).__name__}: {err}"
    return count, last, error


def summary_messages(binary: pathlib.Path, path: pathlib.Path) -> tuple[int, int, str]:
    """`hostsim summary PATH`: exit status, messages (sum of its topic lines), stderr."""
    proc = subprocess.run([str(binary), "summary", str(path)], capture_output=True, text=True, timeout=120, check=False)
    return proc.returncode, sum(int(n) for _, n in TOPIC_LINE.findall(proc.stdout)), proc.stderr


def header_length(path: pathlib.Path) -> int:
    """Bytes of a complete log before its first chunk: the magic, header, schemas, channels and
    metadata that the writer puts on disk when it creates the file."""
    with open(path, "rb") as f:
        data = f.read(1 << 20)
    at = 8  # the magic
    while at + 9 <= len(data):
        opcode, length = data[at], struct.unpack_from("<Q", data, at + 1)[0]
        if opcode == 0x06:  # Chunk
            return at
        at += 9 + length
    raise AssertionError(f"{path}: no chunk in its first MiB")


def kill_one(binary: pathlib.Path, out: pathlib.Path, target_s: float | None, early_s: float,
             header_len: int) -> dict:
    """Starts the 60 s square and SIGKILLs it once it has logged `target_s` seconds (its
    progress lines), or `early_s` seconds of wall time after its start without a target; then
    checks what it left. A `.part` shorter than `header_len` was killed between its creation
    and its header's write, microseconds apart: counted as `headerless`, not read."""
    proc = subprocess.Popen(
        [str(binary), "run", str(ROOT / "scenarios" / "square_60s.toml"), "--out", str(out), "--no-plot", "--progress-lines"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    progress: list[float] = []

    def follow() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            # A line cut by the kill has no newline: skip it. The bound below stays an upper
            # bound, as that step is at most 0.1 s after the last whole line's.
            match = PROGRESS_LINE.fullmatch(line)
            if match:
                progress.append(float(match.group(1)))
                if target_s is not None and progress[-1] >= target_s and proc.returncode is None:
                    proc.send_signal(signal.SIGKILL)

    follower = threading.Thread(target=follow)
    follower.start()
    if target_s is None:
        time.sleep(early_s)
        proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=300)
    follower.join(timeout=30)
    delay_s = target_s if target_s is not None else early_s
    result = {"delay_s": delay_s, "killed": proc.returncode == -signal.SIGKILL, "files": sorted(p.name for p in out.iterdir())}
    # Every progress line printed before the kill has been read by now (the pipe drained).
    # The run had logged every step up to the last one, and not yet printed the next, 0.1 s
    # of simulated time later: the log time it reached is in [reached, reached + 0.1 s].
    result["reached_s"] = progress[-1] if progress else 0.0
    result["progress_lines"] = len(progress)
    log = out / "square-60s.mcap.part"
    if not log.exists():
        return result
    if log.stat().st_size < header_len:
        result["headerless"] = log.stat().st_size
        log.unlink()
        return result
    count, last_ns, error = python_read(log)
    status, rust_count, stderr = summary_messages(binary, log)
    result.update(
        messages=count,
        last_s=(last_ns or 0) / 1e9,
        python_error=error,
        summary_status=status,
        summary_messages=rust_count,
        summary_stderr=stderr,
        size=log.stat().st_size,
    )
    # Checked: the log (up to tens of MB, and a hundred runs) is not kept in the temp folder.
    log.unlink()
    return result


def test_killed_runs_leave_logs_that_open_and_lose_at_most_a_second(hostsim_bin, tmp_path) -> None:
    """SIGKILL `hostsim run` at KILLS random moments of its log time (seeded), PARALLEL runs
    at a time.

    For every run: the only file left is `square-60s.mcap.part` (or nothing, if it died before
    creating it): a killed run is never renamed to `.mcap`. Every `.part` left that holds its
    header opens with the Python mcap reader, which reads exactly the messages `hostsim
    summary` reads (every complete chunk: the two readers agree), and `summary` exits 3
    (damaged) naming a byte offset, never crashes.

    "At most the last second is lost" is measured in log time, the time the log is about:
    the run prints `progress <simulated s>` after each 100 ms of simulated time is logged, so
    when it dies it has logged up to at most the last printed time plus 0.1 s. That bound minus
    the last log time in the file is the loss (an upper bound), and must be below 1 s. The
    simulator runs faster than real time, so a second of log time is less than a second of
    wall-clock time: the wall-clock promise ("data written a second before the kill is in the
    file") follows.
    """
    whole = tmp_path / "whole"
    whole.mkdir()
    subprocess.run(
        [str(hostsim_bin), "run", str(ROOT / "scenarios" / "square_60s.toml"), "--out", str(whole), "--no-plot"],
        capture_output=True, timeout=600, check=True,
    )
    header_len = header_length(whole / "square-60s.mcap")
    (whole / "square-60s.mcap").unlink()
    rng = random.Random(SEED)
    kills = [(None, rng.uniform(0.0, EARLY_S)) if i % EARLY == 0 else (rng.uniform(0.0, KILL_AT_MAX_S), 0.0)
             for i in range(KILLS)]
    started = time.monotonic()
    with concurrent.futures.ThreadPoolExecutor(PARALLEL) as pool:
        futures = []
        for i, (target, early) in enumerate(kills):
            out = tmp_path / f"run{i:03d}"
            out.mkdir()
            futures.append(pool.submit(kill_one, hostsim_bin, out, target, early, header_len))
        results = [f.result() for f in futures]
    elapsed = time.monotonic() - started

    killed = [r for r in results if r["killed"]]
    assert len(killed) == KILLS, [r for r in results if not r["killed"]]
    with_log = [r for r in killed if "messages" in r]
    losses = []
    for r in killed:
        assert r["files"] in ([], ["square-60s.mcap.part"]), r
        if "messages" not in r:
            continue
        assert r["summary_status"] == EXIT_DAMAGED, r
        assert "panicked" not in r["summary_stderr"] and "byte " in r["summary_stderr"], r
        assert r["messages"] == r["summary_messages"], r
        # The reader stopped at the cut-off tail (the file ends inside a record: mcap's
        # EndOfFile, or struct's short unpack), not at a damaged chunk (a CRC error).
        assert r["python_error"] is None or r["python_error"].startswith(TRUNCATED), r
        loss = r["reached_s"] + 0.1 - r["last_s"]
        assert loss < 1.0, f"lost up to {loss:.3f} s of log time: {r}"
        losses.append(loss)
    # Most runs got far enough to have flushed data, and the loss bound was measured (it needs
    # the progress lines: without them it would be vacuous).
    assert sum(r["messages"] > 0 for r in with_log) >= len(killed) // 2
    assert sum(r["progress_lines"] > 0 for r in with_log) >= len(killed) // 2
    worst = max(with_log, key=lambda r: r["reached_s"] + 0.1 - r["last_s"])
    print(
        f"\n{len(killed)} runs killed in {elapsed:.1f} s: {len(with_log)} left a log "
        f"({sum(r['messages'] for r in with_log)} messages, up to {max(r['reached_s'] for r in killed):.1f} s "
        f"simulated), {sum(r['files'] == ['square-60s.mcap.part'] for r in killed)} a .part in all, "
        f"{sum(r['files'] == [] for r in killed)} nothing, {sum('headerless' in r for r in killed)} before "
        f"their header; largest log-time loss bound "
        f"{max(losses):.3f} s (reached {worst['reached_s']:.1f} s, file ends at {worst['last_s']:.3f} s), "
        f"median {sorted(losses)[len(losses) // 2]:.3f} s"
    )


@pytest.fixture(scope="module")
def short_log(hostsim_bin, tmp_path_factory) -> pathlib.Path:
    """A complete 3 s log of a drive forward (about 1.5 MB, 10 chunks)."""
    out = tmp_path_factory.mktemp("short")
    scenario = out / "short.toml"
    scenario.write_text(
        'name = "short"\nduration_s = 3.0\n[[actions]]\nat_s = 0.05\nenable = true\n'
        "[[actions]]\nat_s = 0.1\ntwist = [0.5, 0.0, 0.0]\n"
    )
    proc = subprocess.run(
        [str(hostsim_bin), "run", str(scenario), "--out", str(out), "--no-plot"],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    return out / "short.mcap"


def run(binary: pathlib.Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(binary), *args], capture_output=True, text=True, timeout=300, check=False)


def test_a_complete_log_exits_zero(hostsim_bin, short_log) -> None:
    proc = run(hostsim_bin, "summary", str(short_log))
    assert proc.returncode == 0, proc.stderr
    assert "read: complete:" in proc.stdout and proc.stderr == ""


@pytest.mark.parametrize("fraction", [0.3, 0.77])
def test_a_cut_log_is_summarised_and_replayed_up_to_its_last_complete_chunk(
    hostsim_bin, short_log, tmp_path, fraction
) -> None:
    data = short_log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * fraction)])
    count, _, error = python_read(cut)
    assert error is not None, "the Python reader stops at the cut"

    proc = run(hostsim_bin, "summary", str(cut))
    assert proc.returncode == EXIT_DAMAGED, proc.stdout + proc.stderr
    assert re.search(r"warning: .*cut\.mcap is damaged: truncated inside the [A-Za-z ]+ record at byte \d+", proc.stderr)
    assert sum(int(n) for _, n in TOPIC_LINE.findall(proc.stdout)) == count

    proc = run(hostsim_bin, "replay", str(cut))
    assert proc.returncode == EXIT_DAMAGED, proc.stdout + proc.stderr
    assert "bit-identical" in proc.stdout and "damaged" in proc.stderr

    proc = run(hostsim_bin, "replay", str(cut), "--json")
    assert proc.returncode == EXIT_DAMAGED, proc.stderr
    assert '"complete":false' in proc.stdout and '"identical":true' in proc.stdout


def chunks(data: bytes) -> list[tuple[int, int]]:
    """(start, end) of every Chunk record (opcode 0x06): the record framing is an opcode byte
    and a little-endian u64 length."""
    found, pos = [], 8
    while pos + 9 <= len(data):
        length = int.from_bytes(data[pos + 1 : pos + 9], "little")
        if data[pos] == 0x06:
            found.append((pos, pos + 9 + length))
        pos += 9 + length
    return found


def test_a_corrupt_chunk_is_not_used_and_named(hostsim_bin, short_log, tmp_path) -> None:
    data = bytearray(short_log.read_bytes())
    all_chunks = chunks(bytes(data))
    start, end = all_chunks[len(all_chunks) // 2]
    data[(start + end) // 2] ^= 0x55
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(bytes(data))
    proc = run(hostsim_bin, "summary", str(bad))
    assert proc.returncode == EXIT_DAMAGED, proc.stdout + proc.stderr
    assert f"Chunk record at byte {start}" in proc.stderr, proc.stderr
    proc = run(hostsim_bin, "replay", str(bad))
    assert proc.returncode == EXIT_DAMAGED, proc.stdout + proc.stderr
    assert "bit-identical" in proc.stdout


def test_nothing_readable_is_a_hard_error(hostsim_bin, tmp_path) -> None:
    for name, data in [("empty.mcap", b""), ("magic.mcap", b"\x89MCAP0\r\n"), ("junk.mcap", b"junk" * 10)]:
        path = tmp_path / name
        path.write_bytes(data)
        for command in ("summary", "replay"):
            proc = run(hostsim_bin, command, str(path))
            assert proc.returncode == 2, (name, command, proc.stderr)
            assert name in proc.stderr and "panicked" not in proc.stderr

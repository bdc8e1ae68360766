"""The bad-input corpus (tests/bad_input/cases.toml): careless and hostile input to every program.

Each case runs one command of `hostsim`, `mecanum-runner`, `mecanum-codec` or `boardsim` and
checks what a user would: it ends within its CPU-time and memory bounds (measured by the
kernel for that process: `wait4`'s rusage, so a busy machine does not change them), exits
with its documented status, names the cause (every word of `says` in its output), and leaves
the output folder it was given (`{out}`, filled beforehand with a previous run's files) byte
for byte as it was. The table's format is in tests/bad_input/README.md. A run prints the
corpus's count (conftest.py's terminal summary).
"""

from __future__ import annotations

import os
import pathlib
import re
import socket
import subprocess
import sys
import threading
import tomllib
from collections.abc import Iterator
from typing import Any

import pytest

from conftest import ROOT, _target_dir

HERE = pathlib.Path(__file__).resolve().parent / "bad_input"
CASES: list[dict[str, Any]] = tomllib.loads((HERE / "cases.toml").read_text())["case"]
#: Defaults of a case's bounds: CPU seconds (user + system) and peak resident memory. The
#: memory is the kernel's high-water mark for the process, which counts the forked test
#: process (about 60 MB) before the program's exec: an upper bound on the program's own.
SECONDS = 10.0
MB = 200.0
#: The board image as scripts/test.sh builds it (its stm32f407 stage, before this one).
BOARD_ELF = ROOT / "boards" / "stm32f407" / "target" / "thumbv7em-none-eabihf" / "release" / "board-stm32f407"
#: The output folder's files before each case: what a previous good run left there.
PREVIOUS = {"square.mcap": b"\x89MCAP0\r\nprevious run", "square.png": b"\x89PNG previous plot",
            "s.mcap": b"\x89MCAP0\r\nprevious s", "s.png": b"\x89PNG previous s",
            "sweep.csv": b"index,seed\n0,1\n", "sweep.jsonl": b'{"index":0}\n', "cal.toml": b"# previous\n",
            "stats.json": b"{}\n"}


def _binary(env: str, name: str) -> pathlib.Path | None:
    """A program of the workspace: $ENV if set, else the ci or debug build if there."""
    if os.environ.get(env):
        return pathlib.Path(os.environ[env])
    for profile in ("ci", "debug"):
        path = _target_dir() / profile / name
        if path.is_file():
            return path
    return None


@pytest.fixture(scope="module")
def programs(hostsim_bin: pathlib.Path, codec_bin: pathlib.Path) -> dict[str, pathlib.Path | None]:
    return {
        "hostsim": hostsim_bin,
        "codec": codec_bin,
        "runner": _binary("MECANUM_RUNNER", "mecanum-runner"),
        "boardsim": _binary("BOARDSIM", "boardsim"),
        "board_elf": BOARD_ELF if BOARD_ELF.is_file() else None,
    }


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory, hostsim_bin: pathlib.Path) -> pathlib.Path:
    """Inputs the cases share, made once: large and odd files, and logs good and bad."""
    work = tmp_path_factory.mktemp("bad-input")
    with open(work / "sparse-1g.mcap", "wb") as f:  # a 1 GB file of zeros that takes no disk
        f.truncate(1 << 30)
    with open(work / "sparse-1g.toml", "wb") as f:
        f.truncate(1 << 30)
    (work / "big-line.toml").write_bytes(b"# " + b"x" * (10 << 20) + b"\nlx = \n")
    (work / "victim").write_bytes(b"another user's file\n")
    scenario = work / "short.toml"
    scenario.write_text('name = "short"\nduration_s = 0.5\n[[actions]]\nat_s = 0.05\nenable = true\n'
                        "[[actions]]\nat_s = 0.1\ntwist = [0.3, 0.0, 0.0]\n")
    subprocess.run([str(hostsim_bin), "run", str(scenario), "--out", str(work), "--no-plot"],
                   capture_output=True, check=True, timeout=300)
    good = (work / "short.mcap").read_bytes()
    (work / "cut.mcap").write_bytes(good[: len(good) * 2 // 3])
    (work / "header-only.mcap").write_bytes(good[:600])
    _undecodable(work / "short.mcap", work / "undecodable.mcap")
    _foreign(work / "foreign.mcap")
    return work


def _foreign(out: pathlib.Path) -> None:
    """Another program's MCAP: no `ros2` profile, JSON messages on a /can/rx topic."""
    from mcap.writer import Writer

    with open(out, "wb") as f:
        writer = Writer(f)
        writer.start(profile="", library="another program")
        schema = writer.register_schema("Frame", "jsonschema", b"{}")
        channel = writer.register_channel("/can/rx", "json", schema)
        writer.add_message(channel, 0, b'{"id":513,"data":[]}', 0)
        writer.finish()


@pytest.fixture(scope="module")
def busy_port() -> Iterator[int]:
    """A port on 127.0.0.1 that another program holds (a listening socket of this process)."""
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen(1)
        yield held.getsockname()[1]


def _undecodable(good: pathlib.Path, out: pathlib.Path) -> None:
    """`good` rewritten with its 100th /can/rx message cut to 3 bytes: intact, one message not CDR."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(good, "rb") as src, open(out, "wb") as dst:
        reader = make_reader(src)
        writer = Writer(dst)
        header = reader.get_header()
        writer.start(profile=header.profile, library=header.library)
        for meta in reader.iter_metadata():
            writer.add_metadata(meta.name, meta.metadata)
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        rx = 0
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas.get(channel.schema_id, 0))
            data = message.data
            if channel.topic == "/can/rx":
                rx += 1
                if rx == 100:
                    data = data[:3]
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time)
        writer.finish()


def _expand(text: str, places: dict[str, str]) -> str:
    """`text` with each `{name}` of `places` replaced (other braces, `\\u{1b}`, stay)."""
    return re.sub(r"\{(\w+)\}", lambda m: places.get(m.group(1), m.group(0)), text)


def _config_with(work: pathlib.Path, name: str, key: str, value: str) -> pathlib.Path:
    """config/dji_m3508.toml with `section.field = value` (replaced in its section, or added)."""
    section, field = key.rsplit(".", 1)
    lines = (ROOT / "config" / "dji_m3508.toml").read_text().splitlines()
    out, current, done = [], "", False
    for line in lines:
        head = re.match(r"^\[([\w.]+)\]", line)
        if head:
            if current == section and not done:
                out.append(f"{field} = {value}")
                done = True
            current = head.group(1)
        if current == section and re.match(rf"^{re.escape(field)}\s*=", line):
            line, done = f"{field} = {value}", True
        out.append(line)
    if not done:
        out += [f"[{section}]", f"{field} = {value}"]
    path = work / f"{name}.config.toml"
    path.write_text("\n".join(out) + "\n")
    return path


def _run(cmd: list[str], stdin: bytes | int, cwd: pathlib.Path, wall_s: float) -> tuple[int, str, Any]:
    """Runs `cmd` with `stdin` (bytes, or a count of NUL bytes streamed); its exit status,
    output (stdout and stderr) and rusage, from wait4 on it alone."""
    proc = subprocess.Popen(cmd, cwd=cwd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    out: list[bytes] = []

    def feed() -> None:
        assert proc.stdin is not None
        try:
            if isinstance(stdin, int):
                block = bytes(1 << 20)
                for i in range(0, stdin, len(block)):
                    proc.stdin.write(block[: min(len(block), stdin - i)])
            else:
                proc.stdin.write(stdin)
            proc.stdin.close()
        except (BrokenPipeError, OSError):
            pass

    def drain() -> None:
        assert proc.stdout is not None
        out.append(proc.stdout.read(1 << 20))  # what is said first; the rest is read away
        while proc.stdout.read(1 << 20):
            pass

    threads = [threading.Thread(target=feed, daemon=True), threading.Thread(target=drain, daemon=True)]
    for t in threads:
        t.start()
    timer = threading.Timer(wall_s, proc.kill)
    timer.start()
    try:
        _, status, usage = os.wait4(proc.pid, 0)
    finally:
        timer.cancel()
    proc.returncode = os.waitstatus_to_exitcode(status)
    for t in threads:
        t.join(timeout=30)
    return proc.returncode, b"".join(out).decode("utf-8", "replace"), usage


def _listing(folder: pathlib.Path) -> dict[str, bytes | str]:
    """Every entry of `folder`: a file's bytes, a link's target."""
    return {p.name: (f"-> {os.readlink(p)}" if p.is_symlink() else p.read_bytes() if p.is_file() else "(folder)")
            for p in sorted(folder.iterdir())}


@pytest.mark.parametrize("case", CASES, ids=[c["name"] for c in CASES])
def test_bad_input(case: dict[str, Any], programs: dict[str, pathlib.Path | None], work: pathlib.Path,
                   busy_port: int, tmp_path: pathlib.Path) -> None:
    for need in case.get("needs", []):
        if programs.get(need) is None:
            if os.environ.get("CI"):
                pytest.fail(f"{need} is not built (scripts/test.sh builds it before this stage)")
            pytest.skip(f"{need} is not built")
    out = tmp_path / "out"
    out.mkdir()
    for name, data in PREVIOUS.items():
        (out / name).write_bytes(data)
    for link, target in case.get("links", {}).items():
        (out / link).unlink(missing_ok=True)
        os.symlink(_expand(target, {"work": str(work)}), out / link)
    places = {k: str(v) for k, v in programs.items() if v is not None}
    places |= {"out": str(out), "work": str(work), "files": str(HERE / "files"), "tmp": str(tmp_path),
               "host_elf": os.path.realpath(sys.executable), "root": str(ROOT), "busy_port": str(busy_port)}
    if "config_set" in case:
        places["config"] = str(_config_with(tmp_path, case["name"], *case["config_set"]))
    if "scenario_text" in case:
        scenario = tmp_path / "scenario.toml"
        scenario.write_text(case["scenario_text"])
        places["scenario"] = str(scenario)
    before = _listing(out)
    victim = (work / "victim").read_bytes()
    cmd = [_expand(arg, places) for arg in case["cmd"]]
    stdin: bytes | int = case.get("stdin_zeros", case.get("stdin", "").encode())
    seconds, mb = case.get("seconds", SECONDS), case.get("mb", MB)
    code, text, usage = _run(cmd, stdin, tmp_path, wall_s=max(120.0, 20 * seconds))
    cpu = usage.ru_utime + usage.ru_stime
    rss_mb = usage.ru_maxrss / 1024
    shown = f"{' '.join(cmd)[:300]}\nexit {code}, {cpu:.2f} CPU-s, {rss_mb:.0f} MB:\n{text[:3000]}"
    assert code == case["exit"], shown
    for word in case.get("says", []):
        assert _expand(word, places) in text, f"does not say {word!r}: {shown}"
    assert cpu <= seconds, f"{cpu:.2f} CPU-s, bound {seconds}: {shown}"
    assert rss_mb <= mb, f"{rss_mb:.0f} MB, bound {mb}: {shown}"
    # Input never reaches the terminal raw: no escape or bell byte is echoed.
    assert "\x1b" not in text and "\x07" not in text, shown
    if case.get("keeps_out", True):
        after = _listing(out)
        for name in case.get("leaves", []):  # a failed run's partial output, named in its message
            assert name in after and name in text, f"{name}: {shown}"
            del after[name]
        assert after == before, f"the output folder changed: {shown}"
    assert (work / "victim").read_bytes() == victim, f"a planted link was written through: {shown}"
    for name, want in case.get("out_files", {}).items():
        path = out / name
        assert path.is_file() and not path.is_symlink(), f"{name}: {shown}"
        assert want.encode("latin-1") in path.read_bytes()[:64], f"{name}: {shown}"


def test_the_corpus_covers_every_program_with_at_least_150_cases() -> None:
    programs = {c["cmd"][0] for c in CASES}
    assert programs == {"{hostsim}", "{runner}", "{codec}", "{boardsim}"}, programs
    names = [c["name"] for c in CASES]
    assert len(set(names)) == len(names), "case names are unique"
    assert len(CASES) >= 150, len(CASES)

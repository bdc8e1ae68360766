"""`mecanum-drive sweep --ray`: a `hostsim sweep` shared out over a Ray cluster.

The plan is hostsim's: the local binary checks the sweep first (`hostsim sweep ... --check`:
bad input fails here, at once, with hostsim's own message) and says how many runs it has.
The rows are cut into shards of `--shard-size` runs (`--runs I..J`: every row's draws are
seeded by its index in the whole table, so a shard's rows are the whole table's), each shard
a Ray task that runs hostsim on one CPU of a node and returns its table. Each finished shard
is written to `OUT/parts/rows-I-J/` as it comes (a folder renamed into place when whole), a
progress line is printed, and when all are in, the local hostsim merges them
(`hostsim sweep --merge`): `OUT/sweep.csv`, `sweep.jsonl` and `sweep.png`, byte for byte
what one `hostsim sweep` on one machine writes.

- A shard whose worker died (a node lost, a process killed) is run again by Ray, up to
  `--retries` times; a shard that hostsim refuses is an error, named with hostsim's message.
- Ctrl-C (or SIGTERM) cancels the shards not finished and keeps the finished ones; `--resume`
  runs only the shards missing from `OUT/parts`, of the same sweep: `OUT/parts/request.json`
  holds hostsim's arguments and a digest of the files shipped, and parts of another sweep
  are refused.
- The binary: shipped with the job by default (the local hostsim, through Ray's object store,
  so the nodes need nothing but Ray and a compatible glibc: docs/sweeps-on-ray.md), or found
  on each node at `--hostsim-on-nodes PATH`. The scenario file and its configuration file are
  shipped with each task.

Ray is the package's optional extra `ray` (`pip install './python[ray]'`), imported only here.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

#: Runs per shard unless --shard-size says otherwise: long enough that a task's start-up
#: (a process, the binary written once per node) is small beside it.
DEFAULT_SHARD_SIZE = 250
#: Exit status of a sweep stopped by Ctrl-C (as hostsim's).
EXIT_INTERRUPTED = 130
#: The folder of the finished shards inside --out.
PARTS = "parts"
#: In OUT/parts: what the parts are rows of (`request_of`).
REQUEST = "request.json"
#: How often the driver leaves Ray's wait to see whether it was told to stop, s.
POLL_S = 0.2


class SweepError(Exception):
    """A sweep that cannot start or finish; the message says why."""


@dataclass(frozen=True)
class Shard:
    """Rows `first` to `last` of the plan, both included."""

    first: int
    last: int

    @property
    def name(self) -> str:
        return f"rows-{self.first}-{self.last}"


def shards(runs: int, size: int) -> list[Shard]:
    """The plan's rows in shards of `size` (the last one shorter)."""
    return [Shard(i, min(i + size, runs) - 1) for i in range(0, runs, size)]


def find_hostsim(path: str | None) -> pathlib.Path:
    """The local hostsim: `path`, else $HOSTSIM, else `hostsim` on the PATH."""
    name = path or os.environ.get("HOSTSIM") or shutil.which("hostsim")
    if not name or not pathlib.Path(name).is_file():
        raise SweepError(f"no hostsim binary at {name!r}: build it (cargo build --release -p hostsim) "
                         "and give --hostsim PATH, or put it on the PATH" if name else
                         "no hostsim binary: give --hostsim PATH (cargo build --release -p hostsim), "
                         "set HOSTSIM, or put it on the PATH")
    return pathlib.Path(name)


def bundle(scenario: str, config: str | None) -> tuple[dict[str, bytes], str, str | None]:
    """The files a task needs, by path relative to its work folder, and the scenario and
    --config arguments that name them there. A built-in scenario needs no file; a scenario
    file's own `config = "REL"` is shipped at the same path relative to it."""
    files: dict[str, bytes] = {}
    config_arg = None
    if config is not None:
        files["config/config.toml"] = pathlib.Path(config).read_bytes()
        config_arg = "config/config.toml"
    path = pathlib.Path(scenario)
    if not (path.suffix == ".toml" or path.exists() or "/" in scenario):
        return files, scenario, config_arg
    text = path.read_bytes()
    try:
        rel = tomllib.loads(text.decode()).get("config")
    except (UnicodeDecodeError, tomllib.TOMLDecodeError):
        rel = None  # hostsim's --check has said what is wrong, or will
    # Deep enough that the configuration's relative path stays inside the work folder.
    depth = len(pathlib.PurePosixPath(rel).parts) if isinstance(rel, str) else 0
    home = pathlib.PurePosixPath(*(["s"] * (depth + 1)))
    files[str(home / path.name)] = text
    if isinstance(rel, str) and config is None:
        target = os.path.normpath(str(home / rel))
        files[target] = (path.parent / rel).read_bytes()
    return files, str(home / path.name), config_arg


def run_shard(binary: bytes | str, files: dict[str, bytes], argv: list[str], shard: Shard) -> dict[str, bytes]:
    """A Ray task's work: hostsim on `shard`'s rows, on one CPU, in a folder of its own; the
    part's table files. `binary` is the program itself (shipped) or its path on the node."""
    with tempfile.TemporaryDirectory(prefix="mecanum-sweep-") as tmp:
        work = pathlib.Path(tmp)
        for rel, data in files.items():
            (work / rel).parent.mkdir(parents=True, exist_ok=True)
            (work / rel).write_bytes(data)
        if isinstance(binary, bytes):
            program = work / "hostsim"
            program.write_bytes(binary)
            program.chmod(0o755)
        else:
            program = pathlib.Path(binary)
        out = work / "out"
        cmd = [str(program), "sweep", *argv, "--runs", f"{shard.first}..{shard.last}",
               "--out", str(out), "--no-plot", "--jobs", "1", "--worst", "0"]
        proc = subprocess.run(cmd, cwd=work, capture_output=True, text=True, check=False,
                              preexec_fn=_die_with_parent)
        if proc.returncode != 0:
            raise RuntimeError(f"hostsim sweep, {shard.name}, exit {proc.returncode}: {proc.stderr.strip()}")
        return {name: (out / name).read_bytes() for name in ("sweep.csv", "sweep.jsonl", "sweep.plan.json")}


def _die_with_parent() -> None:
    """In the child, before hostsim starts: SIGKILL when the worker that started it dies (Linux
    `prctl(PR_SET_PDEATHSIG)`), so a cancelled or killed task leaves no hostsim running."""
    import ctypes

    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # 1: PR_SET_PDEATHSIG


def write_part(parts: pathlib.Path, shard: Shard, tables: dict[str, bytes]) -> None:
    """A shard's tables into `parts/rows-I-J`, the folder renamed into place when whole."""
    staging = pathlib.Path(tempfile.mkdtemp(prefix=f".{shard.name}-", dir=parts))
    for name, data in tables.items():
        (staging / name).write_bytes(data)
    staging.rename(parts / shard.name)


def request_of(argv: list[str], files: dict[str, bytes]) -> dict[str, Any]:
    """What a sweep's parts are rows of: hostsim's arguments as the tasks get them, and the
    SHA-256 of each file shipped with them (the scenario, its configuration)."""
    return {"argv": argv, "files": {name: hashlib.sha256(data).hexdigest() for name, data in sorted(files.items())}}


def same_request(parts: pathlib.Path, request: dict[str, Any], resume: bool) -> None:
    """Refuses `parts` if it holds parts of another sweep than `request` (or, without
    `resume`, any parts at all); records `request` there when it holds nothing yet."""
    path = parts / REQUEST
    if path.is_file():
        if not resume:
            raise SweepError(f"{parts} holds parts of a sweep already: --resume to go on with it, "
                             "or give another --out")
        try:
            got = json.loads(path.read_text())
        except ValueError as err:
            raise SweepError(f"{path}: not a sweep's request ({err}); give another --out, or remove {parts}") from err
        argv = got.get("argv") if isinstance(got, dict) else None
        if not (isinstance(argv, list) and all(isinstance(a, str) for a in argv)):
            raise SweepError(f"{path}: not a sweep's request (no list of hostsim's arguments); give another "
                             f"--out, or remove {parts}")
        if got != request:
            if argv != request["argv"]:
                what = (f"hostsim's arguments differ: {' '.join(argv)!r} there, "
                        f"{' '.join(request['argv'])!r} here")
            else:
                what = "the scenario or configuration file changed since"
            raise SweepError(f"{parts} holds parts of another sweep ({what}); give another --out, or remove {parts}")
        return
    if any(not p.name.startswith(".") for p in parts.iterdir()):
        raise SweepError(f"{parts} holds parts without {REQUEST} (a sweep of an older version): "
                         f"give another --out, or remove {parts}")
    staging = parts / f".{REQUEST}"
    staging.write_text(json.dumps(request, indent=1) + "\n")
    staging.rename(path)


def finished(parts: pathlib.Path, shard: Shard, plan: dict[str, Any]) -> bool:
    """Whether `parts` holds `shard` whole, of this plan (a part of another one is refused)."""
    plan_file = parts / shard.name / "sweep.plan.json"
    if not plan_file.is_file():
        return False
    got = json.loads(plan_file.read_text())
    if got.get("runs") != plan["runs"] or got.get("header") != plan["header"]:
        raise SweepError(f"{parts / shard.name} is a part of another sweep ({got.get('runs')} runs, "
                         f"header {got.get('header')!r}); give another --out, or remove {parts}")
    return bool(got.get("rows") == [shard.first, shard.last + 1])


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", help="a scenario TOML file, or the name of a built-in (hostsim's)")
    p.add_argument("--seeds", help="A..B (both included), or a list 1,5,9 (hostsim's)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUES",
                   help="a parameter: KEY=V1,V2,... (a grid axis) or KEY=LO..HI (a draw per run); repeatable")
    p.add_argument("--config", help="drive configuration TOML (overrides the scenario's)")
    p.add_argument("--ray", required=True, metavar="ADDRESS",
                   help="the Ray cluster: 'local' (a cluster of this machine's cores, on 127.0.0.1), "
                        "or its address as ray.init takes it (ray://HEAD:10001 from outside it, auto on "
                        "one of its nodes)")
    p.add_argument("--out", default="out", help="output folder (default out): sweep.csv, sweep.jsonl, "
                                                "sweep.png and parts/, one folder per shard")
    p.add_argument("--shard-size", type=int, default=DEFAULT_SHARD_SIZE, metavar="N",
                   help=f"runs per Ray task, 1 to 1000000 (default {DEFAULT_SHARD_SIZE})")
    p.add_argument("--retries", type=int, default=3, metavar="N",
                   help="times a shard whose worker died is run again, 0 to 100 (default 3)")
    p.add_argument("--resume", action="store_true", help="run only the shards not yet in OUT/parts")
    p.add_argument("--hostsim", help="the local hostsim binary (default $HOSTSIM, else on the PATH): plans, "
                                     "merges, and is shipped to the nodes")
    p.add_argument("--hostsim-on-nodes", metavar="PATH",
                   help="run hostsim from PATH on each node instead of shipping the local binary")
    p.add_argument("--cpus", type=int, metavar="N", help="with --ray local: the cluster's CPUs (default all)")
    p.add_argument("--no-plot", action="store_true", help="do not draw sweep.png")


def run(args: argparse.Namespace) -> int:
    """`mecanum-drive sweep`: exit 0, 2 for input hostsim or this command refuses, 1 for a
    sweep that failed, 130 for Ctrl-C."""
    for name, value, low, high in (("--shard-size", args.shard_size, 1, 1_000_000),
                                   ("--retries", args.retries, 0, 100),
                                   ("--cpus", args.cpus, 1, 4096)):
        if value is not None and not low <= value <= high:
            print(f"mecanum-drive sweep: {name} {value}: expected {low} to {high}", file=sys.stderr)
            return 2
    if args.cpus is not None and args.ray != "local":
        print("mecanum-drive sweep: --cpus is for --ray local (a cluster has its own)", file=sys.stderr)
        return 2
    try:
        hostsim = find_hostsim(args.hostsim)
        argv = [args.scenario, *(["--seeds", args.seeds] if args.seeds else []),
                *(x for s in args.set for x in ("--set", s)), *(["--config", args.config] if args.config else [])]
        check = subprocess.run([str(hostsim), "sweep", *argv, "--check"], capture_output=True, text=True, check=False)
        if check.returncode != 0:
            sys.stderr.write(check.stderr)
            return 2
        plan = json.loads(check.stdout)
        files, scenario_arg, config_arg = bundle(args.scenario, args.config)
    except (SweepError, OSError) as err:
        print(f"mecanum-drive sweep: {err}", file=sys.stderr)
        return 2
    remote_argv = [scenario_arg, *(["--seeds", args.seeds] if args.seeds else []),
                   *(x for s in args.set for x in ("--set", s)), *(["--config", config_arg] if config_arg else [])]
    out = pathlib.Path(args.out)
    parts = out / PARTS
    parts.mkdir(parents=True, exist_ok=True)
    for stale in parts.glob(".rows-*"):
        shutil.rmtree(stale)  # a shard's folder not yet whole when a sweep was stopped
    todo = shards(plan["runs"], args.shard_size)
    try:
        same_request(parts, request_of(remote_argv, files), args.resume)
        done = [s for s in todo if finished(parts, s, plan)] if args.resume else []
    except (SweepError, OSError) as err:
        print(f"mecanum-drive sweep: {err}", file=sys.stderr)
        return 2
    pending = [s for s in todo if s not in done]
    print(f"sweep of {plan['scenario']!r}: {plan['runs']} runs in {len(todo)} shards of up to {args.shard_size}"
          f"{f'; {len(done)} done already' if done else ''}; Ray at {args.ray}", file=sys.stderr)
    status = _run_on_ray(args, hostsim, files, remote_argv, plan, parts, pending, len(todo), len(done))
    if status != 0:
        return status
    merge = [str(hostsim), "sweep", "--merge", *sorted(str(p) for p in parts.iterdir() if p.is_dir()
                                                       and not p.name.startswith(".")), "--out", str(out)]
    if args.no_plot:
        merge.append("--no-plot")
    merging = time.monotonic()
    merged = subprocess.run(merge, capture_output=True, text=True, check=False)
    sys.stdout.write(merged.stdout)
    print(f"sweep: merged in {time.monotonic() - merging:.1f} s", file=sys.stderr)
    if merged.returncode != 0:
        sys.stderr.write(merged.stderr)
        return 1
    return 0


def _run_on_ray(args: argparse.Namespace, hostsim: pathlib.Path, files: dict[str, bytes], argv: list[str],
                plan: dict[str, Any], parts: pathlib.Path, pending: list[Shard], total: int, done: int) -> int:
    """The pending shards as Ray tasks, each written as it finishes; 0, 1 (a shard failed)
    or 130 (Ctrl-C)."""
    # Nothing leaves the machine unasked: no usage statistics, and a local cluster on loopback.
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

    try:
        import ray
    except ImportError:
        print("mecanum-drive sweep --ray: Ray is not installed: pip install './python[ray]' "
              "(the package's ray extra)", file=sys.stderr)
        return 2
    started = time.monotonic()
    # The workers import this module to run the task: it goes with the job (py_modules), so a
    # cluster's nodes need Ray and Python, not this package.
    runtime_env = {"py_modules": [str(pathlib.Path(__file__).resolve().parent)]}
    if args.ray == "local":
        ray.init(num_cpus=args.cpus or os.cpu_count(), include_dashboard=False, log_to_driver=False,
                 _node_ip_address="127.0.0.1", runtime_env=runtime_env)
    else:
        ray.init(address=args.ray, log_to_driver=False, runtime_env=runtime_env)
    # Ctrl-C and SIGTERM (a Slurm job's time limit, a pod stopped) end the sweep alike: the
    # finished shards kept, the rest cancelled, a local cluster shut down. Both only set a
    # flag the loop reads between its waits: set after ray.init, which installs handlers of
    # its own, and independent of whether Ray's code lets a KeyboardInterrupt through.
    stop: list[int] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: stop.append(signum))
    try:
        task = ray.remote(num_cpus=1, max_retries=args.retries)(run_shard)
        binary: Any = args.hostsim_on_nodes or ray.put(hostsim.read_bytes())
        files_ref = ray.put(files)
        start = time.monotonic()
        print(f"sweep: Ray up in {start - started:.1f} s", file=sys.stderr)
        futures = {task.remote(binary, files_ref, argv, s): s for s in pending}
        rows = sum(s.last - s.first + 1 for s in pending)
        rows_done = 0
        try:
            while futures:
                if stop:
                    raise KeyboardInterrupt
                # Back in Python every POLL_S: a signal (Ctrl-C, SIGTERM) is seen only here,
                # not inside Ray's wait.
                ready, _ = ray.wait(list(futures), num_returns=1, timeout=POLL_S)
                if not ready:
                    continue
                shard = futures.pop(ready[0])
                try:
                    tables = ray.get(ready[0])
                except ray.exceptions.RayError as err:
                    cause = getattr(err, "cause", None) or err
                    print(f"mecanum-drive sweep: {shard.name} failed: {cause}", file=sys.stderr)
                    for f in futures:
                        ray.cancel(f)
                    print(f"mecanum-drive sweep: the finished shards are in {parts}; --resume runs the rest",
                          file=sys.stderr)
                    return 1
                write_part(parts, shard, tables)
                done += 1
                rows_done += shard.last - shard.first + 1
                print(f"sweep: {done} of {total} shards, {rows_done} of {rows} runs here, "
                      f"{time.monotonic() - start:.1f} s", file=sys.stderr, flush=True)
        except KeyboardInterrupt:
            for f in futures:
                ray.cancel(f, force=True)
            print(f"sweep: INTERRUPTED: {done} of {total} shards kept in {parts}; the same command "
                  "with --resume runs the rest", file=sys.stderr)
            return EXIT_INTERRUPTED
    finally:
        ray.shutdown()
    return 0

"""The bring-up check's rule in two languages: `hostsim check` (the simulator, its plant's
ground truth watching the wheels) and the Python package's `mecanum_drive.check` (a person
watching) must give the same fix for the same observations, on every single flip (4) and
drive-id transposition (6) of the DJI and the ODrive examples; and the package's check
refuses bad answers and bad configurations by name."""

from __future__ import annotations

import itertools
import json
import pathlib
import subprocess

import pytest

from mecanum_drive import check
from mecanum_drive.cli import main

ROOT = pathlib.Path(__file__).resolve().parents[1]
WHEELS = check.WHEELS

MISWIRINGS = [[]] + [["--flip", w] for w in WHEELS] + [
    ["--swap", f"{a},{b}"] for a, b in itertools.combinations(WHEELS, 2)
]


def hostsim_check(binary: pathlib.Path, config: str, wiring: list[str]) -> tuple[int, dict]:
    run = subprocess.run(
        [str(binary), "check", "--config", str(ROOT / "config" / config), "--json", *wiring],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert run.returncode in (0, 3), run.stderr
    return run.returncode, json.loads(run.stdout)


@pytest.mark.parametrize("config", ["dji_m3508.toml", "odrive.toml"])
def test_python_and_the_simulator_give_the_same_fix_for_every_miswiring(hostsim_bin: pathlib.Path, config: str) -> None:
    configured = check.Wiring.from_config(ROOT / "config" / config)
    for wiring in MISWIRINGS:
        code, report = hostsim_check(hostsim_bin, config, wiring)
        # What the simulator's plant saw, as a person would answer.
        answers = [f"{w['turned']} {'f' if w['forward'] else 'b'}" for w in report["wheels"]]
        d = check.diagnose(configured, [check.parse_seen(a) for a in answers])
        assert d.fix_lines(configured) == report["fix"], (wiring, answers)
        assert d.right == report["right"] == (wiring == []) == (code == 0), wiring
        if wiring:
            # One wrong wheel or pair: its lines name exactly the keys that change.
            assert 1 <= len(report["fix"]) <= 2, report["fix"]
            flipped = wiring[0] == "--flip"
            assert any(line.startswith("inverted") for line in report["fix"]) or not flipped
            assert any(line.startswith(configured.ids_key) for line in report["fix"]) or flipped
        for w in report["wheels"]:
            assert w["firmware"]["outcome"] == "DONE", w


def test_the_fix_of_a_diagonal_swap_on_the_dji_example() -> None:
    """ESC 1 is on RR and ESC 4 on FL: both turn backward (the right side is mirrored)."""
    configured = check.Wiring.from_config(ROOT / "config" / "dji_m3508.toml")
    answers = ["RR b", "FR f", "RL f", "FL b"]
    d = check.diagnose(configured, [check.parse_seen(a) for a in answers])
    assert d.fix_lines(configured) == ["esc_ids = [4, 2, 3, 1]"]
    assert d.verdicts[0] == "RR turned backward instead: wired to the wrong wheel"


@pytest.mark.parametrize("answer, seen", [
    ("FL f", check.Seen(0, True)), ("rr backward", check.Seen(3, False)), ("RL-", check.Seen(2, False)),
    ("fr +", check.Seen(1, True)), ("none", None), ("-", None),
])
def test_answers_parse(answer: str, seen: check.Seen | None) -> None:
    assert check.parse_seen(answer) == seen


def test_bad_answers_and_configurations_are_named(tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ValueError, match="'XL f': expected a wheel and a direction"):
        check.parse_seen("XL f")
    bad = tmp_path / "bad.toml"
    bad.write_text('[drive]\nprotocol = "dji"\nesc_ids = [1, 2, 3]\n')
    with pytest.raises(ValueError, match=r"drive\.esc_ids = \[1, 2, 3\]: expected four ids"):
        check.Wiring.from_config(bad)
    bad.write_text('[drive]\nprotocol = "canopen"\n')
    with pytest.raises(ValueError, match="drive.protocol = 'canopen'"):
        check.Wiring.from_config(bad)
    # Missing or doubled answers: no guess, the reason.
    configured = check.Wiring.from_config(ROOT / "config" / "dji_m3508.toml")
    d = check.diagnose(configured, [check.Seen(0, True), None, check.Seen(2, True), check.Seen(3, True)])
    assert d.fixed is None and "no wheel turned when FR was tested" in (d.unresolved or "")
    # The command line refuses bad answers before any wheel turns (no bus is opened).
    with pytest.raises(SystemExit, match="expected four answers"):
        main(["--channel", "nonexistent", "check", "--config", str(ROOT / "config" / "dji_m3508.toml"),
              "--observed", "FL f,FR f", "--yes"])
    assert main(["--channel", "nonexistent", "check", "--config", str(ROOT / "config" / "dji_m3508.toml"),
                 "--observed", "FL sideways,FR f,RL f,RR f", "--yes"]) == 1
    assert "'FL sideways': expected a wheel and a direction" in capsys.readouterr().err
    assert main(["--channel", "nonexistent", "check", "--config", str(bad), "--yes"]) == 1
    assert "drive.protocol = 'canopen'" in capsys.readouterr().err


def test_the_check_stops_cleanly_when_the_person_does(monkeypatch: pytest.MonkeyPatch,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """End of input (or Ctrl-C) at the first prompt: status 130 and a line, no traceback, and
    no bus was opened (the prompt comes before)."""
    import io

    monkeypatch.setattr("sys.stdin", io.StringIO(""))
    assert main(["--channel", "nonexistent", "check", "--config", str(ROOT / "config" / "dji_m3508.toml")]) == 130
    captured = capsys.readouterr()
    assert "Put the robot on blocks" in captured.out
    assert "check: stopped" in captured.err

"""The robot's parameters, one description: firmware::params as `mecanum-codec params` prints
it, the committed EDS (dbc/mecanum_robot.eds) as python-canopen reads it, and the configuration
files whose keys the parameters are named after."""

from __future__ import annotations

import configparser
import math
import pathlib
import subprocess
import tomllib

import canopen
import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
EDS = ROOT / "dbc" / "mecanum_robot.eds"
TYPES = {"BOOLEAN": 0x0001, "UNSIGNED8": 0x0005, "UNSIGNED32": 0x0007, "REAL32": 0x0008}
# Parameters that are not configuration-file keys: the drive's ids and inversion bits (the
# file's esc_ids or node_ids and inverted array, whichever the protocol) and the pod count.
DERIVED = ("drive.", "odometry.pod_count")


@pytest.fixture(scope="module")
def params(run_codec) -> list[dict]:
    return run_codec("params")


def test_the_committed_eds_is_what_the_table_writes(codec_bin) -> None:
    eds = subprocess.run([str(codec_bin), "params", "--eds"], capture_output=True, text=True,
                         timeout=60, check=True).stdout
    assert EDS.read_text() == eds, "dbc/mecanum_robot.eds is stale: mecanum-codec params --eds > dbc/mecanum_robot.eds"


def test_python_canopen_reads_every_parameter_with_its_type_access_and_limits(params) -> None:
    od = canopen.import_od(str(EDS))
    ini = configparser.ConfigParser()
    ini.optionxform = str
    ini.read_string(EDS.read_text())
    assert len(params) == 73
    for p in params:
        v = od[p["index"]][p["sub"]]
        assert v.name == p["name"]
        assert v.data_type == TYPES[p["type"]], p["name"]
        assert v.access_type == ("ro" if p["change"] == "fixed" else "rw"), p["name"]
        # python-canopen reads integer limits only; the EDS's own text has every one.
        entry = ini[f"{p['index']:04X}sub{p['sub']:X}"]
        assert float(entry["LowLimit"]) == pytest.approx(p["low"]), p["name"]
        assert float(entry.get("HighLimit", "inf")) == pytest.approx(p["high"] or math.inf), p["name"]
        if p["type"] != "REAL32":
            assert (v.min, v.max) == (p["low"], p["high"]), p["name"]
        # Reached by name too, as python-canopen users write it.
        assert od[v.parent.name][p["name"]] is v
    # Each object is a record whose sub-index 0 counts its entries.
    for index in {p["index"] for p in params}:
        subs = [p["sub"] for p in params if p["index"] == index]
        assert od[index][0].default == max(subs) == len(subs)


def lookup(doc: dict, name: str):
    """`doc`'s value at a parameter's name (`odometry.pods[1].x`), or KeyError."""
    node = doc
    for part in name.split("."):
        key, _, i = part.partition("[")
        node = node[key]
        if i:
            node = node[int(i.rstrip("]"))]
    return node


@pytest.mark.parametrize("path", sorted((ROOT / "config").glob("*.toml")), ids=lambda p: p.name)
def test_parameter_names_are_the_files_keys_and_read_the_files_values(run_codec, path) -> None:
    doc = tomllib.loads(path.read_text())
    lines = run_codec("params", "--config", str(path))
    found = 0
    for p in lines:
        if p["name"].startswith(DERIVED):
            continue
        try:
            want = lookup(doc, p["name"])
        except (KeyError, IndexError):
            continue  # the file leaves it at its default (or has no such field)
        found += 1
        if isinstance(want, str):  # an enum: its number
            continue
        got = p["value"]
        assert got is not None, p["name"]
        if p["type"] == "REAL32":
            assert got == pytest.approx(float(want), rel=1e-6) or (math.isinf(want) and math.isinf(got)), p["name"]
        else:
            assert got == float(want), p["name"]
    # Every file gives its geometry, its drive's gains or limits, some timing.
    assert found >= 5, path.name

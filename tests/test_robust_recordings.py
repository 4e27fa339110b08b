"""Damaged recordings: ``replay``, ``diagnose`` and ``info`` give a result from what is good and
say what was skipped; with nothing usable left they exit non-zero with one clear line.

One short closed-loop flight (8 s, paper profile, with sensor noise) is recorded once; each
damage is applied to its bytes (seeded) and the three commands run on the result, in process
through ``companion.cli.main`` (what ``python -m companion`` runs); the cases with nothing
usable also run as ``python -m companion ...`` subprocesses, to see the exit code and stderr a
user sees.

The yardstick for "the good part is kept": the records the damage did not touch are all read,
and the replay's frames before the first damaged byte equal the clean replay's bit for bit.

Run time (2 shared cores): about 20 s (the first diagnose warms its compiled kernels).
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v10 import ardupilotmega as mavlink1
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from companion.cli import main
from companion.config import load_config
from simvehicle.engines.flights import flight_plan, with_sensor_noise
from simvehicle.engines.scenarios import fly

REPO = Path(__file__).resolve().parent.parent
FLIGHT_S = 12.0
SUBPROCESS_TIMEOUT_S = 120.0


# ---------------------------------------------------------------------------------------------
# records of a clean .tlog (8-byte big-endian UNIX time in µs, then one MAVLink packet)


def packet_len(buf: bytes, i: int) -> int:
    """Length of the MAVLink packet starting at ``buf[i]`` (from its header)."""
    if buf[i] == 0xFE:
        return 6 + buf[i + 1] + 2
    assert buf[i] == 0xFD
    return 10 + buf[i + 1] + 2 + (13 if buf[i + 2] & 0x01 else 0)


def split_records(buf: bytes) -> list[tuple[int, bytes]]:
    """(time µs, packet) of every record of an undamaged .tlog."""
    out, i = [], 0
    while i < len(buf):
        t_us = int.from_bytes(buf[i:i + 8], "big")
        n = packet_len(buf, i + 8)
        out.append((t_us, buf[i + 8:i + 8 + n]))
        i += 8 + n
    assert i == len(buf)
    return out


def join_records(records: list[tuple[int, bytes]]) -> bytes:
    return b"".join(t.to_bytes(8, "big") + p for t, p in records)


def msg_name(packet: bytes) -> str:
    msgid = packet[5] if packet[0] == 0xFE else int.from_bytes(packet[7:10], "little")
    return mavlink2.mavlink_map[msgid].msgname


# ---------------------------------------------------------------------------------------------
# damages: clean bytes -> (damaged bytes, offset of the first damaged byte in the clean file)


def bit_flips(buf: bytes, rng: np.random.Generator) -> tuple[bytes, int]:
    """10 random single-bit flips in the second half of the file."""
    b = bytearray(buf)
    where = np.sort(rng.integers(len(b) // 2, len(b), 10))
    for i in where:
        b[i] ^= 1 << int(rng.integers(0, 8))
    return bytes(b), int(where[0])


def truncated_mid_packet(buf: bytes, rng: np.random.Generator) -> tuple[bytes, int]:
    """The file cut in the middle of a packet's payload at about 70 %."""
    recs = split_records(buf)
    k = int(0.7 * len(recs))
    start = len(join_records(recs[:k]))
    cut = start + 8 + 10 + 3  # inside the payload of record k
    return buf[:cut], start


def garbage_first(buf: bytes, rng: np.random.Generator) -> tuple[bytes, int]:
    """2000 random bytes before the first record, with MAVLink start bytes sprinkled in."""
    junk = bytearray(rng.integers(0, 256, 2000, dtype=np.uint8).tobytes())
    for i in rng.integers(0, len(junk), 40):
        junk[i] = 0xFD if i % 2 else 0xFE
    return bytes(junk) + buf, len(buf)  # the clean records are all intact


def duplicated(buf: bytes, rng: np.random.Generator) -> tuple[bytes, int]:
    """A block of 200 records written twice (as a logger that rewrites its buffer), and 20
    single records duplicated in place."""
    recs = split_records(buf)
    k = len(recs) // 2
    block = recs[k:k + 200]
    out = recs[:k] + block + block + recs[k + 200:]
    for i in sorted(rng.choice(np.arange(10, k), 20, replace=False), reverse=True):
        out.insert(int(i), out[int(i)])
    return join_records(out), len(buf)


def reordered(buf: bytes, rng: np.random.Generator) -> tuple[bytes, int]:
    """Records shuffled within windows of 5 over the second half (packets arriving out of order
    on a UDP link), with their time stamps."""
    recs = split_records(buf)
    k = len(recs) // 2
    out = recs[:k]
    for s in range(k, len(recs), 5):
        w = recs[s:s + 5]
        out += [w[i] for i in rng.permutation(len(w))]
    return join_records(out), len(join_records(recs[:k]))


def time_backwards(buf: bytes, rng: np.random.Generator) -> tuple[bytes, int]:
    """The logger's clock steps back 30 s at mid-file (an NTP correction) and runs on from there."""
    recs = split_records(buf)
    k = len(recs) // 2
    out = recs[:k] + [(t - 30_000_000, p) for t, p in recs[k:]]
    return join_records(out), len(buf)


def mixed_v1_v2(buf: bytes, rng: np.random.Generator) -> tuple[bytes, int]:
    """Every RAW_IMU, DISTANCE_SENSOR and ATTITUDE re-sent as MAVLink 1 (the link of an older
    autopilot), the rest MAVLink 2. MAVLink 1 drops extension fields, which these do not need."""
    parser = mavlink2.MAVLink(None)
    encoders: dict[tuple[int, int], mavlink1.MAVLink] = {}
    out = []
    for t, p in split_records(buf):
        if msg_name(p) in ("RAW_IMU", "DISTANCE_SENSOR", "ATTITUDE"):
            m = parser.decode(bytearray(p))
            key = (m.get_srcSystem(), m.get_srcComponent())
            enc = encoders.setdefault(key, mavlink1.MAVLink(None, srcSystem=key[0], srcComponent=key[1]))
            v1 = getattr(mavlink1, type(m).__name__)(*[getattr(m, f) for f in m.get_fieldnames()
                                                        if f in getattr(mavlink1, type(m).__name__).fieldnames])
            p = bytes(v1.pack(enc))
            assert p[0] == 0xFE
        out.append((t, p))
    return join_records(out), len(buf)


def dropping(*names: str) -> Callable[[bytes, np.random.Generator], tuple[bytes, int]]:
    def damage(buf: bytes, rng: np.random.Generator) -> tuple[bytes, int]:
        recs = split_records(buf)
        return join_records([r for r in recs if msg_name(r[1]) not in names]), len(buf)
    damage.__name__ = "no_" + "_".join(n.lower() for n in names)
    return damage


DAMAGES: dict[str, Callable[[bytes, np.random.Generator], tuple[bytes, int]]] = {
    "bit_flips": bit_flips,
    "truncated_mid_packet": truncated_mid_packet,
    "garbage_first": garbage_first,
    "duplicated_records": duplicated,
    "reordered_records": reordered,
    "time_backwards": time_backwards,
    "mavlink1_and_2": mixed_v1_v2,
}
#: damages that leave every record intact and in its order (the reader drops garbage and
#: duplicates, and the tools go by the sensors' own time fields, not the log's)
EXACT = ("garbage_first", "duplicated_records", "time_backwards", "mavlink1_and_2")
#: a message type missing: what each command still does
MISSING = {
    "no_distance_sensor": ("DISTANCE_SENSOR",),
    "no_raw_imu": ("RAW_IMU",),
    "no_attitude": ("ATTITUDE",),
    "no_commands": ("SET_ATTITUDE_TARGET", "ATTITUDE_TARGET"),
}


# ---------------------------------------------------------------------------------------------
# fixtures


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("robust_rec") / "clean.tlog"
    fly(with_sensor_noise(load_config()), flight_plan(3, duration_s=FLIGHT_S).scenario(), seed=3, tlog=path)
    return path


def run_main(capsys, *argv: str) -> tuple[int, str, str]:
    rc = main(list(argv))
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def read_csv(path: Path) -> dict[str, np.ndarray]:
    with path.open() as fh:
        rows = list(csv.DictReader(fh))
    out: dict[str, np.ndarray] = {}
    for k in rows[0]:
        try:
            out[k] = np.array([float(r[k]) if r[k] != "" else np.nan for r in rows])
        except ValueError:  # a text column (hold_cause)
            out[k] = np.array([r[k] for r in rows])
    return out


@pytest.fixture(scope="module")
def clean_outputs(clean, tmp_path_factory) -> dict[str, object]:
    """The three commands on the clean flight."""
    out = tmp_path_factory.mktemp("robust_rec_clean")
    assert main(["replay", str(clean), "--csv", str(out / "r.csv")]) == 0
    assert main(["info", str(clean), "--json", str(out / "i.json")]) == 0
    assert main(["diagnose", str(clean), "--json", str(out / "d.json")]) == 0
    return {"replay": read_csv(out / "r.csv"), "info": json.loads((out / "i.json").read_text()),
            "diagnose": json.loads((out / "d.json").read_text())}


def counts(info: dict) -> dict[str, int]:
    return {m["name"]: m["count"] for m in info["messages"]}


# ---------------------------------------------------------------------------------------------
# damaged but usable: a result from what is good, and what was skipped said


@pytest.mark.parametrize("name", list(DAMAGES))
def test_damaged_recording_gives_a_result_from_the_good_part(name, clean, clean_outputs, tmp_path, capsys):
    buf = clean.read_bytes()
    damaged, first_bad = DAMAGES[name](buf, np.random.default_rng(42))
    path = tmp_path / f"{name}.tlog"
    path.write_bytes(damaged)
    clean_recs = split_records(buf)
    n_flow = sum(msg_name(p) == "OPTICAL_FLOW" for _t, p in clean_recs)
    # records wholly before the first damaged byte are untouched
    good_prefix = 0
    pos = 0
    for _t, p in clean_recs:
        pos += 8 + len(p)
        if pos > first_bad:
            break
        good_prefix += 1

    # info: every untouched record is counted; what was skipped is said
    rc, out, err = run_main(capsys, "info", str(path), "--json", str(tmp_path / "i.json"))
    assert rc == 0, err
    info = json.loads((tmp_path / "i.json").read_text())
    before = counts(clean_outputs["info"])
    after = counts(info)
    assert info["n_messages"] >= good_prefix
    if name in ("bit_flips", "truncated_mid_packet", "garbage_first"):
        assert info["skipped_bytes"] > 0 and "skipped" in out
        assert f"skipped   {info['skipped_bytes']} bytes" in out
    if name in ("duplicated_records", "reordered_records", "time_backwards", "mavlink1_and_2"):
        assert info["skipped_bytes"] == 0
    if name == "duplicated_records":
        assert after["OPTICAL_FLOW"] > before["OPTICAL_FLOW"]  # the reader keeps what is in the file
    elif name in ("reordered_records", "mavlink1_and_2"):
        assert after == before
    if name == "time_backwards":
        assert info["notes"] and any("back" in n or "time" in n for n in info["notes"]), info["notes"]

    # replay: the frames before the damage equal the clean replay's, bit for bit
    rc, _out, err = run_main(capsys, "replay", str(path), "--csv", str(tmp_path / "r.csv"))
    assert rc == 0, err
    rep = read_csv(tmp_path / "r.csv")
    ref = clean_outputs["replay"]
    n = len(rep["t_s"])
    assert n >= 0.5 * n_flow, (n, n_flow)
    flow_before_damage = sum(msg_name(p) == "OPTICAL_FLOW" for _t, p in clean_recs[:good_prefix])
    # every flow, gyro and range record intact and in order: the whole replay is the clean one
    k = len(ref["t_s"]) if name in EXACT else max(0, flow_before_damage - 1)
    if name in EXACT:
        assert n == len(ref["t_s"])
    if name == "truncated_mid_packet":
        assert n in (flow_before_damage, flow_before_damage + 1)
    if name == "bit_flips":  # 10 flips can spoil at most 10 records
        assert n >= len(ref["t_s"]) - 10
    for col in ("vx_m_s", "vy_m_s", "roll_cmd_rad", "pitch_cmd_rad"):
        np.testing.assert_array_equal(rep[col][:k], ref[col][:k], err_msg=col)
    for col in ("roll_cmd_rad", "pitch_cmd_rad"):
        assert np.all(np.isfinite(rep[col])) and np.abs(rep[col]).max() <= np.radians(20.0) + 1e-9
    if info["skipped_bytes"]:
        assert "skipped" in err, err  # the replay says what the reader skipped

    # diagnose: a report of the conventions' shape, naming no effect the clean flight did not have
    rc, out, err = run_main(capsys, "diagnose", str(path), "--json", str(tmp_path / "d.json"))
    assert rc == 0, err
    diag = json.loads((tmp_path / "d.json").read_text())
    assert set(diag) >= {"recording", "baseline", "findings", "unexplained"}
    clean_sig = {f["effect"] for f in clean_outputs["diagnose"]["findings"] if f["significant"]}
    sig = {f["effect"] for f in diag["findings"] if f["significant"]}
    assert sig <= clean_sig | {"wind_force"}, sig  # damage must not invent physics (see docs/robustness.md)
    if info["skipped_bytes"]:
        assert "skipped" in out + err


@pytest.mark.parametrize("name", list(MISSING))
def test_a_missing_message_type_degrades_and_names_it(name, clean, clean_outputs, tmp_path, capsys):
    damaged, _ = dropping(*MISSING[name])(clean.read_bytes(), np.random.default_rng(0))
    path = tmp_path / f"{name}.tlog"
    path.write_bytes(damaged)
    rc, out, err = run_main(capsys, "info", str(path))
    assert rc == 0, err
    role = {"no_distance_sensor": "range", "no_raw_imu": "gyro", "no_attitude": "attitude",
            "no_commands": "commands"}[name]
    assert f"missing for diagnosis: {role}" in out or f", {role}" in out.split("missing for diagnosis:")[1]
    rc, out, err = run_main(capsys, "replay", str(path), "--csv", str(tmp_path / "r.csv"))
    assert rc == 0, err
    rep = read_csv(tmp_path / "r.csv")
    assert len(rep["t_s"]) > 300
    if name in ("no_distance_sensor", "no_raw_imu"):
        # nothing to estimate with: every frame holds level, and the replay says why
        assert np.all(rep["roll_cmd_rad"] == 0) and np.all(rep["pitch_cmd_rad"] == 0)
        assert MISSING[name][0] in err, err
    else:  # eq. 15 and the PI need neither ATTITUDE nor the recorded commands: the clean replay
        for col in ("vx_m_s", "vy_m_s", "roll_cmd_rad", "pitch_cmd_rad"):
            np.testing.assert_array_equal(rep[col], clean_outputs["replay"][col], err_msg=col)
    rc, out, err = run_main(capsys, "diagnose", str(path), "--json", str(tmp_path / "d.json"))
    if name == "no_commands":  # no commanded attitude: the sensor-only diagnosis of what is there
        assert rc == 0 and "sensor-only diagnosis" in out, (rc, err)
        assert (tmp_path / "d.json").exists()
    else:  # a closed-loop diagnosis needs every sensor: one line naming the missing one
        assert rc == 4 and err.count("\n") == 1 and "Traceback" not in err
        assert f"missing {MISSING[name][0]}" in err, err



# ---------------------------------------------------------------------------------------------
# nothing usable: one clear line and a non-zero exit, as a user sees it


def _random_bytes(tmp: Path) -> Path:
    p = tmp / "random.tlog"
    p.write_bytes(np.random.default_rng(5).integers(0, 256, 20_000, dtype=np.uint8).tobytes())
    return p


def _empty(tmp: Path) -> Path:
    p = tmp / "empty.tlog"
    p.write_bytes(b"")
    return p


def _missing(tmp: Path) -> Path:
    return tmp / "does_not_exist.tlog"


def _no_flow(tmp: Path, clean: Path) -> Path:
    p = tmp / "no_flow.tlog"
    p.write_bytes(dropping("OPTICAL_FLOW")(clean.read_bytes(), np.random.default_rng(0))[0])
    return p


UNUSABLE = {
    "empty": (_empty, "no MAVLink"),
    "random_bytes": (_random_bytes, "no MAVLink"),
    "missing_file": (_missing, "not found"),
    "no_flow": (None, "OPTICAL_FLOW"),
}


@pytest.mark.parametrize("tool", ["replay", "diagnose", "info"])
@pytest.mark.parametrize("case", list(UNUSABLE))
def test_nothing_usable_is_one_clear_line(case, tool, clean, tmp_path, capsys):
    make, needle = UNUSABLE[case]
    path = _no_flow(tmp_path, clean) if make is None else make(tmp_path)
    extra = {"replay": ["--csv", str(tmp_path / "r.csv")], "diagnose": ["--json", str(tmp_path / "d.json")],
             "info": []}[tool]
    if case == "no_flow" and tool == "info":
        # info summarises what is there and lists what is missing; it exits 0
        rc, out, err = run_main(capsys, tool, str(path))
        assert rc == 0 and "missing for diagnosis: flow" in out
        return
    rc, out, err = run_main(capsys, tool, str(path), *extra)
    assert rc == 4, (rc, out, err)
    assert err.count("\n") == 1 and err.startswith("error: ") and "Traceback" not in err, err
    assert needle in err, err
    assert not (tmp_path / "r.csv").exists() and not (tmp_path / "d.json").exists()


@pytest.mark.parametrize("tool", ["replay", "diagnose", "info"])
def test_nothing_usable_as_a_user_runs_it(tool, tmp_path):
    """``python -m companion TOOL random.tlog``: exit code 4, one line on stderr, nothing on stdout."""
    path = _random_bytes(tmp_path)
    extra = {"replay": ["--csv", str(tmp_path / "r.csv")], "diagnose": [], "info": []}[tool]
    r = subprocess.run([sys.executable, "-m", "companion", tool, str(path), *extra], capture_output=True,
                       text=True, timeout=SUBPROCESS_TIMEOUT_S, cwd=REPO)
    assert r.returncode == 4, r
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "no MAVLink" in r.stderr and r.stdout == ""

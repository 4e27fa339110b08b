"""``python -m companion fleet``: a fleet of generated recordings with known effects (two vehicles,
some files damaged, one empty) on a Dask LocalCluster of 2 workers, against the truth of the
generator (``simvehicle.engines.flightgen.score``), the per-file reports, and the same fleet in-process.

The flights share one airframe and nominal model (one ``--config``): vehicle A flies clean, then
with its flow sensor's scale moved to 1.15 (the drift the fleet must flag); vehicle B has a gyro
bias in two recordings with the same data a day apart (plain and gzip: a move of exactly zero).
"""

from __future__ import annotations

import csv
import dataclasses
import gzip
import json
import math
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.errors import UsageError
from companion.fleet import engine as eng
from companion.fleet import run as fleet_run
from companion.fleet.run import find_recordings, run_fleet
from companion.fleet.table import OUTLIER_SIGMA, flag_outliers, read_parquet
from simvehicle.engines import flightgen as fg

pytest.importorskip("distributed")

REPO = Path(__file__).resolve().parent.parent
DAY_S = 86_400.0
T0_UNIX_S = 1.75e9
SCALE = {"scale_x": 1.15, "scale_y": 1.15}
BIAS = {"bias_x": 0.03, "bias_y": -0.025}


def _spec(effects: dict, day: float) -> fg.FlightSpec:
    """One airframe, sensor set and noise for every flight (seed 3's draw: turbulence, attitude and
    range noise, record jitter), lossless, 20 s of sinusoidal setpoints, climbing from 0.8 to 1.8 m
    and back to 1 m (a flow scale told from a range offset), starting ``day`` days in."""
    spec = fg.draw_spec(3, ardupilot_share=0.0)
    flight = fg.FlightProfile((fg.SetpointSegment(0.0, 1e4, "sine", (0.0, 0.0), (0.0, 0.0), (0.8, 0.6), 6.0, 0.3),),
                              (0.0, 7.0, 10.0, 15.0, 18.0, 1e4), (0.8, 0.8, 1.8, 1.8, 1.0, 1.0), 2.0)
    return dataclasses.replace(spec, duration_s=20.0, warmup_s=2.0, flight=flight, loss=fg.Loss(),
                               effects=effects, wind_from_start=False, wind_to_end=False,
                               vehicle=dataclasses.replace(spec.vehicle, unix0_s=T0_UNIX_S + day * DAY_S))


@pytest.fixture(scope="module")
def fleet(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("fleet")
    d = root / "logs"
    truth = {}
    for vehicle, stem, effects, day in (("vehA", "a1", {}, 0), ("vehA", "a2", {"flow_scale": SCALE}, 1),
                                        ("vehB", "b1", {"gyro_bias": BIAS}, 0)):
        g = fg.write_flight(_spec(effects, day), fg.simulate(_spec(effects, day)), root / "gen", stem)
        (d / vehicle).mkdir(parents=True, exist_ok=True)
        data = g.tlog.read_bytes()
        if stem == "a2":  # damaged but usable: 300 bytes of garbage in the middle (the reader skips them)
            k = len(data) // 2
            data = data[:k] + np.random.default_rng(1).integers(0, 256, 300, dtype=np.uint8).tobytes() + data[k:]
        (d / vehicle / f"{stem}.tlog").write_bytes(data)
        truth[stem] = g.truth
        config = g.config  # the same nominal model for all
    # b2: b1's flight a day later (the same simulation, each record's UNIX time a day on), compressed
    g = fg.write_flight(_spec({"gyro_bias": BIAS}, 1), fg.simulate(_spec({"gyro_bias": BIAS}, 1)), root / "gen", "b2")
    (d / "vehB" / "b2.tlog.gz").write_bytes(gzip.compress(g.tlog.read_bytes()))
    b1 = (d / "vehB" / "b1.tlog").read_bytes()
    truth["b2"] = truth["b1"]
    # bad files: cut short, not MAVLink, a broken gzip, empty, a CSV without its column map
    (d / "vehA" / "short.tlog").write_bytes((d / "vehA" / "a1.tlog").read_bytes()[:5000])
    (d / "vehB" / "noise.tlog").write_bytes(np.random.default_rng(2).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    (d / "vehB" / "broken.tlog.gz").write_bytes(gzip.compress(b1)[:3000])
    (d / "vehA" / "empty.tlog").write_bytes(b"")
    (d / "vehA" / "log.csv").write_text("t,x\n0,1\n")
    (d / "vehA" / "notes.txt").write_text("not a recording")
    dask_run = run_fleet([str(d)], root / "out", config=config, workers=2, progress=False)
    return {"root": root, "logs": d, "config": config, "truth": truth, "run": dask_run, "out": root / "out"}


ERRORS = {"short.tlog": "no stretch of 5 s", "noise.tlog": "no MAVLink packets", "broken.tlog.gz": "truncated gzip",
          "empty.tlog": "no MAVLink packets", "log.csv": "needs --sensor-config"}
GOOD = ("a1.tlog", "a2.tlog", "b1.tlog", "b2.tlog.gz")


def _by_file(rows: list[dict]) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for r in rows:
        out.setdefault(Path(r["recording"]).name, []).append(r)
    return out


def _report(fleet: dict, name: str) -> dict:
    vehicle = next(p.parent.name for p in fleet["logs"].rglob(name))
    return json.loads((fleet["out"] / "reports" / vehicle / f"{name}.json").read_text())


def test_the_fleet_table_on_two_workers_holds_the_known_effects(fleet) -> None:
    run = fleet["run"]
    assert run.engine == "Dask LocalCluster of 2 worker(s)"
    assert run.diagnosed == 9 and run.skipped == 0 and run.failed == 5  # notes.txt is not a recording
    by = _by_file(run.rows)
    assert sorted(by) == sorted([*GOOD, *ERRORS])
    for name in GOOD:
        rep = _report(fleet, name)
        stem = name.split(".")[0]
        # the finder's report against the generator's truth (the matrix scorer): every effect, no false one
        assert fg.score(fleet["truth"][stem], rep)["right"], (name, rep["headline"])
        rows = by[name]
        # one row per effect tried, in the report's order, with its numbers
        assert [r["effect"] for r in rows] == [f["effect"] for f in rep["findings"]]
        for r, f in zip(rows, rep["findings"], strict=True):
            assert r["significant"] == f["significant"] and r["status"] == "ok" and r["error"] == ""
            assert r["params"] == {k: (math.nan if v is None else v) for k, v in f["parameters"].items()} or \
                any(v is None for v in f["parameters"].values())
            assert r["improvement_pct"] == f["fit"]["improvement_pct"]
        assert {r["effect"] for r in rows if r["significant"]} == set(fleet["truth"][stem]["effects"])
        assert {r["vehicle"] for r in rows} == {"vehA" if stem.startswith("a") else "vehB"}
        # the start is the first record's UNIX time (the first 8 bytes of the .tlog, big-endian us)
        raw = (fleet["logs"] / rows[0]["vehicle"] / name).read_bytes()
        raw = gzip.decompress(raw) if name.endswith(".gz") else raw
        assert rows[0]["start_unix_s"] == struct.unpack(">Q", raw[:8])[0] / 1e6
        # 20 s at 50 Hz: the frames used are the recording's flow frames bar the first and last
        assert rows[0]["duration_s"] == pytest.approx(20.0, abs=0.05)
        assert 0.98 * 1000 <= rows[0]["frames_used"] <= 1001
    scale = next(r for r in by["a2.tlog"] if r["effect"] == "flow_scale")
    assert scale["params"]["scale_x"] == pytest.approx(1.15, abs=0.03)
    assert next(r for r in by["b2.tlog.gz"] if r["effect"] == "gyro_bias")["start_unix_s"] == \
        pytest.approx(next(r for r in by["b1.tlog"] if r["effect"] == "gyro_bias")["start_unix_s"] + DAY_S, abs=1e-6)


def test_a_bad_file_is_one_failed_row_with_its_error(fleet) -> None:
    by = _by_file(fleet["run"].rows)
    for name, error in ERRORS.items():
        assert len(by[name]) == 1, name
        row = by[name][0]
        assert row["status"] == "failed" and error in row["error"] and "\n" not in row["error"]
        assert row["effect"] == "" and not row["significant"] and not row["outlier"]
        rep = _report(fleet, name)  # a failed file's report holds its error: a rerun skips it too
        assert rep["findings"] == [] and error in rep["fleet"]["error"]


def test_a_moved_flow_scale_is_flagged_and_a_steady_bias_is_not(fleet) -> None:
    by = _by_file(fleet["run"].rows)
    s1 = _report(fleet, "a1.tlog")["findings"]
    s2 = _report(fleet, "a2.tlog")["findings"]
    f1 = next(f for f in s1 if f["effect"] == "flow_scale")
    f2 = next(f for f in s2 if f["effect"] == "flow_scale")
    moved = max(abs(f2["parameters"][k] - f1["parameters"][k]) / math.hypot(f1["uncertainty"][k], f2["uncertainty"][k])
                for k in ("scale_x", "scale_y"))
    assert moved > 3 * OUTLIER_SIGMA  # 1.00 -> 1.15 with uncertainties near 0.01
    row = next(r for r in by["a2.tlog"] if r["effect"] == "flow_scale")
    assert row["outlier"] and row["outlier_sigma"] == pytest.approx(moved, rel=1e-12)
    assert "scale_x" in row["outlier_note"] and "a1.tlog" in row["outlier_note"]
    assert not any(r["outlier"] for r in by["a1.tlog"])  # the first recording of a vehicle has nothing before it
    # vehicle B: the same flight a day later moved by nothing (bar the rounding of its UNIX times)
    for r in by["b2.tlog.gz"]:
        assert not r["outlier"] and (r["outlier_sigma"] < 0.01 or r["effect"] == "wind_force"), r["effect"]
    assert not any(r["outlier"] for r in fleet["run"].rows if r["effect"] == "wind_force")


def test_the_outputs_agree_and_the_summary_is_self_contained(fleet) -> None:
    out = fleet["out"]
    rows = fleet["run"].rows
    with open(out / "fleet.csv", newline="") as fh:
        table = list(csv.DictReader(fh))
    pq = read_parquet(out / "fleet.parquet")
    assert len(table) == len(pq) == len(rows)
    for r, c, p in zip(rows, table, pq, strict=True):
        assert c["recording"] == p["recording"] == r["recording"] and c["effect"] == p["effect"] == r["effect"]
        assert p["significant"] is r["significant"] and c["significant"] == str(r["significant"])
        for k, v in r["params"].items():
            assert (math.isnan(v) and math.isnan(p[f"param_{k}"])) or p[f"param_{k}"] == v == float(c[f"param_{k}"])
            sd = r["sds"][k]
            assert (math.isnan(sd) and math.isnan(p[f"param_{k}_sd"])) or p[f"param_{k}_sd"] == sd
    page = (out / "summary.html").read_text()
    assert page.count("data:image/png;base64,") >= 4  # flow_scale x/y, gyro_bias x/y
    assert "http://" not in page and "https://" not in page and "<script" not in page  # readable offline
    assert "vehA (flow_scale)" in page and "truncated gzip" in page


def test_a_rerun_does_no_work_until_a_file_changes(fleet) -> None:
    out = fleet["out"]
    reports = sorted((out / "reports").rglob("*.json"))
    stamps = [p.stat().st_mtime_ns for p in reports]
    csv_before = (out / "fleet.csv").read_text()
    again = run_fleet([str(fleet["logs"])], out, config=fleet["config"], workers=2, progress=False)
    assert again.diagnosed == 0 and again.skipped == 9 and again.engine == "nothing to do"
    assert [p.stat().st_mtime_ns for p in reports] == stamps
    assert (out / "fleet.csv").read_text() == csv_before
    # a file newer than its report is done again, and only it
    a1 = fleet["logs"] / "vehA" / "a1.tlog"
    later = (out / "reports" / "vehA" / "a1.tlog.json").stat().st_mtime + 5
    os.utime(a1, (later, later))
    once = run_fleet([str(fleet["logs"])], out, config=fleet["config"], in_process=True, progress=False)
    assert once.diagnosed == 1 and once.skipped == 8
    assert (out / "fleet.csv").read_text() == csv_before


def test_in_process_gives_the_same_table(fleet) -> None:
    here = run_fleet([str(fleet["logs"])], fleet["root"] / "out_here", config=fleet["config"], in_process=True,
                     progress=False)
    assert here.engine == "in-process" and here.diagnosed == 9
    a = (fleet["out"] / "fleet.csv").read_text().splitlines()
    b = (fleet["root"] / "out_here" / "fleet.csv").read_text().splitlines()
    assert a == b


def test_outliers_follow_the_combined_uncertainty() -> None:
    """Closed form: moves of 1.41, 5.66 and 0.71 combined sigma, in time order (not name order);
    a move of an effect neither recording finds is not flagged, nor is the wind."""
    def row(rec: str, t: float, p: float, sd: float, effect: str = "flow_scale", significant: bool = True) -> dict:
        return {"recording": rec, "vehicle": "v", "status": "ok", "effect": effect, "start_unix_s": t,
                "significant": significant,
                "params": {"scale_x": p, "start_s": t}, "sds": {"scale_x": sd, "start_s": 0.1},
                "outlier": False, "outlier_sigma": math.nan, "outlier_note": ""}

    rows = [row("z_first", 0.0, 1.00, 0.01), row("c", 2.0, 1.10, 0.01), row("b", 1.0, 1.02, 0.01),
            row("a", 3.0, 1.11, 0.01), row("w1", 0.0, 1.0, 0.01, "wind_force"), row("w2", 1.0, 5.0, 0.01, "wind_force"),
            row("d1", 0.0, 0.0, 0.001, "flow_delay", False), row("d2", 1.0, 0.005, 0.001, "flow_delay", False)]
    flag_outliers(rows)
    got = {r["recording"]: (r["outlier"], r["outlier_sigma"]) for r in rows}
    assert math.isnan(got["z_first"][1]) and not got["z_first"][0]
    assert got["b"] == (False, pytest.approx(0.02 / math.hypot(0.01, 0.01)))
    assert got["c"] == (True, pytest.approx(0.08 / math.hypot(0.01, 0.01)))
    assert got["a"] == (False, pytest.approx(0.01 / math.hypot(0.01, 0.01)))
    assert not got["w2"][0]  # wind is weather
    assert got["d2"] == (False, pytest.approx(0.005 / math.hypot(0.001, 0.001)))  # 3.5 sigma, found in neither


def test_without_dask_it_runs_in_process_and_says_how_to_get_the_cluster(monkeypatch) -> None:
    monkeypatch.setattr(eng, "have_dask", lambda: False)
    e = eng.Engine(workers=2)
    assert not e.dask and eng.INSTALL_HINT in e.note and "flowhold[cluster]" in e.note
    with e:
        assert list(e.map(abs, [-1, 2, -3])) == [(0, 1), (1, 2), (2, 3)]
    with pytest.raises(UsageError, match="needs Dask"):
        eng.Engine(scheduler="tcp://127.0.0.1:8786")


def test_the_base_install_gives_the_same_rows_in_process(fleet, tmp_path, monkeypatch) -> None:
    """Without Dask and pyarrow: in-process, the same rows, a CSV and no Parquet, and the note
    says how to get both."""
    monkeypatch.setattr(eng, "have_dask", lambda: False)
    monkeypatch.setattr(fleet_run, "have_pyarrow", lambda: False)
    run = run_fleet([str(fleet["logs"] / "vehB" / "b1.tlog")], tmp_path / "o", config=fleet["config"], workers=2,
                    progress=False)
    assert run.engine == "in-process" and "parquet" not in run.outputs
    assert not (tmp_path / "o" / "fleet.parquet").exists() and (tmp_path / "o" / "fleet.csv").is_file()
    assert "Dask is not installed" in run.note and "pyarrow is not installed" in run.note
    assert run.note.count("pip install 'flowhold[cluster]'") == 2
    drop = ("report", "outlier", "outlier_sigma", "outlier_note")
    want = _by_file(fleet["run"].rows)["b1.tlog"]
    assert [{k: v for k, v in r.items() if k not in drop} for r in run.rows] == \
        [{k: v for k, v in r.items() if k not in drop} for r in want]


def die_on_first_try(marker: str) -> int:
    """Kills its worker process the first time (no marker yet), returns its pid the second."""
    if not os.path.exists(marker):
        Path(marker).touch()
        os._exit(1)
    return os.getpid()


def always_die(_: str) -> int:
    os._exit(1)


def test_a_worker_that_dies_loses_only_its_task_which_runs_once_more(tmp_path) -> None:
    with eng.Engine(workers=2, progress=False) as e:
        got = dict(e.map(die_on_first_try, [str(tmp_path / "m1")]))
        assert isinstance(got[0], int) and got[0] != os.getpid()
        got = dict(e.map(always_die, ["x"]))
        assert isinstance(got[0], eng.TaskLost) and "died 2 times" in str(got[0])
        assert dict(e.map(abs, [-4, 5])) == {0: 4, 1: 5}  # the cluster still works


def test_find_recordings_and_bad_inputs(tmp_path) -> None:
    (tmp_path / "a").mkdir()
    for n in ("x.tlog", "y.BIN", "z.ulg.gz", "w.csv", "v.txt", "u.json"):
        (tmp_path / "a" / n).write_text("")
    assert [p.name for p in find_recordings([str(tmp_path / "a")])] == ["w.csv", "x.tlog", "y.BIN", "z.ulg.gz"]
    assert [p.name for p in find_recordings([str(tmp_path / "a" / "*.tlog"), str(tmp_path / "a" / "v.txt")])] == \
        ["v.txt", "x.tlog"]
    with pytest.raises(UsageError, match="matches no recording"):
        find_recordings([str(tmp_path / "*.bin")])
    r = subprocess.run([sys.executable, "-m", "companion", "fleet", str(tmp_path / "nowhere"), "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert r.returncode == 2 and r.stderr.strip() == f"error: {tmp_path / 'nowhere'}: no such file or folder"
    r = subprocess.run([sys.executable, "-m", "companion", "fleet", str(tmp_path / "a"), "--out", str(tmp_path / "o"),
                        "--workers", "0"], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert r.returncode == 2 and r.stderr.strip() == "error: --workers must be >= 1, got 0"


def test_the_command_line_in_process(fleet, tmp_path) -> None:
    r = subprocess.run([sys.executable, "-m", "companion", "fleet", str(fleet["logs"] / "vehB" / "*.tlog*"),
                        "--out", str(tmp_path / "o"), "--config", str(fleet["config"]), "--in-process"],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "fleet: 4 recording(s): 4 diagnosed, 0 skipped (reports newer than their files), 2 failed; in-process" \
        in r.stdout
    assert r.stderr == ""  # no progress bar when stderr is not a terminal
    assert (tmp_path / "o" / "summary.html").is_file() and (tmp_path / "o" / "fleet.parquet").is_file()


def test_the_fleet_on_a_running_scheduler(fleet, tmp_path) -> None:
    """``--scheduler ADDRESS``: the cluster's own worker diagnoses; the rows are those of the
    LocalCluster run for the same files."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        run = run_fleet([str(fleet["logs"] / "vehB" / "b[12].tlog*")], tmp_path / "o", config=fleet["config"],
                        scheduler=cluster.scheduler_address, progress=False)
    assert run.engine == f"Dask cluster at {cluster.scheduler_address} (1 worker thread(s))"
    assert run.diagnosed == 2 and run.failed == 0
    want = [r for r in fleet["run"].rows if Path(r["recording"]).name in ("b1.tlog", "b2.tlog.gz")]
    drop = ("report", "outlier", "outlier_sigma", "outlier_note")
    assert [{k: v for k, v in r.items() if k not in drop} for r in run.rows] == \
        [{k: v for k, v in r.items() if k not in drop} for r in want]


def test_a_column_map_applies_to_the_csv_recordings_only(fleet, tmp_path) -> None:
    """``--sensor-config``: the StampFly CSV goes to the sensor-only diagnosis through it, the
    .tlog beside it is read as a .tlog (its rows as without the map)."""
    csv_gz = REPO / "data" / "real" / "stampfly" / "square01_13s.csv.gz"
    run = run_fleet([str(csv_gz), str(fleet["logs"] / "vehB" / "b1.tlog")], tmp_path / "o", config=fleet["config"],
                    sensor_config=str(REPO / "configs" / "sensors" / "stampfly.toml"), in_process=True,
                    progress=False)
    by = _by_file(run.rows)
    assert run.failed == 0 and {r["mode"] for r in by["square01_13s.csv.gz"]} == {"sensor"}
    assert by["square01_13s.csv.gz"][0]["duration_s"] == pytest.approx(13.0, abs=0.05)  # the file's 13 s
    drop = ("report", "outlier", "outlier_sigma", "outlier_note", "vehicle")
    want = _by_file(fleet["run"].rows)["b1.tlog"]
    assert [{k: v for k, v in r.items() if k not in drop} for r in by["b1.tlog"]] == \
        [{k: v for k, v in r.items() if k not in drop} for r in want]

"""Parameter sweeps: the sweep file's checks, the table's numbers, the command line."""

from __future__ import annotations

import csv
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion import config as C
from companion.errors import ConfigError
from simvehicle.engines import fastsim
from simvehicle.engines.scenarios import SCENARIOS, figures
from simvehicle.tools import sweep

REPO = Path(__file__).resolve().parent.parent
PAPER = REPO / "configs" / "paper.toml"
Q_TABLE_VI = 0.09 / 57.3


def _write(tmp_path: Path, text: str, name: str = "s.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def _small(tmp_path: Path, extra: str = "", base: Path = PAPER) -> Path:
    return _write(tmp_path, f'base_config = "{base}"\nscenarios = ["step", "gust"]\n{extra}\n[grid]\n'
                            f'"world.altitude_m" = [0.5, 1.0]\n'
                            f'"flow_sensor.q_rad_per_count" = [{Q_TABLE_VI!r}, 0.003]\n')


def _read(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_shipped_sweep_file_parses():
    spec = sweep.load_sweep(REPO / "configs" / "sweeps" / "altitude_q.toml")
    assert spec.scenarios == ("step", "gust")
    assert [k for k, _ in spec.axes] == ["world.altitude_m", "flow_sensor.q_rad_per_count"]
    assert spec.shape == (6, 6)
    points = sweep.grid_configs(spec)
    assert len(points) == 36
    assert points[7][1].world.altitude_m == 0.5 and points[7][1].flow_sensor.q_rad_per_count == 0.001
    assert Q_TABLE_VI in dict(spec.axes)["flow_sensor.q_rad_per_count"]  # Table VI's Q is on the grid


@pytest.mark.parametrize("text,match", [
    ('base_config = "{p}"\nscenarios = ["step"]\nstep_size = 1\n[grid]\n"world.altitude_m" = [1.0]\n',
     "unknown key"),
    ('scenarios = ["step"]\n[grid]\n"world.altitude_m" = [1.0]\n', "missing key base_config"),
    ('base_config = "{p}"\nscenarios = ["hover"]\n[grid]\n"world.altitude_m" = [1.0]\n', "unknown scenario"),
    ('base_config = "{p}"\nscenarios = ["rail"]\n[grid]\n"world.altitude_m" = [1.0]\n', "unknown scenario"),
    ('base_config = "{p}"\nscenarios = ["step"]\n[grid]\n', "at least one axis"),
    ('base_config = "{p}"\nscenarios = ["step"]\n[grid]\n"world.altitude_m" = 1.0\n', "non-empty list"),
    ('base_config = "{p}"\nscenarios = ["step"]\n[grid]\n"world.altitude" = [1.0]\n', "unknown key"),
    ('base_config = "{p}"\nscenarios = ["step"]\n[grid]\n"world.altitude_m" = [-1.0]\n', "altitude_m must be > 0"),
    ('base_config = "{p}"\nscenarios = ["step"]\n[grid]\n"world.altitude_m" = ["high"]\n', "expected a number"),
    ('base_config = "{p}"\nscenarios = ["step"]\n[grid]\n"altitude_m" = [1.0]\n', "section.key"),
    ('base_config = "{p}"\nscenarios = ["step"]\n[grid]\n"effects.linear_drag.b" = [0.1]\n',
     r"must list \[effects.linear_drag\]"),
    ('base_config = "{p}"\nscenarios = ["step"]\n[grid]\n"effects.drag.b" = [0.1]\n', "unknown effect"),
    ('base_config = "{p}"\nscenarios = ["step"]\nseeds = [1.5]\n[grid]\n"world.altitude_m" = [1.0]\n', "seeds"),
    ('base_config = "nowhere.toml"\nscenarios = ["step"]\n[grid]\n"world.altitude_m" = [1.0]\n', "not found"),
    ('base_config = "{p}"\nscenarios = ["step"\n', "not valid TOML"),
])
def test_bad_sweep_files_are_config_errors(tmp_path, text, match):
    with pytest.raises(ConfigError, match=match):
        sweep.load_sweep(_write(tmp_path, text.replace("{p}", str(PAPER))))


def test_sweep_rows_are_the_scenario_figures(tmp_path, paper_cfg):
    """Each row holds ``scenarios.figures`` of its config's flight (fast engine, MAVLink
    quantization: the numbers ``python -m simvehicle scenario`` prints), in grid order."""
    spec = sweep.load_sweep(_small(tmp_path))
    rows = sweep.run_sweep(spec)
    assert [(r["world.altitude_m"], r["flow_sensor.q_rad_per_count"]) for r in rows] == \
        [(0.5, Q_TABLE_VI), (0.5, 0.003), (1.0, Q_TABLE_VI), (1.0, 0.003)]
    for r, (_, cfg) in zip(rows, sweep.grid_configs(spec), strict=True):
        for name in ("step", "gust"):
            fig = figures(fastsim.fly_fast(cfg, SCENARIOS[name]), cfg)
            assert r[f"{name}_overshoot_pct_x" if name == "step" else f"{name}_displacement_m_x"] == \
                (fig["x"]["overshoot_pct"] if name == "step" else fig["x"]["displacement_m"])
    paper_row = rows[2]
    # the paper's point (Table VI): Fig. 16 rise under 1 s, Fig. 17 pushed back 2.7-2.9 m
    assert paper_row["step_rise_time_10_90_s_x"] < 1.0
    assert -2.9 <= paper_row["gust_displacement_m_x"] <= -2.7
    # a 4 N force held by tilt alone: tan(theta) = F / (m g), whatever the altitude and Q
    held = -math.degrees(math.atan(4.0 / (2.3 * 9.81)))
    for r in rows:
        assert r["gust_held_angle_deg_x"] == pytest.approx(held, abs=0.1)
        assert r["step_held_frames"] == 0.0


def test_effect_axis_and_seeds(tmp_path):
    """An effect's parameter as an axis, and Monte Carlo seeds with gyro noise on."""
    base = tmp_path / "noisy.toml"
    base.write_text(PAPER.read_text().replace("gyro_noise = false", "gyro_noise = true")
                    + "\n[effects.linear_drag]\nenabled = true\nb = 0.2\n")
    spec = sweep.load_sweep(_write(tmp_path, f'base_config = "{base.name}"\nscenarios = ["step"]\n'
                                             f'seeds = [1, 2, 3]\n[grid]\n"effects.linear_drag.b" = [0.0, 0.5]\n'))
    assert sweep.grid_configs(spec)[1][1].effects.linear_drag == C.LinearDrag(0.5)
    rows = sweep.run_sweep(spec)
    assert [(r["effects.linear_drag.b"], r["seed"]) for r in rows] == [(b, s) for b in (0.0, 0.5) for s in (1, 2, 3)]
    finals = np.array([r["step_final_velocity_m_s_x"] for r in rows])
    assert len(set(finals.tolist())) == 6  # the noise differs by seed
    assert np.all(np.abs(finals - 2.0) < 0.05)  # and the PI holds 2 m/s with or without drag


def _same_table(out: Path, path: Path) -> None:
    table = _read(out / "sweep.csv")
    here = sweep.run_sweep(sweep.load_sweep(path))
    assert len(table) == len(here)
    for got, want in zip(table, here, strict=True):
        for k, v in want.items():
            assert float(got[k]) == pytest.approx(v, rel=1e-15, abs=0) or (math.isnan(v) and got[k] == "nan")


def test_sweep_command_line_with_workers(tmp_path):
    """``python -m simvehicle sweep --workers 2``: a Dask LocalCluster of two workers, batches of
    two flights per task, a CSV equal to the in-process sweep, a plot; no progress bar in a pipe."""
    pytest.importorskip("distributed")
    path = _small(tmp_path)
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "simvehicle", "sweep", str(path), "--out", str(out), "--workers", "2",
                        "--batch", "2"], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 0, r.stderr
    assert "4 rows" in r.stdout and "8 flights" in r.stdout and "Dask LocalCluster of 2 worker(s)" in r.stdout
    assert "dashboard: http://127.0.0.1:" in r.stdout or "dashboard: none (Dask's dashboard needs bokeh" in r.stdout
    assert r.stderr == ""  # the progress bar is for terminals only
    _same_table(out, path)
    assert (out / "sweep.png").stat().st_size > 20_000


def test_sweep_on_a_running_scheduler(tmp_path):
    """``--scheduler ADDRESS``: the cluster's own workers fly the batches; the same table."""
    pytest.importorskip("distributed")
    from distributed import LocalCluster

    path = _small(tmp_path)
    out = tmp_path / "out"
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        r = subprocess.run([sys.executable, "-m", "simvehicle", "sweep", str(path), "--out", str(out), "--scheduler",
                            cluster.scheduler_address], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 0, r.stderr
    assert f"Dask cluster at {cluster.scheduler_address} (1 worker thread(s))" in r.stdout
    _same_table(out, path)


def test_progress_bar_on_a_terminal_only(tmp_path):
    """stderr a terminal (a pseudo-terminal of 100 columns here): tqdm's bar counts the flights."""
    import fcntl
    import os
    import pty
    import struct
    import termios

    path = _small(tmp_path)
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))
    proc = subprocess.Popen([sys.executable, "-m", "simvehicle", "sweep", str(path), "--out", str(tmp_path / "o"),
                             "--in-process"], stdout=subprocess.PIPE, stderr=slave, cwd=REPO)
    os.close(slave)
    seen = b""
    try:
        while True:
            try:
                chunk = os.read(master, 65536)
            except OSError:  # EIO: the child closed the terminal
                break
            if not chunk:
                break
            seen += chunk
    finally:
        os.close(master)
        proc.communicate(timeout=300)
    assert proc.returncode == 0
    text = seen.decode(errors="replace")
    assert "sweep:" in text and "/8 [" in text and "flight/s" in text  # 8 flights (2 x 2 grid, 2 scenarios)


def test_colour_limits_keep_small_spreads_small():
    """A 0.54-0.56 s spread of rise times spans 0.02 of a colour range at least 0.5 s wide (the
    paper's own rise time): it stays one colour. A spread wider than the floor keeps its range;
    held frames run from 0 to the flight's 750 frames (15 s at 50 Hz)."""
    lo, hi = sweep.colour_limits(np.array([[0.54, 0.56], [0.55, np.nan]]), 0.5)
    assert (lo, hi) == pytest.approx((0.3, 0.8))
    assert (0.56 - 0.54) / (hi - lo) == pytest.approx(0.04)
    assert sweep.colour_limits(np.array([0.0, 2.0]), 0.5) == (0.0, 2.0)
    assert sweep.colour_limits(np.array([0.0, 459.0]), 750.0, from_zero=True) == (0.0, 750.0)
    spec = sweep.load_sweep(REPO / "configs" / "sweeps" / "altitude_q.toml")
    assert sweep._colour_span("step_held_frames", spec) == (15.0 * 50.0, True)
    assert sweep._colour_span("step_rise_time_10_90_s_x", spec) == (0.5, False)


def test_anomalous_cells_are_where_the_scene_rate_passes_the_spike_gate(tmp_path):
    """The companion holds a frame whose scene rate is over ``max_flow_rate_rad_s`` (7.4 rad/s):
    the step's 2 m/s is 2 / h rad/s, over the gate below h = 2 / 7.4 = 0.27 m. So at 0.25 m (8
    rad/s) the step holds frames and cannot settle at 2 m/s; at 0.5 m (4 rad/s) nothing is
    anomalous. With the gate at 9 rad/s (2.25 m/s at 0.25 m) the 2 m/s is seen, but the step's
    overshoot (about 21 %: 2.4 m/s, 9.7 rad/s) passes the gate and is held there; at 12 rad/s
    (3 m/s) nothing is held."""
    path = _write(tmp_path, f'base_config = "{PAPER}"\nscenarios = ["step"]\n[grid]\n'
                            '"world.altitude_m" = [0.25, 0.5]\n"companion.max_flow_rate_rad_s" = [7.4, 9.0, 12.0]\n')
    spec = sweep.load_sweep(path)
    rows = sweep.run_sweep(spec)
    marks = sweep.anomalies(rows, spec)
    cells = {(a.cell, a.code) for a in marks}
    assert ((0, 0), "H") in cells and ((0, 0), "S") in cells
    assert not any(a.cell[0] == 1 for a in marks)  # 0.5 m: nothing
    assert not any(a.cell == (0, 2) for a in marks)  # the 12 rad/s gate: nothing
    over = next(a for a in marks if a.cell == (0, 1) and a.code == "H")
    assert "overshoot" in over.cause and "9 rad/s" in over.cause
    held = next(a for a in marks if a.cell == (0, 0) and a.code == "H")
    assert held.value == rows[0]["step_held_frames"] > 0
    assert "8.0 rad/s" in held.cause and "7.4 rad/s" in held.cause
    settled = next(a for a in marks if a.cell == (0, 0) and a.code == "S")
    assert settled.value == rows[0]["step_final_velocity_m_s_x"] and abs(settled.value - 2.0) > 0.1
    assert f"{7.4 * 0.25:.2f} m/s" in settled.cause  # the fastest speed it can see
    lines = sweep.describe(marks, spec)
    assert any(line.startswith("H at altitude_m = 0.25, max_flow_rate_rad_s = 7.4 (1 cell(s))") for line in lines)
    # with seeds, a cell holds several rows: its marks are per row, its line in the legend one
    seeded = sweep.load_sweep(_write(tmp_path, path.read_text().replace("[grid]", "seeds = [0, 1]\n[grid]"), "t.toml"))
    twice = sweep.anomalies(sweep.run_sweep(seeded), seeded)
    assert len(twice) == 2 * len(marks) and sweep.describe(twice, seeded) == lines
    sweep.plot_sweep(rows, spec, tmp_path / "p.png", marks)
    assert (tmp_path / "p.png").stat().st_size > 20_000


def test_sweep_command_line_bad_file_is_one_line(tmp_path):
    path = _write(tmp_path, f'base_config = "{PAPER}"\nscenarios = ["step"]\nextra = 1\n[grid]\n'
                            '"world.altitude_m" = [1.0]\n')
    r = subprocess.run([sys.executable, "-m", "simvehicle", "sweep", str(path), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.returncode == 3  # ExitCode.CONFIG
    assert r.stderr.strip().count("\n") == 0 and "unknown key(s) extra" in r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize("key,value", [("velocity_estimator", '"tilt"'), ("gyro_source", '"flow"')])
def test_sweep_refuses_what_the_fast_engine_does_not_model(tmp_path, key, value):
    """Issue 13: a sweep over a config the fast engine cannot fly as the companion does (here the
    tilt filter or the flow message's own body rate) stops with one line naming the key, before
    any flight, instead of flying it without."""
    text = PAPER.read_text()
    assert f"\n{key} = " in text
    base = _write(tmp_path, "\n".join(f"{key} = {value}" if line.startswith(f"{key} = ") else line
                                      for line in text.splitlines()), "base.toml")
    path = _write(tmp_path, f'base_config = "{base}"\nscenarios = ["step"]\n[grid]\n"world.altitude_m" = [1.0]\n')
    with pytest.raises(ConfigError, match=f"does not model companion.{key} = {value.replace(chr(34), chr(39))}"):
        sweep.load_sweep(path)
    out = tmp_path / "o"
    r = subprocess.run([sys.executable, "-m", "simvehicle", "sweep", str(path), "--out", str(out), "--in-process"],
                       capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.returncode == 3  # ExitCode.CONFIG
    assert r.stderr.strip().count("\n") == 0 and f"companion.{key}" in r.stderr and "simvehicle scenario" in r.stderr
    assert not out.exists()

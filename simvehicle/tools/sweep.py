"""Parameter sweeps: the paper's figures of merit across a grid of parameters, on Dask.

    python -m simvehicle sweep configs/sweeps/altitude_q.toml --out out/sweep
                               [--workers N | --scheduler tcp://host:8786 | --in-process] [--batch N]

The flights go in batches (``--batch`` flights of one scenario per task; by default about four
tasks per worker, at most ``MAX_BATCH`` flights) to a Dask ``LocalCluster`` of ``--workers``
processes (default: all cores), to the cluster at ``--scheduler``, or through this process
(``--in-process``, and the mode when Dask is not installed: ``pip install 'flowhold[cluster]'``);
the table is the same in every mode (``companion.fleet.engine``). A progress bar counts the
flights on a terminal.

A sweep file is TOML; every key is checked and an unknown one is an error::

    title = "..."                       # optional, for the plot
    base_config = "../paper.toml"       # required: a full parameter set, relative to this file
    scenarios = ["step", "gust"]        # required: closed-loop scenarios of simvehicle.engines.scenarios
    seeds = [0, 1, 2]                   # optional: one flight per seed and grid point (default [0])

    [grid]                              # required: one axis per key, the cartesian product is flown
    "world.altitude_m" = [0.5, 1.0, 2.0]
    "flow_sensor.q_rad_per_count" = [0.001, 0.00157]
    "effects.linear_drag.b" = [0.1, 0.2]   # an effect's parameter: the base config must list the effect

Each grid point is a full ``Config`` built from the base file through ``companion.config`` (so a
misspelt key or a meaningless value is the same error as in a config file). Every flight is
flown on the fast engine (``simvehicle.engines.fastsim``) with the companion fed through MAVLink
quantization, so a row's numbers are those ``python -m simvehicle scenario`` reports for that
config. Output: ``DIR/sweep.csv``, one row per grid point and seed (the grid values, the seed,
then ``<scenario>_<figure>_<axis>`` for every figure of merit of ``scenarios.figures`` and the
number of frames the companion held), and ``DIR/sweep.png``, a heatmap per headline figure over
the first two axes (mean over seeds and any further axes). Each cell has its number written in
it; the colour range is at least ``COLOUR_SPAN`` wide (a spread of rise times from 0.54 to
0.56 s is one colour, not the whole colour map); cells whose figures mean less than they seem
(frames held by the companion's gates, a step that did not settle, a gust not held) are framed in
red with a letter, explained under the plot and in the command's summary (``anomalies``).
"""

from __future__ import annotations

import argparse
import copy
import csv
import itertools
import math
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import EFFECT_TYPES, Config, config_from_dict, read_toml
from companion.errors import ConfigError, FlowholdError, UsageError, check_output, writing
from companion.fleet.engine import Engine, TaskLost
from simvehicle.engines import fastsim
from simvehicle.engines.scenarios import SCENARIOS, figures

_KEYS = {"title", "base_config", "scenarios", "seeds", "grid"}
#: the columns ``scenarios.figures`` reads, plus the hold flag
_FIG_COLUMNS = ("t_s", "vx_m_s", "vy_m_s", "x_m", "y_m", "roll_rad", "pitch_rad", "roll_cmd_rad", "pitch_cmd_rad",
                "flow_x_counts", "flow_y_counts", "hold")
#: the figures drawn in the plot, when their scenario is in the sweep (x axis; y is the same by symmetry)
HEADLINE = ("step_rise_time_10_90_s_x", "step_overshoot_pct_x", "gust_displacement_m_x", "gust_held_angle_deg_x",
            "slow_first_count_after_command_s_x", "slow_pulses_per_s_x")
#: flights per task at most (by default about four tasks per worker)
MAX_BATCH = 256
#: a step that settles further than this share from its setpoint is anomalous
SETTLE_TOLERANCE = 0.05
#: a gust still drifting faster than this at the end (m/s) was not held
GUST_DRIFT_M_S = 0.1
#: the narrowest colour range of each figure, in its unit: a change smaller than this is not
#: dramatic, and the colours must not make it look so (about the paper's own value of the figure,
#: or the whole of its scale: the rise time 0.5 s, the overshoot 20 %, the 2.8 m gust displacement)
COLOUR_SPAN = {"rise_time_10_90_s": 0.5, "overshoot_pct": 20.0, "displacement_m": 2.0, "held_angle_deg": 10.0,
               "first_count_after_command_s": 1.0, "pulses_per_s": 5.0}
_UNITS = {"rise_time_10_90_s": "s", "overshoot_pct": "%", "displacement_m": "m", "held_angle_deg": "deg",
          "first_count_after_command_s": "s", "pulses_per_s": "1/s", "held_frames": "frames"}


@dataclass(frozen=True)
class SweepSpec:
    """A parsed sweep file."""

    path: Path
    title: str
    base_path: Path
    base: dict[str, Any]  # the base config's TOML tables
    scenarios: tuple[str, ...]
    seeds: tuple[int, ...]
    axes: tuple[tuple[str, tuple[Any, ...]], ...]  # (key, values) in file order

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(len(v) for _, v in self.axes)


def load_sweep(path: str | Path) -> SweepSpec:
    """Read and check a sweep file (every grid point is also bound and checked as a Config)."""
    p = Path(path)
    data = read_toml(p, "sweep file")
    unknown = sorted(set(data) - _KEYS)
    if unknown:
        raise ConfigError(f"{p}: unknown key(s) {', '.join(unknown)} (allowed: {', '.join(sorted(_KEYS))})")
    for key in ("base_config", "scenarios", "grid"):
        if key not in data:
            raise ConfigError(f"{p}: missing key {key}")
    if not isinstance(data["base_config"], str):
        raise ConfigError(f"{p}: base_config must be a path (string)")
    base_path = (p.parent / data["base_config"]).resolve()
    try:
        with base_path.open("rb") as fh:
            base = tomllib.load(fh)
    except (FileNotFoundError, IsADirectoryError):
        raise ConfigError(f"{p}: base_config not found: {base_path}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{base_path}: not valid TOML: {exc}") from None
    scen = data["scenarios"]
    if not (isinstance(scen, list) and scen and all(isinstance(s, str) for s in scen)):
        raise ConfigError(f"{p}: scenarios must be a non-empty list of names ({', '.join(SCENARIOS)})")
    bad = [s for s in scen if s not in SCENARIOS]
    if bad:
        raise ConfigError(f"{p}: unknown scenario(s) {', '.join(bad)} (closed-loop: {', '.join(SCENARIOS)})")
    seeds = data.get("seeds", [0])
    if not (isinstance(seeds, list) and seeds and all(isinstance(s, int) and not isinstance(s, bool)
                                                      for s in seeds)):
        raise ConfigError(f"{p}: seeds must be a non-empty list of integers")
    grid = data["grid"]
    if not (isinstance(grid, dict) and grid):
        raise ConfigError(f"{p}: [grid] must list at least one axis, e.g. \"world.altitude_m\" = [0.5, 1.0]")
    axes = []
    for key, values in grid.items():
        if not (isinstance(values, list) and values and all(isinstance(v, (int, float, bool, str)) for v in values)):
            raise ConfigError(f"{p}: grid.{key!r} must be a non-empty list of values")
        _check_key(key, base, p)
        axes.append((key, tuple(values)))
    title = data.get("title", p.stem)
    if not isinstance(title, str):
        raise ConfigError(f"{p}: title must be a string")
    spec = SweepSpec(p, title, base_path, base, tuple(scen), tuple(seeds), tuple(axes))
    grid_configs(spec)  # bind every point now: a bad value fails before any flight
    return spec


def _check_key(key: str, base: dict[str, Any], where: Path) -> None:
    parts = key.split(".")
    if len(parts) == 3 and parts[0] == "effects":
        if parts[1] not in EFFECT_TYPES:
            raise ConfigError(f"{where}: grid key {key!r}: unknown effect {parts[1]!r} "
                              f"(known: {', '.join(EFFECT_TYPES)})")
        if parts[1] not in base.get("effects", {}):
            raise ConfigError(f"{where}: grid key {key!r}: the base config must list [effects.{parts[1]}] "
                              "(enabled and all its parameters) to sweep one of them")
        return
    if len(parts) != 2:
        raise ConfigError(f"{where}: grid key {key!r} must be \"section.key\" or \"effects.<effect>.<parameter>\"")


def grid_configs(spec: SweepSpec) -> list[tuple[dict[str, Any], Config]]:
    """Every grid point (dict key -> value) and its bound Config, in row-major order; a point the
    fast engine does not model (``fastsim.check_modelled``) is a ConfigError."""
    out = []
    keys = [k for k, _ in spec.axes]
    for values in itertools.product(*(v for _, v in spec.axes)):
        point = dict(zip(keys, values, strict=True))
        data = copy.deepcopy(spec.base)
        for key, value in point.items():
            table = data
            *path, last = key.split(".")
            for part in path:
                table = table.setdefault(part, {})
                if not isinstance(table, dict):
                    raise ConfigError(f"{spec.path}: grid key {key!r}: {part!r} is not a table")
            table[last] = value
        label = ", ".join(f"{k}={v}" for k, v in point.items())
        cfg = config_from_dict(data, source=f"{spec.path} [{label}]")
        fastsim.check_modelled(cfg)  # what the fast engine does not model is refused, not ignored
        out.append((point, cfg))
    return out


# ---------------------------------------------------------------------------------------------
# Running


def _flatten(fig: dict[str, Any], scenario: str) -> dict[str, float]:
    row = {}
    for axis in ("x", "y"):
        for name, value in fig[axis].items():
            if name == "command_limit_deg" or isinstance(value, list):
                continue
            row[f"{scenario}_{name}_{axis}"] = float(value)
    return row


def _run_task(task: tuple[str, list[int], list[Config], list[int]]
              ) -> tuple[list[int], list[dict[str, float]], float]:
    """One batch of flights of one scenario -> the flattened figures of each and the seconds it
    took (runs in a worker)."""
    t0 = time.perf_counter()
    name, rows, cfgs, seeds = task
    sc = SCENARIOS[name]
    res = fastsim.simulate_batch(cfgs, duration_s=sc.duration_s, setpoints=sc.setpoint, forces=sc.force,
                                 altitude=sc.altitude, seeds=seeds, turbulence_sigma_n=sc.turbulence_sigma_n,
                                 turbulence_tau_s=sc.turbulence_tau_s, mavlink_quantization=True,
                                 columns=_FIG_COLUMNS, name=name)
    out = []
    with np.errstate(all="ignore"):
        for i, cfg in enumerate(cfgs):
            run = res.run(i)
            out.append({**_flatten(figures(run, cfg), name), f"{name}_held_frames": float(run["hold"].sum())})
    return rows, out, time.perf_counter() - t0


def _tasks(spec: SweepSpec, points: list[tuple[dict[str, Any], Config]], workers: int,
           batch_flights: int | None = None) -> list[tuple[str, list[int], list[Config], list[int]]]:
    """Batches of flights of one scenario and frame rate: ``batch_flights`` each, or by default
    about four per worker and at most ``MAX_BATCH`` (a task long enough that scheduling it is a
    small share of its time, short enough to balance the workers)."""
    flights: list[tuple[int, Config, int]] = []  # (row, config, seed), rows in the order of run_sweep's table
    for _, cfg in points:
        for seed in spec.seeds:
            flights.append((len(flights), cfg, seed))
    if batch_flights is not None and batch_flights < 1:
        raise UsageError(f"--batch must be >= 1 flight per task, got {batch_flights}")
    size = batch_flights or max(1, min(MAX_BATCH, math.ceil(len(flights) / max(1, workers * 4))))
    tasks = []
    for name in spec.scenarios:
        by_rate: dict[float, list[tuple[int, Config, int]]] = {}
        for f in flights:  # a batch shares one frame rate
            by_rate.setdefault(f[1].flow_sensor.frame_period_s, []).append(f)
        for group in by_rate.values():
            for lo in range(0, len(group), size):
                chunk = group[lo:lo + size]
                tasks.append((name, [f[0] for f in chunk], [f[1] for f in chunk], [f[2] for f in chunk]))
    return tasks


def run_sweep(spec: SweepSpec, *, engine: Engine | None = None, batch_flights: int | None = None,
              timings: list[float] | None = None) -> list[dict[str, Any]]:
    """Fly the whole grid; one row per grid point and seed (grid values, seed, figures).

    ``engine``: where the batches run (``companion.fleet.engine.Engine``, opened); default this
    process, one batch after another. ``timings``: if given, each batch's seconds inside its task
    are appended (the benchmark's per-task cost)."""
    points = grid_configs(spec)
    rows: list[dict[str, Any]] = [{**point, "seed": seed} for point, _ in points for seed in spec.seeds]
    if engine is None:
        with Engine(in_process=True, progress=False) as here:
            return run_sweep(spec, engine=here, batch_flights=batch_flights, timings=timings)
    tasks = _tasks(spec, points, engine.n_workers, batch_flights)
    engine.on_every_worker(fastsim.warm_up)  # compile (or load) the kernel once per worker, before any batch
    for k, result in engine.map(_run_task, tasks, weights=[len(t[1]) for t in tasks], desc="sweep", unit="flight",
                                names=[f"sweep-{t[0]}" for t in tasks]):
        if isinstance(result, TaskLost):
            raise FlowholdError(f"sweep batch {k} ({len(tasks[k][1])} {tasks[k][0]} flights) not flown: {result}")
        idx, figs, elapsed_s = result
        if timings is not None:
            timings.append(elapsed_s)
        for r, fig in zip(idx, figs, strict=True):
            rows[r].update(fig)
    return rows


# ---------------------------------------------------------------------------------------------
# Anomalies


@dataclass(frozen=True)
class Anomaly:
    """A grid cell (indices on the first two axes) whose figures mean less than they seem."""

    cell: tuple[int, ...]
    code: str  # one letter, written in the cell: H held frames, S step not settled, G gust not held, N no figure
    what: str  # what was seen, "{}" where its number goes (e.g. "the step held {} frame(s)")
    value: float  # the number (NaN when there is none)
    cause: str  # why, in physics, when it follows from the config ("" otherwise)


def _setpoint_m_s(name: str) -> float:
    sc = SCENARIOS[name]
    return float(sc.setpoint(sc.duration_s)[0])


def anomalies(rows: list[dict[str, Any]], spec: SweepSpec) -> list[Anomaly]:
    """The cells of the plot whose numbers need a second look, and why (physics in words), one
    per row, cell and kind:

    - ``H``: the companion held frames (a gate rejected the data; its figures are not the PI's),
      with the cause when it follows from the config: the setpoint's scene rate v / h over the
      companion's spike gate ``max_flow_rate_rad_s``;
    - ``S``: the step settled more than ``SETTLE_TOLERANCE`` away from its setpoint;
    - ``G``: the gust was not held (still drifting faster than ``GUST_DRIFT_M_S`` at the end);
    - ``N``: a headline figure could not be measured (e.g. the step never reached 90 %)."""
    axes = spec.axes[:2]
    keys = [k for k, _ in spec.axes]
    configs = {tuple(p.values()): cfg for p, cfg in grid_configs(spec)}
    out: list[Anomaly] = []
    for r in rows:
        cfg = configs[tuple(r[k] for k in keys)]
        cell = tuple(values.index(r[key]) for key, values in axes)
        h_m = cfg.world.altitude_m
        gate = cfg.companion.max_flow_rate_rad_s
        for s in spec.scenarios:
            held = r.get(f"{s}_held_frames", 0.0)
            if held > 0:
                v = abs(_setpoint_m_s(s))
                peak = v * (1 + max(r.get(f"{s}_overshoot_pct_x", 0.0), 0.0) / 100) if s == "step" else v
                if v / h_m > gate:
                    cause = (f"{v:g} m/s at {h_m:g} m is a scene rate of {v / h_m:.1f} rad/s, over the companion's "
                             f"spike gate of {gate:g} rad/s (companion.max_flow_rate_rad_s): those frames are held")
                elif peak / h_m > gate:
                    cause = (f"the overshoot to {peak:.2f} m/s at {h_m:g} m is {peak / h_m:.1f} rad/s, over the "
                             f"companion's spike gate of {gate:g} rad/s (companion.max_flow_rate_rad_s): those frames "
                             "are held")
                else:
                    cause = "a gate (flow spike, range, gyro saturation) rejected frames"
                out.append(Anomaly(cell, "H", f"the {s} held {{}} frame(s)", held, cause))
        if "step" in spec.scenarios:
            final = r.get("step_final_velocity_m_s_x", math.nan)
            want = _setpoint_m_s("step")
            if math.isfinite(final) and abs(final - want) > SETTLE_TOLERANCE * abs(want):
                blind = ""
                if r.get("step_held_frames", 0.0) > 0:
                    blind = (f"the companion takes any speed over {gate * h_m:.2f} m/s ({gate:g} rad/s x {h_m:g} m) "
                             "for a flow spike and holds its last command, so " +
                             ("it cannot measure the speed it is asked to keep" if abs(want) / h_m > gate else
                              "once the overshoot passed it, it never saw the speed come back"))
                out.append(Anomaly(cell, "S", f"the step settled at {{}} m/s, not {want:g} m/s", final, blind))
            for m in ("step_rise_time_10_90_s_x", "step_overshoot_pct_x"):
                if m in r and not math.isfinite(r[m]):
                    out.append(Anomaly(cell, "N", f"no {m.removeprefix('step_').removesuffix('_x')}", math.nan,
                                       f"the step never crossed 10 % and 90 % of {want:g} m/s after it was commanded"))
        if "gust" in spec.scenarios:
            drift = r.get("gust_final_speed_m_s_x", math.nan)
            if math.isfinite(drift) and drift > GUST_DRIFT_M_S:
                out.append(Anomaly(cell, "G", "the gust was not held: still drifting at {} m/s at the end", drift, ""))
    return out


def _values(xs: list[float]) -> str:
    xs = sorted(x for x in xs if math.isfinite(x))
    if not xs:
        return ""
    lo, hi = f"{xs[0]:.3g}", f"{xs[-1]:.3g}"
    return lo if lo == hi else f"{lo} to {hi}"


def _where(cells: set[tuple[int, ...]], spec: SweepSpec) -> str:
    """The cells in words: ``altitude_m = 0.25, every q_rad_per_count`` when they are a block."""
    parts = []
    for axis, (key, values) in enumerate(spec.axes[:2]):
        seen = sorted({c[axis] for c in cells})
        label = key.split(".")[-1]
        parts.append(f"every {label}" if len(seen) == len(values) and len(values) > 1
                     else f"{label} = {', '.join(str(values[i]) for i in seen)}")
    block = math.prod(len({c[a] for c in cells}) for a in range(len(spec.axes[:2])))
    if block == len(cells):
        return ", ".join(parts)
    return "; ".join(", ".join(f"{k.split('.')[-1]}={v[c[a]]}" for a, (k, v) in enumerate(spec.axes[:2]))
                     for c in sorted(cells))


def describe(marks: list[Anomaly], spec: SweepSpec) -> list[str]:
    """One line per kind and cause: the code, where, what with its numbers, why."""
    groups: dict[tuple[str, str, str], list[Anomaly]] = {}
    for a in marks:
        groups.setdefault((a.code, a.what, a.cause), []).append(a)
    lines = []
    for (code, what, cause), members in groups.items():
        cells = {a.cell for a in members}
        vals = _values([a.value for a in members])
        lines.append(f"{code} at {_where(cells, spec)} ({len(cells)} cell(s)): {what.replace('{}', vals)}"
                     + (f"; {cause}" if cause else ""))
    return lines


# ---------------------------------------------------------------------------------------------
# Output


def write_csv(rows: list[dict[str, Any]], path: str | Path) -> None:
    keys: list[str] = []
    for r in rows:
        keys.extend(k for k in r if k not in keys)
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: (repr(v) if isinstance(v, float) else v) for k, v in r.items()})


def _grid_mean(rows: list[dict[str, Any]], spec: SweepSpec, metric: str) -> np.ndarray:
    """The metric on the grid of the first two axes (mean over seeds and further axes; NaN kept out)."""
    axes = spec.axes[:2]
    acc = np.zeros([len(v) for _, v in axes])
    cnt = np.zeros_like(acc)
    for r in rows:
        v = r.get(metric, math.nan)
        if not math.isfinite(v):
            continue
        idx = tuple(values.index(r[key]) for key, values in axes)
        acc[idx] += v
        cnt[idx] += 1
    with np.errstate(invalid="ignore"):
        return np.where(cnt > 0, acc / np.maximum(cnt, 1), np.nan)


def _colour_span(metric: str, spec: SweepSpec) -> tuple[float, bool]:
    """(narrowest colour range in the metric's unit, anchored at zero?) ``COLOUR_SPAN``; held
    frames span the whole flight's frames from zero."""
    scen, _, tail = metric.partition("_")
    if tail == "held_frames":
        cfg = grid_configs(spec)[0][1]
        return SCENARIOS[scen].duration_s * cfg.flow_sensor.frame_rate_hz, True
    return next((span for name, span in COLOUR_SPAN.items() if tail.startswith(name)), 0.0), False


def colour_limits(grid: np.ndarray, span: float, from_zero: bool = False) -> tuple[float, float]:
    """The colour range of a heatmap: the data's range, widened about its middle to at least
    ``span`` (or from 0 to at least ``span`` with ``from_zero``), so a spread much smaller than
    what matters physically stays one colour instead of using the whole colour map."""
    finite = grid[np.isfinite(grid)]
    if not finite.size:
        return 0.0, 1.0
    lo, hi = float(finite.min()), float(finite.max())
    if from_zero:
        return min(lo, 0.0), max(hi, span, 1e-12)
    if hi - lo >= span:
        return (lo, hi) if hi > lo else (lo - 0.5, hi + 0.5)
    mid = (lo + hi) / 2
    return mid - span / 2, mid + span / 2


def plot_sweep(rows: list[dict[str, Any]], spec: SweepSpec, path: str | Path,
               marks: list[Anomaly] | None = None) -> None:
    """Heatmaps (two or more axes) or curves (one axis) of the headline figures, each cell's
    number written in it, colour ranges at least ``COLOUR_SPAN`` wide, anomalous cells framed in
    red with their letter and explained under the figure (``anomalies``)."""
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    marks = anomalies(rows, spec) if marks is None else marks
    letters: dict[tuple[int, ...], set[str]] = {}
    for a in marks:  # one mark per row: a cell of several seeds or further axes has a letter once
        letters.setdefault(a.cell, set()).add(a.code)
    codes = {cell: "".join(c for c in "HSGN" if c in found) for cell, found in letters.items()}
    metrics = [m for m in HEADLINE if any(m in r for r in rows)]
    # where the companion held (a gate rejected the data) the figures mean little: show where
    metrics += [f"{s}_held_frames" for s in spec.scenarios if any(r.get(f"{s}_held_frames", 0) > 0 for r in rows)]
    n = len(metrics)
    ncols = min(3, n)
    nrows = math.ceil(n / ncols)
    legend = describe(marks, spec)
    shown = legend[:10] + ([f"... and {len(legend) - 10} more (the command's summary lists them all)"]
                           if len(legend) > 10 else [])
    lines = [w for item in shown for w in textwrap.wrap(item, 150, subsequent_indent="    ")]
    foot_in = 0.25 + 0.17 * (len(lines) + 1) if lines else 0.3
    fig, axs = plt.subplots(nrows, ncols, figsize=(5.4 * ncols, 4.3 * nrows + foot_in), squeeze=False)
    (k0, v0), *rest = spec.axes

    def ticks(values: tuple[Any, ...]) -> list[str]:
        return [f"{v:.3g}" if isinstance(v, float) else str(v) for v in values]

    for ax, metric in zip(axs.ravel(), metrics, strict=False):
        grid = _grid_mean(rows, spec, metric)
        scen, _, tail = metric.partition("_")
        unit = next((u for name, u in _UNITS.items() if tail.startswith(name)), "")
        label = f"{scen}: {tail.removesuffix('_x')}" + (f" ({unit})" if unit else "")
        span, from_zero = _colour_span(metric, spec)
        lo, hi = colour_limits(grid, span, from_zero)
        if not rest:
            ax.plot(range(len(v0)), grid, "o-")
            for i in range(len(v0)):
                if (i,) in codes and math.isfinite(grid[i]):
                    ax.plot(i, grid[i], "o", ms=12, mfc="none", mec="red", mew=1.5)
                    ax.annotate(codes[(i,)], (i, grid[i]), textcoords="offset points", xytext=(6, 6), color="red",
                                fontsize=8)
            ax.set_ylim(lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo))
            ax.set_xticks(range(len(v0)), ticks(v0))
            ax.set_xlabel(k0)
            ax.set_title(label, fontsize=10)
            ax.grid(True, alpha=0.3)
            continue
        k1, v1 = rest[0]
        im = ax.imshow(np.ma.masked_invalid(grid.T), origin="lower", aspect="auto", cmap="viridis", vmin=lo, vmax=hi)
        cb = fig.colorbar(im, ax=ax, shrink=0.85)
        if span:
            cb.set_label(f"colour range >= {span:g} {unit}".rstrip() + (" from 0" if from_zero else ""), fontsize=7)
        ax.set_xticks(range(len(v0)), ticks(v0))
        ax.set_yticks(range(len(v1)), ticks(v1))
        ax.set_xlabel(k0)
        ax.set_ylabel(k1)
        ax.set_title(label, fontsize=10)
        for i in range(grid.shape[0]):
            for j in range(grid.shape[1]):
                val = grid[i, j]
                text = "n/a" if not math.isfinite(val) else f"{0.0 if abs(val) < 1e-9 else val:.3g}"
                frac = (val - lo) / (hi - lo) if math.isfinite(val) and hi > lo else 0.0
                code = codes.get((i, j), "")
                ax.text(i, j, text + (f"\n{code}" if code else ""), ha="center", va="center", fontsize=8,
                        color="white" if frac < 0.55 else "black", fontweight="bold" if code else "normal")
                if code:
                    ax.add_patch(Rectangle((i - 0.5, j - 0.5), 1, 1, fill=False, ec="red", lw=2))
    for ax in axs.ravel()[n:]:
        ax.set_visible(False)
    extra = f" (mean over {', '.join(k for k, _ in spec.axes[2:])})" if len(spec.axes) > 2 else ""
    seeds = f", {len(spec.seeds)} seeds averaged" if len(spec.seeds) > 1 else ""
    fig.suptitle(f"{spec.title}{extra}{seeds}", fontsize=11)
    bottom = foot_in / fig.get_figheight()
    if lines:
        fig.text(0.01, bottom - 0.1 / fig.get_figheight(), "Red: anomalous cells (H held frames, S step not settled, "
                 "G gust not held, N no figure):\n" + "\n".join(lines), fontsize=7, va="top", color="darkred",
                 family="monospace")
    else:
        fig.text(0.01, 0.02, "No anomalous cell: no held frame, every step settled within "
                 f"{100 * SETTLE_TOLERANCE:g} % of its setpoint, every gust held.", fontsize=7)
    fig.tight_layout(rect=(0, bottom, 1, 0.97))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_cli(args: argparse.Namespace) -> int:
    """``python -m simvehicle sweep CONFIG --out DIR [--workers N | --scheduler ADDRESS | --in-process]
    [--batch N]``."""
    spec = load_sweep(args.sweep_config)
    engine = Engine(scheduler=args.scheduler, workers=args.workers, in_process=args.in_process)
    if args.batch is not None and args.batch < 1:
        raise UsageError(f"--batch must be >= 1 flight per task, got {args.batch}")
    out = check_output(args.out, "--out", folder=True)
    if engine.note:
        print(f"note: {engine.note.replace('one file after another', 'one batch after another')}")
    t0 = time.perf_counter()
    with engine:
        if engine.dashboard:
            print(f"dashboard: {engine.dashboard}", flush=True)
        elif engine.dask:
            print(f"dashboard: none ({engine.dashboard_note})", flush=True)
        rows = run_sweep(spec, engine=engine, batch_flights=args.batch)
        where = engine.description
    elapsed = time.perf_counter() - t0
    with writing("--out", out / "sweep.csv"):
        write_csv(rows, out / "sweep.csv")
    marks = anomalies(rows, spec)
    with writing("--out", out / "sweep.png"):
        plot_sweep(rows, spec, out / "sweep.png", marks)
    n_flights = len(rows) * len(spec.scenarios)
    print(f"sweep {spec.title}: {len(rows)} rows ({' x '.join(map(str, spec.shape))} grid x {len(spec.seeds)} "
          f"seed(s)), {n_flights} flights in {elapsed:.1f} s, {where}")
    for line in describe(marks, spec):
        print(f"anomalous: {line}")
    print(f"table: {out / 'sweep.csv'}")
    print(f"plot: {out / 'sweep.png'}")
    return 0

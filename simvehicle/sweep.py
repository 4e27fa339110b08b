"""Parameter sweeps: the paper's figures of merit across a grid of parameters, on all cores.

    python -m simvehicle sweep configs/sweeps/altitude_q.toml --out out/sweep [--workers N]

A sweep file is TOML; every key is checked and an unknown one is an error::

    title = "..."                       # optional, for the plot
    base_config = "../paper.toml"       # required: a full parameter set, relative to this file
    scenarios = ["step", "gust"]        # required: closed-loop scenarios of simvehicle.scenarios
    seeds = [0, 1, 2]                   # optional: one flight per seed and grid point (default [0])

    [grid]                              # required: one axis per key, the cartesian product is flown
    "world.altitude_m" = [0.5, 1.0, 2.0]
    "flow_sensor.q_rad_per_count" = [0.001, 0.00157]
    "effects.linear_drag.b" = [0.1, 0.2]   # an effect's parameter: the base config must list the effect

Each grid point is a full ``Config`` built from the base file through ``companion.config`` (so a
misspelt key or a meaningless value is the same error as in a config file). Every flight is
flown on the fast engine (``simvehicle.fastsim``) with the companion fed through MAVLink
quantization, so a row's numbers are those ``python -m simvehicle scenario`` reports for that
config. Output: ``DIR/sweep.csv``, one row per grid point and seed (the grid values, the seed,
then ``<scenario>_<figure>_<axis>`` for every figure of merit of ``scenarios.figures`` and the
number of frames the companion held), and ``DIR/sweep.png``, a heatmap per headline figure over
the first two axes (mean over seeds and any further axes).
"""

from __future__ import annotations

import argparse
import copy
import csv
import itertools
import math
import os
import sys
import time
import tomllib
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import EFFECT_TYPES, Config, config_from_dict, read_toml
from companion.errors import ConfigError, check_output, writing
from simvehicle import fastsim
from simvehicle.scenarios import SCENARIOS, figures

_KEYS = {"title", "base_config", "scenarios", "seeds", "grid"}
#: the columns ``scenarios.figures`` reads, plus the hold flag
_FIG_COLUMNS = ("t_s", "vx_m_s", "vy_m_s", "x_m", "y_m", "roll_rad", "pitch_rad", "roll_cmd_rad", "pitch_cmd_rad",
                "flow_x_counts", "flow_y_counts", "hold")
#: the figures drawn in the plot, when their scenario is in the sweep (x axis; y is the same by symmetry)
HEADLINE = ("step_rise_time_10_90_s_x", "step_overshoot_pct_x", "gust_displacement_m_x", "gust_held_angle_deg_x",
            "slow_first_count_after_command_s_x", "slow_pulses_per_s_x")
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
    """Every grid point (dict key -> value) and its bound Config, in row-major order."""
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
        out.append((point, config_from_dict(data, source=f"{spec.path} [{label}]")))
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


def _run_task(task: tuple[str, list[int], list[Config], list[int]]) -> tuple[list[int], list[dict[str, float]]]:
    """One chunk of flights of one scenario -> the flattened figures of each (runs in a worker)."""
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
    return rows, out


def _tasks(spec: SweepSpec, points: list[tuple[dict[str, Any], Config]], workers: int
           ) -> list[tuple[str, list[int], list[Config], list[int]]]:
    flights = []  # (row, config, seed), rows in the order of run_sweep's table
    for _, cfg in points:
        for seed in spec.seeds:
            flights.append((len(flights), cfg, seed))
    n_chunks = max(1, workers * 4)
    size = max(1, min(256, math.ceil(len(flights) / n_chunks)))
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


def run_sweep(spec: SweepSpec, *, workers: int = 1, progress: bool = True) -> list[dict[str, Any]]:
    """Fly the whole grid; one row per grid point and seed (grid values, seed, figures)."""
    points = grid_configs(spec)
    rows: list[dict[str, Any]] = [{**point, "seed": seed} for point, _ in points for seed in spec.seeds]
    tasks = _tasks(spec, points, workers)
    total = sum(len(t[1]) for t in tasks)
    from tqdm import tqdm

    bar = tqdm(total=total, unit="flight", file=sys.stderr, disable=not progress, desc="sweep")
    results: list[tuple[list[int], list[dict[str, float]]]] = []
    try:
        if workers <= 1:
            for task in tasks:
                results.append(_run_task(task))
                bar.update(len(task[1]))
        else:
            fastsim.warm_up()  # compile once here; the forked workers inherit the kernel
            with ProcessPoolExecutor(max_workers=workers) as pool:
                futures: dict[Future[Any], int] = {pool.submit(_run_task, t): len(t[1]) for t in tasks}
                for fut in as_completed(futures):
                    results.append(fut.result())
                    bar.update(futures[fut])
    finally:
        bar.close()
    for idx, figs in results:
        for r, fig in zip(idx, figs, strict=True):
            rows[r].update(fig)
    return rows


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


def plot_sweep(rows: list[dict[str, Any]], spec: SweepSpec, path: str | Path) -> None:
    """Heatmaps (two or more axes) or curves (one axis) of the headline figures."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = [m for m in HEADLINE if any(m in r for r in rows)]
    # where the companion held (a gate rejected the data) the figures mean little: show where
    metrics += [f"{s}_held_frames" for s in spec.scenarios if any(r.get(f"{s}_held_frames", 0) > 0 for r in rows)]
    n = len(metrics)
    ncols = min(3, n)
    nrows = math.ceil(n / ncols)
    fig, axs = plt.subplots(nrows, ncols, figsize=(5.2 * ncols, 4.2 * nrows), squeeze=False)
    (k0, v0), *rest = spec.axes
    for ax, metric in zip(axs.ravel(), metrics, strict=False):
        grid = _grid_mean(rows, spec, metric)
        scen, _, tail = metric.partition("_")
        unit = next((u for name, u in _UNITS.items() if tail.startswith(name)), "")
        label = f"{scen}: {tail.removesuffix('_x')}" + (f" ({unit})" if unit else "")
        if not rest:
            ax.plot(range(len(v0)), grid, "o-")
            ax.set_xticks(range(len(v0)), [f"{v:.3g}" if isinstance(v, float) else str(v) for v in v0])
            ax.set_xlabel(k0)
            ax.set_title(label, fontsize=10)
            ax.grid(True, alpha=0.3)
            continue
        k1, v1 = rest[0]
        im = ax.imshow(np.ma.masked_invalid(grid.T), origin="lower", aspect="auto", cmap="viridis")
        fig.colorbar(im, ax=ax, shrink=0.85)
        ax.set_xticks(range(len(v0)), [f"{v:.3g}" if isinstance(v, float) else str(v) for v in v0])
        ax.set_yticks(range(len(v1)), [f"{v:.3g}" if isinstance(v, float) else str(v) for v in v1])
        ax.set_xlabel(k0)
        ax.set_ylabel(k1)
        ax.set_title(label, fontsize=10)
        finite = grid[np.isfinite(grid)]
        mid = (finite.min() + finite.max()) / 2 if finite.size else 0.0
        for i in range(grid.shape[0]):
            for j in range(grid.shape[1]):
                val = grid[i, j]
                text = "n/a" if not math.isfinite(val) else f"{0.0 if abs(val) < 1e-9 else val:.3g}"
                ax.text(i, j, text, ha="center", va="center",
                        fontsize=8, color="white" if not math.isfinite(val) or val < mid else "black")
    for ax in axs.ravel()[n:]:
        ax.set_visible(False)
    extra = f" (mean over {', '.join(k for k, _ in spec.axes[2:])})" if len(spec.axes) > 2 else ""
    seeds = f", {len(spec.seeds)} seeds averaged" if len(spec.seeds) > 1 else ""
    fig.suptitle(f"{spec.title}{extra}{seeds}", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_cli(args: argparse.Namespace) -> int:
    """``python -m simvehicle sweep CONFIG --out DIR [--workers N]``."""
    workers = args.workers if args.workers is not None else (os.cpu_count() or 1)
    if workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    spec = load_sweep(args.sweep_config)
    out = check_output(args.out, "--out", folder=True)
    t0 = time.perf_counter()
    rows = run_sweep(spec, workers=workers)
    elapsed = time.perf_counter() - t0
    with writing("--out", out / "sweep.csv"):
        write_csv(rows, out / "sweep.csv")
    with writing("--out", out / "sweep.png"):
        plot_sweep(rows, spec, out / "sweep.png")
    n_flights = len(rows) * len(spec.scenarios)
    print(f"sweep {spec.title}: {len(rows)} rows ({' x '.join(map(str, spec.shape))} grid x {len(spec.seeds)} "
          f"seed(s)), {n_flights} flights in {elapsed:.1f} s on {workers} worker(s)")
    print(f"table: {out / 'sweep.csv'}")
    print(f"plot: {out / 'sweep.png'}")
    return 0

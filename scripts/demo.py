"""`make demo`: the paper's closed-loop scenarios in simulation, with plots and recordings."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from companion.config import load_config  # noqa: E402
from simvehicle.plots import plot_run  # noqa: E402
from simvehicle.scenarios import figures, run_named  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="out/demo")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = load_config()
    for name in ("step", "gust", "slow", "rail", "triangle"):
        tlog = out / f"{name}.tlog" if name in ("step", "gust", "slow") else None
        run = run_named(name, cfg, tlog=tlog)
        png = plot_run(run, out / f"{name}.png")
        fig = figures(run, cfg)
        print(f"{name}: plot {png}" + (f", recording {tlog}" if tlog else ""))
        if "x" in fig:
            print("   x axis:", {k: round(v, 3) if isinstance(v, float) else v for k, v in fig["x"].items()})
    print(f"wrote figures and recordings to {out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())

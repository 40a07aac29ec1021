"""Make the README figure ``docs/readme_target_vs_render.png``: three targets above the board
rendered from each of the three views after a short optimisation.

Run from the repository root (a few minutes on a laptop CPU with the defaults)::

    python scripts/make_readme_figure.py [--size 128] [--scratches 8000] [--iterations 100]

The targets are the three images bundled with scikit-image (`jscratch.design.default_targets`),
the views the paper's layout (`jscratch.render.views_on_circle`, light and cameras 50 degrees from
the board normal) and the optimiser `jscratch.design.design` with its default configuration except
for the sizes given. Prints the per-view SSIM/PSNR and the run time.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "docs" / "readme_target_vs_render.png"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--size", type=int, default=128, help="image side (pixels)")
    p.add_argument("--scratches", type=int, default=8000, help="number of scratches")
    p.add_argument("--iterations", type=int, default=100, help="Adam iterations")
    p.add_argument("--theta-deg", type=float, default=50.0, help="polar angle of light and cameras (degrees)")
    p.add_argument("--seed", type=int, default=0, help="seed of the initial layout")
    p.add_argument("--dpi", type=int, default=100, help="resolution of the PNG")
    p.add_argument("--out", default=str(DEFAULT_OUT), help="output PNG")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from jscratch import design
    from jscratch import render

    t0 = time.perf_counter()
    shape = (args.size, args.size)
    board = render.Board(shape=shape)
    targets, names = design.default_targets(3, shape)
    views = render.views_on_circle(3, math.radians(args.theta_deg), board=board)
    config = design.DesignConfig(n_scratches=args.scratches, iterations=args.iterations, seed=args.seed)
    result = design.design(targets, views, board, config, progress=not args.quiet)
    m = result.metrics

    fig, axes = plt.subplots(2, 3, figsize=(7.8, 5.9), layout="constrained")
    azimuths = np.degrees(np.arctan2(np.asarray(views.camera)[:, 1] - board.Sy / 2,
                                     np.asarray(views.camera)[:, 0] - board.Sx / 2)) % 360
    for j in range(3):
        axes[0, j].imshow(result.targets[j], cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        axes[0, j].set_title(f"target: {names[j].split('.')[-1]}", fontsize=10)
        axes[1, j].imshow(result.display[j], cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        axes[1, j].set_title(f"board, camera at {azimuths[j]:.0f}° (SSIM {m['ssim'][j]:.2f})", fontsize=9)
        for ax in axes[:, j]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.suptitle(f"One board, three views: {m['kept']} scratches ({m['discarded']} discarded), "
                 f"{args.size}x{args.size} px, {m['iterations']} Adam iterations", fontsize=10)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=args.dpi)
    plt.close(fig)
    print(f"wrote {out} ({os.path.getsize(out) / 1024:.0f} KB) in {time.perf_counter() - t0:.0f} s; "
          f"SSIM {[round(x, 3) for x in m['ssim']]}, PSNR {[round(x, 2) for x in m['psnr']]} dB, "
          f"design time {m['time_total']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

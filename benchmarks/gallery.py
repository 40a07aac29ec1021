"""Parameter gallery of the scratch reflectance model, in the spirit of the paper's Figs. 12-13.

Renders random, horizontally brushed and vertically brushed scratch patterns under several views,
and sweeps of the roughness ``alpha``, the width ``w`` and the scratch count, and writes PNG
figures to ``docs/gallery/``:

- ``patterns.png``: rows random / horizontal / vertical brushing, columns the views of
  `views_on_circle` (light at polar angle 40 deg, azimuth 0; cameras at the same polar angle).
- ``sweep_alpha.png``, ``sweep_width.png``, ``sweep_count.png``: one view, one parameter varied.

Each figure shares one exposure (radiance divided by the figure's 99.5th percentile, then the
display transform `render.display`, clipped to [0, 1]), so panels within a figure compare.

    python benchmarks/gallery.py            # 128x128 panels, writes docs/gallery/*.png
    python benchmarks/gallery.py --res 256 --out /tmp/gallery
"""

from __future__ import annotations

import argparse
import math
import os

import jax
import jax.numpy as jnp
import numpy as np


from jscratch import render


def brushed(key, n, board, angle, *, spread=math.radians(4), length=(0.02, 0.06), **kw):
    """``n`` scratches with directions ``angle +- spread`` (rad, Gaussian), midpoints uniform,
    lengths uniform in ``length`` (m), shortened about the midpoint to stay on the board."""
    k1, k2, k3 = jax.random.split(key, 3)
    size = np.array([board.Sx, board.Sy])
    mid = np.asarray(jax.random.uniform(k1, (n, 2))) * size
    phi = angle + spread * np.asarray(jax.random.normal(k2, (n,)))
    half = 0.5 * np.asarray(jax.random.uniform(k3, (n,), minval=length[0], maxval=length[1]))
    t = np.stack([np.cos(phi), np.sin(phi)], -1)
    with np.errstate(divide="ignore"):
        reach = np.min(np.where(t > 0, (size - mid) / t, np.where(t < 0, -mid / t, np.inf)), -1)
        reach_back = np.min(np.where(t < 0, (size - mid) / -t, np.where(t > 0, mid / t, np.inf)),
                            -1)
    s = np.minimum(half, np.minimum(reach, reach_back))[:, None]
    p0, p1 = np.clip(mid - s * t, 0, size), np.clip(mid + s * t, 0, size)
    return render.Scratches(jnp.asarray(p0, jnp.float32), jnp.asarray(p1, jnp.float32), **kw)


def _random(key, n, board, **kw):
    s = render.Scratches.random(key, n, board, dtype=jnp.float32)
    return render.Scratches(s.p0, s.p1, **kw)


def _save(path, panels, row_titles, col_titles, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rad = np.asarray(panels, np.float64)  # (rows, cols, H, W)
    scale = np.percentile(rad, 99.5)
    img = np.clip(np.asarray(render.display(jnp.asarray(rad / scale))), 0, 1)
    rows, cols = img.shape[:2]
    fig, axes = plt.subplots(rows, cols, figsize=(1.6 * cols + 0.6, 1.6 * rows + 0.4),
                             squeeze=False)
    for i in range(rows):
        for j in range(cols):
            ax = axes[i, j]
            ax.imshow(img[i, j], cmap="gray", vmin=0, vmax=1, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0 and col_titles:
                ax.set_title(col_titles[j], fontsize=7)
            if j == 0 and row_titles:
                ax.set_ylabel(row_titles[i], fontsize=7)
    fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=72)
    plt.close(fig)
    print(f"wrote {path} ({os.path.getsize(path) // 1024} KiB)")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--res", type=int, default=128, help="panel size in pixels (default 128)")
    ap.add_argument("--count", type=int, default=3000, help="scratches per pattern (default 3000)")
    ap.add_argument("--views", type=int, default=4, help="views in patterns.png (default 4)")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                                   "..", "docs", "gallery"))
    args = ap.parse_args(argv)
    if args.views < 1 or args.res < 1 or args.count < 1:
        ap.error("--views, --res and --count must be at least 1")
    os.makedirs(args.out, exist_ok=True)
    board = render.Board(shape=(args.res, args.res))
    key = jax.random.PRNGKey(12)
    views = render.views_on_circle(args.views, math.radians(40), board=board, dtype=jnp.float32)
    az = [math.degrees(math.atan2(c[1] - 0.15, c[0] - 0.15)) % 360 for c in
          np.asarray(views.camera)]
    base = dict(width=1e-4, depth=1e-4, alpha=0.04)

    patterns = {
        "random": _random(key, args.count, board, **base),
        "horizontal": brushed(key, args.count, board, 0.0, **base),
        "vertical": brushed(key, args.count, board, math.pi / 2, **base),
    }
    panels = [np.asarray(render.render(s, views, board)) for s in patterns.values()]
    _save(os.path.join(args.out, "patterns.png"), panels, list(patterns),
          [f"camera az {a:.0f} deg" for a in az],
          f"{args.count} scratches, w = d = 0.1 mm, alpha = 0.04; light az 0, polar 40 deg")

    k = min(1, args.views - 1)  # the sweeps' view: the second, or the only one
    one = render.Views(views.camera[k:k + 1], views.light[k:k + 1], views.intensity[k:k + 1])
    sweeps = {
        "alpha": ("alpha", [0.01, 0.04, 0.12, 0.3], lambda v: dict(base, alpha=v)),
        "width": ("w (mm)", [5e-5, 1e-4, 2e-4, 4e-4], lambda v: dict(base, width=v)),
    }
    for name, (label, values, kw) in sweeps.items():
        rows = []
        for pat in ("random", "horizontal"):
            row = []
            for val in values:
                s = (_random(key, args.count, board, **kw(val)) if pat == "random"
                     else brushed(key, args.count, board, 0.0, **kw(val)))
                row.append(np.asarray(render.render(s, one, board))[0])
            rows.append(row)
        fmt = (lambda v: f"{label} = {1e3 * v:g}") if name == "width" else (
            lambda v: f"{label} = {v:g}")
        _save(os.path.join(args.out, f"sweep_{name}.png"), rows, ["random", "horizontal"],
              [fmt(v) for v in values], f"sweep of {label}; camera az {az[k]:.0f} deg")

    counts = [300, 1000, 3000, 10000]
    rows = [[np.asarray(render.render(f(key, c, board, **base), one, board))[0] for c in counts]
            for f in (_random, lambda k, c, b, **kw: brushed(k, c, b, 0.0, **kw))]
    _save(os.path.join(args.out, "sweep_count.png"), rows, ["random", "horizontal"],
          [f"{c} scratches" for c in counts], f"sweep of scratch count; camera az {az[k]:.0f} deg")


if __name__ == "__main__":
    main()

"""Build ``notebooks/quickstart.ipynb`` from the cells below (reproducible, committed without outputs).

Run from the repository root: ``python notebooks/make_quickstart.py`` (``--check`` only compares
the generated notebook with the committed one and exits 1 when they differ).

The notebook reads ``JSCRATCH_NOTEBOOK_SMALL=1`` in its parameter cell to run at toy size; the
test suite (``tests/test_notebook.py``) executes it that way.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

PATH = Path(__file__).with_name("quickstart.ipynb")


def md(text: str):
    return new_markdown_cell(text.strip("\n"))


def code(text: str, **metadata):
    cell = new_code_cell(text.strip("\n"))
    cell.metadata.update(metadata)
    return cell


CELLS = [
    md(r"""
# jscratch quickstart: scratch-based reflection art

A polished metal board carved with thousands of short straight scratches shows a *different image
from each viewpoint*: every scratch is a tiny groove whose curved walls reflect a point light into
a camera only when the scratch runs at the right angle. jscratch reimplements Shen, Li, Wang and
Liu, *Scratch-based Reflection Art via Differentiable Rendering* (ACM TOG 42(4), SIGGRAPH 2023) in
JAX: a closed-form scratch NDF, a differentiable multi-view renderer, an optimiser that places the
scratches, and a fabrication stage that turns the result into G-code.

This notebook walks through each stage with a few lines of the public API:

1. the model in pictures: groove profile and normals, the point NDF, one pixel-scratch pair integral;
2. a forward render of random and brushed scratches under two views;
3. a small three-view optimisation (loss curve, renders beside targets);
4. the discard step;
5. a fabrication dry run with its toolpath preview.

Units are SI (metres, radians) except G-code (millimetres). Section numbers like §3.2 refer to
the paper; the module docstrings (`help(jscratch.ndf)`, `help(jscratch.render)`, ...) give the
exact definitions.
"""),
    md(r"""
**Parameters.** The defaults take a few minutes on a laptop CPU. The test suite sets
`JSCRATCH_NOTEBOOK_SMALL=1`, which shrinks the images, scratch counts and iterations to a toy size
(the pictures then look rough, but every cell runs).
"""),
    code(r"""
import os

SMALL = os.environ.get("JSCRATCH_NOTEBOOK_SMALL", "0") == "1"
SIZE = 40 if SMALL else 128           # image side in pixels (the board is 0.3 m x 0.3 m)
N_RENDER = 1500 if SMALL else 20000   # scratches in the forward-render examples
N_DESIGN = 300 if SMALL else 8000     # scratches in the optimisation
ITERATIONS = 5 if SMALL else 100      # Adam iterations (the paper uses 100)
SEED = 0
""", tags=["parameters"]),
    code(r"""
import math
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
from IPython.display import Image, display
from matplotlib.collections import LineCollection
from matplotlib.colors import LogNorm

import jscratch
from jscratch import designfile, fabricate, ndf

OUT = Path(tempfile.mkdtemp(prefix="jscratch_quickstart_"))  # files written by this notebook
print("jax", jax.__version__, "on", jax.devices()[0].platform, "| outputs in", OUT)


def draw_scratches(ax, p0, p1, board, **kw):
    # Top view of scratches in board metres (y up, as the images: row 0 is the edge y = Sy).
    segs = np.stack([np.asarray(p0), np.asarray(p1)], 1)
    ax.add_collection(LineCollection(segs, **{"colors": "k", "linewidths": 0.5, **kw}))
    ax.set(xlim=(0, board.Sx), ylim=(0, board.Sy), aspect="equal", xticks=[], yticks=[])
"""),
    md(r"""
## 1. The model in pictures

### 1a. One scratch: groove profile and normals (§3.2)

Across a scratch (local coordinate `x`), the carved surface follows
`h(x) = -(w/2) log(1 - 4x²/w²) - d`, clipped by the board surface at `|x| = x_max`,
`x_max = (w/2) sqrt(1 - exp(-2d/w))`. The normal depends on `u = x/w` only,
`n(u) = (-4u, 0, 1 - 4u²) / (1 + 4u²)`: it tilts across the scratch and never along it. So a scratch
is a strip of mirrors covering a *fan* of normals in the plane across it; the depth `d` decides how
far the fan reaches (the steepest wall), the width `w` how wide the groove is.
"""),
    code(r"""
w = 1e-4                                       # profile width (m); the paper's default w = d = 1e-4
fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 3.8), width_ratios=(1, 1.5))
for ratio in (2.0, 1.0, 0.5, 0.25):             # deepest first, so the shallower ones draw on top
    d = ratio * w
    xm = float(ndf.groove_half_width(w, d))   # where the profile meets the board surface
    x = jnp.linspace(-1.2 * xm, 1.2 * xm, 400)
    (line,) = ax0.plot(1e6 * x, 1e6 * ndf.height_profile(x, w, d), label=f"d/w = {ratio}")
    xs = jnp.linspace(-0.9 * xm, 0.9 * xm, 7)
    n = ndf.normal(xs, w)                      # (7, 3): (across, along, up)
    ax0.quiver(1e6 * xs, 1e6 * ndf.height_profile(xs, w, d), n[:, 0], n[:, 2], color=line.get_color(),
               angles="xy", scale=8, width=0.006)
    xi = jnp.linspace(-xm, xm, 200)
    tilt_deg = jnp.degrees(jnp.arctan2(-ndf.normal(xi, w)[:, 0], ndf.normal(xi, w)[:, 2]))
    ax1.plot(xi / w, tilt_deg, color=line.get_color(), lw=2, label=f"d/w = {ratio}: x_max = {xm / w:.3f} w")
    ax1.plot(xi[jnp.array([0, -1])] / w, tilt_deg[jnp.array([0, -1])], "o", color=line.get_color())
ax1.legend(fontsize=8)
ax0.set(xlabel="x across the scratch (µm)", ylabel="height (µm)", aspect="equal",
        title="profile h(x) and normals")
ax0.legend(fontsize=8, loc="lower right")
ax1.set(xlabel="u = x / w", ylabel="normal tilt across the scratch (deg)",
        title="the fan of normals ends at ±x_max")
plt.tight_layout()
"""),
    md(r"""
### 1b. The point NDF (§3.3, Eq. 6-7)

Each point of the groove is itself a slightly rough surface: a GGX lobe of roughness `alpha` around
the local normal `n(x)`. For a half vector `h` (the direction halfway between the light and the
camera) the point NDF is `D_x(h, n(x)) = chi+(n·h) alpha² / (pi ((n·h)²(alpha² - 1) + 1)²)`.
Left: as `h` tilts across the scratch, the glint walks along the wall (only the strip whose normal
is near `h` lights up; `chi+` removes the wall facing away). Right: tilting `h` *along* the scratch
dims every point, because no groove normal leans that way: a scratch lights up only when it runs
roughly perpendicular to the half vector's horizontal part.
"""),
    code(r"""
alpha, d = 0.04, 1e-4
xm = float(ndf.groove_half_width(w, d))
xg = jnp.linspace(-xm, xm, 400)
tilt = jnp.radians(jnp.linspace(-60.0, 60.0, 241))
h_across = jnp.stack([jnp.sin(tilt), jnp.zeros_like(tilt), jnp.cos(tilt)], -1)   # local (x, y, z)
Dx = ndf.point_ndf(h_across[:, None, :], xg[None, :], w, alpha)                   # (241, 400)

fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 3.6))
im = ax0.imshow(np.maximum(Dx, 1e-2), extent=[-xm / w, xm / w, -60, 60], origin="lower",
                aspect="auto", norm=LogNorm(1e-2, 1 / (math.pi * alpha**2)), cmap="magma")
fig.colorbar(im, ax=ax0, label="D_x (1/sr)")
ax0.set(xlabel="u = x / w", ylabel="tilt of h across the scratch (deg)", title="where the groove glints")
for along in (0, 5, 10, 20):
    a = math.radians(along)
    h = jnp.array([math.sin(0.3) * math.cos(a), math.sin(a), math.cos(0.3) * math.cos(a)])
    ax1.semilogy(xg / w, jnp.maximum(ndf.point_ndf(h, xg, w, alpha), 1e-3), label=f"{along} deg along")
ax1.set(xlabel="u = x / w", ylabel="D_x (1/sr)", ylim=(1e-3, 300),
        title="h tilted 0.3 rad across, then along the scratch")
ax1.legend(fontsize=8)
plt.tight_layout()
"""),
    md(r"""
### 1c. One pixel and one scratch: the pair integral (§3.3, Eq. 8-10)

A pixel's footprint `F` on the board sees `D_hat = ∫∫_{F ∩ groove} D_x dx dy` from each scratch it
overlaps, and the covered area `A`. The paper turns the area integral into a boundary integral
(Green's theorem) with a closed-form antiderivative, so it is exact, cheap and differentiable;
`ndf.pair_integral(h, footprint, p0, p1, width, depth, alpha)` returns `(D_hat, A)` (m²) and
`jax.vmap` makes it a batch. Below a square footprint `3 x_max` wide slides across a scratch.
Dividing by the footprint area gives the pixel's share: its NDF contribution `D_hat / S_P` (1/sr)
and coverage `A / S_P`. A brute-force sum over 200 000 points agrees with the closed form;
Gauss-Legendre quadrature (`ndf.pair_integral_quadrature`) of the same integral needs many nodes
to resolve the sharp glint (its width is about `alpha` in `u`) that the closed form gets exactly.
"""),
    code(r"""
p0, p1 = jnp.array([0.0, 0.0]), jnp.array([0.0, 0.01])   # a 1 cm scratch along board +y
side = 3 * xm
square = side / 2 * jnp.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])   # CCW quad
offsets = jnp.linspace(-2.5 * xm, 2.5 * xm, 301)
footprints = square[None] + jnp.stack([offsets, jnp.full_like(offsets, 0.005)], -1)[:, None, :]
h = jnp.array([math.sin(0.3), 0.0, math.cos(0.3)])       # tilted 0.3 rad across the scratch

pair = jax.jit(jax.vmap(ndf.pair_integral, in_axes=(None, 0, None, None, None, None, None)))
D_hat, A = pair(h, footprints, p0, p1, w, d, alpha)

fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 3.4))
# Brute force: along the scratch the footprint lies inside it, and D_x depends on x only, so
# D_hat = side * (integral of D_x over the footprint's x-range within the groove): a fine midpoint sum.
xf = np.linspace(-xm, xm, 200_001)
D_mid = np.asarray(ndf.point_ndf(h, 0.5 * (xf[1:] + xf[:-1]), w, alpha), np.float64)
cum = np.concatenate([[0.0], np.cumsum(D_mid * np.diff(xf))])
o = np.asarray(offsets, np.float64)
D_brute = side * (np.interp(np.clip(o + side / 2, -xm, xm), xf, cum)
                  - np.interp(np.clip(o - side / 2, -xm, xm), xf, cum))
errors = {"brute-force sum": np.abs(D_brute - D_hat).max() / D_brute.max()}

ax0.plot(offsets / xm, D_hat / side**2, "k", lw=2, label="closed form")
ax0.plot(offsets / xm, D_brute / side**2, ":", color="C3", lw=2, label="brute-force sum")
for n_nodes in (64, 256):
    quad = jax.jit(jax.vmap(lambda f: ndf.pair_integral_quadrature(h, f, p0, p1, w, d, alpha, n_nodes)))
    D_q, _ = quad(footprints)
    errors[f"{n_nodes}-node quadrature"] = float(jnp.abs(D_q - D_hat).max() / D_brute.max())
    ax0.plot(offsets / xm, D_q / side**2, "--", label=f"{n_nodes}-node quadrature")
ax0.set(xlabel="footprint centre offset / x_max", ylabel="D_hat / S_P (1/sr)", title="NDF share")
ax0.legend(fontsize=8)
ax1.plot(offsets / xm, A / side**2, "k")
ax1.set(xlabel="footprint centre offset / x_max", ylabel="A / S_P", title="coverage")
plt.tight_layout()
print("max |other - closed form| / max:", {k: f"{e:.2g}" for k, e in errors.items()})
"""),
    md(r"""
## 2. Forward render: random and brushed scratches under two views (§3.3, §4.1)

A `Board` fixes the board size (default 0.3 m) and the image grid; `Scratches` holds endpoints,
width, depth and roughness per scratch; `Views` holds camera and light positions and light
intensities. `views_on_circle(M, theta)` is the paper's set-up: one light and `M` cameras at polar
angle `theta` around the board, none where the flat board would mirror the light. `render` finds
the (pixel, scratch) pairs, sums their pair integrals into each pixel's NDF
`D_P = sum_i D_hat_i / S_P`, adds the flat board over the uncovered part, shades with Smith masking
and Schlick Fresnel and returns linear radiance `(M, H, W)`; `display` applies the gamma.

The brushed board has every scratch within a few degrees of one direction, chosen perpendicular to
view 0's half vector: it glints in view 0 and stays dark in view 1. Random directions glint a
little in every view. This direction selectivity is what lets one board show several images.
"""),
    code(r"""
board = jscratch.Board(shape=(SIZE, SIZE))
views2 = jscratch.views_on_circle(2, math.radians(50), board=board)
random_scratches = jscratch.Scratches.random(jax.random.PRNGKey(SEED), N_RENDER, board)

# Brushed: same midpoints and lengths, directions within ~5 deg of the line perpendicular to the
# horizontal part of view 0's half vector at the board centre.
h0 = jscratch.half_vectors(views2, board)[0].mean(0)
brush = math.atan2(float(h0[1]), float(h0[0])) + math.pi / 2
mid = 0.5 * (random_scratches.p0 + random_scratches.p1)
half = 0.5 * jnp.linalg.norm(random_scratches.p1 - random_scratches.p0, axis=1, keepdims=True)
phi = brush + math.radians(5) * jax.random.normal(jax.random.PRNGKey(SEED + 1), (N_RENDER,))
t = jnp.stack([jnp.cos(phi), jnp.sin(phi)], -1)
size = jnp.array([board.Sx, board.Sy])
brushed = jscratch.Scratches(jnp.clip(mid - half * t, 0, size), jnp.clip(mid + half * t, 0, size))

fig, axes = plt.subplots(2, 3, figsize=(10, 6.6))
for row, (name, s) in zip(axes, [("random", random_scratches), ("brushed", brushed)]):
    img = jscratch.display(jscratch.render.render(s, views2, board))  # (2, SIZE, SIZE) display values
    draw_scratches(row[0], s.p0, s.p1, board, linewidths=0.3)
    row[0].set_title(f"{name}: {s.n} scratches (top view)")
    for j in range(2):
        row[1 + j].imshow(img[j], cmap="gray", vmin=0, vmax=float(img.max()))
        row[1 + j].set(title=f"{name}, view {j}", xticks=[], yticks=[])
plt.tight_layout()
print("cameras (m):\n", np.round(np.asarray(views2.camera), 3), "\nlight (m):", np.round(np.asarray(views2.light[0]), 3))
"""),
    md(r"""
## 3. A three-view optimisation (§3.4, §4.1)

`design(targets, views, board, config)` optimises the scratches so that view `j` shows
`targets[j]`. The loss is the paper's `E_p + lambda_g E_g` plus a small ghosting term: a blurred
L2 distance between display images (`E_p`), a distance between Gram matrices of image features
(`E_g`, texture statistics; a fixed weight-free filter bank by default, VGG-19 if you supply
weights; `lambda_g` is 20, or 60 for a dense design, at least 0.4 scratches per pixel), and
`w_x E_x`, the SSIM of each view with the other views' targets (`lambda_x = 1e-3`). Adam updates
the endpoints (in board-normalised coordinates kept on the board), one plunge per scratch (the
groove's width and depth follow from the cutter's profile: every groove can be carved) and the
log light intensity per view; `alpha` stays frozen at 0.04 as for fabrication.
Each step renders all views differentiably through the pair integrals of section 1. The targets are
three images bundled with scikit-image; `python -m jscratch.design` does the same from the shell.
"""),
    code(r"""
targets, names = jscratch.design.default_targets(3, (SIZE, SIZE))  # (3, SIZE, SIZE), in [0, 1]
views3 = jscratch.views_on_circle(3, math.radians(50), board=board)
config = jscratch.DesignConfig(n_scratches=N_DESIGN, iterations=ITERATIONS, seed=SEED)
result = jscratch.design.design(targets, views3, board, config, progress=not SMALL)
m = result.metrics
print(f"{m['iterations']} iterations in {m['time_total']:.1f} s (the step compiled in "
      f"{m['time_compile_step']:.1f} s on a second thread); intensities "
      f"{np.round(m['intensity'], 3)} W/sr")
print("SSIM per view", np.round(m["ssim"], 3), "| PSNR (dB)", np.round(m["psnr"], 2))
"""),
    code(r"""
hist = result.history
lambda_g = config.design_loss(SIZE * SIZE).lambda_g  # (60 for a dense design)
lambda_g = jscratch.loss.LAMBDA_G if lambda_g is None else lambda_g
fig, ax = plt.subplots(figsize=(5.5, 3.4))
ax.plot(hist["total"], "k", label="E = E_p + lambda_g E_g + w_x E_x")
ax.plot(hist["terms"]["E_p"], "--", label="E_p (blurred L2)")
ax.plot(lambda_g * np.asarray(hist["terms"]["E_g"]), "--", label=f"lambda_g E_g (Gram), lambda_g = {lambda_g:g}")
ax.set(xlabel="iteration", ylabel="loss", yscale="log", title="loss curve")
ax.legend(fontsize=8)
plt.tight_layout()

fig, axes = plt.subplots(2, 3, figsize=(9, 6.2))
for j in range(3):
    axes[0, j].imshow(result.targets[j], cmap="gray", vmin=0, vmax=1)
    axes[0, j].set(title=f"target {j}: {names[j].split('.')[-1]}", xticks=[], yticks=[])
    axes[1, j].imshow(result.display[j], cmap="gray", vmin=0, vmax=1)
    axes[1, j].set(title=f"render, view {j} (SSIM {m['ssim'][j]:.2f})", xticks=[], yticks=[])
plt.tight_layout()
"""),
    md(r"""
## 4. The discard step (§4.1, Fig. 21)

After the optimisation many scratches contribute little to any view. `design` scores each scratch
by its largest share of a view's scratch radiance and drops the lowest-scoring ones, as many as
keep the loss within `1 + discard_tol` (default 1 %) of the loss with every scratch: fewer
scratches to carve, no visible change. `result.keep` marks the survivors, `result.params` still
holds all `N` scratches and `result.scratches` the kept ones. (At toy sizes and few iterations the
step can drop far more than the paper's ~26 %: many scratches have not found a role yet.)
"""),
    code(r"""
all_scratches = result.params.scratches()                     # all N, before the discard
before = jscratch.display(jscratch.render.render(all_scratches, result.views, board))
after = result.display
print(f"kept {m['kept']} of {N_DESIGN} scratches ({m['discarded']} dropped); loss "
      f"{m['loss_before_discard']:.5g} -> {m['loss']:.5g}")
print("SSIM before", np.round(m["metrics_before_discard"]["ssim"], 3), "after", np.round(m["ssim"], 3))

keep = np.asarray(result.keep)
fig, axes = plt.subplots(1, 4, figsize=(13, 3.5))
draw_scratches(axes[0], all_scratches.p0[keep], all_scratches.p1[keep], board)
draw_scratches(axes[0], all_scratches.p0[~keep], all_scratches.p1[~keep], board, colors="r")
axes[0].set_title("kept (black), dropped (red)")
vmax = float(before[0].max())
for ax, img, title in [(axes[1], before[0], "view 0, all scratches"), (axes[2], after[0], "view 0, kept only")]:
    ax.imshow(img, cmap="gray", vmin=0, vmax=vmax)
    ax.set(title=title, xticks=[], yticks=[])
im = axes[3].imshow(np.abs(np.asarray(before[0]) - after[0]), cmap="viridis")
axes[3].set(title="|difference|", xticks=[], yticks=[])
fig.colorbar(im, ax=axes[3])
plt.tight_layout()
"""),
    md(r"""
## 5. Fabrication dry run (§5)

`save_result` writes a design run's folder: `design.npz` (the kept scratches, board and views, the
machine profile the grooves were designed for and each groove's plunge depth), the renders,
`metrics.json` and `config.json`; `load_design` checks the file and names any bad scratch.
`fabricate.make_program` orders the scratches to shorten the travel between them, cuts each groove
at its recorded plunge with the recorded ball-end cutter (`machine_for_design`) and writes GRBL 1.1
G-code in millimetres with a line map (which G-code line carves which scratch); `write_preview`
draws the toolpath. Nothing talks to a machine unless you stream the file to a serial port. From
the shell: `python -m jscratch.fabricate RUN_DIR --dry-run`.
"""),
    code(r"""
backend = plt.get_backend()
jscratch.design.save_result(result, OUT / "run")
design_file = designfile.load_design(OUT / "run" / "design.npz")
machine = fabricate.machine_for_design(design_file, None, {})  # the profile it was designed for
program = fabricate.make_program(design_file, machine, time_limit=10.0)
fabricate.write_program(program, OUT / "design.gcode")
fabricate.write_preview(program, OUT / "preview.png", 1000 * design_file.board)
print(fabricate.summarize(program.info))
print("\nfirst lines of", OUT / "design.gcode")
print("\n".join(program.lines[:9]))
display(Image(filename=str(OUT / "preview.png"), width=460))
"""),
    md(r"""
## Sanity checks

The test suite runs this notebook top to bottom; these checks make it fail loudly if a stage
silently breaks.
"""),
    code(r"""
assert errors["brute-force sum"] < 1e-3, errors               # closed form = brute force
assert abs(float(A.max()) - 2 * xm * side) < 1e-3 * 2 * xm * side   # full overlap: area = groove width x side
assert np.isfinite(result.display).all() and np.isfinite(np.asarray(before)).all()
assert hist["total"][-1] < hist["total"][0], hist["total"]   # the optimisation made progress
assert m["loss"] <= m["loss_before_discard"] * (1 + config.discard_tol) * (1 + 1e-5)
assert m["kept"] + m["discarded"] == N_DESIGN == keep.size
assert program.info["scratches"] == design_file.n == m["kept"]
assert program.info["fit"]["unreachable"] == 0                # every groove as designed
assert plt.get_backend() == backend                           # saving left the backend alone
print("all checks passed")
"""),
    md(r"""
**Next:** `python -m jscratch.design --help` runs full-size designs from your own images (with
checkpoints and resume); `python -m jscratch.fabricate --help` streams G-code to a GRBL carver with
a crash-safe journal.
"""),
]


def build() -> nbformat.NotebookNode:
    nb = new_notebook(cells=CELLS)
    nb.metadata["kernelspec"] = {"display_name": "Python 3", "language": "python", "name": "python3"}
    nb.metadata["language_info"] = {"name": "python"}
    # Stable cell ids so that regenerating gives byte-identical files.
    for i, cell in enumerate(nb.cells):
        cell["id"] = f"cell-{i:02d}"
    nbformat.validate(nb)
    return nb


def render_text(nb: nbformat.NotebookNode) -> str:
    return nbformat.writes(nb) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="compare with the committed notebook, write nothing")
    args = p.parse_args(argv)
    text = render_text(build())
    if args.check:
        same = PATH.exists() and PATH.read_text(encoding="utf-8") == text
        print(f"{PATH}: {'up to date' if same else 'differs from the generator'}")
        return 0 if same else 1
    PATH.write_text(text, encoding="utf-8")
    print(f"wrote {PATH}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Multi-view scratch design: optimise scratches and light intensities so that the board shows each
target image from its view (paper sections 3.4 and 4.1, docs/model.md §6).

**Library:** `design(targets, views=None, board=None, config=None, *, checkpoint=None, ...)
-> DesignResult`.
**Command line:** ``python -m jscratch.design [TARGET ...] [options]`` (``--help`` lists every
option; with no targets it uses three images bundled with scikit-image).

**Parameters** (`DesignParams`, an equinox module) live in unconstrained coordinates:

- endpoints: ``p = S * sigmoid(4 z)`` per coordinate (``S`` the board size), i.e. board-normalised
  ``u = p / S`` through a sigmoid of unit slope at the centre, so an Adam step of ``lr`` moves an
  endpoint by at most about ``lr`` board widths and never off the board. The ablation
  parameterisation ``"midpoint"`` uses the midpoint (same map), the direction angle (rad) and the
  log length (log m); its endpoints are clipped to the board.
- ``log width``, ``log depth`` (log m), ``logit alpha``, ``log intensity`` (log W/sr).

Each group (``"endpoints"``, ``"width"``, ``"depth"``, ``"alpha"``, ``"intensity"``) has its own
learning rate and can be frozen (the paper freezes ``alpha = 0.04`` for fabrication; so does our
default). The optimiser is optax's Adam (``optax.scale_by_adam``) followed by a per-group scale
``-lr_g``; a frozen group gets a zero gradient and a zero step.

**Light intensities** start in closed form: with ``R_j`` the view-``j`` radiance at ``I_j = 1``,
``I_j = (mean(T_j) / mean(display(R_j)))^2.2``, which makes the mean display value equal the
target's mean wherever the render is above the display knee (``display`` is a pure power there).

**Each iteration** (one jitted step): the pair lists (`bvh.PairLists`, from `bvh.allocate_lists`)
are culled for the current parameters (`bvh.update_lists`) and rendered: unculled, the shared list
serves every view; with ``cull_eps > 0`` each view's list is culled with `bvh.cull` (pairs whose
NDF bound is below ``cull_eps`` of their possible maximum) and compacted to a per-view capacity,
and with ``coverage_eps > 0`` the coverage pass keeps only the pairs `bvh.cull_coverage` keeps. Both
are off by default: culling bounds the forward error but removes the small gradients that turn
unlit grooves towards a view, and Adam's per-parameter scaling makes those matter (measured on the
default run: loss 0.0136 unculled against 0.0323 at ``cull_eps = 1e-3``); a cull relative to each
pair's brightest view keeps those but raises the ghosting, since what it drops is the ghost image
itself, and an absolute one that keeps each pair's brightest view costs the first view's SSIM
from ``1e-4`` on, even culling gradients alone (docs/model.md §11, `benchmarks/RESULTS.md`).
With ``skip_eps > 0`` the step keeps the shared list and the kernel skips the pair-views
`cull.view_keep` drops (below ``skip_eps`` of their peak, never a pair's brightest view): the
first cull that saves time (6 % of a default step at ``5e-5``; the jnp path evaluates and zeroes
them, saving nothing). It is off by default because the designs come out slightly worse, by
amounts that only seeds paired resolve (one seed moves by as much when a learning rate changes
by 1e-4): at ``5e-5`` over eight seeds the first view's SSIM -0.003 and the third view's
ghosting +0.004, the loss +1 % (what stopping at 94 iterations saves and costs), and at 3 views
x 60,000 (a dense design) the first view's SSIM -0.007, the loss +4 % and 9 % fewer scratches
kept (docs/model.md §11).
The renderer (`render.render_pairs`) gives radiance, `render.display` gives display values, and
the loss (`loss.make_loss`) its value and gradient; Adam updates the parameters. Inside the same jitted step `bvh.needs_rebin` says whether
the shared list still holds every pair for the new parameters and, only when it does not, the list
is rebuilt there at the same capacities (no host round trip, no recompilation); the host rebuilds
it with larger capacities when that list overflows. Capacity overflows (shared list or per-view lists:
`bvh.grow_lists`) re-allocate and recompile; they are rare (margins 1.25).

**Discard** (paper Fig. 21): after the optimisation each scratch gets a score, the largest over
views of its share of the view's scratch radiance relative to the mean scratch's
(``sum over its pairs of D_hat * shading / S_P``); scratches are dropped in increasing score order,
as many as bisection finds while the loss stays within ``(1 + discard_tol)`` of the loss with all
scratches (default ``discard_tol = 0.01``: at most 1 % higher).

**Failures** raise `DesignError` (a `jscratch.InputError`, also a `ValueError`) for bad input
(targets, views, config), `jscratch.DesignFileError` for an unreadable checkpoint, and
`NonFiniteError` (also a `RuntimeError`) when the loss, a gradient or an updated parameter becomes NaN or
infinite: the message names the iteration, the parameter group and the first bad scratch or view,
and the last good state stays in the checkpoint. All are `jscratch.JscratchError`s.

**Modules** (one way: config <- params <- solver <- discard <- run <- cli):

- `jscratch.design.config`: `DesignConfig`, `GROUPS`, `NonFiniteError`.
- `jscratch.design.params`: `DesignParams`, `group_tree`.
- `jscratch.design.solver`: the jitted step (`Context`, `view_lists`, `evaluate`, `step`, ...).
- `jscratch.design.carvable`: carvable grooves (one plunge per scratch in the machine's range,
  mapped to the groove profile); `jscratch.design.prune`: prune/re-seed rounds (on by default).
- `jscratch.design.discard`, `jscratch.design.checkpoint`, `jscratch.design.result`.
- `jscratch.design.io`: targets, images and outputs; `jscratch.design.maker`: the machine's
  outputs (as-carved render, carving estimate); `jscratch.design.run`: `design` and its seams
  (`setup`, `pair_lists`, `rebin`, `initial_state`: what tests and notebooks drive a step
  through);
  `jscratch.design.cli`: the command line (``python -m jscratch.design``).
"""

from jscratch.design.cli import main as main
from jscratch.design.config import (
    DEFAULT_IMAGES as DEFAULT_IMAGES,
    GROUPS as GROUPS,
    PARAMETERISATIONS as PARAMETERISATIONS,
    DesignConfig as DesignConfig,
    NonFiniteError as NonFiniteError,
    SceneConfig as SceneConfig,
)
from jscratch.design.io import (
    default_targets as default_targets,
    load_result as load_result,
    load_scene as load_scene,
    load_target as load_target,
    save_result as save_result,
)
from jscratch.design.params import DesignParams as DesignParams
from jscratch.design.result import DesignResult as DesignResult
from jscratch.design.run import design as design
from jscratch.designfile import DesignError as DesignError

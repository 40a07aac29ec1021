"""The command line: ``python -m jscratch.design [TARGET ...] [options]``."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
from collections.abc import Sequence

import jax
import numpy as np

from jscratch import loss as loss_mod
from jscratch import native
from jscratch.designfile import DesignError
from jscratch.scene import Board, views_on_circle
from jscratch.design.config import DEFAULT_IMAGES, DesignConfig, GROUPS, NonFiniteError, PARAMETERISATIONS
from jscratch.design.io import default_targets, load_target, write_outputs
from jscratch.design.run import design


def _parser() -> argparse.ArgumentParser:
    d = DesignConfig()
    p = argparse.ArgumentParser(
        prog="python -m jscratch.design",
        description="Optimise a scratch design so that a board shows one target image per view "
                    "(Shen et al. 2023). With no TARGET it uses skimage.data images "
                    f"({', '.join(DEFAULT_IMAGES)}).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("targets", nargs="*", metavar="TARGET",
                   help="target image files, one per view (grayscale or RGB; same aspect as the board)")
    p.add_argument("--views", type=int, default=None,
                   help="number of views M (default: number of targets, or 3)")
    p.add_argument("--theta-deg", type=float, default=50.0,
                   help="polar angle of the light and cameras from the board normal (degrees)")
    p.add_argument("--camera-theta-deg", type=float, default=None,
                   help="polar angle of the cameras (degrees; default --theta-deg)")
    p.add_argument("--distance", type=float, default=1.0, help="distance of light and cameras from the board centre (m)")
    p.add_argument("--offset-deg", type=float, default=None,
                   help="azimuth of camera 0 relative to the light (degrees; default keeps cameras away from the light's mirror direction)")
    p.add_argument("--board", type=float, default=0.3, help="board side (m), square board")
    p.add_argument("--size", type=int, default=256, help="image size (pixels per side)")
    p.add_argument("--scratches", type=int, default=d.n_scratches, help="number of scratches")
    p.add_argument("--iterations", type=int, default=None,
                   help=f"Adam iterations (default {d.iterations}; with --resume, the saved value)")
    p.add_argument("--loss", choices=loss_mod.LOSS_KINDS, default=d.loss.kind, help="loss")
    p.add_argument("--lambda-p", type=float, default=1.0, help="weight of E_p (or of L2)")
    p.add_argument("--lambda-g", type=float, default=None,
                   help=f"weight of E_g (default {loss_mod.LAMBDA_G} for the filter bank)")
    p.add_argument("--vgg-weights", default=None, help="local VGG-19 .npz for E_g (scripts/convert_vgg19.py)")
    p.add_argument("--freeze", default=",".join(d.freeze),
                   help=f"comma-separated groups not optimised, from {','.join(GROUPS)}; 'none' for none")
    for g in GROUPS:
        p.add_argument(f"--lr-{g}", type=float, default=getattr(d, f"lr_{g}"),
                       help=f"learning rate of {g}")
    p.add_argument("--parameterisation", choices=PARAMETERISATIONS, default=d.parameterisation,
                   help="scratch position parameters")
    p.add_argument("--init-width", type=float, default=d.init_width, help="initial width w (m)")
    p.add_argument("--init-depth", type=float, default=d.init_depth, help="initial depth d (m)")
    p.add_argument("--init-alpha", type=float, default=d.init_alpha, help="initial roughness alpha")
    p.add_argument("--cull-eps", type=float, default=d.cull_eps, help="per-view pair culling tolerance (0: none, default; 1e-3 is ~2x faster but optimises worse)")
    p.add_argument("--coverage-eps", type=float, default=d.coverage_eps,
                   help="coverage-pass culling tolerance (0: none; faster but can lose contrast in dark regions)")
    p.add_argument("--no-discard", action="store_true", help="skip the discard step")
    p.add_argument("--discard-tol", type=float, default=d.discard_tol,
                   help="discard: allowed relative loss increase")
    p.add_argument("--seed", type=int, default=0, help="seed of the initial layout")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32", help="working precision")
    p.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every,
                   help="iterations between checkpoints")
    p.add_argument("--out", default="design_out", help="output folder")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/checkpoint.npz with OUT/config.json (other options ignored except --iterations, --quiet)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    p.add_argument("--machine", default=None,
                   help="machine profile TOML (python -m jscratch.machine prints the default, the paper's "
                        "ball-end cutter); recorded in design.npz for python -m jscratch.fabricate")
    p.add_argument("--groove", choices=("carvable", "free"), default="carvable",
                   help="carvable: one plunge per scratch within the machine's range, mapped to the "
                        "groove profile (every groove cuttable); free: width and depth optimised freely "
                        "(before issue 15)")
    p.add_argument("--as-carved-samples", type=int, default=0,
                   help="strata per pixel side of the brute-force 'as carved' render, the design with the "
                        "ball's real arc (0: skip it, the default, so the main job stays fast; 32 is what "
                        "the maker's path uses: ~35-50 s more at 256 px, 20k scratches; 8 is too noisy to "
                        "judge, see benchmarks/RESULTS.md)")
    # issue 17: quality per scratch
    p.add_argument("--lambda-x", type=float, default=d.loss.lambda_x,
                   help="weight of the cross-view ghosting term E_x (sum over view pairs of the SSIM "
                        "of a render with another view's target, beyond --ghost-baseline; 0: off)")
    p.add_argument("--ghost-baseline", choices=("targets", "zero"), default=d.loss.ghost_baseline,
                   help="E_x penalises the cross-view SSIM beyond the targets' own (targets) or all of "
                        "it (zero: the SPEC-7 ghosting itself)")
    p.add_argument("--prune-every", type=int, default=d.prune_every,
                   help="iterations between prune/re-seed rounds that move the least useful "
                        "scratches to where a view is too dark (0: never)")
    p.add_argument("--prune-fraction", type=float, default=d.prune_fraction,
                   help="fraction of the scratches moved per prune/re-seed round")
    p.add_argument("--prune-until", type=float, default=d.prune_until,
                   help="last prune/re-seed round at this fraction of the iterations")
    p.add_argument("--target-ssim", type=float, default=d.target_ssim,
                   help="ask for a quality, get the fewest scratches: instead of the discard, keep the "
                        "fewest scratches whose mean SSIM over the views (SPEC section 7, 0-1) stays at "
                        "least this (all are kept if the full design is below it; metrics.json "
                        "'target' has the search); default: the discard's loss tolerance decides")
    p.add_argument("--lr-schedule", choices=("constant", "cosine"), default=d.lr_schedule,
                   help="learning rates constant (paper) or cosine-decayed to --lr-final of their "
                        "values over the iterations")
    p.add_argument("--lr-final", type=float, default=d.lr_final,
                   help="cosine schedule: final learning rates as a fraction of the initial ones (0-1)")
    return p


def _run_cli(args) -> int:
    native.prepare()  # the native kernel builds (first run only) while the inputs load
    out = args.out
    cfg_path = os.path.join(out, "config.json")
    if args.resume:
        if not os.path.isfile(cfg_path):
            raise DesignError(f"--resume: no {cfg_path!r} (run without --resume first)")
        with open(cfg_path) as f:
            saved = json.load(f)
        cli = saved["cli"]
        config = DesignConfig.from_dict(saved["design"])
        if args.iterations is not None:
            config = dataclasses.replace(config, iterations=args.iterations)
    else:
        cli = {k: getattr(args, k) for k in ("targets", "views", "theta_deg", "camera_theta_deg",
                                              "distance", "offset_deg", "board", "size")}
        freeze = () if args.freeze.strip().lower() in ("", "none") else tuple(
            g.strip() for g in args.freeze.split(","))
        config = DesignConfig(
            n_scratches=args.scratches,
            iterations=100 if args.iterations is None else args.iterations,
            seed=args.seed, parameterisation=args.parameterisation,
            init_width=args.init_width, init_depth=args.init_depth, init_alpha=args.init_alpha,
            freeze=freeze, cull_eps=args.cull_eps, coverage_eps=args.coverage_eps,
            discard=not args.no_discard,
            discard_tol=args.discard_tol, checkpoint_every=args.checkpoint_every, dtype=args.dtype,
            loss=loss_mod.LossConfig(kind=args.loss, lambda_p=args.lambda_p, lambda_g=args.lambda_g,
                                     vgg_weights=args.vgg_weights),
            **{f"lr_{g}": getattr(args, f"lr_{g}") for g in GROUPS},
            groove=args.groove, machine=_machine_dict(args.machine))
        config = dataclasses.replace(  # issue 17's options
            config, prune_every=args.prune_every, prune_fraction=args.prune_fraction,
            prune_until=args.prune_until, target_ssim=args.target_ssim,
            lr_schedule=args.lr_schedule, lr_final=args.lr_final,
            loss=dataclasses.replace(config.loss, lambda_x=args.lambda_x,
                                     ghost_baseline=args.ghost_baseline))
    if config.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    size = int(cli["size"])
    if size < 16:
        raise DesignError(f"--size must be at least 16 px, got {size}")
    shape = (size, size)
    if cli["targets"]:
        m = len(cli["targets"]) if cli["views"] is None else cli["views"]
        if m != len(cli["targets"]):
            raise DesignError(f"got {len(cli['targets'])} target images for --views {m}: give one per view")
        targets = np.stack([load_target(t, shape) for t in cli["targets"]])
        names = list(cli["targets"])
    else:
        m = 3 if cli["views"] is None else cli["views"]
        if m < 1:
            raise DesignError(f"--views must be >= 1, got {m}")
        targets, names = default_targets(m, shape)
    board = Board(shape=shape, Sx=cli["board"], Sy=cli["board"])
    ct = cli["camera_theta_deg"]
    try:
        views = views_on_circle(
            m, math.radians(cli["theta_deg"]), cli["distance"],
            None if cli["offset_deg"] is None else math.radians(cli["offset_deg"]), board,
            camera_theta=None if ct is None else math.radians(ct))
    except ValueError as e:
        raise DesignError(f"impossible view set-up: {e}") from None
    os.makedirs(out, exist_ok=True)
    if not args.resume:
        with open(cfg_path, "w") as f:
            json.dump({"design": config.to_dict(), "cli": cli, "targets": names}, f, indent=2)
    result = design(targets, views, board, config, checkpoint=os.path.join(out, "checkpoint.npz"),
                    resume=args.resume, progress=not args.quiet)
    write_outputs(result, out, {"cli": cli, "targets": names})
    from jscratch.design.maker import write_maker_outputs

    maker = write_maker_outputs(result, out, config.machine_profile(),
                                as_carved_samples=args.as_carved_samples)
    if not args.quiet:
        mt = result.metrics
        print(f"wrote {out}: {mt['kept']} scratches ({mt['discarded']} discarded), loss "
              f"{mt['loss']:.5g}, SSIM {[round(x, 3) for x in mt['ssim']]}, PSNR "
              f"{[round(x, 2) for x in mt['psnr']]} dB, {mt['time_total']:.1f} s")
        if "target" in mt:
            tg = mt["target"]
            print(f"target mean SSIM {tg['ssim']:.3f}: " + (
                f"reached with {mt['kept']} scratches (mean SSIM {tg['mean_ssim']:.3f})"
                if tg["reached"] else f"not reached (full design: {tg['mean_ssim']:.3f})"))
        ac, cv = maker.get("as_carved"), maker["carving"]
        print(f"machine {config.machine_profile().name!r}, {maker['groove']} grooves: "
              + (f"as-carved SSIM {[round(x, 3) for x in ac['ssim']]}, " if ac else "")
              + f"carving ~{cv['estimated_hours']:.2f} h")
    return 0


def _machine_dict(path):
    """The profile in TOML file `path` as a dict (None: the shipped default)."""
    if path is None:
        return None
    from jscratch.machine import MachineProfile

    return MachineProfile.from_toml(path).to_dict()


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point; returns the exit status (0 ok, 2 bad input, 3 non-finite)."""
    args = _parser().parse_args(argv)
    try:
        return _run_cli(args)
    except (ValueError, FileNotFoundError) as e:  # DesignError, and config errors (LossConfig)
        print(f"error: {e}", file=sys.stderr)
        return 2
    except NonFiniteError as e:
        print(f"error: {e}", file=sys.stderr)
        return 3

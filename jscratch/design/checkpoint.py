"""Checkpoints: the loop `State` and its save/load (bitwise resume)."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import tempfile
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jscratch import bvh
from jscratch.designfile import DesignError
from jscratch.errors import DesignFileError, error_line
from jscratch.design.config import DesignConfig
from jscratch.design.params import DesignParams


def _umask() -> int:
    """The process's umask, read without changing it where Linux says it (another thread may be
    creating files meanwhile)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def save_npz(path: str, arrays: dict[str, np.ndarray]) -> None:
    """Write `arrays` to `path` through a temporary file beside it (a kill part-way leaves the
    file as it was); an `OSError` names `path`."""
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=".ckpt-", suffix=".npz.tmp", dir=directory)
        os.fchmod(fd, 0o666 & ~_umask())  # as `open` makes files (mkstemp's: the owner's alone)
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)
    except BaseException as e:
        try:
            if tmp is not None and os.path.exists(tmp):
                os.unlink(tmp)
        except OSError:  # (a folder made read-only: the error below says why)
            pass
        if isinstance(e, OSError) and e.strerror:  # named by the file meant, not the temporary
            raise OSError(e.errno, e.strerror, path) from None
        raise


def _fields(module_type) -> tuple[str, ...]:
    """The field names of an equinox Module (a dataclass): what a checkpoint saves of it, so a
    field added to `bvh.Pairs` or `bvh.GridSpec` is saved without a list to keep in step. (Of a
    `bvh.PairLists` the shared list, its spec and the capacities are saved: the per-view lists
    are recomputed by every step.)"""
    return tuple(f.name for f in dataclasses.fields(module_type))


@dataclasses.dataclass
class State:
    """Everything the loop carries between iterations (what a checkpoint holds)."""

    iteration: int
    params: DesignParams
    opt_state: Any
    lists: bvh.PairLists
    history: dict[str, Any]
    rebins: int


#: Config fields a resumed run may change: the total of iterations to reach and what happens
#: after the loop or beside it; every other field must equal the checkpoint's.
RESUMABLE = ("iterations", "checkpoint_every", "discard", "discard_tol", "target_ssim")


def _first_difference(saved, given, path=""):
    """The first key path where two config dicts differ, with both values, or None."""
    if isinstance(saved, dict) and isinstance(given, dict):
        for k in sorted(set(saved) | set(given)):
            d = _first_difference(saved.get(k), given.get(k), f"{path}.{k}" if path else k)
            if d is not None:
                return d
        return None
    return None if saved == given else (path, saved, given)


def save_checkpoint(path: str, state: State, config: DesignConfig, inputs: dict) -> None:
    arrays: dict[str, np.ndarray] = {}
    for i, leaf in enumerate(jax.tree_util.tree_leaves(state.params)):
        arrays[f"params/{i}"] = np.asarray(leaf)
    for i, leaf in enumerate(jax.tree_util.tree_leaves(state.opt_state)):
        arrays[f"opt/{i}"] = np.asarray(leaf)
    for f in _fields(bvh.Pairs):
        arrays[f"pairs/{f}"] = np.asarray(getattr(state.lists.shared, f))
    meta = {
        "iteration": state.iteration,
        "spec": {f: getattr(state.lists.spec, f) for f in _fields(bvh.GridSpec)},
        "caps": list(state.lists.caps),
        "n_counts": int(np.shape(state.lists.counts)[0]),
        "history": state.history,
        "rebins": state.rebins,
        "config": config.to_dict(),
        **inputs,
    }
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    save_npz(path, arrays)


def load_checkpoint(path: str, like: State, config: DesignConfig, inputs: dict,
                    raw: bytes | None = None) -> State:
    """The `State` saved at `path` (its contents `raw` when given: the bytes process 0 read, on
    a mesh of several processes), checked against this design (`like`, `config`, `inputs` from
    `jscratch.design.io.inputs_hash`): the same targets, scene and config but for `RESUMABLE`,
    and no more iterations done than `config.iterations`."""
    if raw is None and not os.path.isfile(path):
        raise DesignFileError(f"resume: no checkpoint at {path!r}")
    try:
        with np.load(path if raw is None else io.BytesIO(raw), allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
        meta = json.loads(bytes(data["meta"]).decode())
        absent = [k for k in ("config", "spec", "caps", "iteration", *inputs) if k not in meta]
        if absent:
            raise KeyError(f"meta lacks {absent}")
        saved = DesignConfig.from_dict(meta["config"]).to_dict()
    except Exception as exc:  # not an .npz, no or a broken "meta" record
        raise DesignFileError(f"checkpoint {path!r} is not a readable jscratch checkpoint ({error_line(exc)})") from None
    if meta["targets_hash"] != inputs["targets_hash"]:
        raise DesignError(f"checkpoint {path!r} was made for different target images")
    if meta["scene_hash"] != inputs["scene_hash"]:
        raise DesignError(f"checkpoint {path!r} was made for another scene (board, cameras, "
                          "lights or intensities)")
    given = config.to_dict()
    for k in RESUMABLE:
        saved.pop(k, None), given.pop(k, None)
    diff = _first_difference(saved, given)
    if diff is not None:
        raise DesignError(f"checkpoint {path!r} was made with {diff[0]} = {diff[1]!r}, not "
                          f"{diff[2]!r}: resume with the run's own config (its config.json)")
    if meta["iteration"] > config.iterations:
        raise DesignError(f"checkpoint {path!r} is at iteration {meta['iteration']}, past the "
                          f"{config.iterations} iterations asked for: ask for at least that many")

    def restore(tree, prefix):
        leaves, treedef = jax.tree_util.tree_flatten(tree)
        new = []
        for i, leaf in enumerate(leaves):
            a = data.get(f"{prefix}/{i}")
            if a is None or a.shape != np.shape(leaf):
                raise DesignError(f"checkpoint {path!r} does not match this design ({prefix} leaf {i})")
            # (the design step checks what it updates, not what it is given: a resumed state
            # is checked here)
            if np.issubdtype(a.dtype, np.floating) and not np.all(np.isfinite(a)):
                raise DesignFileError(f"checkpoint {path!r} holds non-finite values ({prefix} "
                                      f"leaf {i}): it is damaged")
            new.append(jnp.asarray(a, dtype=jnp.asarray(leaf).dtype))
        return jax.tree_util.tree_unflatten(treedef, new)

    params = restore(like.params, "params")
    opt_state = restore(like.opt_state, "opt")
    missing = [f for f in _fields(bvh.Pairs) if f"pairs/{f}" not in data]
    missing += [f for f in _fields(bvh.GridSpec) if f not in meta["spec"]]
    if missing:
        raise DesignFileError(f"checkpoint {path!r} lacks {', '.join(missing)}: it was written by"
                              " another version of jscratch")
    pairs = bvh.Pairs(**{f: jnp.asarray(data[f"pairs/{f}"]) for f in _fields(bvh.Pairs)})
    # (JSON turns tuples into lists; the spec is static and hashed by jit, so tuples again)
    try:
        spec = bvh.GridSpec(**{f: tuple(v) if isinstance(v, list) else v
                               for f, v in meta["spec"].items()})
    except (TypeError, ValueError) as exc:
        raise DesignFileError(f"checkpoint {path!r}: its pair lists' spec is damaged "
                              f"({error_line(exc)})") from None
    caps = tuple(meta["caps"])  # (the counts are the next step's: `bvh.update_lists`)
    # (as many counts as the saved lists had, so that the resumed step has the shapes the
    # uninterrupted one was compiled for)
    n_counts = int(meta.get("n_counts", len(caps)))
    lists = bvh.PairLists(pairs, spec, jnp.zeros((n_counts,), jnp.int32), caps=caps,
                          cull_eps=float(config.cull_eps),
                          coverage_eps=float(config.coverage_eps))
    return State(meta["iteration"], params, opt_state, lists, meta["history"], meta["rebins"])

"""The pair kernel as native CPU kernels (XLA FFI custom calls, `native_lit.cc` and the arc
groove's `native_arc.h`, which it includes), and the grid binning's strip and cell stage
(`native_bin.cc`, in the same library).

`jscratch.ndf` evaluates a pair with jnp (XLA's CPU backend evaluates the many gradient outputs
in separate fusions that each recompute the shared arithmetic); where this module is available,
`native_lit.cc` runs the same formulas, line by line, on XLA's intra-op thread pool. Two kernels,
each with a values-only and a reverse-pass variant:

- the whole pair (`pair_values`, `pair_vjp`, differentiable `pairs`; what `jscratch.render` runs
  per chunk): the view-independent geometry (`ndf.pair_geometry`) and its Jacobian with respect
  to ``p0, p1, width, depth`` (forward mode), then every view's lit integral over the pair's
  pieces that are not points, chained; one SIMD lane per pair. ``profile="paper"`` (default)
  integrates the paper's groove, ``profile="arc"`` a ball cutter's (`arc.arc_lit_integral`,
  the geometry of `arc.arc_groove`'s (width, depth));
- the per-view stage (`lit`, `lit_values`, `lit_partials`; what `ndf.lit_integral` calls): the
  slab, lobe, cut and piece integrals and their partials; one SIMD lane per pair-view.

Same results up to rounding (`tests/test_native.py` compares them with the jnp path in float64
and float32). A third kernel, the grid binning's strip and cell stage (`bin_cells`, what
`jscratch.grid.update` runs: one pass over scratches, strips and cells writing the pair list),
gives the same bits as its jnp path (`tests/test_grid.py`).

- `prepare(dtype=float32)`: start that dtype's build on a background thread (the design does,
  before its setup); `building(dtype)`: whether the compiler is running for it now.
- `available(dtype) -> bool`: whether the kernels can run for arrays of `dtype` here: the
  native kernel is enabled (`enabled`), the default backend is the CPU and the kernel was built
  and loaded. Otherwise jscratch uses the jnp path.
- `lit(n_gl, ua, ub, Ya, Yb, X, h, b, t, alpha)`: the lit integral, differentiable (reverse
  mode: its partials from the kernel; `ndf` calls this).
- `lit_partials(n_gl, ua, ub, Ya, Yb, X, h, b, t, alpha)`: the lit integral and its partials
  (`native_lit.cc` says which); `lit_values(...)`: the integral alone.
- `pair_values(n_gl, footprint, p0, p1, width, depth, alpha, valid, h, profile="paper") ->
  (D, A)`, `pair_vjp(..., ct_D, ct_A, profile=...)`, `pairs(..., profile)`: the whole pair;
  `pair_jacobian(..., profile=...)`: its values and Jacobians in one pass (the renderer's
  gradient on one device keeps them).
- `bin_cells(fl, ints, *, shape, ...)`: the grid binning's strip and cell stage.
- `status()`: what runs and why, a JSON-friendly dict (the design writes it to metrics.json);
  ``python -m jscratch.native [--json]`` prints it (and builds the kernel if needed).

Build. The kernels (native_lit.cc, which includes native_arc.h and native_simd.h, and
native_bin.cc) are compiled on first use with the system's C++ compiler (``$CXX``, else ``g++``,
``c++`` or ``clang++`` on ``PATH``), one library per dtype, each when a kernel of that dtype is
first asked for (the two sources side by side, then a link: about 10 s each on 2 cores; a
float32 design never builds the float64 one), into
``native_lit-<key>-f32.so`` and ``native_lit-<key>-f64.so`` in ``$JSCRATCH_CACHE`` (else
``$XDG_CACHE_HOME/jscratch`` or ``~/.cache/jscratch``). The key (`_key`)
covers everything the binary depends on: the text of the four source files, the compiler's path and
its ``--version`` output, the flags (``-march=native``), the CPU's model and features, the jaxlib
version and a hash of the XLA FFI headers under ``jax.ffi.include_dir()``. After a build the
cache's ``native_lit-*.so`` of other keys (stale) are deleted. Nothing is downloaded.

Settings, read from the environment ONCE, when this module is imported (changing them later in
the process changes nothing):

- ``JSCRATCH_NATIVE``: ``1`` (default) use the native kernel where it can be built; ``0`` always
  use the jnp path.
- ``JSCRATCH_NATIVE_THREADS``: the most threads one kernel call uses (the calling thread and XLA's
  intra-op pool, whose size also caps it); default: the CPUs this process may run on. The
  results are the same bits for any value.
- ``JSCRATCH_KEEP_MEMORY``: ``1`` (default) `keep_freed_memory` tunes glibc's allocator when a
  design runs on the CPU; ``0`` leaves it alone.

`enabled()` and `threads()` give the decisions; `override(enabled=..., threads=...)` changes them
for what is traced inside it (tests and benchmarks that compare the two paths in one process).

Fallback. Where the native kernel is enabled and the backend is the CPU but the kernel cannot be
built or loaded (no compiler, a failed build, an FFI this jaxlib lacks; a compiler that cannot be
started for a moment, on a busy or memory-short machine, is started again twice first), jscratch
runs the jnp path (a default design step about 16x slower with the arc grooves, 5x with the
fitted paper profile), and warns once per process (`NativeKernelWarning`).
Disabled, or another backend: the jnp path without a warning; `status()` says why in each case.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import functools
import hashlib
import json
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import time
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import jaxlib
import numpy as np

from jscratch.errors import InputError, error_line, shown

__all__ = ["PROFILES", "NativeKernelWarning", "available", "bin_cells", "building", "enabled",
           "keep_freed_memory", "lit",
           "lit_partials", "lit_values", "override", "pair_jacobian", "pair_values",
           "pair_vjp", "pairs", "prepare", "status", "threads"]

_SOURCE = Path(__file__).with_name("native_lit.cc")
#: The arc groove's per-view stage, included by `_SOURCE` (the key covers both).
_ARC_SOURCE = Path(__file__).with_name("native_arc.h")
#: The grid binning's strip and cell stage (`bin_cells`), compiled into the same libraries.
_BIN_SOURCE = Path(__file__).with_name("native_bin.cc")
#: The SIMD vector type and per-lane elementary functions, included by `_SOURCE`.
_SIMD_SOURCE = Path(__file__).with_name("native_simd.h")
#: The whole-pair kernels' groove profiles (docs/model.md §2, §13) -> their ``profile`` attribute.
PROFILES = {"paper": 0, "arc": 1}
#: (dtype, with partials) -> (FFI target name, symbol in the library).
_TARGETS = {(jnp.dtype(dt), partials): (f"jscratch_lit{'' if partials else '_values'}_{name}",
                                        f"JscratchLit{'' if partials else 'Values'}{name.upper()}")
            for dt, name in ((jnp.float32, "f32"), (jnp.float64, "f64"))
            for partials in (True, False)}
#: (dtype, reverse pass) -> (FFI target name, symbol) of the whole-pair kernel.
_PAIR_TARGETS = {(jnp.dtype(dt), vjp): (f"jscratch_pairs{'_vjp' if vjp else ''}_{name}",
                                        f"JscratchPairs{'Vjp' if vjp else ''}{name.upper()}")
                 for dt, name in ((jnp.float32, "f32"), (jnp.float64, "f64"))
                 for vjp in (True, False)}
#: dtype -> (FFI target name, symbol) of the whole-pair kernel's Jacobian mode.
_JAC_TARGETS = {jnp.dtype(dt): (f"jscratch_pairs_jac_{name}", f"JscratchPairsJac{name.upper()}")
                for dt, name in ((jnp.float32, "f32"), (jnp.float64, "f64"))}
#: dtype -> (FFI target name, symbol) of the grid binning's strip and cell stage.
_BIN_TARGETS = {jnp.dtype(dt): (f"jscratch_bin_{name}", f"JscratchBin{name.upper()}")
                for dt, name in ((jnp.float32, "f32"), (jnp.float64, "f64"))}
_FLAGS = ("-O3", "-march=native", "-fno-math-errno", "-ffp-contract=off", "-std=c++17", "-shared",
          "-fPIC", "-pthread", "-w")
#: The dtypes the kernels run for, one library each -> the library's name (its symbols' suffix).
_DTYPES = {jnp.dtype(jnp.float32): "f32", jnp.dtype(jnp.float64): "f64"}
#: What the jnp path costs, in the fallback warning (`benchmarks/RESULTS.md`).
FALLBACK_COST = ("the jnp path runs instead: a design step about 16x slower with the default arc "
         "grooves, 5x with groove_fit = \"height\"")

# The settings, read once (module docstring); validated on first use by `_settings`.
_ENV = {k: os.environ.get(k) for k in ("JSCRATCH_NATIVE", "JSCRATCH_NATIVE_THREADS",
                                       "JSCRATCH_KEEP_MEMORY")}
_overrides: dict = {}


class NativeKernelWarning(RuntimeWarning):
    """The native kernel was wanted (enabled, CPU backend) but cannot be built or loaded: jscratch
    runs the slower jnp path. Issued once per process."""


@functools.cache
def _settings() -> tuple[bool, int]:
    """``(enabled, threads)`` from the environment as it was at import."""
    raw = (_ENV["JSCRATCH_NATIVE"] or "1").strip()
    if raw not in ("0", "1"):
        raise InputError(f"JSCRATCH_NATIVE={raw!r}: expected 0 (the jnp path) or 1 (the native "
                         "kernel where it can be built, the default)")
    n = (_ENV["JSCRATCH_NATIVE_THREADS"] or "").strip()
    if n:
        if not n.isdigit() or int(n) < 1:
            raise InputError(f"JSCRATCH_NATIVE_THREADS={n!r}: expected a whole number >= 1")
        count = int(n)
    else:
        count = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (
            os.cpu_count() or 1)
    return raw == "1", max(1, count)


def enabled() -> bool:
    """Whether the native kernel is wanted: ``JSCRATCH_NATIVE`` (read at import) unless
    `override` says otherwise. Wanted is not available: see `available`."""
    return _overrides.get("enabled", _settings()[0])


def threads() -> int:
    """The most threads one kernel call uses: ``JSCRATCH_NATIVE_THREADS`` (read at import), else
    the CPUs this process may run on, unless `override` says otherwise."""
    return _overrides.get("threads", _settings()[1])


@contextlib.contextmanager
def override(enabled: bool | None = None, threads: int | None = None):
    """Within the ``with`` block, `enabled` / `threads` return these values (None: unchanged).
    Functions traced inside it keep the choice; those traced before keep theirs. For tests and
    benchmarks that compare the native and jnp paths, or thread counts, in one process."""
    saved = dict(_overrides)
    if enabled is not None:
        _overrides["enabled"] = bool(enabled)
    if threads is not None:
        _overrides["threads"] = max(1, int(threads))
    try:
        yield
    finally:
        _overrides.clear()
        _overrides.update(saved)


def _cache_dir() -> Path:
    root = os.environ.get("JSCRATCH_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "jscratch")
    return Path(root)


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


def _cpu() -> tuple[str, str]:
    """``(model, features)`` of this CPU (Linux ``/proc/cpuinfo``), else the processor's name."""
    try:
        with open("/proc/cpuinfo") as f:
            lines = sorted({ln.strip() for ln in f
                            if ln.startswith(("model name", "flags", "Features", "CPU part"))})
    except OSError:
        return platform.processor() or "unknown", ""
    model = next((ln.split(":", 1)[1].strip() for ln in lines if ln.startswith("model name")),
                 platform.processor() or "unknown")
    return model, "\n".join(lines)


def _compiler() -> str:
    """The C++ compiler's path: ``$CXX``, else the first of g++, c++, clang++ on ``PATH``."""
    cxx = os.environ.get("CXX")
    if cxx:
        found = shutil.which(cxx)
        if found is None:
            raise RuntimeError(f"no C++ compiler: CXX={cxx} is not an executable")
        return found
    for name in ("g++", "c++", "clang++"):
        if found := shutil.which(name):
            return found
    raise RuntimeError("no C++ compiler (CXX unset; no g++, c++ or clang++ on PATH)")


#: Why starting a process can fail for a moment on a busy or memory-short machine (the same
#: command started again succeeds): `_spawn` retries these.
_TRANSIENT_SPAWN = frozenset({errno.EAGAIN, errno.EFAULT, errno.ENOMEM, errno.EINTR})


def _spawn(start, *args, **kwargs):
    """``start(*args, **kwargs)`` (`subprocess.run` or `subprocess.Popen` of the compiler), tried
    up to three times, 0.2 s and 0.4 s apart, where starting the process fails with an error of
    `_TRANSIENT_SPAWN`; any other error, or the third, is raised."""
    for attempt in range(3):
        try:
            return start(*args, **kwargs)
        except OSError as e:
            if e.errno not in _TRANSIENT_SPAWN or attempt == 2:
                raise
            time.sleep(0.2 * (attempt + 1))
    raise AssertionError("unreachable")


def _compiler_version(cxx: str) -> str:
    """The compiler's ``--version`` output (all of it: the key's input; its first line names it)."""
    try:
        proc = _spawn(subprocess.run, [cxx, "--version"], capture_output=True, text=True,
                      timeout=60)
    except (OSError, subprocess.SubprocessError) as e:
        raise RuntimeError(f"C++ compiler {cxx} cannot be run: {error_line(e)}") from None
    if proc.returncode != 0:
        raise RuntimeError(f"C++ compiler {cxx} --version exited with {proc.returncode}")
    return proc.stdout.strip()


def _ffi_headers() -> str:
    """Hash of every file under ``jax.ffi.include_dir()`` (paths and contents)."""
    root = Path(jax.ffi.include_dir())
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def _key_parts(cxx: str) -> dict:
    """What the library depends on, as strings: the cache key's inputs (`_key`)."""
    model, features = _cpu()
    return {"source": _sha(_SOURCE.read_bytes() + b"\0" + _ARC_SOURCE.read_bytes() + b"\0"
                           + _BIN_SOURCE.read_bytes() + b"\0" + _SIMD_SOURCE.read_bytes()),
            "compiler": cxx,
            "compiler_version": _compiler_version(cxx), "flags": " ".join(_FLAGS),
            "cpu": f"{platform.machine()} {model}", "cpu_features": _sha(features.encode()),
            "jaxlib": jaxlib.__version__, "ffi_headers": _ffi_headers()}


def _key(parts: dict) -> str:
    """The cache key (16 hex digits) of `_key_parts`' dict."""
    return _sha(json.dumps(parts, sort_keys=True).encode())


def _prune(keep: Path) -> list[Path]:
    """Delete the ``native_lit-*.so`` next to `keep` whose key is not `keep`'s (stale keys; the
    other dtypes' libraries of its key stay; a process that loaded one keeps its mapping).
    Returns what was deleted; errors are ignored."""
    prefix = keep.name.rsplit("-", 1)[0] + "-"  # native_lit-<key>-
    gone = []
    for p in keep.parent.glob("native_lit-*.so"):
        if not p.name.startswith(prefix):
            with contextlib.suppress(OSError):
                p.unlink()
                gone.append(p)
    return gone


def _compile(name: str = "f32") -> dict:
    """The kernels' shared library for the dtype `name` (``"f32"`` or ``"f64"``: `_DTYPES`),
    compiled unless the cache has it for this key:
    ``{"library", "key", "covers", "compiler", "built", "seconds"}``."""
    cxx = _compiler()
    parts = _key_parts(cxx)
    key = _key(parts)
    lib = _cache_dir() / f"native_lit-{key}-{name}.so"
    info = {"library": lib, "key": key, "covers": parts, "built": False, "seconds": 0.0,
            "compiler": f"{cxx} ({parts['compiler_version'].splitlines()[0]})"}
    if lib.exists():
        return info
    t0 = time.perf_counter()
    if name in _build:  # (what `building` reports)
        _build[name]["compiling"] = True
    lib.parent.mkdir(parents=True, exist_ok=True)
    flags = [*_FLAGS, f"-DJSCRATCH_DTYPE_{name.upper()}", f"-I{jax.ffi.include_dir()}"]
    with tempfile.TemporaryDirectory(dir=lib.parent) as tmp:
        out = Path(tmp) / lib.name
        # The two sources compile side by side (a process each), then one link.
        objs = {src: Path(tmp) / f"{src.stem}.o" for src in (_SOURCE, _BIN_SOURCE)}
        procs = {src: _spawn(subprocess.Popen, [cxx, *flags, "-c", str(src), "-o", str(o)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for src, o in objs.items()}
        errors = {src: p.communicate()[1] for src, p in procs.items()}

        def check(rc, what, err):
            if rc != 0:
                last = (err.strip().splitlines() or ["?"])[-1]
                raise RuntimeError(f"{Path(cxx).name} failed on {what}: {last}")

        for src, p in procs.items():
            check(p.returncode, src.name, errors[src])
        link = _spawn(subprocess.run, [cxx, *flags, *map(str, objs.values()), "-o", str(out)],
                      capture_output=True, text=True)
        check(link.returncode, "the link of " + " and ".join(o.name for o in objs.values()),
              link.stderr)
        os.replace(out, lib)  # atomic: concurrent processes see a whole library or none
    _prune(lib)
    return info | {"built": True, "seconds": round(time.perf_counter() - t0, 1)}


def _build_and_open(name: str) -> dict:
    """`_compile(name)`, then the library opened (``"handle"``). A library deleted between the
    two (by another process's prune) is built again, once."""
    for attempt in (0, 1):
        info = _compile(name)
        try:
            return info | {"handle": ctypes.cdll.LoadLibrary(str(info["library"]))}
        except OSError:
            if attempt or info["library"].exists():
                raise
    raise AssertionError("unreachable")


#: The background builds (`prepare`), by dtype name: {"thread": ..., "info" or "error": ...}.
_build: dict = {}
_build_lock = threading.Lock()


def _on_cpu() -> bool:
    return jax.default_backend() == "cpu"


def _dtype_arg(dtype, who: str) -> jnp.dtype:
    """`dtype` as a dtype; `InputError` (one line, naming `who`) for what is not one (`available`,
    `building`, `prepare`, `status`)."""
    try:
        return jnp.dtype(dtype)
    except TypeError:
        raise InputError(f"native.{who}: `dtype` must be a dtype (float32 or float64), got "
                         f"{shown(dtype)}") from None


def prepare(dtype=jnp.float32) -> None:
    """Start building the kernels for `dtype` (float32 or float64) on a background thread (the
    compiler runs as a subprocess, so the caller's setup goes on meanwhile); `available` waits
    for it. A no-op when already started, built, disabled (`enabled`), off the CPU or for
    another dtype; `InputError` for what is not a dtype."""
    name = _DTYPES.get(_dtype_arg(dtype, "prepare"))
    if name is None or not enabled() or not _on_cpu():
        return
    _start(name)


def building(dtype=jnp.float32) -> bool:
    """Whether the compiler is running now for `dtype`'s library (a first run; a library found
    in the cache is not a build). For progress messages; starts nothing."""
    build = _build.get(_DTYPES.get(_dtype_arg(dtype, "building")))
    return bool(build and build.get("compiling") and build["thread"].is_alive())


def _start(name: str) -> None:
    """`prepare`'s build of the library `name` on its thread, once per process."""
    with _build_lock:
        if name in _build:
            return
        build = _build[name] = {}

        def work():
            try:
                build["info"] = _build_and_open(name)
            except Exception as e:  # reported by `available` (its warning) and `status`
                build["error"] = str(e) if type(e) is RuntimeError else error_line(e, 300)

        build["thread"] = threading.Thread(target=work, name=f"jscratch-native-build-{name}",
                                           daemon=True)
        build["thread"].start()


_memory: dict = {}  # `keep_freed_memory`'s outcome: {"kept": bool, "why": str}

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_MAX = -1, -2, -4


def keep_freed_memory() -> dict:
    """Ask the C allocator to keep the memory XLA frees, for the next step to reuse.

    A design step on the CPU allocates and frees the same large buffers every step (the pairs'
    Jacobians: tens of MB). glibc serves blocks above 32 MB by ``mmap`` and gives them back with
    ``munmap``, so every step faults in and zeroes those pages again (on two loaded cores, 15
    default steps took 3.9-4.0 s with this setting against 4.4-5.0 s without; in the default
    design the difference was within the noise: `benchmarks/RESULTS.md`). This sets glibc's
    ``M_MMAP_MAX`` to 0 (large blocks come from the heap), ``M_TRIM_THRESHOLD`` to 2 GiB (freed
    memory is not returned below that: mallopt takes a C int) and ``M_TOP_PAD`` to 64 MiB, for
    the whole process, from now on: its resident memory then stays at its peak.
    `jscratch.design` calls it; off the CPU it does nothing. ``JSCRATCH_KEEP_MEMORY=0`` (read at
    import) leaves the allocator alone; so does another C
    library. Returns ``{"kept": bool, "why": str}`` (also in `status`); does the work once."""
    with _load_lock:
        if _memory:
            return dict(_memory)
        raw = (_ENV["JSCRATCH_KEEP_MEMORY"] or "1").strip()
        if raw not in ("0", "1"):
            raise InputError(f"JSCRATCH_KEEP_MEMORY={raw!r}: expected 0 (leave the C allocator "
                             "alone) or 1 (keep freed memory, the default)")
        if raw == "0":
            _memory.update(kept=False, why="JSCRATCH_KEEP_MEMORY=0")
        elif not _on_cpu():
            _memory.update(kept=False, why="not on the CPU")
        elif platform.libc_ver()[0] != "glibc":
            _memory.update(kept=False, why="not glibc: the allocator is left as it is")
        else:
            libc = ctypes.CDLL(None)
            ok = all(libc.mallopt(p, v) == 1 for p, v in (
                (_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, 2**31 - 1), (_M_TOP_PAD, 1 << 26)))
            _memory.update(kept=ok, why="glibc: freed memory kept (no mmap, no trim)" if ok
                           else "glibc's mallopt refused a setting")
        return dict(_memory)


_loaded: dict = {}  # by dtype name: {"ok": bool, "why": str}, set once by `_load_once`
_warned: list = []  # the fallback's warning, once per process whatever the dtype
_load_lock = threading.Lock()


def _load(name: str) -> bool:
    with _load_lock:  # the design traces on two threads at once
        return _load_once(name)


def _targets_of(dt) -> list[tuple[str, str]]:
    """The (FFI target, symbol) pairs of the kernels for dtype `dt`."""
    return [v for table in (_TARGETS, _PAIR_TARGETS) for (d, _), v in table.items() if d == dt] + [
        _JAC_TARGETS[dt], _BIN_TARGETS[dt]]


@functools.cache
def _load_once(name: str) -> bool:
    dt = next(d for d, n in _DTYPES.items() if n == name)
    _start(name)
    build = _build[name]
    build["thread"].join()
    try:
        if "error" in build:
            raise RuntimeError(build["error"])
        handle = build["info"]["handle"]
        for target, symbol in _targets_of(dt):
            jax.ffi.register_ffi_target(target, jax.ffi.pycapsule(getattr(handle, symbol)),
                                        platform="cpu")
    except Exception as e:  # no compiler, a failed build, an FFI this jaxlib lacks: jnp path
        why = str(e) if type(e) is RuntimeError else error_line(e, 300)
        _loaded[name] = {"ok": False, "why": why}
        if not _warned:
            _warned.append(why)
            warnings.warn(f"jscratch's native kernel is off: {why}; {FALLBACK_COST} "
                          "(JSCRATCH_NATIVE=0 chooses the jnp path without this warning)",
                          NativeKernelWarning, stacklevel=4)
        return False
    info = build["info"]
    how = (f"compiled ({info['seconds']} s)" if info["built"] else "found in the cache")
    _loaded[name] = {"ok": True, "why": f"{how} and registered as an XLA FFI target"}
    return True


def _registered(dtype) -> jnp.dtype:
    """`dtype`, its kernels built and registered as FFI targets before a call to them is traced
    (a caller may have asked `available` for another dtype; `override` does not stop a direct
    call). Raises `InputError`, saying why, where they cannot be: a caller asks `available`
    first."""
    dt = jnp.dtype(dtype)
    name = _DTYPES.get(dt)
    why = ("no native kernel for " + dt.name if name is None
           else "disabled (JSCRATCH_NATIVE=0)" if not _settings()[0]
           else "the default backend is not the CPU" if not _on_cpu()
           else None if _load(name) else _loaded[name]["why"])
    if why is not None:
        raise InputError(f"jscratch's native kernel cannot run for {dt.name} here ({why}): "
                         "ask native.available(dtype) first")
    return dt


def available(dtype) -> bool:
    """Whether `lit_partials` runs for `dtype` arrays (float32 or float64) here: `enabled`, CPU
    backend, and the kernel built and loaded (building it the first time; warns once if that
    fails)."""
    name = _DTYPES.get(_dtype_arg(dtype, "available"))
    if name is None or not enabled() or not _on_cpu():
        return False
    return _load(name)


def status(dtype=jnp.float32) -> dict:
    """What runs the kernels for `dtype` arrays (float32 or float64) and why, JSON-friendly::

        {"kernel": "native" | "jnp", "why": str, "enabled": bool, "backend": str,
         "library": path or None, "key": str or None, "covers": {str: str} or None,
         "compiler": str or None, "jaxlib": str, "threads": int,
         "memory": `keep_freed_memory`'s outcome or None}

    ``library``: that dtype's; ``covers``: the key's inputs (`_key_parts`). Starts nothing; waits
    for a build. ``"jnp"`` also where nothing here has asked for that dtype's kernel yet."""
    dt = _dtype_arg(dtype, "status")
    on, backend = enabled(), jax.default_backend()
    st = {"kernel": "jnp", "why": "", "enabled": on, "backend": backend, "library": None,
          "key": None, "covers": None, "compiler": None, "jaxlib": jaxlib.__version__,
          "threads": threads(), "memory": dict(_memory) or None}
    if not on:
        return st | {"why": "disabled (JSCRATCH_NATIVE=0)"}
    if backend != "cpu":
        return st | {"why": f"the default backend is {backend}; the native kernel is CPU-only"}
    name = _DTYPES.get(dt)
    if name is None:
        return st | {"why": f"no native kernel for {dt.name}"}
    build = _build.get(name)
    if build is None:
        return st | {"why": "not asked for in this process yet (python -m jscratch.native "
                            "builds it)"}
    build["thread"].join()
    if "info" in build:
        info = build["info"]
        st.update(library=str(info["library"]), key=info["key"], covers=dict(info["covers"]),
                  compiler=info["compiler"])
    if name in _loaded:
        return st | {"kernel": "native" if _loaded[name]["ok"] else "jnp",
                     "why": _loaded[name]["why"]}
    return st | {"why": build.get("error") or "built, not used in this process yet"}


def lit_values(n_gl: int, ua, ub, Ya, Yb, X, h, b, t, alpha):
    """`lit_partials`' first output alone (the forward pass; cheaper). Needs `available` for
    its dtype (else `InputError`, saying why)."""
    dt = _registered(ua.dtype)
    call = jax.ffi.ffi_call(_TARGETS[dt, False][0], jax.ShapeDtypeStruct(X.shape, dt),
                            vmap_method="broadcast_all")
    return call(ua, ub, Ya, Yb, X, h, b, t, alpha, n_gl=int(n_gl), threads=threads())


def lit_partials(n_gl: int, ua, ub, Ya, Yb, X, h, b, t, alpha):
    """The lit integral of the pieces ``(ua, ub, Ya, Yb)`` (``(..., k)``, cut to the groove of
    half-width ``X`` in widths, ``(...)``) under the half vector ``h`` (``(..., 3)``, board frame)
    for a scratch along ``t`` and across ``b`` (``(..., 2)``) with roughness ``alpha``
    (``(...)``), and its partials: ``(lit, (d_ua, d_ub, d_Ya, d_Yb, d_X, d_h, d_b, d_t,
    d_alpha))``, shapes as the inputs. Jittable and vmappable; needs `available` for its dtype."""
    dt = _registered(ua.dtype)
    args = (ua, ub, Ya, Yb, X, h, b, t, alpha)
    out = (jax.ShapeDtypeStruct(X.shape, dt),) + tuple(jax.ShapeDtypeStruct(a.shape, dt)
                                                       for a in args)
    call = jax.ffi.ffi_call(_TARGETS[dt, True][0], out, vmap_method="broadcast_all")
    res = call(*args, n_gl=int(n_gl), threads=threads())
    return res[0], tuple(res[1:])


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def lit(n_gl: int, ua, ub, Ya, Yb, X, h, b, t, alpha):
    """`lit_values`, differentiable: its reverse pass multiplies `lit_partials`' partials by the
    cotangent (`ndf`'s `_lit_sum` reverse pass chained through the slab and the lobe parameters,
    per pair-view in one native call). Works under `jax.shard_map`. Needs `available` for its
    dtype."""
    args = (ua, ub, Ya, Yb, X, h, b, t, alpha)
    return functools.reduce(_varying_like, args, lit_values(n_gl, *args))


def _varying_like(x, like):
    """`x` marked device-varying over the mesh axes `like` varies over (inside `jax.shard_map`
    the custom call's outputs carry no such type, its inputs do)."""
    varying = lambda v: set(getattr(getattr(jax.typeof(v), "mat", None), "varying", ()) or ())
    missing = tuple(sorted(varying(like) - varying(x)))
    return jax.lax.pcast(x, missing, to="varying") if missing else x


def _lit_fwd(n_gl, ua, ub, Ya, Yb, X, h, b, t, alpha):
    args = (ua, ub, Ya, Yb, X, h, b, t, alpha)
    value, partials = lit_partials(n_gl, *args)
    value = functools.reduce(_varying_like, args, value)
    return value, tuple(_varying_like(d, a) for d, a in zip(partials, args))


def _lit_bwd(n_gl, partials, ct):
    return tuple(ct[..., None] * d if d.ndim > ct.ndim else ct * d for d in partials)


lit.defvjp(_lit_fwd, _lit_bwd)

def _profile(profile) -> int:
    """The ``profile`` attribute of a groove profile's name (`PROFILES`), else `InputError`."""
    if not isinstance(profile, str) or profile not in PROFILES:
        raise InputError(f"profile={profile!r}: expected one of {', '.join(map(repr, PROFILES))}")
    return PROFILES[profile]


def _skip_attr(skip_eps) -> np.float64:
    """The kernels' ``skip_eps`` attribute, else `InputError`."""
    if not (isinstance(skip_eps, (int, float, np.floating)) and 0 <= skip_eps <= 1):
        raise InputError(f"skip_eps must be a float in [0, 1], got {skip_eps!r}")
    return np.float64(skip_eps)


def pair_values(n_gl: int, footprint, p0, p1, width, depth, alpha, valid, h, profile="paper",
                skip_eps=0.0):
    """The whole pair integral of ``n`` pixel-scratch pairs under ``V`` views, natively:
    ``(D_hat, A)``, ``(V, n)`` and ``(n,)``, as ``ndf.lit_integral(ndf.pair_geometry(...), ...)``
    and that geometry's ``area`` give them (the geometry once per pair, every view on its pieces
    that are not points). ``footprint`` ``(n, 4, 2)``, ``p0, p1`` ``(n, 2)``, ``width, depth,
    alpha`` ``(n,)`` (m, m, m, 1), ``valid`` ``(n,)`` bool (padding slots: exact zeros), ``h``
    ``(V, n, 3)`` board-frame half vectors. Needs `available` for their dtype; works under
    `jax.shard_map`.

    ``profile`` (static) chooses the groove (docs/model.md §2, §13):

    - ``"paper"`` (default): the paper's profile of width ``w`` and depth ``d``; ``n_gl`` the
      Gauss-Legendre nodes of its smooth lobe and short pieces (`lobe.nodes`: 4 in float32, 16 in
      float64);
    - ``"arc"``: a ball cutter's groove, given as ``(width, depth) = arc.arc_groove(plunge,
      radius)`` (``width = 2R``); the same geometry, each view's ``D_hat`` that of
      `arc.arc_lit_integral`; ``n_gl`` the nodes of its rule on every piece (`arc.nodes`: 8 in
      float32, 24 in float64).

    ``skip_eps`` (static, in ``[0, 1]``): skip the pair-views `cull.view_keep` drops at this
    tolerance (bound ``rho < skip_eps`` and not the pair's brightest view): exact zeros in the
    values and in every derivative, and no work where every pair of a SIMD block skips a view.
    The kernel computes the bound itself (`cull.cull_ratio`'s, in the dtype's arithmetic: a
    pair-view within rounding of the tolerance may fall either side). ``0`` (default) skips none.
    Anything else: `InputError`."""
    dt = _registered(width.dtype)
    code = _profile(profile)
    skip = _skip_attr(skip_eps)
    args = (footprint, p0, p1, width, depth, alpha, valid, h)
    call = jax.ffi.ffi_call(_PAIR_TARGETS[dt, False][0],
                            (jax.ShapeDtypeStruct(h.shape[:-1], dt),
                             jax.ShapeDtypeStruct(width.shape, dt)))
    D, A = call(*args, n_gl=int(n_gl), profile=code, skip_eps=skip, threads=threads())
    return (functools.reduce(_varying_like, args, D), functools.reduce(_varying_like, args, A))


def pair_vjp(n_gl: int, footprint, p0, p1, width, depth, alpha, valid, h, ct_D, ct_A,
             profile="paper", skip_eps=0.0):
    """The reverse pass of `pair_values` at the cotangents ``ct_D`` ``(V, n)`` and ``ct_A``
    ``(n,)``: ``(d_p0, d_p1, d_width, d_depth, d_alpha, d_h)``, shaped as those inputs (zeros on
    padding slots; the footprint is data). The geometry's Jacobian is computed in forward mode
    (six tangents) and chained with every view's partials (`lit_partials`' formulas for the
    paper's profile, `native_arc.h`'s for the arc). ``profile``, ``skip_eps`` as in
    `pair_values`."""
    dt = _registered(width.dtype)
    code = _profile(profile)
    skip = _skip_attr(skip_eps)
    args = (footprint, p0, p1, width, depth, alpha, valid, h, ct_D, ct_A)
    out = tuple(jax.ShapeDtypeStruct(x.shape, dt) for x in (p0, p1, width, depth, alpha, h))
    call = jax.ffi.ffi_call(_PAIR_TARGETS[dt, True][0], out)
    res = call(*args, n_gl=int(n_gl), profile=code, skip_eps=skip, threads=threads())
    return tuple(functools.reduce(_varying_like, args, r) for r in res)


def pair_jacobian(n_gl: int, footprint, p0, p1, width, depth, alpha, valid, h, profile="paper",
                  skip_eps=0.0):
    """`pair_values` and the pairs' Jacobians, natively, in one pass: ``(D_hat (V, n), A (n),
    J_D (V, n, 7), J_h (V, n, 3), J_A (n, 6))``, ``J_D`` the derivatives of each view's
    ``D_hat`` with respect to ``(p0x, p0y, p1x, p1y, width, depth, alpha)``, ``J_h`` with respect
    to that view's ``h``, ``J_A`` those of ``A`` with respect to the first six (zeros on padding
    slots). `pair_vjp` at cotangents ``(ct_D, ct_A)`` is ``sum_v ct_D[v] J_D[v] + ct_A J_A`` (and
    ``ct_D[v] J_h[v]``): a reverse pass that keeps these needs no second evaluation. ``profile``,
    ``skip_eps`` as in `pair_values`."""
    dt = _registered(width.dtype)
    code = _profile(profile)
    skip = _skip_attr(skip_eps)
    args = (footprint, p0, p1, width, depth, alpha, valid, h)
    V, n = h.shape[0], width.shape[0]
    out = (jax.ShapeDtypeStruct((V, n), dt), jax.ShapeDtypeStruct((n,), dt),
           jax.ShapeDtypeStruct((V, n, 7), dt), jax.ShapeDtypeStruct((V, n, 3), dt),
           jax.ShapeDtypeStruct((n, 6), dt))
    res = jax.ffi.ffi_call(_JAC_TARGETS[dt][0], out)(*args, n_gl=int(n_gl), profile=code,
                                                      skip_eps=skip, threads=threads())
    return tuple(functools.reduce(_varying_like, args, r) for r in res)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0, 9))
def pairs(n_gl: int, footprint, p0, p1, width, depth, alpha, valid, h, profile="paper"):
    """`pair_values`, differentiable (reverse mode, by `pair_vjp`; no gradient to the
    footprint or `valid`). ``profile`` (static, positional or keyword) as in `pair_values`."""
    return pair_values(n_gl, footprint, p0, p1, width, depth, alpha, valid, h, profile)


def _pairs_fwd(n_gl, footprint, p0, p1, width, depth, alpha, valid, h, profile):
    args = (footprint, p0, p1, width, depth, alpha, valid, h)
    return pair_values(n_gl, *args, profile), args


def _pairs_bwd(n_gl, profile, args, ct):
    d0, d1, dw, dd, da, dh = pair_vjp(n_gl, *args, *ct, profile=profile)
    return jnp.zeros_like(args[0]), d0, d1, dw, dd, da, None, dh


pairs.defvjp(_pairs_fwd, _pairs_bwd)


def bin_cells(fl, ints, *, shape, strip_capacity: int, rows: int, pair_capacity: int,
              tol: float, tolg: float, csx: float, csy: float, hx: float, hy: float,
              sy: float):
    """The strip and cell stage of `jscratch.grid`'s binning, natively (`native_bin.cc`): the
    same ``(pixel, scratch, valid, overflow, stats)`` as the jnp path (``(L,)`` int32, int32,
    bool, ``()`` bool, ``(3,)`` int32 = strips needed, most cells in a strip, pairs needed;
    ``L = pair_capacity``). ``fl`` ``(N, 12)`` float32 or float64: ``tu, tv, bu, bv, mu, mv,
    half_w, half_l, cx, cy, tx, ty`` of `grid._strip_setup`; ``ints`` ``(N, 4)`` int32: ``k_lo,
    k_hi, n_strips, col_major``. ``shape`` ``(H, W)``; the capacities; the slacks ``tol``
    (metres) and ``tolg`` (grid units); the pixel pitch ``csx = Sx / W``, ``csy = Sy / H``, half
    pitch ``hx, hy`` and board height ``sy`` (metres), as Python floats (rounded to the dtype
    inside, as jnp rounds them). Jittable; under `jax.vmap` one call per batch element. Needs
    `available`."""
    dt = _registered(fl.dtype)
    L = int(pair_capacity)
    out = (jax.ShapeDtypeStruct((L,), jnp.int32), jax.ShapeDtypeStruct((L,), jnp.int32),
           jax.ShapeDtypeStruct((L,), jnp.bool_), jax.ShapeDtypeStruct((), jnp.bool_),
           jax.ShapeDtypeStruct((3,), jnp.int32))
    f64 = lambda v: np.float64(float(v))
    return jax.ffi.ffi_call(_BIN_TARGETS[dt][0], out, vmap_method="sequential")(
        fl, ints.astype(jnp.int32), h_px=int(shape[0]), w_px=int(shape[1]),
        strip_capacity=int(strip_capacity), rows=int(rows), pair_capacity=L, tol=f64(tol),
        tolg=f64(tolg), csx=f64(csx), csy=f64(csy), hx=f64(hx), hy=f64(hy), sy=f64(sy))

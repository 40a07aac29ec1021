"""The pair kernel's per-view stage as a native CPU kernel (an XLA FFI custom call).

`jscratch.ndf` evaluates a pair-view's per-view stage (slab, lobe, cut, piece integrals) and its
hand-written partial derivatives either with jnp (`ndf._view`, `lobe`, `ndf._lit_sum`: XLA's CPU
backend evaluates the many gradient outputs in separate fusions that each recompute the shared
arithmetic) or, where this module is available, with `native_lit.cc`: the same formulas, line
by line, one SIMD lane per pair-view, on all cores, in a values-only and a values + partials
variant. Same results up to rounding (`tests/test_native.py` compares the two in float64 and
float32).

- `prepare()`: start the build on a background thread (the design does, before its setup).
- `available(dtype) -> bool`: whether `lit_partials` can run for arrays of `dtype` here: the
  default backend is the CPU, the kernel compiled (once per source, with the system's C++
  compiler, cached in ``$JSCRATCH_CACHE`` or ``~/.cache/jscratch``) and ``JSCRATCH_NATIVE`` is
  not ``0``. Otherwise jscratch uses the jnp reverse pass.
- `lit(n_gl, ua, ub, Ya, Yb, X, h, b, t, alpha)`: the lit integral, differentiable (reverse
  mode: its partials from the kernel; `ndf` calls this).
- `lit_partials(n_gl, ua, ub, Ya, Yb, X, h, b, t, alpha)`: the lit integral and its partials
  (`native_lit.cc` says which); `lit_values(...)`: the integral alone.

Nothing is downloaded; a machine without a C++ compiler runs the jnp path (`status()` says why).
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import jax
import jax.numpy as jnp

__all__ = ["available", "lit_partials", "lit_values", "prepare", "status"]

_SOURCE = Path(__file__).with_name("native_lit.cc")
#: (dtype, with partials) -> (FFI target name, symbol in the library).
_TARGETS = {(jnp.dtype(dt), partials): (f"jscratch_lit{'' if partials else '_values'}_{name}",
                                        f"JscratchLit{'' if partials else 'Values'}{name.upper()}")
            for dt, name in ((jnp.float32, "f32"), (jnp.float64, "f64"))
            for partials in (True, False)}
_status = {"loaded": False, "why": "not tried"}


def _cache_dir() -> Path:
    root = os.environ.get("JSCRATCH_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "jscratch")
    return Path(root)


def _cpu_flags() -> str:
    """This CPU's model and feature flags (Linux), else the processor's name."""
    try:
        with open("/proc/cpuinfo") as f:
            lines = [ln for ln in f if ln.startswith(("model name", "flags", "Features"))]
        return "".join(sorted(set(lines)))
    except OSError:
        return platform.processor()


def _compile() -> Path:
    """The kernel's shared library, compiled once per source text and compiler flags."""
    cxx = os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++") or shutil.which(
        "clang++")
    if cxx is None:
        raise RuntimeError("no C++ compiler (g++, c++ or clang++) on PATH")
    flags = ["-O3", "-march=native", "-fno-math-errno", "-ffp-contract=off", "-std=c++17",
             "-shared", "-fPIC", "-pthread", "-w", f"-I{jax.ffi.include_dir()}"]
    src = _SOURCE.read_bytes()
    # -march=native: the library is for this CPU (a cache shared between machines keys on it).
    key = hashlib.sha256(src + " ".join([cxx, *flags, platform.machine(), _cpu_flags()])
                         .encode()).hexdigest()[:16]
    lib = _cache_dir() / f"native_lit-{key}.so"
    if lib.exists():
        return lib
    lib.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=lib.parent) as tmp:
        out = Path(tmp) / lib.name
        proc = subprocess.run([cxx, *flags, str(_SOURCE), "-o", str(out)], capture_output=True,
                              text=True)
        if proc.returncode != 0:
            last = (proc.stderr.strip().splitlines() or ["?"])[-1]
            raise RuntimeError(f"{Path(cxx).name} failed on native_lit.cc: {last}")
        os.replace(out, lib)  # atomic: concurrent processes see a whole library or none
    return lib


_build: dict = {}  # the background build (`prepare`): {"thread": ..., "lib" or "error": ...}
_build_lock = threading.Lock()


def prepare() -> None:
    """Start building the kernel on a background thread (the compiler runs as a subprocess, so
    the caller's setup goes on meanwhile); `available` waits for it. A no-op when already
    started, built, disabled (``JSCRATCH_NATIVE=0``) or off the CPU."""
    if os.environ.get("JSCRATCH_NATIVE", "1") == "0" or jax.default_backend() != "cpu":
        return
    with _build_lock:
        if _build:
            return

        def work():
            try:
                _build["lib"] = _compile()
            except Exception as e:  # reported by `available` (through `status`)
                _build["error"] = e

        _build["thread"] = threading.Thread(target=work, name="jscratch-native-build",
                                            daemon=True)
        _build["thread"].start()


_load_lock = threading.Lock()


def _load() -> bool:
    with _load_lock:  # the design traces on two threads at once
        return _load_once()


@functools.lru_cache(maxsize=None)
def _load_once() -> bool:
    try:
        prepare()
        _build["thread"].join()
        if "error" in _build:
            raise _build["error"]
        lib = ctypes.cdll.LoadLibrary(str(_build["lib"]))
        for target, symbol in _TARGETS.values():
            jax.ffi.register_ffi_target(target, jax.ffi.pycapsule(getattr(lib, symbol)),
                                        platform="cpu")
    except Exception as e:  # no compiler, a failed build, an FFI this jaxlib lacks: jnp path
        _status.update(why=f"{type(e).__name__}: {e}")
        return False
    _status.update(loaded=True, why="compiled and registered")
    return True


def status() -> dict:
    """``{"loaded": bool, "why": str}``: whether the native kernel is in use, and why not."""
    return dict(_status)


def available(dtype) -> bool:
    """Whether `lit_partials` runs for `dtype` arrays (float32 or float64, CPU backend)."""
    if (jnp.dtype(dtype), True) not in _TARGETS or jax.default_backend() != "cpu":
        return False
    if os.environ.get("JSCRATCH_NATIVE", "1") == "0":  # read when a function is traced
        return False
    return _load()


def _threads() -> int:
    n = os.environ.get("JSCRATCH_NATIVE_THREADS")
    if n:
        return max(1, int(n))
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
               else os.cpu_count() or 1)


def lit_values(n_gl: int, ua, ub, Ya, Yb, X, h, b, t, alpha):
    """`lit_partials`' first output alone (the forward pass; cheaper). Needs `available`."""
    dt = jnp.dtype(ua.dtype)
    call = jax.ffi.ffi_call(_TARGETS[dt, False][0], jax.ShapeDtypeStruct(X.shape, dt),
                            vmap_method="broadcast_all")
    return call(ua, ub, Ya, Yb, X, h, b, t, alpha, n_gl=int(n_gl), threads=_threads())


def lit_partials(n_gl: int, ua, ub, Ya, Yb, X, h, b, t, alpha):
    """The lit integral of the pieces ``(ua, ub, Ya, Yb)`` (``(..., k)``, cut to the groove of
    half-width ``X`` in widths, ``(...)``) under the half vector ``h`` (``(..., 3)``, board frame)
    for a scratch along ``t`` and across ``b`` (``(..., 2)``) with roughness ``alpha``
    (``(...)``), and its partials: ``(lit, (d_ua, d_ub, d_Ya, d_Yb, d_X, d_h, d_b, d_t,
    d_alpha))``, shapes as the inputs. Jittable and vmappable; needs `available`."""
    dt = jnp.dtype(ua.dtype)
    args = (ua, ub, Ya, Yb, X, h, b, t, alpha)
    out = (jax.ShapeDtypeStruct(X.shape, dt),) + tuple(jax.ShapeDtypeStruct(a.shape, dt)
                                                       for a in args)
    call = jax.ffi.ffi_call(_TARGETS[dt, True][0], out, vmap_method="broadcast_all")
    res = call(*args, n_gl=int(n_gl), threads=_threads())
    return res[0], tuple(res[1:])


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def lit(n_gl: int, ua, ub, Ya, Yb, X, h, b, t, alpha):
    """`lit_values`, differentiable: its reverse pass multiplies `lit_partials`' partials by the
    cotangent (`ndf`'s `_lit_sum` reverse pass chained through the slab and the lobe parameters,
    per pair-view in one native call). Works under `jax.shard_map`. Needs `available`."""
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

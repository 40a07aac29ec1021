"""The native reverse pass of the per-view pair kernel (`jscratch.native`, `native_lit.cc`)
against the jnp reverse pass it replaces (`ndf._lit_sum`, hand-written) and against float64
autodiff: equal to rounding in float64, as accurate in float32, for every piece budget, any
thread count. And the kernel as a library: its cache key covers what the binary depends on,
stale builds are pruned, the settings are read once, jscratch falls back to jnp with one warning
where the kernel cannot be built (none where it is disabled), and ``python -m jscratch.native``
describes it."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import warnings

import jax
import jax.numpy as jnp
import jaxlib
import numpy as np
import pytest

from jscratch import arc, cull, lobe, native, ndf
from jscratch.bench import ndf_cases
from jscratch.errors import InputError

needs_native = pytest.mark.skipif(not native.available(jnp.float32),
                                  reason=f"native kernel unavailable: {native.status()['why']}")


def _population():
    fams = ndf_cases.all_families()
    return ndf_cases.concat(fams.values())


def _grads(pieces, use_native: bool, threads: int | None = None, jit: bool = True):
    """``(D_hat, gradients)`` of `lit_integral(pair_geometry(...), pieces=...)`, traced with the
    native kernel on or off (a new function each call: jit traces it afresh). ``jit=False``
    evaluates op by op: the reference for the jnp path, whose XLA-fused reverse pass gives a
    different half-vector gradient on some grazing pairs than op by op (jax 0.10.1, CPU:
    -2.1e-7 against -2.7e-12; the native kernel gives the op-by-op value; see
    benchmarks/RESULTS.md, also for grazing pairs where no derivative path matches central
    differences). The choice holds while the function runs (`native.override`), so it is
    traced with it."""

    def D(h, fp, p0, p1, w, d, a):
        return ndf.lit_integral(ndf.pair_geometry(fp, p0, p1, w, d), h, a, pieces=pieces)

    f = jax.vmap(lambda *a: (D(*a), jax.grad(D, argnums=tuple(range(7)))(*a)))
    f = jax.jit(f) if jit else f

    def run(*args):
        with native.override(enabled=use_native, threads=threads):
            return f(*args)

    return run


def _assert_as_accurate_as_jnp(native_rows, jnp_rows, reference_rows):
    """Per gradient (rows: pairs), the native kernel's float32 error against the float64
    reference is finite and at most twice the jnp path's, at the median and the 99th percentile
    (each pair's error scaled by its largest reference entry)."""
    for k, (a, b, r) in enumerate(zip(native_rows, jnp_rows, reference_rows)):
        s = np.max(np.abs(r), axis=1)
        scale = s + 1e-5 * np.percentile(s, 90)
        e_nat = np.max(np.abs(a - r), axis=1) / scale
        e_jnp = np.max(np.abs(b - r), axis=1) / scale
        assert np.all(np.isfinite(a)), k
        assert np.median(e_nat) <= 2 * np.median(e_jnp) + 1e-7, (k, np.median(e_nat))
        assert np.percentile(e_nat, 99) <= 2 * np.percentile(e_jnp, 99) + 1e-4, k


def _flat(g, n):
    return [np.asarray(x, np.float64).reshape(n, -1) for x in g]


@needs_native
@pytest.mark.float64
@pytest.mark.parametrize("pieces", [2, ndf.N_COMPACT, ndf.N_PIECES])
def test_native_equals_jnp_reverse_pass_float64(pieces):
    """Every gradient of every adversarial pair, native against the jnp hand-written reverse
    pass (op by op), float64: equal to 1e-9 of each gradient's scale (they differ only in
    rounding)."""
    jax.config.update("jax_enable_x64", True)
    C = _population().astype(np.float64)
    n = C.len()
    D1, g1 = _grads(pieces, True)(*C.args())
    D0, g0 = _grads(pieces, False, jit=False)(*C.args())
    np.testing.assert_allclose(np.asarray(D1), np.asarray(D0), rtol=1e-12,
                               atol=1e-14 * np.max(np.abs(np.asarray(D0))))
    for k, (a, b) in enumerate(zip(_flat(g1, n), _flat(g0, n))):
        scale = np.max(np.abs(b), axis=1)
        tol = 1e-9 * scale + 1e-12 * np.percentile(scale, 90)
        err = np.max(np.abs(a - b), axis=1) / np.where(tol > 0, tol, 1)
        assert err.max() <= 1, (pieces, k, err.max())
        assert np.any(np.abs(b) > 0), k  # the test sees gradients


@needs_native
@pytest.mark.float64
def test_native_float32_as_accurate_as_jnp():
    """Float32 gradients against float64 at the same rounded inputs: the native kernel's error
    is that of the jnp reverse pass (median within 2x, 99th percentile within 2x + 1e-4)."""
    jax.config.update("jax_enable_x64", True)
    C = _population()
    C32, n = C.astype(np.float32), C.len()
    Dr, ref = _grads(ndf.N_PIECES, False)(*C32.astype(np.float64).args())
    Dn, g1 = _grads(ndf.N_PIECES, True)(*C32.args())
    Dj, g0 = _grads(ndf.N_PIECES, False)(*C32.args())
    # Values: the native kernel's against float64 as close as the jnp code's.
    Dr, Dn, Dj = (np.asarray(x, np.float64) for x in (Dr, Dn, Dj))
    top = np.max(np.abs(Dr))
    den = np.abs(Dr) + 1e-6 * top
    e_nat, e_jnp = np.abs(Dn - Dr) / den, np.abs(Dj - Dr) / den
    assert np.percentile(e_nat, 99) <= 2 * np.percentile(e_jnp, 99) + 1e-6, np.percentile(e_nat, 99)
    assert e_nat.max() <= 2 * e_jnp.max() + 1e-5, (e_nat.max(), e_jnp.max())
    _assert_as_accurate_as_jnp(_flat(g1, n), _flat(g0, n), _flat(ref, n))


@needs_native
def test_native_threads_give_identical_results():
    """Pair-views are independent: one thread or four (chunks claimed in any order on XLA's
    pool) give the same bits."""
    C = ndf_cases.random_cases(6000).astype(np.float32)
    one = _grads(2, True, threads=1)(*C.args())
    four = _grads(2, True, threads=4)(*C.args())
    for a, b in zip(jax.tree_util.tree_leaves(one), jax.tree_util.tree_leaves(four)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def _python(code: str, **env) -> dict:
    """Run `code` in a fresh Python (environment: this one's plus `env`); the JSON it prints."""
    out = subprocess.run([sys.executable, "-c", code], env=dict(os.environ, **env),
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


#: In a fresh process: `available` twice and a gradient through `ndf` with every warning recorded,
#: the fallback warnings, `status()`, whether changing the environment later changes anything,
#: and what ``python -m jscratch.native --json`` (`jscratch.native.__main__.main`) returns.
_FALLBACK = """
import contextlib, io, json, os, warnings
import jax, jax.numpy as jnp, numpy as np
with warnings.catch_warnings(record=True) as seen:
    warnings.simplefilter("always")
    from jscratch import native, ndf
    from jscratch.native.__main__ import main as native_main
    ok = [native.available(jnp.float32), native.available(jnp.float64)]
    g = jax.grad(lambda w: ndf.pair_integral(jnp.array([0.1, 0.0, 1.0]),
        jnp.array([[0., 0.], [1e-3, 0.], [1e-3, 1e-3], [0., 1e-3]]), jnp.array([5e-4, -1e-3]),
        jnp.array([5e-4, 2e-3]), w, 1e-4, 0.04)[0])(2.5e-4)
os.environ["JSCRATCH_NATIVE"] = "0" if native.enabled() else "1"
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    rc = native_main(["--json"])
print(json.dumps({"ok": ok, "g": float(g), "status": native.status(), "enabled": native.enabled(),
    "rc": rc, "warnings": [str(w.message) for w in seen
                           if issubclass(w.category, native.NativeKernelWarning)]}))
"""


def test_without_a_compiler_jscratch_falls_back_to_jnp_and_warns_once(tmp_path):
    """No C++ compiler (and nothing cached): `available` is False, one `NativeKernelWarning`
    says why and what it costs, `status` says "jnp" and why, the kernel's gradients come from
    the jnp reverse pass, and ``python -m jscratch.native`` exits 1."""
    r = _python(_FALLBACK, CXX=str(tmp_path / "no-such-compiler"), JSCRATCH_CACHE=str(tmp_path),
                JSCRATCH_NATIVE="1")
    assert r["ok"] == [False, False] and np.isfinite(r["g"]) and r["g"] != 0.0, r
    assert len(r["warnings"]) == 1, r["warnings"]
    assert "native kernel is off" in r["warnings"][0] and "no-such-compiler" in r["warnings"][0]
    assert native.FALLBACK_COST in r["warnings"][0] and "16x slower" in native.FALLBACK_COST
    st = r["status"]
    assert st["kernel"] == "jnp" and "no-such-compiler" in st["why"], st
    assert st["enabled"] is True and st["library"] is None and st["jaxlib"] == jaxlib.__version__
    assert r["enabled"] is True and r["rc"] == 1  # the switch was read once, at import
    assert list(tmp_path.iterdir()) == []


def test_disabled_kernel_runs_jnp_without_a_warning(tmp_path):
    """``JSCRATCH_NATIVE=0``: the jnp path, no warning (even without a compiler), `status` says
    disabled, ``python -m jscratch.native`` exits 0; setting the variable later changes nothing."""
    r = _python(_FALLBACK, CXX=str(tmp_path / "no-such-compiler"), JSCRATCH_CACHE=str(tmp_path),
                JSCRATCH_NATIVE="0")
    assert r["ok"] == [False, False] and np.isfinite(r["g"]) and r["g"] != 0.0, r
    assert r["warnings"] == [] and r["rc"] == 0 and r["enabled"] is False
    st = r["status"]
    assert st["kernel"] == "jnp" and "disabled" in st["why"] and st["enabled"] is False, st


def test_compiler_lookup_without_compilers(monkeypatch, tmp_path):
    """``CXX`` unset and no g++, c++ or clang++ on ``PATH``: a one-line reason; ``CXX`` naming
    nothing executable: the reason names it."""
    monkeypatch.delenv("CXX", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(RuntimeError, match="no C.. compiler .CXX unset; no g.., c.. or clang"):
        native._compiler()
    monkeypatch.setenv("CXX", "no-such-cxx")
    with pytest.raises(RuntimeError, match="CXX=no-such-cxx is not an executable"):
        native._compiler()


def test_a_transient_spawn_failure_is_retried(monkeypatch, tmp_path):
    """Starting the compiler can fail for a moment (EFAULT, EAGAIN, ENOMEM, EINTR: a busy or
    memory-short machine): it is started again, up to three times; another error, or a third
    failure, is the one-line reason the kernel is off."""
    import errno

    exe = tmp_path / "cxx"
    exe.write_text("#!/bin/sh\necho 'cxx (test) 1.0'\n")
    exe.chmod(0o755)
    real, calls = subprocess.run, []

    def failing(codes):
        def run(*a, **k):
            calls.append(a[0])
            if len(calls) <= len(codes):
                raise OSError(codes[len(calls) - 1], os.strerror(codes[len(calls) - 1]))
            return real(*a, **k)
        return run

    monkeypatch.setattr(native.time, "sleep", lambda s: None)
    monkeypatch.setattr(subprocess, "run", failing([errno.EFAULT, errno.EAGAIN]))
    assert native._compiler_version(str(exe)) == "cxx (test) 1.0" and len(calls) == 3
    calls.clear()
    monkeypatch.setattr(subprocess, "run", failing([errno.EFAULT] * 3))
    with pytest.raises(RuntimeError, match="cannot be run: .*Bad address"):
        native._compiler_version(str(exe))
    assert len(calls) == 3
    calls.clear()
    monkeypatch.setattr(subprocess, "run", failing([errno.EACCES]))
    with pytest.raises(RuntimeError, match="cannot be run: .*Permission denied"):
        native._compiler_version(str(exe))
    assert len(calls) == 1


def test_cache_key_covers_source_compiler_jaxlib_and_ffi_headers(monkeypatch, tmp_path):
    """The key changes with the source text (any of the three files), the compiler's path and version, the
    jaxlib
    version and the FFI headers, and is the same for the same inputs."""
    monkeypatch.setattr(native, "_compiler_version", lambda cxx: "g++ (X) 12.2.0")
    key = lambda: native._key(native._key_parts("/usr/bin/g++"))
    k0 = key()
    assert key() == k0 and len(k0) == 16
    keys = {k0}
    monkeypatch.setattr(jaxlib, "__version__", "0.0.1")
    keys.add(key())
    monkeypatch.setattr(native, "_compiler_version", lambda cxx: "g++ (X) 13.1.0")
    keys.add(key())
    keys.add(native._key(native._key_parts("/opt/bin/g++")))
    src = tmp_path / "native_lit.cc"
    src.write_text(native._SOURCE.read_text() + "\n// one more line\n")
    monkeypatch.setattr(native, "_SOURCE", src)
    keys.add(key())
    arc_src = tmp_path / "native_arc.h"
    arc_src.write_text(native._ARC_SOURCE.read_text() + "\n// one more line\n")
    monkeypatch.setattr(native, "_ARC_SOURCE", arc_src)
    keys.add(key())
    bin_src = tmp_path / "native_bin.cc"
    bin_src.write_text(native._BIN_SOURCE.read_text() + "\n// one more line\n")
    monkeypatch.setattr(native, "_BIN_SOURCE", bin_src)
    keys.add(key())
    (tmp_path / "include" / "xla").mkdir(parents=True)
    (tmp_path / "include" / "xla" / "ffi.h").write_text("// other headers\n")
    monkeypatch.setattr(jax.ffi, "include_dir", lambda: str(tmp_path / "include"))
    keys.add(key())
    assert len(keys) == 8, keys
    parts = native._key_parts("/usr/bin/g++")
    assert {"source", "compiler", "compiler_version", "flags", "cpu", "cpu_features", "jaxlib",
            "ffi_headers"} <= set(parts), parts
    assert parts["jaxlib"] == "0.0.1" and "-march=native" in parts["flags"]


def _fake_cxx(tmp_path):
    """A stand-in C++ compiler: a shell script that answers ``--version`` and writes its ``-D``
    flags into its ``-o`` file (fast; what the library-management tests need)."""
    cxx = tmp_path / "fake-cxx"
    cxx.write_text('#!/bin/sh\n'
                   'if [ "$1" = --version ]; then echo "fake-cxx 1.0"; exit 0; fi\n'
                   'defs=""\n'
                   'while [ $# -gt 1 ]; do\n'
                   '  case "$1" in -D*) defs="$defs $1";; esac\n'
                   '  if [ "$1" = -o ]; then echo "lib$defs" > "$2"; fi; shift\n'
                   'done\n')
    cxx.chmod(0o755)
    return cxx


def test_build_prunes_stale_libraries(monkeypatch, tmp_path):
    """One library per dtype, built with only that dtype's handlers (its ``-D`` flag); a build
    deletes the cache's ``native_lit-*.so`` of other keys (and nothing else), not the other
    dtype's library of its key; a second call finds the library in the cache and builds nothing.
    A stand-in compiler (`_fake_cxx`) keeps this fast."""
    cxx = _fake_cxx(tmp_path)
    cache = tmp_path / "cache"
    cache.mkdir()
    stale = [cache / "native_lit-0123456789abcdef.so", cache / "native_lit-old.so"]
    for p in stale:
        p.write_text("stale")
    (cache / "notes.txt").write_text("kept")
    monkeypatch.setenv("CXX", str(cxx))
    monkeypatch.setenv("JSCRATCH_CACHE", str(cache))
    info = native._compile("f32")
    assert info["built"] and info["library"].read_text() == "lib -DJSCRATCH_DTYPE_F32\n"
    assert info["compiler"] == f"{cxx} (fake-cxx 1.0)"
    assert info["library"].name == f"native_lit-{info['key']}-f32.so"
    assert sorted(p.name for p in cache.iterdir()) == sorted([info["library"].name, "notes.txt"])
    other = native._compile("f64")
    assert other["built"] and other["library"].read_text() == "lib -DJSCRATCH_DTYPE_F64\n"
    assert other["key"] == info["key"] and other["library"].name.endswith("-f64.so")
    assert sorted(p.name for p in cache.iterdir()) == sorted(
        [info["library"].name, other["library"].name, "notes.txt"])
    again = native._compile("f32")
    assert not again["built"] and again["library"] == info["library"]


def test_a_failed_build_names_the_source_and_the_compiler_s_last_line(monkeypatch, tmp_path):
    """The two sources compile side by side, then link; a compiler that fails on one of them
    gives one `RuntimeError` naming that file and the compiler's last line, and leaves nothing in
    the cache."""
    cxx = tmp_path / "failing-cxx"
    cxx.write_text('#!/bin/sh\n'
                   'if [ "$1" = --version ]; then echo "failing-cxx 1.0"; exit 0; fi\n'
                   'for a in "$@"; do case "$a" in *native_bin.cc)\n'
                   '  echo "native_bin.cc:1: note: first" >&2; echo "error: boom" >&2; exit 1;;\n'
                   'esac; done\n'
                   'while [ $# -gt 1 ]; do\n'
                   '  if [ "$1" = -o ]; then echo obj > "$2"; fi; shift\n'
                   'done\n')
    cxx.chmod(0o755)
    cache = tmp_path / "cache"
    monkeypatch.setenv("CXX", str(cxx))
    monkeypatch.setenv("JSCRATCH_CACHE", str(cache))
    with pytest.raises(RuntimeError, match=r"^failing-cxx failed on native_bin\.cc: error: boom$"):
        native._compile("f32")
    assert list(cache.iterdir()) == []


def test_a_float32_run_builds_only_the_float32_library(tmp_path):
    """`prepare(float32)` (what a float32 design calls) builds the float32 library alone; the
    float64 one is built when a float64 kernel is first asked for. In a fresh process, with a
    stand-in compiler (`_fake_cxx`)."""
    cxx = _fake_cxx(tmp_path)
    code = """
import json, os, jax.numpy as jnp
from jscratch import native
native.prepare(jnp.float32)
native.prepare(jnp.float32)  # (a second call starts nothing)
native._build["f32"]["thread"].join()
first = sorted(os.listdir(os.environ["JSCRATCH_CACHE"]))
native.prepare(jnp.float64)
native._build["f64"]["thread"].join()
print(json.dumps({"first": first, "then": sorted(os.listdir(os.environ["JSCRATCH_CACHE"])),
                  "builds": sorted(native._build)}))
"""
    r = _python(code, CXX=str(cxx), JSCRATCH_CACHE=str(tmp_path / "cache"), JSCRATCH_NATIVE="1")
    assert len(r["first"]) == 1 and r["first"][0].endswith("-f32.so"), r
    assert len(r["then"]) == 2 and r["then"][1].endswith("-f64.so"), r
    assert r["builds"] == ["f32", "f64"]
    assert (tmp_path / "cache" / r["first"][0]).read_text() == "lib -DJSCRATCH_DTYPE_F32\n"


def test_settings_are_read_once_and_checked(monkeypatch):
    """Changing ``JSCRATCH_NATIVE`` in the environment after import changes nothing;
    `override` does, within its block; a malformed value is refused naming the variable."""
    before = native.enabled(), native.threads()
    monkeypatch.setenv("JSCRATCH_NATIVE", "0" if before[0] else "1")
    monkeypatch.setenv("JSCRATCH_NATIVE_THREADS", str(before[1] + 3))
    assert (native.enabled(), native.threads()) == before
    with native.override(enabled=not before[0], threads=7):
        assert (native.enabled(), native.threads()) == (not before[0], 7)
    assert (native.enabled(), native.threads()) == before
    try:
        for var, value in (("JSCRATCH_NATIVE", "yes"), ("JSCRATCH_NATIVE_THREADS", "0")):
            with monkeypatch.context() as m:
                m.setitem(native._ENV, var, value)
                native._settings.cache_clear()
                with pytest.raises(InputError, match=f"{var}='{value}': expected"):
                    native.enabled()
    finally:
        native._settings.cache_clear()
    assert (native.enabled(), native.threads()) == before


def test_a_kernel_call_for_a_dtype_without_kernels_is_refused_in_one_line():
    """A direct call for a dtype the kernels do not cover is an `InputError` naming the dtype."""
    z = lambda *shape: jnp.zeros(shape, jnp.int32)
    with pytest.raises(InputError, match=r"cannot run for int32 here \(no native kernel for int32"):
        native.pair_values(4, z(1, 4, 2), z(1, 2), z(1, 2), z(1), z(1), z(1), jnp.ones((1,), bool),
                           z(1, 1, 3))


@needs_native
def test_a_kernel_call_loads_its_own_dtype():
    """Asking `available` for float32 builds and registers the float32 kernels alone; a direct
    float64 kernel call then loads the float64 library itself (in a fresh process, the suite's
    kernel cache) and gives the float32 call's result to float32 rounding."""
    code = """
import json, jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
from jscratch import lobe, native
ok = native.available(jnp.float32)
before = native.status(jnp.float64)["kernel"]
fp = np.array([[[0., 0.], [1e-3, 0.], [1e-3, 1e-3], [0., 1e-3]]])
args = [fp, [[4e-4, -1e-3]], [[6e-4, 2e-3]], [2.5e-4], [1e-4], [0.04], [True],
        [[[0.1, 0.02, 1.0]]]]
out = {}
for dt in (jnp.float32, jnp.float64):
    a = [jnp.asarray(x, dt if i != 6 else bool) for i, x in enumerate(args)]
    out[jnp.dtype(dt).name] = float(native.pair_values(lobe.nodes(dt), *a)[0][0, 0])
print(json.dumps({"ok": ok, "before": before, "after": native.status(jnp.float64)["kernel"],
                  "D": out}))
"""
    r = _python(code)
    assert r["ok"] and r["before"] == "jnp" and r["after"] == "native", r
    D32, D64 = r["D"]["float32"], r["D"]["float64"]
    assert D64 != 0 and abs(D32 - D64) <= 1e-5 * abs(D64), r


@needs_native
def test_status_and_cli_describe_the_kernel(capsys):
    """`status` names the loaded library, its key and what the key covers;
    ``python -m jscratch.native --json`` prints the same in a fresh process and exits 0."""
    st = native.status()
    assert st["kernel"] == "native" and st["enabled"] and st["backend"] == "cpu", st
    assert st["library"].endswith(f"native_lit-{st['key']}-f32.so")
    assert os.path.exists(st["library"])
    assert native.available(jnp.float64)
    st64 = native.status(jnp.float64)
    assert st64["kernel"] == "native" and st64["key"] == st["key"], st64
    assert st64["library"].endswith(f"native_lit-{st['key']}-f64.so")
    assert st["covers"]["jaxlib"] == jaxlib.__version__ and st["compiler"]
    assert isinstance(st["threads"], int) and st["threads"] >= 1
    assert json.loads(json.dumps(st)) == st
    from jscratch.native.__main__ import main as native_main
    assert native_main([]) == 0
    text = capsys.readouterr().out
    assert text.startswith("jscratch native kernel: native") and st["key"] in text
    assert "float64's is in the cache too" in text  # (float64's was built above)
    out = subprocess.run([sys.executable, "-m", "jscratch.native", "--json"], capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    fresh = json.loads(out.stdout)
    assert fresh["kernel"] == "native" and fresh["key"] == st["key"], fresh
    assert fresh["library"] == st["library"]


@needs_native
def test_design_with_and_without_the_native_kernel_agree(tmp_path):
    """A small design (64 px, 800 scratches, 5 iterations) run with the native kernel and with
    the jnp fallback (``JSCRATCH_NATIVE=0``) ends at the same loss and SSIM (rounding apart)."""
    import json

    out = {}
    for flag in ("1", "0"):
        d = tmp_path / f"native{flag}"
        r = subprocess.run(
            [sys.executable, "-m", "jscratch.design", "--iterations", "5", "--size", "64",
             "--scratches", "800", "--no-discard", "--quiet", "--out", str(d)],
            env=dict(os.environ, JSCRATCH_NATIVE=flag), capture_output=True, text=True,
            timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
        out[flag] = json.loads((d / "metrics.json").read_text())
    assert out["1"]["loss"] == pytest.approx(out["0"]["loss"], rel=1e-5)
    np.testing.assert_allclose(out["1"]["ssim"], out["0"]["ssim"], atol=1e-5)


# --------------------------------------------------------------------------------------------
# The whole-pair kernel (`native.pair_values`, `native.pair_vjp`): geometry and every view.


def _pair_population(dtype):
    """Every adversarial family (grazing, degenerate, ...) and 512 random pairs, two views (the
    case's own half vector and another case's), about one slot in eight padding."""
    C = ndf_cases.concat([*ndf_cases.all_families().values(), ndf_cases.random_cases(512)])
    h, fp, p0, p1, w, d, a = (jnp.asarray(x, dtype) for x in C.astype(np.float64).args())
    H = jnp.stack([h, jnp.roll(h, 7, axis=0)])
    valid = jnp.asarray(np.random.default_rng(3).random(C.len()) > 0.12)
    return fp, p0, p1, w, d, a, valid, H


def _pair_reference(fp, p0, p1, w, d, a, valid, H):
    """`(D (V, n), A (n,))` of `ndf.pair_geometry` + `ndf.lit_integral` (all pieces), padding
    zeroed: the jnp path the kernel replaces."""
    def one(fp, p0, p1, w, d, a, h):
        g = ndf.pair_geometry(fp, p0, p1, w, d)
        return ndf.lit_integral(g, h, a), g.area

    D, A = jax.vmap(jax.vmap(one), in_axes=(None,) * 6 + (0,))(fp, p0, p1, w, d, a, H)
    return jnp.where(valid, D, 0), jnp.where(valid, A[0], 0)


def _pair_vjps(args, ct, use_native: bool):
    """``(d_p0, d_p1, d_w, d_d, d_alpha, d_h)`` at the cotangents `ct`: the kernel's reverse pass,
    or op by op through the jnp path (`_pair_reference`, the jnp per-view stage too)."""
    if use_native:
        return native.pair_vjp(lobe.nodes(args[1].dtype), *args, *ct)
    fp, p0, p1, w, d, a, valid, H = args
    with native.override(enabled=False):
        _, vjp = jax.vjp(lambda *x: _pair_reference(fp, *x[:5], valid, x[5]), p0, p1, w, d, a, H)
        return vjp(ct)


def _kinks(fp, p0, p1, w, d, a, valid, H):
    """Pairs with a view whose lit slab ends where the groove does, to rounding (`max(-X, u_-)`,
    `min(X, u_+)` at a tie: a kink of the integral, whose one-sided derivatives differ), per
    pair."""
    def one(fp, p0, p1, w, d, h):
        g = ndf.pair_geometry(fp, p0, p1, w, d)
        hx, _, hz, _, _ = ndf._view(g, h)
        u_m, u_p = ndf.lit_interval(hx, hz)
        return (jnp.abs(u_m + g.X) <= 1e-12) | (jnp.abs(u_p - g.X) <= 1e-12)

    k = jax.vmap(jax.vmap(one), in_axes=(None,) * 5 + (0,))(fp, p0, p1, w, d, H)
    return np.asarray(jnp.any(k, axis=0))


def _assert_gradients_close(got, ref, D, args, valid, checked):
    """float64 gradient rows ``got`` against ``ref`` (each ``(n, ...)``): finite, zero on padding,
    nonzero somewhere, and within 1e-10 of each row's scale plus 1e-14 of what a gradient cancels
    from (a sharp peak of width ``alpha w`` moves with the scratch's axis: ``D / (alpha w)`` per
    metre) on the ``checked`` rows."""
    w, a = np.asarray(args[3]), np.asarray(args[5])
    cancels = np.sum(np.abs(np.asarray(D)), axis=0) / (a * w)
    for k, (x, r) in enumerate(zip(got, ref)):
        assert np.all(np.isfinite(x)) and np.all(x[~valid] == 0), k
        scale = np.max(np.abs(r), axis=1)
        tol = 1e-10 * scale + 1e-14 * cancels + 1e-15 * np.percentile(scale[valid], 90)
        err = (np.max(np.abs(x - r), axis=1) / np.where(tol > 0, tol, 1))[checked]
        assert err.max() <= 1, (k, err.max(), int(np.argmax(err)))
        assert np.any(np.abs(r) > 0), k


def _rows(g, n):
    """Per-pair rows of a reverse pass's outputs (`d_h`'s view axis moved behind the pair)."""
    return [np.asarray(jnp.moveaxis(x, 0, 1) if x.ndim == 3 else x, np.float64).reshape(n, -1)
            for x in g]


@needs_native
@pytest.mark.float64
def test_pair_kernel_equals_jnp_path_float64():
    """The whole-pair kernel against the jnp path (geometry and per-view stage, op by op) on
    every adversarial family and random pairs, float64: values to 1e-12 relative, every gradient
    to 1e-10 of its pair's scale (plus 1e-14 of what it cancels from), padding exactly zero. Pairs at
    a kink (`_kinks`: the grazing family's slab ending on the groove edge) are left out of the
    gradient comparison: there each path takes another one-sided derivative."""
    jax.config.update("jax_enable_x64", True)
    args = _pair_population(jnp.float64)
    valid, n = np.asarray(args[6]), args[1].shape[0]
    D, A = native.pair_values(lobe.nodes(jnp.float64), *args)
    with native.override(enabled=False):
        Dr, Ar = _pair_reference(*args)
    for x, r in ((D, Dr), (A, Ar)):
        x, r = np.asarray(x), np.asarray(r)
        np.testing.assert_allclose(x, r, rtol=1e-12, atol=1e-14 * np.max(np.abs(r)))
        assert np.all(x[..., ~valid] == 0)
    rng = np.random.default_rng(5)
    ct = (jnp.asarray(rng.normal(size=D.shape)), jnp.asarray(rng.normal(size=A.shape)))
    got = _rows(_pair_vjps(args, ct, True), n)
    ref = _rows(_pair_vjps(args, ct, False), n)
    kink = _kinks(*args)
    assert 0 < kink.sum() < 0.05 * n
    _assert_gradients_close(got, ref, D, args, valid, ~kink)


@needs_native
@pytest.mark.float64
def test_pair_kernel_float32_as_accurate_as_jnp():
    """Float32 values and gradients against float64 at the same rounded inputs: the kernel's
    error is that of the jnp path (median within 2x, 99th percentile within 2x + 1e-4 of each
    pair's gradient scale; values: 99th percentile within 2x + 1e-6, worst within 3x or
    float32's 1e-3)."""
    jax.config.update("jax_enable_x64", True)
    a32 = _pair_population(jnp.float32)
    a64 = tuple(x.astype(jnp.float64) if x.dtype == jnp.float32 else x for x in a32)
    n = a32[1].shape[0]
    Dr, _ = _pair_reference(*a64)
    Dn, _ = native.pair_values(lobe.nodes(jnp.float32), *a32)
    with native.override(enabled=False):
        Dj, _ = jax.jit(_pair_reference)(*a32)
    Dr = np.asarray(Dr)
    den = np.abs(Dr) + 1e-6 * np.max(np.abs(Dr))
    e_nat = np.abs(np.asarray(Dn, np.float64) - Dr) / den
    e_jnp = np.abs(np.asarray(Dj, np.float64) - Dr) / den
    assert np.percentile(e_nat, 99) <= 2 * np.percentile(e_jnp, 99) + 1e-6
    assert e_nat.max() <= max(3 * e_jnp.max(), 1e-3), (e_nat.max(), e_jnp.max())
    rng = np.random.default_rng(6)
    ct = (rng.normal(size=Dr.shape), rng.normal(size=(n,)))
    ref = _rows(_pair_vjps(a64, tuple(jnp.asarray(c) for c in ct), False), n)
    ct32 = tuple(jnp.asarray(c, jnp.float32) for c in ct)
    nat = _rows(native.pair_vjp(lobe.nodes(jnp.float32), *a32, *ct32), n)
    with native.override(enabled=False):
        jnp32 = _rows(jax.jit(lambda *x: _pair_vjps(x, ct32, False))(*a32), n)
    _assert_as_accurate_as_jnp(nat, jnp32, ref)


@needs_native
@pytest.mark.parametrize("profile", ["paper", "arc"])
def test_pair_kernel_padding_is_exactly_zero_whatever_it_holds(profile):
    """Padding slots give exact zeros, value and reverse pass, even holding NaN and infinities;
    the valid slots are unchanged by them (both profiles)."""
    pop = _pair_population if profile == "paper" else _arc_population
    fp, p0, p1, w, d, a, valid, H = pop(jnp.float32)
    bad = ~valid
    junk = lambda x, v: jnp.where(bad.reshape(bad.shape + (1,) * (x.ndim - 1)), v, x)
    dirty = (junk(fp, jnp.nan), junk(p0, jnp.inf), junk(p1, jnp.nan), junk(w, 0.0),
             junk(d, -1.0), junk(a, jnp.nan), valid,
             jnp.where(bad[None, :, None], jnp.nan, H))
    clean = (fp, p0, p1, w, d, a, valid, H)
    ng = (lobe.nodes if profile == "paper" else arc.nodes)(jnp.float32)
    ct = (jnp.ones(H.shape[:2], jnp.float32), jnp.ones(w.shape, jnp.float32))
    pair_axis = (1, 0, 0, 0, 0, 0, 0, 1)  # D, A, d_p0, d_p1, d_w, d_d, d_alpha, d_h
    run = lambda x: (native.pair_values(ng, *x, profile=profile)
                     + native.pair_vjp(ng, *x, *ct, profile=profile))
    for x, y, ax in zip(run(dirty), run(clean), pair_axis):
        x, y = np.asarray(x), np.asarray(y)
        assert np.all(np.isfinite(x))
        np.testing.assert_array_equal(x, y)
        assert np.all(np.moveaxis(x, ax, 0)[np.asarray(bad)] == 0)


@needs_native
def test_pair_kernel_threads_give_identical_results():
    """One thread or four give the same bits, values and reverse pass."""
    args = _pair_population(jnp.float32)
    ct = (jnp.full(args[7].shape[:2], 0.5, jnp.float32), jnp.ones(args[3].shape, jnp.float32))
    ng = lobe.nodes(jnp.float32)
    res = {}
    for t in (1, 4):
        with native.override(threads=t):
            res[t] = jax.jit(lambda *x: (native.pair_values(ng, *x),
                                         native.pair_vjp(ng, *x, *ct)))(*args)
    for a, b in zip(jax.tree_util.tree_leaves(res[1]), jax.tree_util.tree_leaves(res[4])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@needs_native
@pytest.mark.parametrize("profile", ["paper", "arc"])
def test_pair_kernels_give_each_pair_its_own_result_in_any_order(profile):
    """A pair's values, reverse pass and Jacobians are the same bits wherever it stands in the
    list: the pairs shuffled, evaluated and put back give what the list in its order gives (a
    SIMD block shares its loops, not its results; the arc's shorter quadrature rule is chosen per
    pair)."""
    fp, p0, p1, w, d, a, valid, H = (_pair_population if profile == "paper"
                                     else _arc_population)(jnp.float32)
    n = p0.shape[0]
    rng = np.random.default_rng(8)
    ctD = jnp.asarray(rng.normal(size=H.shape[:2]), jnp.float32)
    ctA = jnp.asarray(rng.normal(size=(n,)), jnp.float32)
    ng = (lobe.nodes if profile == "paper" else arc.nodes)(jnp.float32)
    pair_axis = (1, 0, 0, 0, 0, 0, 0, 1, 1, 1, 0)  # the outputs below, in order

    def run(order):
        x = [fp[order], p0[order], p1[order], w[order], d[order], a[order], valid[order],
             H[:, order], ctD[:, order], ctA[order]]
        out = (native.pair_values(ng, *x[:8], profile=profile)
               + native.pair_vjp(ng, *x, profile=profile)
               + native.pair_jacobian(ng, *x[:8], profile=profile)[2:])
        back = np.argsort(order)
        return [np.take(np.asarray(y), back, axis=ax) for y, ax in zip(out, pair_axis)]

    for _ in range(3):
        for x, y in zip(run(rng.permutation(n)), run(np.arange(n))):
            np.testing.assert_array_equal(x, y)


@needs_native
@pytest.mark.float64
def test_pair_kernel_gradients_match_finite_differences_float64():
    """`native.pairs` (the differentiable wrapper): the directional derivative of a weighted sum
    of ``D`` and ``A`` over random pairs against central differences of the kernel's values."""
    jax.config.update("jax_enable_x64", True)
    C = ndf_cases.random_cases(256)
    h, fp, p0, p1, w, d, a = (jnp.asarray(x, jnp.float64) for x in C.args())
    H = jnp.stack([h, jnp.roll(h, 3, axis=0)])
    valid = jnp.ones(w.shape, bool)
    rng = np.random.default_rng(8)
    cD, cA = rng.normal(size=H.shape[:2]), rng.normal(size=w.shape) * 1e3

    def f(p0, p1, w, d, a, H):
        D, A = native.pairs(16, fp, p0, p1, w, d, a, valid, H)
        return jnp.sum(cD * D) + jnp.sum(cA * A)

    x = (p0, p1, w, d, a, H)
    g = jax.grad(f, argnums=range(6))(*x)
    scales = (1e-5, 1e-5, 0.1 * w, 0.1 * d, 0.1 * a, 0.1)
    for k in range(6):
        u = jnp.asarray(rng.normal(size=x[k].shape)) * scales[k]
        step = 1e-5
        at = lambda t: f(*(xi + t * u if i == k else xi for i, xi in enumerate(x)))
        fd = float(at(step) - at(-step)) / (2 * step)
        ad = float(jnp.sum(g[k] * u))
        assert abs(ad - fd) <= 1e-6 * abs(fd) + 1e-12, (k, ad, fd)


@needs_native
@pytest.mark.float64
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("profile", ["paper", "arc"])
def test_pair_jacobian_contracts_to_the_reverse_pass(dtype, profile):
    """`pair_jacobian`'s values are `pair_values`' bit for bit, and its Jacobians contracted with
    random cotangents give `pair_vjp` (summed in another order: 1e-13 / 1e-5 of each gradient's
    scale); padding slots are exact zeros even when they hold NaN (both profiles)."""
    fp, p0, p1, w, d, a, valid, H = (_pair_population if profile == "paper"
                                     else _arc_population)(dtype)
    bad = np.asarray(~valid)
    H = jnp.where(jnp.asarray(bad)[None, :, None], jnp.nan, H)
    args = (fp, p0, p1, w, d, a, valid, H)
    ng = (lobe.nodes if profile == "paper" else arc.nodes)(dtype)
    D, A, JD, Jh, JA = native.pair_jacobian(ng, *args, profile=profile)
    D0, A0 = native.pair_values(ng, *args, profile=profile)
    np.testing.assert_array_equal(np.asarray(D), np.asarray(D0))
    np.testing.assert_array_equal(np.asarray(A), np.asarray(A0))
    rng = np.random.default_rng(3)
    ctD = jnp.asarray(rng.normal(size=D.shape), dtype)
    ctA = jnp.asarray(rng.normal(size=A.shape), dtype)
    d0, d1, dw, dd, da, dh = native.pair_vjp(ng, *args, ctD, ctA, profile=profile)
    g = np.einsum("vn,vnk->nk", np.asarray(ctD, np.float64), np.asarray(JD, np.float64))
    g[:, :6] += np.asarray(ctA, np.float64)[:, None] * np.asarray(JA, np.float64)
    ref = np.concatenate([np.asarray(x, np.float64).reshape(len(bad), -1)
                          for x in (d0, d1, dw, dd, da)], 1)
    tol = 1e-13 if dtype == jnp.float64 else 1e-5
    assert np.all(np.max(np.abs(ref), 0) > 0)
    assert np.all(np.abs(g - ref) <= tol * np.max(np.abs(ref), 0))
    gh = np.asarray(ctD, np.float64)[..., None] * np.asarray(Jh, np.float64)
    np.testing.assert_allclose(gh, np.asarray(dh, np.float64), rtol=0,
                               atol=tol * np.max(np.abs(np.asarray(dh, np.float64))))
    for x in (JD, Jh):
        assert np.all(np.asarray(x)[:, bad] == 0)
    assert np.all(np.asarray(JA)[bad] == 0) and np.all(np.isfinite(np.asarray(JD)))


@needs_native
@pytest.mark.float64
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("profile", ["paper", "arc"])
def test_pair_kernels_skip_exactly_what_view_keep_drops(dtype, profile):
    """With ``skip_eps`` every kernel gives, bit for bit, what it gives without, with the
    pair-views `cull.view_keep` drops zeroed: the values, the Jacobians, and the reverse pass at
    cotangents zeroed there (the kernel computes the bound itself). A NaN half vector keeps every
    view of its pair; padding stays exact zeros; a bad ``skip_eps`` is refused in one line."""
    fp, p0, p1, w, d, a, valid, H = (_pair_population if profile == "paper"
                                     else _arc_population)(dtype)
    i_nan = int(np.nonzero(np.asarray(valid))[0][3])
    H = H.at[0, i_nan, 0].set(jnp.nan)
    args = (fp, p0, p1, w, d, a, valid, H)
    ng = (lobe.nodes if profile == "paper" else arc.nodes)(dtype)
    rng = np.random.default_rng(5)
    ctD = jnp.asarray(rng.normal(size=H.shape[:2]), dtype)
    ctA = jnp.asarray(rng.normal(size=p0.shape[:1]), dtype)
    D0, A0 = native.pair_values(ng, *args, profile=profile)
    J0 = native.pair_jacobian(ng, *args, profile=profile)
    ok = np.asarray(valid)[None]
    for eps in (1e-4, 1e-2):
        keep = cull.view_keep(H, p0, p1, w, d, a, eps, profile)
        kept = np.asarray(keep)
        assert 0.05 < 1 - kept[np.broadcast_to(ok, kept.shape)].mean() < 0.6
        assert kept[:, i_nan].all() and np.isnan(np.asarray(D0)[0, i_nan])
        z = lambda x: jnp.where(keep.reshape(keep.shape + (1,) * (x.ndim - 2)), x, 0)  # noqa: E731
        D1, A1 = native.pair_values(ng, *args, profile=profile, skip_eps=eps)
        for x, y in ((z(D0), D1), (A0, A1)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        J1 = native.pair_jacobian(ng, *args, profile=profile, skip_eps=eps)
        for x, y in zip((z(J0[0]), J0[1], z(J0[2]), z(J0[3]), J0[4]), J1):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        g0 = native.pair_vjp(ng, *args, z(ctD), ctA, profile=profile)
        g1 = native.pair_vjp(ng, *args, ctD, ctA, profile=profile, skip_eps=eps)
        for x, y in zip(g0, g1):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    for bad in (-1e-3, 2.0, float("nan"), "1e-3"):
        with pytest.raises(InputError, match="skip_eps must be a float in \\[0, 1\\]"):
            native.pair_values(ng, *args, profile=profile, skip_eps=bad)


# --------------------------------------------------------------------------------------------
# The ball cutter's groove (``profile="arc"``): the same kernels, each view's integral that of
# `arc.arc_lit_integral` on the geometry of `arc.arc_groove`.


def _arc_population(dtype):
    """`_pair_population`'s pairs and views with each scratch an arc groove: radius 0.05-0.34 mm,
    plunge ratio rho = p / R log-uniform in [1e-4, 1] (one in sixteen exactly 1), as the
    (width, depth) of `arc.arc_groove` (in float64, then rounded)."""
    fp, p0, p1, _, _, a, valid, H = _pair_population(dtype)
    n = p0.shape[0]
    rng = np.random.default_rng(11)
    R = 1.25e-4 * np.exp(rng.uniform(-1, 1, n))
    rho = np.exp(rng.uniform(np.log(1e-4), 0, n))
    rho[::16] = 1.0
    w, d = 2 * R, -2 * R * np.log1p(-np.minimum(rho, arc._RHO_CAP))  # `arc.arc_groove`
    return fp, p0, p1, jnp.asarray(w, dtype), jnp.asarray(d, dtype), a, valid, H


def _arc_reference(fp, p0, p1, w, d, a, valid, H):
    """`(D (V, n), A (n,))` of `ndf.pair_geometry` + `arc.arc_lit_integral`, padding zeroed; its
    per-view stage differentiated by plain autodiff (not by the jnp path's hand-written partials,
    which are the kernel's formulas)."""
    def one(fp, p0, p1, w, d, a, h):
        g = ndf.pair_geometry(fp, p0, p1, w, d)
        return arc._lit_integral(g, h, a, ndf.N_PIECES, False), g.area

    D, A = jax.vmap(jax.vmap(one), in_axes=(None,) * 6 + (0,))(fp, p0, p1, w, d, a, H)
    return jnp.where(valid, D, 0), jnp.where(valid, A[0], 0)


def _arc_vjps(args, ct):
    """The jnp reference's values ``(D, A)`` and reverse pass (autodiff of `_arc_reference`, as
    `pair_vjp` orders it), from one evaluation."""
    fp, p0, p1, w, d, a, valid, H = args
    out, vjp = jax.vjp(lambda *x: _arc_reference(fp, *x[:5], valid, x[5]), p0, p1, w, d, a, H)
    return out, vjp(ct)


@needs_native
@pytest.mark.float64
def test_arc_pair_kernel_equals_jnp_float64():
    """``profile="arc"`` against `arc.arc_lit_integral` on `ndf.pair_geometry` (autodiff), every
    adversarial family with arc grooves, float64: values to 1e-12 relative, every gradient to
    1e-10 of its pair's scale (plus 1e-14 of what it cancels from, as for the paper's profile),
    padding exactly zero."""
    jax.config.update("jax_enable_x64", True)
    args = _arc_population(jnp.float64)
    valid, n = np.asarray(args[6]), args[1].shape[0]
    ng = arc.nodes(jnp.float64)
    D, A = native.pair_values(ng, *args, profile="arc")
    rng = np.random.default_rng(5)
    ct = (jnp.asarray(rng.normal(size=D.shape)), jnp.asarray(rng.normal(size=A.shape)))
    (Dr, Ar), g_ref = jax.jit(_arc_vjps)(args, ct)
    for x, r in ((D, Dr), (A, Ar)):
        x, r = np.asarray(x), np.asarray(r)
        np.testing.assert_allclose(x, r, rtol=1e-12, atol=1e-14 * np.max(np.abs(r)))
        assert np.all(x[..., ~valid] == 0)
    assert np.mean(np.asarray(Dr)[:, valid] > 0) > 0.3  # lit pairs, not zeros
    got = _rows(native.pair_vjp(ng, *args, *ct, profile="arc"), n)
    ref = _rows(g_ref, n)
    _assert_gradients_close(got, ref, D, args, valid, np.ones(n, bool))


@needs_native
@pytest.mark.float64
def test_arc_pair_kernel_float32_as_accurate_as_jnp():
    """``profile="arc"`` in float32 against the float64 jnp reference at the same rounded
    inputs: the kernel's error is that of `arc.arc_lit_integral` in float32 (values: 99th
    percentile within 2x + 1e-6, worst within 3x or 1e-3; gradients: `_assert_as_accurate_as_jnp`)."""
    jax.config.update("jax_enable_x64", True)
    a32 = _arc_population(jnp.float32)
    a64 = tuple(x.astype(jnp.float64) if x.dtype == jnp.float32 else x for x in a32)
    n = a32[1].shape[0]
    rng = np.random.default_rng(6)
    ct = (rng.normal(size=a32[7].shape[:2]), rng.normal(size=(n,)))  # D: (V, n)
    ct32 = tuple(jnp.asarray(c, jnp.float32) for c in ct)
    (Dr, _), g_ref = jax.jit(_arc_vjps)(a64, tuple(jnp.asarray(c) for c in ct))
    (Dj, _), g_jnp = jax.jit(_arc_vjps)(a32, ct32)
    Dr, Dj = np.asarray(Dr), np.asarray(Dj, np.float64)
    Dn = np.asarray(native.pair_values(arc.nodes(jnp.float32), *a32, profile="arc")[0],
                    np.float64)
    den = np.abs(Dr) + 1e-6 * np.max(np.abs(Dr))
    e_nat, e_jnp = np.abs(Dn - Dr) / den, np.abs(Dj - Dr) / den
    assert np.percentile(e_nat, 99) <= 2 * np.percentile(e_jnp, 99) + 1e-6
    assert e_nat.max() <= max(3 * e_jnp.max(), 1e-3), (e_nat.max(), e_jnp.max())
    ref = _rows(g_ref, n)
    nat = _rows(native.pair_vjp(arc.nodes(jnp.float32), *a32, *ct32, profile="arc"), n)
    jnp32 = _rows(g_jnp, n)
    _assert_as_accurate_as_jnp(nat, jnp32, ref)


@needs_native
@pytest.mark.float64
def test_arc_pairs_gradients_match_finite_differences_float64():
    """`native.pairs(..., profile="arc")` (the differentiable wrapper, profile by keyword): the
    directional derivative of a weighted sum of ``D`` and ``A`` against central differences."""
    jax.config.update("jax_enable_x64", True)
    fp, p0, p1, w, d, a, _, H = _arc_population(jnp.float64)
    fp, p0, p1, w, d, a, H = (*(x[:256] for x in (fp, p0, p1, w, d, a)), H[:, :256])
    a = jnp.maximum(a, 0.05)  # the difference step must resolve the peak
    valid = jnp.ones(w.shape, bool)
    rng = np.random.default_rng(8)
    cD, cA = rng.normal(size=H.shape[:2]), rng.normal(size=w.shape) * 1e3

    def f(p0, p1, w, d, a, H):
        D, A = native.pairs(arc.nodes(jnp.float64), fp, p0, p1, w, d, a, valid, H, profile="arc")
        return jnp.sum(cD * D) + jnp.sum(cA * A)

    x = (p0, p1, w, d, a, H)
    g = jax.grad(f, argnums=range(6))(*x)
    scales = (1e-7, 1e-7, 1e-3 * w, 1e-3 * d, 0.01 * a, 0.01)
    for k in range(6):
        u = jnp.asarray(rng.normal(size=x[k].shape)) * scales[k]
        step = 1e-4
        at = lambda t: f(*(xi + t * u if i == k else xi for i, xi in enumerate(x)))
        fd = float(8 * (at(step) - at(-step)) - (at(2 * step) - at(-2 * step))) / (12 * step)
        ad = float(jnp.sum(g[k] * u))
        assert abs(ad - fd) <= 1e-6 * abs(fd) + 1e-12, (k, ad, fd)


@needs_native
def test_pair_kernels_refuse_an_unknown_profile():
    args = _pair_population(jnp.float32)
    for bad in ("ball", 1, None):
        with pytest.raises(InputError, match=r"profile=.*expected one of 'paper', 'arc'"):
            native.pair_values(4, *args, profile=bad)
    with pytest.raises(InputError, match="profile='Arc'"):
        native.pairs(4, *args, "Arc")


_SIMD_HARNESS = r"""
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <random>
#include "native_simd.h"

static long ulps(float a, float b) {  // distance in float32 steps; 0 for equal or both NaN
  if (a == b || (std::isnan(a) && std::isnan(b))) return 0;
  int32_t ia, ib;
  std::memcpy(&ia, &a, 4);
  std::memcpy(&ib, &b, 4);
  if ((ia < 0) != (ib < 0)) return 1L << 40;
  return std::labs(long(ia) - long(ib));
}

int main() {
  typedef Vec<float>::type V;
  std::mt19937 g(7);
  std::uniform_real_distribution<float> u(-1, 1);
  long wa = 0, wl = 0;
  for (long it = 0; it < 200000; ++it) {
    V y, x, q;
    for (int l = 0; l < 8; ++l) {
      y[l] = u(g) * std::pow(10.f, 6 * u(g));
      x[l] = it % 5 == 0 ? 1 + 1e-3f * u(g) : u(g) * std::pow(10.f, 6 * u(g));
      q[l] = it % 7 == 0 ? 1e-7f * std::fabs(u(g)) : std::fabs(u(g)) * std::pow(10.f, 8 * u(g));
    }
    V r = vatan2<float>(y, x), s = vlog1p<float>(q);
    for (int l = 0; l < 8; ++l) {
      wa = std::max(wa, ulps(r[l], std::atan2(y[l], x[l])));
      wl = std::max(wl, ulps(s[l], std::log1p(q[l])));
    }
  }
  const float inf = INFINITY, nan = NAN;
  V ys = {0.f, -0.f, 0.f, -0.f, 1.f, -1.f, nan, 1.f}, xs = {1.f, 1.f, -1.f, -1.f, 0.f, 0.f, 1.f, -0.f};
  V qs = {0.f, 1e-30f, 1e-8f, inf, 3e38f, 1e20f, 0.5f, nan};
  V r = vatan2<float>(ys, xs), s = vlog1p<float>(qs);
  long special = 0;
  for (int l = 0; l < 8; ++l)
    special = std::max({special, ulps(r[l], std::atan2(ys[l], xs[l])),
                        ulps(s[l], std::log1p(qs[l]))});
  // vfma: one rounding (the C library's fma) where the CPU fuses, two elsewhere; float and double.
  long fma_bad = 0;
  typedef Vec<double>::type VD;
  for (long it = 0; it < 20000; ++it) {
    V a, b, c;
    VD ad, bd, cd;
    for (int l = 0; l < 8; ++l) a[l] = u(g), b[l] = u(g) * 1e3f, c[l] = u(g);
    for (int l = 0; l < 4; ++l) ad[l] = a[l] * 1.1, bd[l] = b[l] * 1.3, cd[l] = c[l] * 0.7;
    V f = vfma(a, b, c);
    VD fd = vfma(ad, bd, cd);
#if defined(__FMA__) && defined(__AVX__)
    for (int l = 0; l < 8; ++l) fma_bad += f[l] != std::fma(a[l], b[l], c[l]);
    for (int l = 0; l < 4; ++l) fma_bad += fd[l] != std::fma(ad[l], bd[l], cd[l]);
#else
    for (int l = 0; l < 8; ++l) fma_bad += f[l] != a[l] * b[l] + c[l];
    for (int l = 0; l < 4; ++l) fma_bad += fd[l] != ad[l] * bd[l] + cd[l];
#endif
  }
  std::printf("%ld %ld %ld %ld\n", wa, wl, special, fma_bad);
}
"""


def test_simd_atan2_and_log1p_against_libm(tmp_path):
    # The kernels' float32 atan2 and log1p (native_simd.h) against the C library's, on
    # 1.6 million random arguments over twelve decades and at signed zeros, infinities and NaN;
    # and `vfma` against the C library's fma.
    try:
        cxx = native._compiler()
    except RuntimeError as e:
        pytest.skip(str(e))
    src = tmp_path / "simd.cc"
    src.write_text(_SIMD_HARNESS)
    exe = tmp_path / "simd"
    flags = [f for f in native._FLAGS if f not in ("-shared", "-fPIC")]
    built = subprocess.run([cxx, *flags, f"-I{native._SIMD_SOURCE.parent}", str(src), "-o",
                            str(exe)], capture_output=True, text=True, timeout=300)
    assert built.returncode == 0, built.stderr[-2000:]
    out = subprocess.run([str(exe)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    atan2_ulps, log1p_ulps, special_ulps, fma_mismatches = map(int, out.stdout.split())
    assert atan2_ulps <= 3 and log1p_ulps <= 1 and special_ulps == 0, out.stdout
    assert fma_mismatches == 0, out.stdout  # `vfma` is one fused multiply-add where it can be


_MEMORY_PROBE = r"""
import json, os, numpy as np
from jscratch import native
def rss():  # resident pages, in MB
    return int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
out = native.keep_freed_memory()
before = rss()
x = np.ones(96 * 2**20 // 8)  # 96 MB, every page touched
del x
print(json.dumps({"memory": out, "again": native.keep_freed_memory(),
                  "status": native.status()["memory"], "kept_mb": rss() - before}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_keep_freed_memory_keeps_a_freed_block_and_can_be_turned_off():
    def probe(value):
        env = dict(os.environ, JSCRATCH_KEEP_MEMORY=value)
        out = subprocess.run([sys.executable, "-c", _MEMORY_PROBE], capture_output=True,
                             text=True, timeout=300, env=env)
        return out
    on, off, bad = probe("1"), probe("0"), probe("2")
    assert on.returncode == 0 and off.returncode == 0, on.stderr[-2000:] + off.stderr[-2000:]
    on, off = json.loads(on.stdout), json.loads(off.stdout)
    assert off["memory"] == {"kept": False, "why": "JSCRATCH_KEEP_MEMORY=0"} == off["status"]
    assert off["kept_mb"] < 16  # the 96 MB block went back to the system (munmap)
    if on["memory"]["kept"]:  # glibc
        assert on["memory"] == on["again"] == on["status"]
        assert on["kept_mb"] > 80  # ... and stays in the process when kept
    assert bad.returncode != 0 and "JSCRATCH_KEEP_MEMORY='2'" in bad.stderr


def test_status_available_building_and_prepare_refuse_what_is_no_dtype():
    for who, call in (("status", native.status), ("available", native.available),
                      ("building", native.building), ("prepare", native.prepare)):
        for bad, shown in (("foo", "'foo'"), (1.5, "1.5")):
            want = rf"^native.{who}: `dtype` must be a dtype \(float32 or float64\), got "
            with pytest.raises(InputError, match=want + re.escape(shown) + "$"):
                call(bad)
    assert native.status(jnp.int32)["kernel"] == "jnp"  # a dtype without a kernel: says why
    assert native.available(jnp.int32) is False and native.building(jnp.int32) is False
    assert native.prepare(jnp.int32) is None  # (nothing to build)

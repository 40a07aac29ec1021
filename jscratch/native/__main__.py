"""``python -m jscratch.native [--json]``: what the native kernel is, where it lives, whether it
is in use (`main`)."""

import json
import os
import sys
import warnings

import jax.numpy as jnp

from jscratch.errors import InputError
from jscratch.native import FALLBACK_COST, NativeKernelWarning, available, status

_COVERS = {"source": "native_lit.cc, native_arc.h, native_bin.cc and native_simd.h sha256",
           "compiler": "compiler",
           "compiler_version": "its --version", "flags": "flags", "cpu": "CPU",
           "cpu_features": "CPU features sha256", "jaxlib": "jaxlib",
           "ffi_headers": "XLA FFI headers sha256"}


def main(argv=None) -> int:
    """``python -m jscratch.native [--json]``: build the kernel if needed and say what runs the
    per-view stage. Exit 0, or 1 (one line on stderr) where it was wanted and is unavailable."""
    from jscratch.options import OneLineParser  # only the command line needs it

    ap = OneLineParser(prog="python -m jscratch.native",
                       description="Build (if needed) and describe jscratch's native CPU kernel.",
                       epilog="exit status: 0 described (in use or not, as asked); 1 the kernel "
                              "was wanted and is unavailable (one line on stderr); 2 a refused "
                              "option or setting (JSCRATCH_NATIVE, ...).")
    ap.add_argument("--json", action="store_true", help="print status() as JSON")
    a = ap.parse_args(argv)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NativeKernelWarning)  # said below, in one line
            available(jnp.float32)
        st = status()
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(st, indent=2))
    else:
        what = ("native_lit.cc as an XLA FFI custom call (CPU, float32/float64, "
                f"up to {st['threads']} threads)" if st["kernel"] == "native"
                else "the jnp path (jscratch.ndf)")
        print(f"jscratch native kernel: {st['kernel']}: {what}")
        lib = st["library"] or ""
        f64 = lib[:-len("-f32.so")] + "-f64.so" if lib.endswith("-f32.so") else None
        built = "in the cache too" if f64 and os.path.isfile(f64) else "built when first asked for"
        print(f"library (float32; float64's is {built}): {st['library']}")
        covers = ", ".join(f"{_COVERS.get(k, k)} {v}" for k, v in (st["covers"] or {}).items()
                           if k != "compiler_version")
        print(f"key: {st['key']}" + (f" (covers {covers}, compiler version)" if covers else ""))
        print(f"compiler: {st['compiler']}")
        print(f"in use: {'yes' if st['kernel'] == 'native' else 'no'}: {st['why']}")
        print(f"jaxlib: {st['jaxlib']}; backend: {st['backend']}")
    if st["kernel"] != "native" and st["enabled"] and st["backend"] == "cpu":
        print(f"error: the native kernel is unavailable: {st['why']} ({FALLBACK_COST})",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The scene: board, scratches and views (docs/model.md §1, §2, §4 and §5), and the one set of rules
every stage checks them by.

**Scene objects** (equinox modules, data only):

- `Board`: board size ``Sx, Sy`` (m), image shape ``(H, W)`` and the board material (``F0``,
  Smith roughness ``a_G``, board GGX roughness ``a_S``); all static.
- `Scratches`: ``p0, p1`` ``(N, 2)`` (m), ``width, depth`` ``(N,)`` (m), ``alpha`` ``(N,)``.
- `Views`: ``camera, light`` ``(M, 3)`` (m), ``intensity`` ``(M,)`` (W/sr).
- `views_on_circle`: the paper's view layout (docs/model.md §5); `flat_highlight`.

**The rules** (`SCRATCH_RULES`, `check_scratches`, `check_views`, `scene_checks`): every value
finite; ``width > 0``, ``depth > 0`` (m); ``ALPHA_RANGE[0] <= alpha <= ALPHA_RANGE[1]`` (where
the float32 pair integral and its gradients are accurate; `ndf.pair_integral`'s domain is
``(0, 1)``); endpoints on the board ``[0, Sx] x [0, Sy]`` (within `ON_BOARD_RTOL` of its size)
when the board is known; cameras and lights at least `MIN_HEIGHT` above the board, every
coordinate within ``+-MAX_DISTANCE``; intensities ``I >= 0`` with
``I / z_light^2 <= MAX_IRRADIANCE``; float32 or float64 arrays. The scene objects
(`Scratches`, `Views`), the binning (`jscratch.bvh`), the renderer (`jscratch.render`), the
design file (`jscratch.designfile`) and the optimiser (`jscratch.design`) all check by these
functions, so a scene one of them accepts the others accept too. Host checks raise one line
naming the source, the scratch (or view) and the field; traced checks (`scene_checks`) give
``(condition, message)`` pairs for `eqx.error_if`.

Imports: ``jax``, ``equinox``, ``numpy`` and `jscratch.errors` (no other jscratch module).
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jscratch.errors import InputError, count_arg, float64_arg, real_number, shape_arg, shown

__all__ = [
    "ALPHA_RANGE",
    "MAX_DISTANCE",
    "MAX_IRRADIANCE",
    "MIN_BOARD",
    "MIN_HEIGHT",
    "MIN_WIDTH",
    "ON_BOARD_RTOL",
    "PROFILES",
    "SCRATCH_RULES",
    "Board",
    "Scratches",
    "Views",
    "array_arg",
    "check_scratches",
    "check_views",
    "dtype_arg",
    "flat_highlight",
    "scene_checks",
    "views_on_circle",
]

#: Endpoints may exceed the board by this fraction of its size (float32 rounding of values the
#: optimiser keeps on ``[0, S]``: one float32 ulp at 0.3 m is 3e-8 m = 1e-7 of the board).
ON_BOARD_RTOL = 1e-6

#: Groove cross-sections (`Scratches.profile`): the paper's and the ball cutter's circular arc.
PROFILES = ("paper", "arc")

#: The roughness a scratch may have: the float32 pair integral is accurate to the stability
#: sweep's tolerance down to 1e-4 (it loses digits below, and overflows to NaN near 1e-8), and
#: its alpha gradient to 1e-3 of ``D / alpha`` up to 0.99 (1e-2 at 0.999).
ALPHA_RANGE = (1e-4, 0.99)

#: Cameras and lights: at least this high above the board (m; closer, the squared distance to a
#: pixel below underflows float32) and at most this far from its origin (m; farther, it
#: overflows; 1e3 m is already the far field, where every pixel sees the same directions).
MIN_HEIGHT, MAX_DISTANCE = 1e-6, 1e9

#: The brightest light, as its irradiance scale ``I / z^2`` at the board below it (W/m^2, `I`
#: in W/sr, `z` its height): brighter, float32 values and gradients overflow (the default scene
#: needs about 2e2, a light at `MAX_DISTANCE` about 1e2).
MAX_IRRADIANCE = 1e20

#: The narrowest groove (m; narrower, the float32 width derivative of the pair integral is NaN
#: from about 1e-19 m) and the smallest board side (m; smaller, a pixel's area underflows
#: float32 on fine grids): a picometre and a micrometre, far below anything carved.
MIN_WIDTH, MIN_BOARD = 1e-12, 1e-6

#: The array dtypes a scene may hold.
DTYPES = ("float32", "float64")

# The bounds above are inclusive of their float32 roundings (float32(1e-4) is 9.99999975e-5).
_LOW, _HIGH = 1 - 1e-6, 1 + 1e-6

#: The range rule of each per-scratch value: ``name -> (predicate, text)``; the predicate works
#: elementwise on numpy and jax arrays alike.
SCRATCH_RULES = {
    "width": (lambda v: v >= _LOW * MIN_WIDTH, f"must be >= {MIN_WIDTH:g} m"),
    "depth": (lambda v: v > 0, "must be > 0 m"),
    "alpha": (lambda v: (v >= _LOW * ALPHA_RANGE[0]) & (v <= _HIGH * ALPHA_RANGE[1]),
              f"must lie in [{ALPHA_RANGE[0]:g}, {ALPHA_RANGE[1]:g}]"),
}


# --------------------------------------------------------------------------------------------
# The rules
# --------------------------------------------------------------------------------------------


def _first_bad(mask: np.ndarray) -> int:
    """Index of the first True along axis 0 (rows reduced with any)."""
    rows = mask.reshape(mask.shape[0], -1).any(axis=1) if mask.ndim > 1 else mask
    return int(np.flatnonzero(rows)[0])


def check_scratches(p0, p1, width, depth, alpha=None, *, board=None, source: str = "scratches",
                    error: type[Exception] = InputError) -> None:
    """Check scratch values on the host (numpy) by the scene's rules; shapes are the caller's.

    **Arguments:** `p0`, `p1` ``(N, 2)`` (m); `width`, `depth`, `alpha` ``(N,)`` or scalars
    (`alpha` may be ``None``: not checked); `board` ``(Sx, Sy)`` (m) or ``None`` (endpoints not
    checked); `source` names the caller in messages; `error` the exception class raised.

    **Raises:** `error`, one line: ``"{source}: scratch {i}: {field} = {value} {what is wrong}"``.
    """
    fields = {"p0": p0, "p1": p1, "width": width, "depth": depth}
    if alpha is not None:
        fields["alpha"] = alpha
    arrays = {k: np.asarray(v, np.float64) for k, v in fields.items()}
    n = arrays["p0"].shape[0] if arrays["p0"].ndim else 1
    for name, a in arrays.items():
        bad = ~np.isfinite(a)
        if bad.any():
            i = _first_bad(bad) if a.ndim else 0
            count = int(bad.reshape(a.shape[0], -1).any(axis=1).sum()) if a.ndim else n
            v = a[i].tolist() if a.ndim else a.tolist()
            raise error(f"{source}: scratch {i}: {name} = {v} is not finite ({count} scratches"
                        f" have a non-finite {name})")
    for name, (ok, text) in SCRATCH_RULES.items():
        if name not in arrays:
            continue
        a = arrays[name]
        bad = ~ok(a)
        if bad.any():
            i = _first_bad(bad) if a.ndim else 0
            raise error(f"{source}: scratch {i}: {name} = {float(a[i] if a.ndim else a)!r} {text}")
    if board is not None:
        b = np.asarray(board, np.float64)
        tol = ON_BOARD_RTOL * float(b.max())
        for name in ("p0", "p1"):
            pts = arrays[name]
            off = (pts < -tol) | (pts > b + tol)
            if off.any():
                i = _first_bad(off)
                raise error(
                    f"{source}: scratch {i}: {name} = ({pts[i, 0]:.6g}, {pts[i, 1]:.6g}) m lies off"
                    f" the board [0, {b[0]:.6g}] x [0, {b[1]:.6g}] m ({int(off.any(axis=1).sum())}"
                    f" such endpoints in {name})")


def check_views(camera, light, intensity, *, source: str = "views",
                error: type[Exception] = InputError) -> None:
    """Check view values on the host by the scene's rules (finite; cameras and lights at
    ``z >= MIN_HEIGHT`` and every coordinate within ``+-MAX_DISTANCE``; intensities ``>= 0``
    with ``I / z_light^2 <= MAX_IRRADIANCE``); shapes are the caller's.

    **Arguments:** `camera`, `light` ``(M, 3)`` (m); `intensity` ``(M,)`` or a scalar (W/sr);
    `source` names the caller in messages; `error` the exception class raised.

    **Raises:** `error`, one line: ``"{source}: view {j}: {field} ..."``, or naming the argument
    whose shape is wrong.
    """
    arrays = {}
    for name, v in (("camera", camera), ("light", light), ("intensity", intensity)):
        try:
            arrays[name] = np.asarray(v, np.float64)
        except (TypeError, ValueError):
            raise error(f"{source}: `{name}` is not a numeric array; got {shown(v)}") from None
    cs, ls = arrays["camera"].shape, arrays["light"].shape
    if len(cs) != 2 or cs[1] != 3 or ls != cs:
        raise error(f"{source}: `camera` and `light` must have one shape (M, 3); got camera {cs},"
                    f" light {ls}")
    m = arrays["camera"].shape[0]
    if arrays["intensity"].ndim == 0:
        arrays["intensity"] = np.broadcast_to(arrays["intensity"], (m,))
    if arrays["intensity"].shape != (m,):
        raise error(f"{source}: `intensity` must have shape (M,) = ({m},) or be a scalar; got "
                    f"{arrays['intensity'].shape}")
    for name, a in arrays.items():
        bad = ~np.isfinite(a)
        if bad.any():
            raise error(f"{source}: view {_first_bad(bad)}: {name} is not finite")
    for name in ("camera", "light"):
        z = arrays[name][:, 2]
        if (z <= 0).any():
            j = int(np.argmax(z <= 0))
            raise error(f"{source}: view {j}: {name} is at z = {z[j]}: it must be above the board"
                        " (z > 0)")
        if (z < _LOW * MIN_HEIGHT).any():
            j = int(np.argmax(z < _LOW * MIN_HEIGHT))
            raise error(f"{source}: view {j}: {name} is at z = {z[j]:g} m: it must be at least "
                        f"{MIN_HEIGHT:g} m above the board")
        far = np.abs(arrays[name]).max(axis=1) > _HIGH * MAX_DISTANCE
        if far.any():
            j = int(np.argmax(far))
            raise error(f"{source}: view {j}: {name} lies farther than {MAX_DISTANCE:g} m from the "
                        f"board's origin (float32 squares overflow; 1e3 m is already the far "
                        f"field)")
    i = arrays["intensity"]
    if (i < 0).any():
        j = int(np.argmax(i < 0))
        raise error(f"{source}: view {j}: intensity is negative ({i[j]}): it must be >= 0")
    e = i / arrays["light"][:, 2] ** 2
    if (e > _HIGH * MAX_IRRADIANCE).any():
        j = int(np.argmax(e > _HIGH * MAX_IRRADIANCE))
        raise error(f"{source}: view {j}: intensity {i[j]:g} W/sr at {arrays['light'][j, 2]:g} m "
                    f"above the board is {e[j]:g} W/m^2 there, above {MAX_IRRADIANCE:g} (float32 "
                    f"overflows)")


def scene_checks(scratches: "Scratches", views: "Views | None" = None, *,
                 source: str = "render") -> list:
    """The rules as traced ``(condition, message)`` pairs (a condition True means broken), for
    `eqx.error_if` inside jit. Endpoints are not checked here (the board is static: the host
    checks them)."""
    s = scratches
    checks = [(~(jnp.all(jnp.isfinite(s.p0)) & jnp.all(jnp.isfinite(s.p1))),
               f"{source}: a scratch endpoint (p0 or p1) is not finite")]
    for name, (ok, text) in SCRATCH_RULES.items():
        v = getattr(s, name)
        checks.append((~jnp.all(jnp.isfinite(v) & ok(v)),
                       f"{source}: a scratch {name} is not finite or breaks the rule:"
                       f" {name} {text}"))
    if views is not None:
        checks += [
            (~(jnp.all(jnp.isfinite(views.camera)) & jnp.all(jnp.isfinite(views.light))
               & jnp.all(jnp.isfinite(views.intensity))),
             f"{source}: a view (camera, light or intensity) is not finite"),
            (jnp.any(views.camera[:, 2] < _LOW * MIN_HEIGHT)
             | jnp.any(views.light[:, 2] < _LOW * MIN_HEIGHT),
             f"{source}: every camera and light must be at least {MIN_HEIGHT:g} m above the "
             f"board"),
            (jnp.any(jnp.abs(views.camera) > _HIGH * MAX_DISTANCE)
             | jnp.any(jnp.abs(views.light) > _HIGH * MAX_DISTANCE),
             f"{source}: a camera or light lies farther than {MAX_DISTANCE:g} m"),
            ((jnp.any(views.intensity < 0)
              | jnp.any(views.intensity > _HIGH * MAX_IRRADIANCE * views.light[:, 2] ** 2)),
             f"{source}: a view intensity is negative, or above {MAX_IRRADIANCE:g} W/m^2 at the "
             f"board (I / z^2)"),
        ]
    return checks


# --------------------------------------------------------------------------------------------
# Scene objects
# --------------------------------------------------------------------------------------------


def _to_float(name: str):
    """The converter of `Board`'s field `name`: ``float``, refusing in one line what it cannot
    convert."""

    def convert(v) -> float:
        try:
            if np.ndim(v) == 0:
                return float(v)
        except (TypeError, ValueError):
            pass
        raise InputError(f"Board: `{name}` must be a real number; got {shown(v)}")

    return convert


def _to_shape(shape) -> tuple[int, int]:
    try:
        h, w = (int(s) for s in shape)
        whole = all(float(s) == int(s) for s in shape)
    except (TypeError, ValueError, OverflowError):
        whole = False
    if not whole:
        raise InputError(f"Board: `shape` must be (H, W), two positive ints; got {shape!r}")
    return (h, w)


class Board(eqx.Module):
    """The board ``[0, Sx] x [0, Sy]`` (m) in the plane ``z = 0``, its image grid and material.

    Every field is static (hashable, no array leaves): changing one recompiles a jitted render.

    **Arguments:**

    - `shape`: image ``(H, W)`` in pixels; row 0 lies along the board edge ``y = Sy`` (docs/model.md §1).
    - `Sx`, `Sy`: board size (m). Default 0.3.
    - `F0`: Schlick reflectance at normal incidence. Default 0.91 (aluminium).
    - `a_G`: roughness of the Smith GGX shadowing-masking term. Default 0.04.
    - `a_S`: GGX roughness of the flat (unscratched) board. Default 0.04.
    """

    shape: tuple[int, int] = eqx.field(static=True, default=(256, 256), converter=_to_shape)
    Sx: float = eqx.field(static=True, default=0.3, converter=_to_float("Sx"))
    Sy: float = eqx.field(static=True, default=0.3, converter=_to_float("Sy"))
    F0: float = eqx.field(static=True, default=0.91, converter=_to_float("F0"))
    a_G: float = eqx.field(static=True, default=0.04, converter=_to_float("a_G"))
    a_S: float = eqx.field(static=True, default=0.04, converter=_to_float("a_S"))

    def __check_init__(self):
        h, w = self.shape
        if h < 1 or w < 1:
            raise InputError(f"Board: `shape` must be positive (H, W); got {self.shape}")
        for name in ("Sx", "Sy"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= MIN_BOARD):
                raise InputError(f"Board: `{name}` must be a finite length >= {MIN_BOARD:g} m; "
                                 f"got {v}")
        if not 0.0 <= self.F0 <= 1.0:
            raise InputError(f"Board: `F0` must lie in [0, 1]; got {self.F0}")
        for name in ("a_G", "a_S"):
            v = getattr(self, name)
            if not 0.0 < v <= 1.0:
                raise InputError(f"Board: `{name}` must lie in (0, 1]; got {v}")

    @property
    def H(self) -> int:
        return self.shape[0]

    @property
    def W(self) -> int:
        return self.shape[1]

    @property
    def n_pixels(self) -> int:
        return self.shape[0] * self.shape[1]

    @property
    def pixel_area(self) -> float:
        """Footprint area ``S_P`` (m^2)."""
        return (self.Sx / self.W) * (self.Sy / self.H)


def _is_tracer(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def _board_arg(source: str, board) -> "Board":
    """`board`, or `Board()` for None; `InputError` for anything that is no `Board`."""
    if board is None:
        return Board()
    if not isinstance(board, Board):
        raise InputError(f"{source}: `board` must be a jscratch.Board or None; got "
                         f"{type(board).__name__} {shown(board)}")
    return board


def dtype_arg(source: str, dtype):
    """`dtype` as one of `DTYPES` (None: the default float); `InputError` otherwise."""
    if dtype is None:
        return jnp.dtype(jnp.result_type(float))
    try:
        dt = jnp.dtype(dtype)
    except TypeError:
        dt = None
    if dt is None or dt.name not in DTYPES:
        got = dt.name if dt is not None else shown(dtype)
        raise InputError(f"{source}: `dtype` must be float32 or float64; got {got}")
    return dt


def _prng_key(source: str, key):
    """`key` if it is one PRNG key (``jax.random.key`` or a raw ``jax.random.PRNGKey``, also
    traced); `InputError` otherwise."""
    dt, ndim = getattr(key, "dtype", None), getattr(key, "ndim", None)
    typed = dt is not None and jax.dtypes.issubdtype(dt, jax.dtypes.prng_key)
    if not ((typed and ndim == 0) or (not typed and dt == np.uint32 and ndim == 1)):
        raise InputError(f"{source}: `key` must be one PRNG key (jax.random.key(seed) or "
                         f"jax.random.PRNGKey(seed)); got {shown(key)}")
    return key


def _float_dtype(*xs, source: str):
    """The scene dtype of arrays `xs`: theirs when float32 or float64, the default float for
    integers; `InputError` for complex, half-precision or non-numeric arrays."""
    dt = jnp.result_type(*xs)
    if jnp.issubdtype(dt, jnp.complexfloating):
        raise InputError(f"{source}: the arrays are complex ({dt}); a scene is real: float32 or "
                         f"float64")
    if jnp.issubdtype(dt, jnp.floating) and jnp.dtype(dt).name not in DTYPES:
        raise InputError(f"{source}: the arrays are {dt}; a scene is float32 or float64 (half "
                         f"precision cannot hold the pair integrals)")
    if not jnp.issubdtype(dt, jnp.floating):
        if not (jnp.issubdtype(dt, jnp.integer) or dt == jnp.bool_):
            raise InputError(f"{source}: the arrays are {dt}, not numbers")
        dt = jnp.result_type(float)
    return dt


def array_arg(source: str, name: str, x):
    """`jnp.asarray(x)`, with a one-line `InputError` naming `source` and `name` for what is no
    numeric array."""
    try:
        return jnp.asarray(x)
    except (TypeError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"{source}: `{name}` is not a numeric array ({first[:100]})") from None


class Scratches(eqx.Module):
    """``N`` straight scratches (docs/model.md §1-§2).

    **Arguments:**

    - `p0`, `p1`: endpoints, ``(N, 2)``, board metres.
    - `width`: profile width ``w`` (m), ``(N,)`` or a scalar broadcast to ``(N,)``. Default ``1e-4``.
    - `depth`: depth ``d`` (m), ``(N,)`` or scalar. Default ``1e-4``.
    - `alpha`: intrinsic GGX roughness in `ALPHA_RANGE` (``[1e-4, 0.99]``, where float32 is
      accurate; `ndf.pair_integral`'s domain is ``(0, 1)``), ``(N,)`` or scalar. Default ``0.04``.
    - `profile` (static): the grooves' cross-section, one of `PROFILES`: ``"paper"`` (default)
      the profile ``theta(x) = 2 atan(2x / w)`` of docs/model.md §2 with width ``w`` and depth
      ``d``; ``"arc"`` the circular arc a ball of radius ``R`` cuts at plunge ``p``
      (docs/model.md §13), stored as ``width = 2R`` and ``depth = -2R log(1 - p/R)``
      (`jscratch.arc.arc_groove`), the paper groove with the same footprint on the board.

    All five arrays share one floating dtype (that of ``p0, p1``; integers become the default float).
    Shapes are checked always; values (`check_scratches`: finite, ``width, depth > 0``,
    alpha in `ALPHA_RANGE`) when the arrays are concrete. Inside jit, `render_pairs` checks values
    with `eqx.error_if` (`scene_checks`).
    """

    p0: Float[Array, "n 2"]
    p1: Float[Array, "n 2"]
    width: Float[Array, " n"]
    depth: Float[Array, " n"]
    alpha: Float[Array, " n"]
    profile: str = eqx.field(static=True, default="paper")

    def __init__(self, p0: ArrayLike, p1: ArrayLike, width: ArrayLike = 1e-4,
                 depth: ArrayLike = 1e-4, alpha: ArrayLike = 0.04, profile: str = "paper"):
        if profile not in PROFILES:
            raise InputError(f"Scratches: `profile` must be one of {PROFILES}; got {profile!r}")
        self.profile = profile
        p0 = array_arg("Scratches", "p0", p0)
        p1 = array_arg("Scratches", "p1", p1)
        dtype = _float_dtype(p0, p1, source="Scratches")
        for name, p in (("p0", p0), ("p1", p1)):
            if p.ndim != 2 or p.shape[1] != 2:
                raise InputError(f"Scratches: `{name}` must have shape (N, 2); got {p.shape}")
        if p0.shape != p1.shape:
            raise InputError(f"Scratches: `p0` {p0.shape} and `p1` {p1.shape} must have the same shape")
        n = p0.shape[0]
        self.p0 = p0.astype(dtype)
        self.p1 = p1.astype(dtype)
        for name, v in (("width", width), ("depth", depth), ("alpha", alpha)):
            _float_dtype(array_arg("Scratches", name, v), source="Scratches")
            v = jnp.asarray(v, dtype=dtype)
            if v.ndim == 0:
                v = jnp.broadcast_to(v, (n,))
            if v.shape != (n,):
                raise InputError(f"Scratches: `{name}` must have shape (N,) = ({n},) or be a scalar;"
                                 f" got {v.shape}")
            setattr(self, name, v)

    def __check_init__(self):
        if any(_is_tracer(a) for a in (self.p0, self.p1, self.width, self.depth, self.alpha)):
            return
        check_scratches(self.p0, self.p1, self.width, self.depth, self.alpha, source="Scratches")

    @property
    def n(self) -> int:
        return self.p0.shape[0]

    @property
    def dtype(self):
        return self.p0.dtype

    @staticmethod
    def random(key, n: int, board: Board | None = None, *, length=(0.005, 0.025),
               width: float = 1e-4, depth: float = 1e-4, alpha: float = 0.04,
               dtype=None) -> "Scratches":
        """The initial layout of docs/model.md §5: midpoints uniform on the board, directions uniform,
        lengths uniform in ``length`` (m); a segment that would leave the board is shortened about
        its midpoint (keeping its direction) so both endpoints lie on the board.

        **Arguments:** `key` a PRNG key; `n` number of scratches (an int >= 0); `board` (default
        `Board()`); `length` ``(min, max)`` (m) with ``0 < min <= max``; `width, depth, alpha`
        scalars; `dtype` float32 or float64 (default float).

        **Returns:** `Scratches`. **Raises:** `InputError`, one line naming the argument.
        """
        where = "Scratches.random"
        n = count_arg(where, "n", n, 0)
        key = _prng_key(where, key)
        board = _board_arg(where, board)
        try:
            lo, hi = (real_number(x) for x in length)
        except (TypeError, ValueError):
            lo = hi = None
        if lo is None or hi is None or not (math.isfinite(hi) and 0 < lo <= hi):
            raise InputError(f"{where}: `length` must be (min, max) metres with 0 < min <= max; "
                             f"got {shown(length)}")
        p0, p1 = _random_endpoints(key, n, float(board.Sx), float(board.Sy), (lo, hi),
                                   dtype_arg(where, dtype))
        return Scratches(p0, p1, width, depth, alpha)


@functools.partial(jax.jit, static_argnums=(1, 2, 3, 4, 5))
def _random_endpoints(key, n: int, Sx: float, Sy: float, length: tuple, dtype):
    """`Scratches.random`'s endpoints ``(n, 2), (n, 2)`` in one compiled call."""
    k1, k2, k3 = jax.random.split(key, 3)
    size = jnp.asarray([Sx, Sy], dtype)
    mid = jax.random.uniform(k1, (n, 2), dtype) * size
    phi = jax.random.uniform(k2, (n,), dtype, 0.0, 2 * jnp.pi)
    half = 0.5 * jax.random.uniform(k3, (n,), dtype, length[0], length[1])
    t = jnp.stack([jnp.cos(phi), jnp.sin(phi)], -1)

    def reach(direction):  # largest s with mid + s * direction on the board, (n,)
        pos = (size - mid) / jnp.where(direction > 0, direction, 1)
        neg = mid / jnp.where(direction < 0, -direction, 1)
        r = jnp.where(direction > 0, pos, jnp.where(direction < 0, neg, jnp.inf))
        return r.min(-1)

    s = jnp.minimum(half, jnp.minimum(reach(t), reach(-t)))
    return jnp.clip(mid - s[:, None] * t, 0, size), jnp.clip(mid + s[:, None] * t, 0, size)


class Views(eqx.Module):
    """``M`` view/light configurations (docs/model.md §1; shaded in §4).

    **Arguments:**

    - `camera`: camera positions ``(M, 3)`` (m), above the board (``z >= MIN_HEIGHT``).
    - `light`: point-light positions ``(M, 3)`` (m), above the board (``z >= MIN_HEIGHT``).
    - `intensity`: light intensities ``I_j`` (W/sr), ``(M,)`` or a scalar. Default 1.

    Shapes are checked always; values (`check_views`) when concrete.
    """

    camera: Float[Array, "m 3"]
    light: Float[Array, "m 3"]
    intensity: Float[Array, " m"]

    def __init__(self, camera: ArrayLike, light: ArrayLike, intensity: ArrayLike = 1.0):
        camera = array_arg("Views", "camera", camera)
        light = array_arg("Views", "light", light)
        dtype = _float_dtype(camera, light, source="Views")
        for name, p in (("camera", camera), ("light", light)):
            if p.ndim != 2 or p.shape[1] != 3:
                raise InputError(f"Views: `{name}` must have shape (M, 3); got {p.shape}")
        if camera.shape != light.shape:
            raise InputError(f"Views: `camera` {camera.shape} and `light` {light.shape} must have"
                             " the same shape")
        m = camera.shape[0]
        _float_dtype(array_arg("Views", "intensity", intensity), source="Views")
        intensity = jnp.asarray(intensity, dtype)
        if intensity.ndim == 0:
            intensity = jnp.broadcast_to(intensity, (m,))
        if intensity.shape != (m,):
            raise InputError(f"Views: `intensity` must have shape (M,) = ({m},) or be a scalar;"
                             f" got {intensity.shape}")
        self.camera = camera.astype(dtype)
        self.light = light.astype(dtype)
        self.intensity = intensity

    def __check_init__(self):
        if any(_is_tracer(a) for a in (self.camera, self.light, self.intensity)):
            return
        check_views(self.camera, self.light, self.intensity, source="Views")

    @property
    def m(self) -> int:
        return self.camera.shape[0]


def _direction(polar, azimuth):
    return np.array([math.sin(polar) * math.cos(azimuth), math.sin(polar) * math.sin(azimuth),
                     math.cos(polar)])


def flat_highlight(camera, light) -> np.ndarray:
    """Where the flat board mirrors the light into the camera: the point of ``z = 0`` on the
    segment from ``camera`` to the light's mirror image ``(Lx, Ly, -Lz)`` (board metres, ``(..., 2)``).

    At that point the half vector is the board normal, so the flat board's GGX peak
    ``1 / (pi a_S^2)`` shows there.

    **Raises:** `InputError`, one line: `camera` or `light` not points ``(..., 3)`` of numbers,
    or shapes that do not broadcast.
    """
    c, l = (float64_arg("flat_highlight", name, v, "points (..., 3) of numbers (m)")
            for name, v in (("camera", camera), ("light", light)))
    shape_arg("flat_highlight", "camera", c, (..., 3), what=" (m)")
    shape_arg("flat_highlight", "light", l, (..., 3), what=" (m)")
    try:
        np.broadcast_shapes(c.shape, l.shape)
    except ValueError:
        raise InputError(f"flat_highlight: `camera` {c.shape} and `light` {l.shape} do not "
                         f"broadcast") from None
    s = c[..., 2:3] / (c[..., 2:3] + l[..., 2:3])
    return c[..., :2] + s * (l[..., :2] - c[..., :2])


#: The default polar angle of the light and cameras of `views_on_circle` (rad): 50 degrees, the
#: command line's default (`jscratch.design.SceneConfig.theta_deg`).
DEFAULT_THETA = math.radians(50.0)


def views_on_circle(M: int, theta: float = DEFAULT_THETA, distance: float = 1.0, offset: float | None = None,
                    board: Board | None = None, *, light_azimuth: float = 0.0,
                    camera_theta: float | None = None, intensity: ArrayLike = 1.0,
                    dtype=None) -> Views:
    """The paper's view layout (section 4.1, docs/model.md §5), angles in radians.

    One light at polar angle ``theta`` (from the board normal) and azimuth ``light_azimuth``;
    camera ``j`` at polar angle ``camera_theta`` (default ``theta``) and azimuth
    ``2 pi j / M + offset``; all at ``distance`` from the board centre. Every view shares the light.

    A camera that sees the light mirrored by the flat board is refused: if the flat-board
    highlight (`flat_highlight`, where the half vector is the board normal) falls on the board,
    the board's own specular peak would dominate that view. With the light and cameras on one
    circle this is the camera near the light's mirror azimuth ``light_azimuth + pi``.

    **Arguments:**

    - `M`: number of views (>= 1).
    - `theta`: polar angle of the light (rad), in ``[0, pi/2)``. Default `DEFAULT_THETA` (50 deg).
    - `distance`: distance of light and cameras from the board centre (m). Default 1.
    - `offset`: azimuth of camera 0 relative to ``light_azimuth`` (rad). Default: ``pi / M`` for
      even ``M`` (the mirror azimuth midway between two cameras, every camera ``pi / M`` from it
      and from the light); for odd ``M``, ``pi / (2M)`` (every camera at least ``pi / (2M)`` from
      both the light and its mirror) when that keeps every flat-board highlight off the board,
      else ``0`` (the mirror midway between two cameras, ``pi / M`` from both; camera 0 then shares
      the light's azimuth, a retro-reflection view).
    - `board`: the board (its centre and extent). Default `Board()`.
    - `light_azimuth`, `camera_theta`, `intensity` ((M,) or scalar, W/sr), `dtype` (float32 or
      float64; default float).

    **Returns:** `Views` with ``camera, light`` ``(M, 3)`` and ``intensity`` ``(M,)``.
    """
    where = "views_on_circle"
    board = _board_arg(where, board)
    try:
        whole = int(M) == M
    except (TypeError, ValueError, OverflowError):
        whole = False
    if isinstance(M, (bool, str)) or not whole or M < 1:
        raise InputError(f"views_on_circle: `M` must be a positive int; got {shown(M)}")
    M = int(M)
    dtype = dtype_arg(where, dtype)
    camera_theta = theta if camera_theta is None else camera_theta
    given = {"theta": theta, "camera_theta": camera_theta, "distance": distance,
             "light_azimuth": light_azimuth, "offset": offset}
    for name, v in given.items():
        if (v is not None or name != "offset") and real_number(v) is None:
            raise InputError(f"views_on_circle: `{name}` must be a real number"
                             f"{' (m)' if name == 'distance' else ' (rad)'}; got {shown(v)}")
    theta, camera_theta, distance, light_azimuth = (
        real_number(given[k]) for k in ("theta", "camera_theta", "distance", "light_azimuth"))
    for name in ("light_azimuth", "offset"):
        if given[name] is not None and not math.isfinite(real_number(given[name])):
            raise InputError(f"views_on_circle: `{name}` must be finite (rad); got {given[name]}")
    for name, v in (("theta", theta), ("camera_theta", camera_theta)):
        if not (math.isfinite(v) and 0.0 <= v < math.pi / 2):
            hint = (f" (angles are in radians: did you mean {math.radians(v):.4f}?)"
                    if math.isfinite(v) and 1.6 <= v < 90 else "")
            raise InputError(f"views_on_circle: `{name}` must lie in [0, pi/2) rad so that it is"
                             f" above the board; got {v}{hint}")
    if not (math.isfinite(distance) and distance > 0):
        raise InputError(f"views_on_circle: `distance` must be positive (m); got {distance}")
    centre = np.array([board.Sx / 2, board.Sy / 2, 0.0])
    light = centre + distance * _direction(theta, light_azimuth)

    def layout(offset):
        azimuths = [2 * math.pi * j / M + offset + light_azimuth for j in range(M)]
        cameras = np.stack([centre + distance * _direction(camera_theta, a) for a in azimuths])
        spot = flat_highlight(cameras, light[None])
        on = ((spot[:, 0] >= 0) & (spot[:, 0] <= board.Sx) & (spot[:, 1] >= 0)
              & (spot[:, 1] <= board.Sy))
        return azimuths, cameras, spot, on

    if offset is None:
        azimuths, cameras, spot, on = layout(math.pi / (2 * M) if M % 2 else math.pi / M)
        if on.any() and M % 2:
            azimuths, cameras, spot, on = layout(0.0)
    else:
        azimuths, cameras, spot, on = layout(float(offset))
    if on.any():
        j = int(np.argmax(on))
        raise InputError(
            f"views_on_circle: camera {j} (azimuth {math.degrees(azimuths[j]) % 360:.1f} deg) sees"
            f" the light mirrored by the flat board at board point ({spot[j, 0]:.4f},"
            f" {spot[j, 1]:.4f}) m, inside the board: the board's specular peak would dominate"
            " that view. Change `offset`, `M`, `theta`/`camera_theta` or `distance`.")
    return Views(jnp.asarray(cameras, dtype), jnp.asarray(np.repeat(light[None], M, 0), dtype),
                 jnp.asarray(intensity, dtype))

// The grid binning's strip and cell stage (`jscratch.grid._bin`) as an XLA FFI custom call for
// the CPU (`jscratch.native.bin_cells`): one pass over scratches -> strips -> cells that writes
// the kept (pixel, scratch) pairs straight into the fixed-capacity list, instead of XLA's padded
// (strip_capacity, rows) candidate array, its cumsum, scatter and gathers.
//
// The per-scratch quantities (`grid._strip_setup`) come from XLA, so they are the same bits as
// the jnp path's: fl (N, 12) = tu, tv, bu, bv, mu, mv, half_w, half_l, cx, cy, tx, ty (grid units,
// then metres) and ints (N, 4) = k_lo, k_hi, n_strips, col_major. The result must be the jnp
// path's exactly (same pairs, same order, same overflow flag and counts), so every comparison
// below is computed with `_bin`'s formulas in its order. XLA's CPU backend contracts a multiply
// feeding an add or subtract into a fused multiply-add where the product has no other use in its
// fusion; `fused` stands exactly where it does (`tests/test_grid.py` compares the two paths).
//
// Attributes: h_px, w_px (image rows, columns), strip_capacity, rows (cells per strip),
// pair_capacity; tol, tolg (slack of the exact test, metres, and of candidate generation, grid
// units), csx = Sx / W, csy = Sy / H, hx, hy (half a pixel, metres), sy = Sy (metres), as Python
// computes them in double; each is rounded to the input dtype before use, as jnp does.
// Outputs: pixel, scratch (pair_capacity) int32, valid (pair_capacity) bool, overflow () bool,
// stats (3) int32 = strips needed, most cells in a strip, pairs needed.
//
// One thread: the pass is a few milliseconds at the design's default size, and its order is the
// list's order.

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "xla/ffi/api/ffi.h"

// The dtypes whose handlers this build defines: jscratch.native builds one library per dtype
// (-DJSCRATCH_DTYPE_F32 or -DJSCRATCH_DTYPE_F64); neither defined: both.
#if !defined(JSCRATCH_DTYPE_F32) && !defined(JSCRATCH_DTYPE_F64)
#define JSCRATCH_DTYPE_F32
#define JSCRATCH_DTYPE_F64
#endif

namespace ffi = xla::ffi;

namespace {

// a * b + c as XLA's CPU backend computes a product whose only use is that add: one rounding
// where the CPU has fused multiply-add instructions (XLA compiles for the host's features, as
// -march=native does here), two where it has none.
template <typename T>
inline T fused(T a, T b, T c) {
#if defined(__FMA__) || defined(__ARM_FEATURE_FMA)
  return std::fma(a, b, c);
#else
  return a * b + c;
#endif
}

// `grid._floor_index`: floor(clip(g, -1, n)) as int32 (XLA: maximum, then minimum).
template <typename T>
inline int32_t floor_index(T g, int32_t n) {
  T c = std::min(static_cast<T>(n), std::max(static_cast<T>(-1), g));
  return static_cast<int32_t>(std::floor(c));
}

template <ffi::DataType DT>
ffi::Error BinImpl(ffi::Buffer<DT> fl, ffi::Buffer<ffi::DataType::S32> ints, int64_t h_px,
                   int64_t w_px, int64_t strip_capacity, int64_t rows, int64_t pair_capacity,
                   double tol_d, double tolg_d, double csx_d, double csy_d, double hx_d,
                   double hy_d, double sy_d, ffi::ResultBuffer<ffi::DataType::S32> pixel,
                   ffi::ResultBuffer<ffi::DataType::S32> scratch,
                   ffi::ResultBuffer<ffi::DataType::PRED> valid,
                   ffi::ResultBuffer<ffi::DataType::PRED> overflow,
                   ffi::ResultBuffer<ffi::DataType::S32> stats) {
  using T = ffi::NativeType<DT>;
  const auto fdims = fl.dimensions();
  const auto idims = ints.dimensions();
  if (fdims.size() != 2 || fdims[1] != 12 || idims.size() != 2 || idims[1] != 4 ||
      idims[0] != fdims[0])
    return ffi::Error::InvalidArgument("bin_cells: expected fl (N, 12) and ints (N, 4)");
  if (pixel->element_count() != static_cast<size_t>(pair_capacity) ||
      scratch->element_count() != static_cast<size_t>(pair_capacity) ||
      valid->element_count() != static_cast<size_t>(pair_capacity))
    return ffi::Error::InvalidArgument("bin_cells: outputs must have pair_capacity slots");
  const int64_t n = fdims[0];
  const T* F = fl.typed_data();
  const int32_t* I = ints.typed_data();
  int32_t* pix = pixel->typed_data();
  int32_t* scr = scratch->typed_data();
  bool* val = valid->typed_data();

  // The Python floats as jnp uses them: rounded to the dtype.
  const T tol = static_cast<T>(tol_d), tolg = static_cast<T>(tolg_d);
  const T csx = static_cast<T>(csx_d), csy = static_cast<T>(csy_d);
  const T hx = static_cast<T>(hx_d), hy = static_cast<T>(hy_d), sy = static_cast<T>(sy_d);
  const T half = static_cast<T>(0.5), one = static_cast<T>(1);
  // With square pixels (hx == hy in the dtype) XLA shares hx |ty| and hx |tx| between the b and
  // t tests (one product, two uses: not contracted); otherwise each product has one use.
  const bool square = hx == hy;
  const int32_t H = static_cast<int32_t>(h_px), W = static_cast<int32_t>(w_px);
  const int32_t sentinel = static_cast<int32_t>(n);

  int64_t strips_needed = 0;
  for (int64_t i = 0; i < n; ++i) strips_needed += I[4 * i + 2];

  int64_t slot = 0;       // strips generated so far (the strip list's next slot)
  int64_t pos = 0;        // pairs kept so far (the pair list's next slot)
  int32_t max_rows = 0;
  for (int64_t i = 0; i < n && slot < strip_capacity; ++i) {
    const int32_t k_lo = I[4 * i], k_hi = I[4 * i + 1], n_strips = I[4 * i + 2];
    if (n_strips <= 0) continue;
    const bool col_major = I[4 * i + 3] != 0;
    const T* f = F + 12 * i;
    const T tu = f[0], tv = f[1], bu = f[2], bv = f[3], mu = f[4], mv = f[5];
    const T half_w = f[6], half_l = f[7], cx = f[8], cy = f[9], tx = f[10], ty = f[11];
    const int32_t n_u = col_major ? W : H, n_v = col_major ? H : W;
    const T abu = std::abs(bu), abv = std::abs(bv), atx = std::abs(tx), aty = std::abs(ty);
    // Per-strip thresholds of the four separating axes (`_bin`'s sep_x, sep_y, sep_b, sep_t).
    const T thr_x = fused(half_l, atx, fused(half_w, aty, hx)) + tol;
    const T thr_y = fused(half_l, aty, fused(half_w, atx, hy)) + tol;
    const T thr_b = (square ? (half_w + hx * aty) + hy * atx
                            : fused(hy, atx, fused(hx, aty, half_w))) + tol;
    const T thr_t = (square ? (half_l + hx * atx) + hy * aty
                            : fused(hy, aty, fused(hx, atx, half_l))) + tol;
    const T spread = fused(half_w, abv, tolg);
    for (int32_t s = 0; s < n_strips && slot < strip_capacity; ++s, ++slot) {
      const int32_t k = k_lo + s;
      if (!(k >= 0 && k <= k_hi && k < n_u)) continue;  // the spare strip (`_strip_setup`)
      const T kf = static_cast<T>(k);
      // Along-scratch parameter range whose cross-section reaches the strip [k, k + 1].
      const T lo = fused(-half_w, abu, kf - mu) - tolg;
      const T hi = fused(half_w, abu, (kf + one) - mu) + tolg;
      const T tau1 = lo / tu, tau2 = hi / tu;
      const T tau_a = std::min(half_l, std::max(-half_l, std::min(tau1, tau2)));
      const T tau_b = std::min(half_l, std::max(-half_l, std::max(tau1, tau2)));
      const T va = fused(tau_a, tv, mv), vb = fused(tau_b, tv, mv);
      const int32_t r_lo = std::max(floor_index(std::min(va, vb) - spread, n_v), 0);
      const int32_t r_hi = std::min(floor_index(std::max(va, vb) + spread, n_v), n_v - 1);
      const int32_t n_rows = std::max(r_hi - r_lo + 1, 0);
      max_rows = std::max(max_rows, n_rows);
      const int32_t m = static_cast<int32_t>(std::min<int64_t>(n_rows, rows));
      for (int32_t j = 0; j < m; ++j) {
        const int32_t minor = r_lo + j;
        const int32_t col = col_major ? k : minor, row = col_major ? minor : k;
        const T dx = fused(static_cast<T>(col) + half, csx, -cx);
        const T dy = fused(-(static_cast<T>(row) + half), csy, sy) - cy;
        if (!(std::abs(dx) <= thr_x) || !(std::abs(dy) <= thr_y)) continue;
        const T d_b = fused(dx, ty, -(dy * tx));
        const T d_t = fused(dx, tx, dy * ty);
        if (!(std::abs(d_b) <= thr_b) || !(std::abs(d_t) <= thr_t)) continue;
        if (pos < pair_capacity) {
          const bool on = row >= 0 && row < H && col >= 0 && col < W;
          pix[pos] = on ? row * W + col : 0;
          scr[pos] = on ? static_cast<int32_t>(i) : sentinel;
          val[pos] = on;
        }
        ++pos;
      }
    }
  }
  for (int64_t p = std::min<int64_t>(pos, pair_capacity); p < pair_capacity; ++p) {
    pix[p] = 0;
    scr[p] = sentinel;
    val[p] = false;
  }
  int32_t* st = stats->typed_data();
  st[0] = static_cast<int32_t>(strips_needed);
  st[1] = max_rows;
  st[2] = static_cast<int32_t>(pos);
  *overflow->typed_data() =
      strips_needed > strip_capacity || max_rows > rows || pos > pair_capacity;
  return ffi::Error::Success();
}

}  // namespace

#define JSCRATCH_BIN_BIND(DT)                                                              \
  ffi::Ffi::Bind()                                                                         \
      .Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<ffi::DataType::S32>>()                       \
      .Attr<int64_t>("h_px").Attr<int64_t>("w_px").Attr<int64_t>("strip_capacity")        \
      .Attr<int64_t>("rows").Attr<int64_t>("pair_capacity").Attr<double>("tol")           \
      .Attr<double>("tolg").Attr<double>("csx").Attr<double>("csy").Attr<double>("hx")    \
      .Attr<double>("hy").Attr<double>("sy")                                              \
      .Ret<ffi::Buffer<ffi::DataType::S32>>().Ret<ffi::Buffer<ffi::DataType::S32>>()       \
      .Ret<ffi::Buffer<ffi::DataType::PRED>>().Ret<ffi::Buffer<ffi::DataType::PRED>>()     \
      .Ret<ffi::Buffer<ffi::DataType::S32>>()

#ifdef JSCRATCH_DTYPE_F32
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchBinF32, BinImpl<ffi::DataType::F32>,
                              JSCRATCH_BIN_BIND(ffi::DataType::F32));
#endif
#ifdef JSCRATCH_DTYPE_F64
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchBinF64, BinImpl<ffi::DataType::F64>,
                              JSCRATCH_BIN_BIND(ffi::DataType::F64));
#endif

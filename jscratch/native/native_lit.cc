// The scratch NDF's pair integral with its derivatives, as XLA FFI custom calls for the CPU
// (`jscratch.native`): line-by-line ports of the jnp code they replace, evaluated in registers
// instead of through XLA's fusions. The jnp code stays the reference: tests compare the two in
// float64 (equal to rounding) and float32.
//
// The per-view stage (`JscratchLit*`, `JscratchLitValues*`; `jscratch.ndf._view`,
// `lit_interval`, `jscratch.lobe.lobe`, `lobe_params`, `ndf._cut`, `lobe.piece_values`,
// `ndf._cut_transpose` and the autodiff of the view algebra), one SIMD lane per pair-view.
// Inputs (leading axes flattened, n pair-views; the pieces have a trailing axis of k): ua, ub,
// Ya, Yb (n, k) the boundary pieces cut to the groove (`ndf.PairGeometry`), X (n) the groove
// half-width in widths, h (n, 3) the board-frame half vector (normalised here), b, t (n, 2) the
// scratch's across and along unit vectors, alpha (n). Outputs: lit (n) = sum over pieces of the
// integral of Y (F1 + F2) du over the piece cut to the lit slab, and its partial derivatives with
// respect to every input, or the value alone.
//
// The whole pair (`JscratchPairs*`, `JscratchPairsVjp*`; `ndf._pair_geometry`, then the
// per-view stage for every view), one SIMD lane per pair. Inputs: footprint (n, 4, 2), p0, p1
// (n, 2), width, depth, alpha (n), valid (n, bool), h (V, n, 3); outputs D (V, n) and A (n), or,
// given the cotangents ctD (V, n) and ctA (n), the gradients with respect to p0, p1, width, depth,
// alpha and h. The geometry's Jacobian with respect to p0, p1, width and depth is carried in
// forward mode (`Dual`, kGeo tangents) and chained with every view's partials. Padding slots
// (valid false) are evaluated as a benign dummy pair and give exact zeros.
//
// Attributes: n_gl Gauss-Legendre nodes per piece, threads (the most workers one call uses, the
// calling thread included); the whole-pair kernels' skip_eps: a pair-view whose bound
// (`skip_bound`, `cull.cull_ratio`'s) is below it and below its pair's largest over the views is
// skipped (exact zeros in D and every derivative; a view that no lane of a block keeps is not
// evaluated at all), as `cull.view_keep` chooses them (0: none).
//
// Threads: the lanes are cut into chunks (`kChunk` pair-views, `kPairChunk` pairs: whole vectors;
// the cut depends on n alone) that the calling thread and up to threads - 1 tasks on XLA's
// intra-op thread pool (the FFI execution context's `ThreadPool`, alive as long as the client)
// claim one at a time. The lanes are independent, so the results are the same bits for any
// thread count; a task that starts after the last chunk was claimed returns at once, and the
// caller never waits for a task that has not started (no deadlock when the pool is busy or runs
// tasks inline).

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <condition_variable>
#include <functional>
#include <limits>
#include <memory>
#include <mutex>
#if defined(__FMA__) && defined(__AVX__)
#include <immintrin.h>  // vfma (native_simd.h)
#endif

#include "xla/ffi/api/ffi.h"

// The dtypes whose handlers this build defines: jscratch.native builds one library per dtype
// (-DJSCRATCH_DTYPE_F32 or -DJSCRATCH_DTYPE_F64); neither defined: both.
#if !defined(JSCRATCH_DTYPE_F32) && !defined(JSCRATCH_DTYPE_F64)
#define JSCRATCH_DTYPE_F32
#define JSCRATCH_DTYPE_F64
#endif

namespace ffi = xla::ffi;

namespace {

constexpr int kMaxNodes = 32;
constexpr int kMaxPieces = 8;
constexpr int kTan = 9;  // tangents of the view algebra: X, h (3), b (2), t (2), alpha

#include "native_simd.h"

// Forward-mode number with N tangents: the view algebra's Jacobian (N = kTan, a few dozen
// operations per pair-view, as jax's autodiff of the same jnp code computes it) and the pair
// geometry's (N = kGeo: p0, p1, width, depth; N = 0 for values alone).
template <typename V, int N = kTan>
struct Dual {
  V v;
  V d[N > 0 ? N : 1];
};

template <int N = kTan, typename V>
Dual<V, N> cst(V v) {
  Dual<V, N> r;
  r.v = v;
  for (int i = 0; i < N; ++i) r.d[i] = V{};
  return r;
}
template <int N = kTan, typename V>
Dual<V, N> var(V v, int i) {
  Dual<V, N> r = cst<N>(v);
  if (i < N) r.d[i] = splat<V>(1);
  return r;
}
template <typename V, int N>
Dual<V, N> operator+(const Dual<V, N>& a, const Dual<V, N>& b) {
  Dual<V, N> r;
  r.v = a.v + b.v;
  for (int i = 0; i < N; ++i) r.d[i] = a.d[i] + b.d[i];
  return r;
}
template <typename V, int N>
Dual<V, N> operator-(const Dual<V, N>& a, const Dual<V, N>& b) {
  Dual<V, N> r;
  r.v = a.v - b.v;
  for (int i = 0; i < N; ++i) r.d[i] = a.d[i] - b.d[i];
  return r;
}
template <typename V, int N>
Dual<V, N> operator-(const Dual<V, N>& a) {
  Dual<V, N> r;
  r.v = -a.v;
  for (int i = 0; i < N; ++i) r.d[i] = -a.d[i];
  return r;
}
template <typename V, int N>
Dual<V, N> operator*(const Dual<V, N>& a, const Dual<V, N>& b) {
  Dual<V, N> r;
  r.v = a.v * b.v;
  for (int i = 0; i < N; ++i) r.d[i] = a.d[i] * b.v + a.v * b.d[i];
  return r;
}
template <typename V, int N>
Dual<V, N> scale(V s, const Dual<V, N>& a) {
  Dual<V, N> r;
  r.v = s * a.v;
  for (int i = 0; i < N; ++i) r.d[i] = s * a.d[i];
  return r;
}
template <typename V, int N>
Dual<V, N> operator/(const Dual<V, N>& a, const Dual<V, N>& b) {
  Dual<V, N> r;
  r.v = a.v / b.v;
  const V inv = 1 / b.v;
  for (int i = 0; i < N; ++i) r.d[i] = (a.d[i] - r.v * b.d[i]) * inv;
  return r;
}
template <typename V, int N>
Dual<V, N> dsel(decltype(V{} < V{}) m, const Dual<V, N>& a, const Dual<V, N>& b) {
  Dual<V, N> r;
  r.v = sel<V>(m, a.v, b.v);
  for (int i = 0; i < N; ++i) r.d[i] = sel<V>(m, a.d[i], b.d[i]);
  return r;
}
template <typename T, typename V, int N>
Dual<V, N> dsqrt(const Dual<V, N>& a) {
  Dual<V, N> r;
  r.v = vsqrt<T>(a.v);
  const V inv = splat<V>(0.5) / r.v;
  for (int i = 0; i < N; ++i) r.d[i] = a.d[i] * inv;
  return r;
}
// `ndf._safe_sqrt`: 0 with derivative 0 where the argument is not positive.
template <typename T, typename V, int N>
Dual<V, N> dsafe_sqrt(const Dual<V, N>& a) {
  auto pos = a.v > 0;
  Dual<V, N> safe = dsel(pos, a, cst<N>(splat<V>(1)));
  return dsel(pos, dsqrt<T>(safe), cst<N>(V{}));
}
template <typename T, typename V, int N>
Dual<V, N> dabs(const Dual<V, N>& a) {
  V s = sel<V>(a.v > 0, splat<V>(1), sel<V>(a.v < 0, splat<V>(-1), V{}));
  Dual<V, N> r;
  r.v = vabs<T>(a.v);
  for (int i = 0; i < N; ++i) r.d[i] = s * a.d[i];
  return r;
}
// jax's max/min: at a tie each argument gets half the derivative.
template <typename T, typename V, int N>
Dual<V, N> dmax(const Dual<V, N>& a, const Dual<V, N>& b) {
  V wa = sel<V>(a.v > b.v, splat<V>(1), sel<V>(a.v == b.v, splat<V>(0.5), V{}));
  Dual<V, N> r;
  r.v = vmax<T>(a.v, b.v);
  for (int i = 0; i < N; ++i) r.d[i] = wa * a.d[i] + (1 - wa) * b.d[i];
  return r;
}
template <typename T, typename V, int N>
Dual<V, N> dmin(const Dual<V, N>& a, const Dual<V, N>& b) {
  V wa = sel<V>(a.v < b.v, splat<V>(1), sel<V>(a.v == b.v, splat<V>(0.5), V{}));
  Dual<V, N> r;
  r.v = vmin<T>(a.v, b.v);
  for (int i = 0; i < N; ++i) r.d[i] = wa * a.d[i] + (1 - wa) * b.d[i];
  return r;
}

// Gauss-Legendre nodes and weights on [-1, 1] (Newton on P_n, in double).
void gauss_legendre(int n, double* x, double* w) {
  const double pi = 3.14159265358979323846;
  for (int i = 0; i < n; ++i) {
    double z = std::cos(pi * (i + 0.75) / (n + 0.5)), dp = 1;
    for (int it = 0; it < 100; ++it) {
      double p0 = 1, p1 = z;
      for (int j = 2; j <= n; ++j) {
        double p2 = ((2 * j - 1) * z * p1 - (j - 1) * p0) / j;
        p0 = p1;
        p1 = p2;
      }
      if (n == 1) p0 = 1;
      dp = n * (z * p1 - p0) / (z * z - 1);
      double dz = p1 / dp;
      z -= dz;
      if (std::abs(dz) < 1e-16) break;
    }
    x[n - 1 - i] = z;  // ascending, as numpy's leggauss
    w[n - 1 - i] = 2 / ((1 - z * z) * dp * dp);
  }
}

// `ndf._lerp`: a + t d from the nearer end.
template <typename V>
inline V lerp(V a, V b, V d, V t) {
  return sel<V>(t <= splat<V>(0.5), a + t * d, b - (1 - t) * d);
}

// `lobe._lobes` at one abscissa per lane.
template <typename V>
struct Lobes {
  V F1, T2, inv2, N, e, se, ee, see;
};

template <typename V>
inline Lobes<V> lobes(V u, const V* p) {
  const V u1 = p[5], q1 = p[6], g = p[7], k = p[8], hx = p[9], hz = p[10];
  Lobes<V> r;
  V u2 = u * u;
  V B = 1 + 4 * u2;
  r.N = hz * (1 - 4 * u2) - 4 * hx * u;
  V d = u - u1;
  V inv1 = 1 / (q1 * q1 + d * d);
  V T1 = g * B * inv1 / 4;
  r.inv2 = 1 / (B + k * r.N);
  r.e = q1 * q1 * inv1;
  r.se = q1 * d * inv1;
  r.F1 = T1 * T1 + T1;
  r.T2 = B * r.inv2;
  r.ee = r.e * r.e;
  r.see = r.se * r.e;
  return r;
}

// `lobe.piece_values(..., with_partials=True)` for one piece per lane: the value, the partials
// with respect to the ends (ua, ub, Ya, Yb) and (accumulated into dp) the 11 lobe parameters.
template <typename T, typename V, bool kPartials>
V piece(int n_gl, const double* xs, const double* ws, V ua, V ub, V Ya, V Yb, const V* p, V* d_ua,
        V* d_ub, V* d_Ya, V* d_Yb, V* dp) {
  const V c0 = p[0], u1 = p[5], q1 = p[6], k = p[8];
  const V ct[4] = {p[1], p[2], p[3], p[4]};
  const V one = splat<V>(1), zero = V{};
  V du = ub - ua, half = du / 2, um = ua + half, Ym = (Ya + Yb) / 2, dY = Yb - Ya;
  V ds = du / q1, sa = (ua - u1) / q1, sm = sa + ds / 2;
  auto use_cf = vabs<T>(ds) >= vmax<T>(one, splat<V>(0.5) * vabs<T>(sm));
  V ds_s = sel<V>(use_cf, ds, one), sa_s = sel<V>(use_cf, sa, zero), sb_s = sa_s + ds_s;
  V ea = 1 / (1 + sa_s * sa_s), eb = 1 / (1 + sb_s * sb_s);
  // `lobe._t1_closed`.
  V B0[5], B1[5], E0, E1, Et0;
  {
    V s_a = sa_s, s_d = ds_s, s_b = s_a + s_d, s_m = s_a + s_d / 2;
    V y0 = 1 + s_a * s_b, ps = s_d * (s_a + s_b);
    auto up = ps >= 0;
    V larg = sel<V>(up, ps * ea, -ps * eb);
    V I0, lg;
    I0 = vatan2<T>(s_d, y0);
    lg = vlog1p<T>(larg);
    V I1 = splat<V>(0.5) * sel<V>(up, one, -one) * lg;
    V K1 = splat<V>(0.5) * (s_d * ea) * ((s_a + s_b) * eb);
    V K0 = splat<V>(0.5) * I0 + splat<V>(0.5) * (s_d * ea) * ((1 - s_a * s_b) * eb);
    B0[0] = s_d; B0[1] = I0; B0[2] = I1; B0[3] = K0; B0[4] = K1;
    B1[0] = zero;
    B1[1] = I1 - s_m * I0;
    B1[2] = s_d - I0 - s_m * I1;
    B1[3] = K1 - s_m * K0;
    B1[4] = (I0 - K0) - s_m * K1;
    E0 = c0 * B0[0] + ct[0] * B0[1] + ct[1] * B0[2] + ct[2] * B0[3] + ct[3] * B0[4];
    E1 = ct[0] * B1[1] + ct[1] * B1[2] + ct[2] * B1[3] + ct[3] * B1[4];
    Et0 = ct[0] * B0[1] + ct[1] * B0[2] + ct[2] * B0[3] + ct[3] * B0[4];
  }
  V cf = q1 * (Ym * E0 + (dY / ds_s) * E1);
  if constexpr (!kPartials) {  // the value alone: `lobe.piece_values(..., False)`
    V t1 = zero, t2 = zero;
    for (int j = 0; j < n_gl; ++j) {
      const V x = splat<V>(xs[j]), w = splat<V>(ws[j]);
      Lobes<V> at = lobes(um + half * x, p);
      V wy = w * (Ym + (dY / 2) * x);
      t1 += wy * at.F1;
      t2 += wy * (at.T2 * at.T2 + at.T2);
    }
    return sel<V>(use_cf, cf, half * t1) + half * t2;
  }
  V gl_t1 = zero, gl_t2 = zero, m0_2 = zero, mc_2 = zero, m0t_gl = zero, mc_gl = zero;
  V bas[4] = {zero, zero, zero, zero};
  V ft_wy = zero, dk = zero, dhx = zero, dhz = zero;
  for (int j = 0; j < n_gl; ++j) {
    const V x = splat<V>(xs[j]), w = splat<V>(ws[j]);
    V uu = um + half * x;
    Lobes<V> at = lobes(uu, p);
    V F2 = at.T2 * at.T2 + at.T2;
    V wy = w * (Ym + (dY / 2) * x);
    gl_t2 += wy * F2;
    gl_t1 += wy * at.F1;
    m0_2 += w * F2;
    mc_2 += w * x * F2;
    V Ft = ct[0] * at.e + ct[1] * at.se + ct[2] * at.ee + ct[3] * at.see;
    m0t_gl += w * Ft;
    mc_gl += w * x * at.F1;
    bas[0] += wy * at.e;
    bas[1] += wy * at.se;
    bas[2] += wy * at.ee;
    bas[3] += wy * at.see;
    ft_wy += wy * Ft;
    V f = half * wy * (-(2 * at.T2 + 1) * at.T2 * at.inv2);
    dk += f * at.N;
    dhx += f * (-4 * k * uu);
    dhz += f * (k * (1 - 4 * uu * uu));
  }
  gl_t2 *= half;
  gl_t1 *= half;
  V value = sel<V>(use_cf, cf, gl_t1) + gl_t2;
  m0_2 /= 2;
  mc_2 /= 4;
  m0t_gl /= 2;
  mc_gl /= 4;
  V m0t_1 = sel<V>(use_cf, Et0 / ds_s, m0t_gl);
  V mc_1 = sel<V>(use_cf, E1 / (ds_s * ds_s), mc_gl);
  V m0 = m0t_1 + c0 + m0_2, mc = mc_1 + mc_2;
  V ma = m0 / 2 - mc, mb = m0 / 2 + mc;
  Lobes<V> ea_ = lobes(ua, p), eb_ = lobes(ub, p);
  V Da = ea_.F1 + ea_.T2 * ea_.T2 + ea_.T2;
  V Db = eb_.F1 + eb_.T2 * eb_.T2 + eb_.T2;
  auto point = (ua == ub) & (Ya == Yb);
  *d_ua = sel<V>(point, zero, -Ya * Da - dY * ma);
  *d_ub = sel<V>(point, zero, Yb * Db - dY * mb);
  *d_Ya = du * ma;
  *d_Yb = du * mb;
  V d_c[4];
  for (int i = 0; i < 4; ++i)
    d_c[i] = sel<V>(use_cf, q1 * (Ym * B0[i + 1] + (dY / ds_s) * B1[i + 1]), half * bas[i]);
  V sb = sa + ds;
  V Fta = ct[0] * ea_.e + ct[1] * ea_.se + ct[2] * ea_.ee + ct[3] * ea_.see;
  V Ftb = ct[0] * eb_.e + ct[1] * eb_.se + ct[2] * eb_.ee + ct[3] * eb_.see;
  V d_u1 = -(Yb * Ftb - Ya * Fta) + dY * m0t_1;
  V It_over_q1 = sel<V>(use_cf, Ym * Et0 + (dY / ds_s) * E1, (ds / 2) * ft_wy);
  V d_q1 = -(Yb * sb * Ftb - Ya * sa * Fta) + dY * (mc_1 * ds + sm * m0t_1) + It_over_q1;
  // A point's partials are zero (`lobe.piece_values`).
  dp[0] += sel<V>(point, zero, Ym * du);
  for (int i = 0; i < 4; ++i) dp[1 + i] += sel<V>(point, zero, d_c[i]);
  dp[5] += sel<V>(point, zero, d_u1);
  dp[6] += sel<V>(point, zero, d_q1);
  dp[8] += sel<V>(point, zero, dk);
  dp[9] += sel<V>(point, zero, dhx);
  dp[10] += sel<V>(point, zero, dhz);
  return value;
}

// The view algebra with its Jacobian (`ndf._lit_integral`'s half vector in the scratch frame,
// `_view`, `lit_interval`, `lobe.lobe`, `lobe_params`), from sv = (X, h (3), b (2), t (2),
// alpha): computed here with IEEE operations, not in an XLA fusion (whose rewrites, such as
// x / sqrt(y) -> x * rsqrt(y), move a sharp peak by an ulp or two). Out: X, the roots u_m, u_p of
// N (`lit_interval`) and the 11 lobe parameters, each with the tangents of the template's
// count (kTan with the partials; 0 for the value alone, which needs none).
template <typename V, int N = kTan>
struct View {
  Dual<V, N> X, u_m, u_p, pd[11];
};

template <typename T, typename V, int N = kTan>
void view_algebra(const V* sv, View<V, N>* o) {
  const V one = splat<V>(1), two = splat<V>(2);
  Dual<V, N> Xd = var<N>(sv[0], 0), h0 = var<N>(sv[1], 1), h1 = var<N>(sv[2], 2),
             h2 = var<N>(sv[3], 3), b0 = var<N>(sv[4], 4), b1 = var<N>(sv[5], 5),
             t0 = var<N>(sv[6], 6), t1 = var<N>(sv[7], 7), al = var<N>(sv[8], 8);
  Dual<V, N> nrm = dsqrt<T>(h0 * h0 + h1 * h1 + h2 * h2);
  Dual<V, N> hn0 = h0 / nrm, hn1 = h1 / nrm, hz = h2 / nrm;
  Dual<V, N> hx = hn0 * b0 + hn1 * b1, hy = hn0 * t0 + hn1 * t1;
  Dual<V, N> r = dsqrt<T>(hx * hx + hz * hz);
  Dual<V, N> rp = r + dabs<T>(hx);
  Dual<V, N> near = hz / scale(two, rp), far = rp / scale(two, hz);
  auto hx_pos = hx.v >= 0;
  o->X = Xd;
  o->u_p = dsel(hx_pos, near, far);
  o->u_m = dsel(hx_pos, -far, -near);
  Dual<V, N> a2 = al * al;
  Dual<V, N> kk = dsafe_sqrt<T>(cst<N>(one) - a2);
  Dual<V, N> g = cst<N>(one) / (cst<N>(one) + kk * hz);
  Dual<V, N> beta2 = a2 + kk * kk * hy * hy;
  Dual<V, N> beta = dsqrt<T>(beta2);
  Dual<V, N> u1 = -(g * kk * hx) / cst<N>(two);
  Dual<V, N> q1 = g * beta / cst<N>(two);
  Dual<V, N> a = -(scale(two, g) * kk * hx) / beta;
  Dual<V, N> m = scale(two, kk) * (hz + g * kk * hx * hx) / beta2;
  Dual<V, N> g21 = scale(two, g) + cst<N>(one);
  const Dual<V, N> pd[11] = {g * g + g, g21 * m + a * a, g21 * a, m * m - a * a,
                             scale(two, a) * m, u1, q1, g, kk, hx, hz};
  for (int i = 0; i < 11; ++i) o->pd[i] = pd[i];
}

// `ndf._cut` of k pieces (one per lane) to the slab [Lo, Hi], with what its transpose
// (`ndf._cut_transpose`, `cut_transpose`) needs; `ref` (`ndf._centre`, no derivative) is to be
// subtracted from Ya2, Yb2.
template <typename V>
struct Cut {
  typedef decltype(V{} < V{}) M;
  V ca[kMaxPieces], cb[kMaxPieces], Ya2[kMaxPieces], Yb2[kMaxPieces], ta[kMaxPieces],
      tb[kMaxPieces], dYs[kMaxPieces], inv_du[kMaxPieces];
  M ta_free[kMaxPieces], tb_free[kMaxPieces], lo_a[kMaxPieces], hi_a[kMaxPieces],
      lo_b[kMaxPieces], hi_b[kMaxPieces], pt[kMaxPieces];
  V ref;
};

template <typename T, typename V>
void cut(int k, const V* ua, const V* ub, const V* Ya, const V* Yb, V Lo, V Hi, Cut<V>* c) {
  typedef typename Cut<V>::M M;
  const V zero = V{}, one = splat<V>(1);
  V sw = zero, swy = zero;
  for (int i = 0; i < k; ++i) {
    V du = ub[i] - ua[i], dY = Yb[i] - Ya[i];
    c->lo_a[i] = ua[i] < Lo; c->hi_a[i] = ua[i] > Hi;
    c->lo_b[i] = ub[i] < Lo; c->hi_b[i] = ub[i] > Hi;
    M moved_a = c->lo_a[i] | c->hi_a[i], moved_b = c->lo_b[i] | c->hi_b[i];
    V c_a = sel<V>(c->lo_a[i], Lo, sel<V>(c->hi_a[i], Hi, ua[i]));
    V c_b = sel<V>(c->lo_b[i], Lo, sel<V>(c->hi_b[i], Hi, ub[i]));
    M nz = du != 0;
    V inv = 1 / sel<V>(nz, du, one);
    auto param = [&](V cc, M moved, V dflt, M* fr) {
      V rr = (cc - ua[i]) * inv;
      M mm = moved & nz;
      *fr = mm & (rr > 0) & (rr < 1);
      return sel<V>(mm, sel<V>(rr <= 0, zero, sel<V>(rr >= 1, one, rr)), dflt);
    };
    c->ta[i] = param(c_a, moved_a, zero, &c->ta_free[i]);
    c->tb[i] = param(c_b, moved_b, one, &c->tb_free[i]);
    V y_a = lerp(Ya[i], Yb[i], dY, c->ta[i]);
    V y_b = lerp(Ya[i], Yb[i], dY, c->tb[i]);
    c->pt[i] = (nz & (c_a == c_b)) | (~nz & moved_a);
    c_b = sel<V>(c->pt[i], c_a, c_b);
    y_b = sel<V>(c->pt[i], y_a, y_b);
    c->ca[i] = c_a; c->cb[i] = c_b; c->Ya2[i] = y_a; c->Yb2[i] = y_b; c->dYs[i] = dY;
    c->inv_du[i] = inv;
    V wgt = vabs<T>(c_b - c_a) + vabs<T>(y_b - y_a);
    sw += wgt;
    swy += wgt * (y_a + y_b) / 2;
  }
  c->ref = sel<V>(sw > 0, swy / sel<V>(sw > 0, sw, one), zero);
}

// `ndf._cut_transpose` of piece i: from the partials with respect to the cut piece's ends to
// those of the uncut piece (g_ua .. g_Yb) and, summed, of the slab bounds (g_lo, g_hi).
template <typename V>
void cut_transpose(const Cut<V>& c, int i, V dca, V dcb, V dYa, V dYb, V* g_ua, V* g_ub,
                   V* g_Ya, V* g_Yb, V* g_lo, V* g_hi) {
  const V zero = V{};
  dca = dca + sel<V>(c.pt[i], dcb, zero);
  dYa = dYa + sel<V>(c.pt[i], dYb, zero);
  dcb = sel<V>(c.pt[i], zero, dcb);
  dYb = sel<V>(c.pt[i], zero, dYb);
  *g_Ya = dYa * (1 - c.ta[i]) + dYb * (1 - c.tb[i]);
  *g_Yb = dYa * c.ta[i] + dYb * c.tb[i];
  V ga = sel<V>(c.ta_free[i], dYa * c.dYs[i] * c.inv_du[i], zero);
  V gb = sel<V>(c.tb_free[i], dYb * c.dYs[i] * c.inv_du[i], zero);
  dca += ga;
  dcb += gb;
  V gua = ga * (c.ta[i] - 1) + gb * (c.tb[i] - 1);
  V gub = -(ga * c.ta[i] + gb * c.tb[i]);
  gua += sel<V>(c.lo_a[i] | c.hi_a[i], zero, dca);
  gub += sel<V>(c.lo_b[i] | c.hi_b[i], zero, dcb);
  *g_ua = gua;
  *g_ub = gub;
  *g_lo += sel<V>(c.lo_a[i], dca, zero) + sel<V>(c.lo_b[i], dcb, zero);
  *g_hi += sel<V>(c.hi_a[i], dca, zero) + sel<V>(c.hi_b[i], dcb, zero);
}

// One lane per pair-view: `L` pair-views from lanes of the inputs (pieces `k` per lane).
template <typename T, typename V, bool kPartials>
void lit_lanes(int n_gl, const double* xs, const double* ws, int k, const V* ua, const V* ub,
               const V* Ya, const V* Yb, const V* sv, V* out, V* g_ua, V* g_ub, V* g_Ya,
               V* g_Yb, V* gs) {
  const V zero = V{};
  constexpr int NV = kPartials ? kTan : 0;  // (the value alone needs no tangents)
  View<V, NV> vw;
  view_algebra<T, V, NV>(sv, &vw);
  const Dual<V, NV> lo = dmax<T>(-vw.X, vw.u_m);
  const Dual<V, NV> hi = dmax<T>(dmin<T>(vw.X, vw.u_p), lo);
  V p[11];
  for (int i = 0; i < 11; ++i) p[i] = vw.pd[i].v;
  Cut<V> c;
  cut<T>(k, ua, ub, Ya, Yb, lo.v, hi.v, &c);
  V value = zero, dp[11], g_lo = zero, g_hi = zero;
  for (int i = 0; i < 11; ++i) dp[i] = zero;
  for (int i = 0; i < k; ++i) {
    V dca, dcb, dYa, dYb;
    value += piece<T, V, kPartials>(n_gl, xs, ws, c.ca[i], c.cb[i], c.Ya2[i] - c.ref,
                                    c.Yb2[i] - c.ref, p, &dca, &dcb, &dYa, &dYb, dp);
    if constexpr (kPartials)
      cut_transpose(c, i, dca, dcb, dYa, dYb, &g_ua[i], &g_ub[i], &g_Ya[i], &g_Yb[i], &g_lo,
                    &g_hi);
  }
  *out = value;
  if constexpr (kPartials) {
    // Chain the slab bounds' and the lobe parameters' partials through the view algebra.
    for (int t = 0; t < kTan; ++t) {
      V s = g_lo * lo.d[t] + g_hi * hi.d[t];
      for (int i = 0; i < 11; ++i) s += dp[i] * vw.pd[i].d[t];
      gs[t] = s;
    }
  }
}

// Pair-views [i0, i1), `L` at a time, lanes gathered from and scattered to the flat arrays
// (a tail of fewer than `L` repeats its last pair-view in the spare lanes and keeps only its
// own). `in`: ua, ub, Ya, Yb (k per pair-view), X, h (3), b (2), t (2), alpha; `res`: lit, then
// the partials in the same layout.
constexpr int kFields = 5;                          // X, h, b, t, alpha
constexpr int kFieldWidth[kFields] = {1, 3, 2, 2, 1};  // their kTan = 9 values per pair-view

template <typename T, bool kPartials>
void lit_range(int n_gl, const double* xs, const double* ws, size_t k, size_t i0, size_t i1,
               const T* const* in, T* const* res) {
  typedef typename Vec<T>::type V;
  constexpr int L = Vec<T>::L;
  for (size_t b = i0; b < i1; b += L) {
    const int lanes = static_cast<int>(std::min<size_t>(L, i1 - b));
    V pc[4][kMaxPieces], sv[kTan];
    for (int l = 0; l < L; ++l) {
      const size_t i = b + std::min(l, lanes - 1);
      for (int f = 0; f < 4; ++f)
        for (size_t j = 0; j < k; ++j) pc[f][j][l] = in[f][i * k + j];
      for (int f = 0, c = 0; f < kFields; ++f)
        for (int w = 0; w < kFieldWidth[f]; ++w, ++c) sv[c][l] = in[4 + f][i * kFieldWidth[f] + w];
    }
    V out, gp[4][kMaxPieces], gs[kTan];
    lit_lanes<T, V, kPartials>(n_gl, xs, ws, static_cast<int>(k), pc[0], pc[1], pc[2], pc[3],
                               sv, &out, gp[0], gp[1], gp[2], gp[3], gs);
    for (int l = 0; l < lanes; ++l) {
      const size_t i = b + l;
      res[0][i] = out[l];
      if constexpr (!kPartials) continue;
      for (int f = 0; f < 4; ++f)
        for (size_t j = 0; j < k; ++j) res[1 + f][i * k + j] = gp[f][j][l];
      for (int f = 0, c = 0; f < kFields; ++f)
        for (int w = 0; w < kFieldWidth[f]; ++w, ++c) res[5 + f][i * kFieldWidth[f] + w] = gs[c][l];
    }
  }
}

// Pair-views per chunk of work (a multiple of every vector width).
constexpr size_t kChunk = 2048;

// One call's chunks, shared by the caller and its pool tasks (kept alive by the tasks that hold
// it; `body` is only called for a claimed chunk, i.e. while the caller waits).
struct Job {
  std::atomic<size_t> next{0};
  size_t chunks = 0;
  std::function<void(size_t)> body;
  std::mutex mu;
  std::condition_variable cv;
  size_t done = 0;

  // Claim and run chunks until none is left.
  void drain() {
    size_t mine = 0;
    for (size_t c; (c = next.fetch_add(1, std::memory_order_relaxed)) < chunks; ++mine) body(c);
    if (mine == 0) return;
    std::lock_guard<std::mutex> lock(mu);
    done += mine;
    if (done == chunks) cv.notify_all();
  }
  // Until every claimed chunk has run (called after `drain`, so all chunks are claimed).
  void wait() {
    std::unique_lock<std::mutex> lock(mu);
    cv.wait(lock, [this] { return done == chunks; });
  }
};

// `work(i0, i1)` over [0, n) in chunks of `chunk` on the caller and up to `threads` - 1 tasks
// of `pool` (the cut depends on n and chunk alone).
template <typename F>
void parallel(ffi::ThreadPool& pool, size_t n, size_t chunk, int64_t threads, F work) {
  const size_t chunks = (n + chunk - 1) / chunk;
  size_t workers = std::min<size_t>(chunks, static_cast<size_t>(std::max<int64_t>(1, threads)));
  if (workers > 1) workers = std::min<size_t>(workers, std::max<int64_t>(1, pool.num_threads()));
  if (workers <= 1) {
    work(size_t{0}, n);
    return;
  }
  auto job = std::make_shared<Job>();
  job->chunks = chunks;
  job->body = [&](size_t c) { work(c * chunk, std::min(n, (c + 1) * chunk)); };
  for (size_t w = 1; w < workers; ++w) pool.Schedule([job] { job->drain(); });
  job->drain();
  job->wait();
}

// Pair-views [0, n) on the caller and up to `threads` - 1 tasks of `pool` (chunks of `kChunk`).
template <typename T, bool kPartials>
ffi::Error run(ffi::ThreadPool& pool, const size_t* counts, int64_t n_gl, int64_t threads,
               const T* const* in, T* const* res) {
  // counts: element counts of ua, ub, Ya, Yb, X, h, b, t, alpha.
  const size_t n = counts[4];
  if (n == 0) return ffi::Error::Success();
  const size_t k = counts[0] / n;
  bool ok = k * n == counts[0] && k <= kMaxPieces && n_gl >= 1 && n_gl <= kMaxNodes;
  for (int f = 1; f < 4; ++f) ok = ok && counts[f] == counts[0];
  for (int f = 0; f < kFields; ++f) ok = ok && counts[4 + f] == n * kFieldWidth[f];
  if (!ok)
    return ffi::Error(ffi::ErrorCode::kInvalidArgument,
                      "jscratch lit: inputs must be (n, k) pieces, (n,) X and alpha, (n, 3) h, "
                      "(n, 2) b and t, k <= 8");
  double xs[kMaxNodes], ws[kMaxNodes];
  gauss_legendre(static_cast<int>(n_gl), xs, ws);
  parallel(pool, n, kChunk, threads, [&](size_t i0, size_t i1) {
    lit_range<T, kPartials>(static_cast<int>(n_gl), xs, ws, k, i0, i1, in, res);
  });
  return ffi::Error::Success();
}

template <ffi::DataType DT>
ffi::Error LitImpl(ffi::ThreadPool pool, ffi::Buffer<DT> ua, ffi::Buffer<DT> ub,
                   ffi::Buffer<DT> Ya, ffi::Buffer<DT> Yb, ffi::Buffer<DT> X, ffi::Buffer<DT> h,
                   ffi::Buffer<DT> b, ffi::Buffer<DT> t, ffi::Buffer<DT> alpha, int64_t n_gl,
                   int64_t threads, ffi::ResultBuffer<DT> out,
                   ffi::ResultBuffer<DT> g_ua, ffi::ResultBuffer<DT> g_ub,
                   ffi::ResultBuffer<DT> g_Ya, ffi::ResultBuffer<DT> g_Yb,
                   ffi::ResultBuffer<DT> g_X, ffi::ResultBuffer<DT> g_h,
                   ffi::ResultBuffer<DT> g_b, ffi::ResultBuffer<DT> g_t,
                   ffi::ResultBuffer<DT> g_alpha) {
  using T = ffi::NativeType<DT>;
  const T* in[9] = {ua.typed_data(), ub.typed_data(), Ya.typed_data(), Yb.typed_data(),
                    X.typed_data(),  h.typed_data(), b.typed_data(), t.typed_data(),
                    alpha.typed_data()};
  T* res[10] = {out->typed_data(),  g_ua->typed_data(), g_ub->typed_data(), g_Ya->typed_data(),
                g_Yb->typed_data(), g_X->typed_data(),  g_h->typed_data(),  g_b->typed_data(),
                g_t->typed_data(),  g_alpha->typed_data()};
  const size_t counts[9] = {ua.element_count(), ub.element_count(), Ya.element_count(),
                            Yb.element_count(), X.element_count(),  h.element_count(),
                            b.element_count(),  t.element_count(),  alpha.element_count()};
  return run<T, true>(pool, counts, n_gl, threads, in, res);
}

template <ffi::DataType DT>
ffi::Error LitValuesImpl(ffi::ThreadPool pool, ffi::Buffer<DT> ua, ffi::Buffer<DT> ub,
                         ffi::Buffer<DT> Ya, ffi::Buffer<DT> Yb, ffi::Buffer<DT> X,
                         ffi::Buffer<DT> h, ffi::Buffer<DT> b, ffi::Buffer<DT> t,
                         ffi::Buffer<DT> alpha,
                         int64_t n_gl, int64_t threads, ffi::ResultBuffer<DT> out) {
  using T = ffi::NativeType<DT>;
  const T* in[9] = {ua.typed_data(), ub.typed_data(), Ya.typed_data(), Yb.typed_data(),
                    X.typed_data(),  h.typed_data(), b.typed_data(), t.typed_data(),
                    alpha.typed_data()};
  T* res[1] = {out->typed_data()};
  const size_t counts[9] = {ua.element_count(), ub.element_count(), Ya.element_count(),
                            Yb.element_count(), X.element_count(),  h.element_count(),
                            b.element_count(),  t.element_count(),  alpha.element_count()};
  return run<T, false>(pool, counts, n_gl, threads, in, res);
}

// The ball cutter's groove: `arc_lit_lanes`, the per-view stage of `arc.arc_lit_integral`.
#include "native_arc.h"

// ------------------------------------------------------------------------------------------
// The whole pair: the view-independent geometry (`ndf._pair_geometry`) with its Jacobian with
// respect to p0, p1, width and depth (forward mode, kGeo tangents; the footprint is data), then
// every view's lit integral (`lit_lanes`) on the pieces that are not points, chained.

constexpr int kGeo = 6;     // tangents of the pair geometry: p0 (2), p1 (2), width, depth
constexpr int kPieces = 6;  // `ndf.N_PIECES`

template <typename V>
inline V vsign(V x) {
  return sel<V>(x > 0, splat<V>(1), sel<V>(x < 0, splat<V>(-1), V{}));
}

// Error-free sum and product (`ndf._two_sum`, `ndf._two_prod`; -ffp-contract=off keeps them so).
template <typename T, typename V>
inline void two_sum(V a, V b, V* s, V* e) {
  *s = a + b;
  V bb = *s - a;
  *e = (a - (*s - bb)) + (b - bb);
}
template <typename T, typename V>
inline void two_prod(V a, V b, V* p, V* e) {
  const V split = splat<V>(sizeof(T) == 4 ? 4097.0 : 134217729.0);
  *p = a * b;
  V ca = split * a, ah = ca - (ca - a), al = a - ah;
  V cb = split * b, bh = cb - (cb - b), bl = b - bh;
  *e = ((ah * bh - *p) + ah * bl + al * bh) + al * bl;
}

// `ndf._cross_accurate(o, p0, p1)` for a constant `o`: the value compensated, the tangents those
// of `(o - p0) x (p1 - p0)` (what autodiff of the compensated form gives, up to rounding).
template <typename T, typename V, int N>
Dual<V, N> cross_accurate(V ox, V oy, const Dual<V, N>& p0x, const Dual<V, N>& p0y,
                          const Dual<V, N>& p1x, const Dual<V, N>& p1y) {
  V ex, ex_lo, ey, ey_lo, dx, dx_lo, dy, dy_lo, a, a_lo, b, b_lo;
  two_sum<T>(ox, -p0x.v, &ex, &ex_lo);
  two_sum<T>(oy, -p0y.v, &ey, &ey_lo);
  two_sum<T>(p1x.v, -p0x.v, &dx, &dx_lo);
  two_sum<T>(p1y.v, -p0y.v, &dy, &dy_lo);
  two_prod<T>(ex, dy, &a, &a_lo);
  two_prod<T>(ey, dx, &b, &b_lo);
  V small = (a_lo - b_lo) + (ex * dy_lo + ex_lo * dy) - (ey * dx_lo + ey_lo * dx);
  Dual<V, N> r;
  r.v = (a - b) + small;
  for (int i = 0; i < N; ++i)
    r.d[i] = (-p0x.d[i] * dy + ex * (p1y.d[i] - p0y.d[i])) -
             (-p0y.d[i] * dx + ey * (p1x.d[i] - p0x.d[i]));
  return r;
}

// `ndf._lerp` with a dual parameter.
template <typename V, int N>
inline Dual<V, N> dlerp(const Dual<V, N>& a, const Dual<V, N>& b, const Dual<V, N>& d,
                        const Dual<V, N>& t) {
  return dsel(t.v <= splat<V>(0.5), a + t * d, b - (cst<N>(splat<V>(1)) - t) * d);
}

// `ndf._ratio_clipped`.
template <typename T, typename V>
inline V ratio_clipped(V num, V den) {
  auto ok = (vabs<T>(num) <= 2 * vabs<T>(den)) & (den != 0);
  V r = num / sel<V>(ok, den, splat<V>(1));
  V out = 2 * vsign(num) * vsign(den);
  return sel<V>(ok, r, sel<V>(den == 0, 2 * vsign(num), out));
}

// One pair per lane, view-independent: Q's boundary cut to the groove (`ndf.PairGeometry`'s
// `pieces`), the area, `scale` = -w (orientation sign), the frame and X.
template <typename V, int N>
struct Geo {
  Dual<V, N> ua[kPieces], ub[kPieces], Ya[kPieces], Yb[kPieces];
  Dual<V, N> area, scale, X, tx, ty, bx, by;
};

template <typename T, typename V, int N>
void geometry(const V (&fp)[4][2], const Dual<V, N>& p0x, const Dual<V, N>& p0y,
              const Dual<V, N>& p1x, const Dual<V, N>& p1y, const Dual<V, N>& w,
              const Dual<V, N>& dep, Geo<V, N>* g) {
  typedef Dual<V, N> D;
  const V zero = V{}, one = splat<V>(1), half = splat<V>(0.5);
  const D cone = cst<N>(one), czero = cst<N>(zero);
  // `ndf.local_frame`.
  D dx = p1x - p0x, dy = p1y - p0y;
  D L2 = dx * dx + dy * dy;
  D L = dsafe_sqrt<T>(L2);
  auto pos = L2.v > 0;
  D Ls = dsel(pos, L, cone);
  D tx = dsel(pos, dx / Ls, czero), ty = dsel(pos, dy / Ls, cone);
  D bx = ty, by = -tx;
  // `ndf._strip_frame`: origin at vertex 0.
  const V cx = fp[0][0], cy = fp[0][1];
  V qx[4], qy[4];
  for (int i = 0; i < 4; ++i) {
    qx[i] = fp[i][0] - cx;
    qy[i] = fp[i][1] - cy;
  }
  D cpx = cst<N>(cx) - p0x, cpy = cst<N>(cy) - p0y;
  auto Lpos = L.v > 0;
  D x_c = dsel(Lpos, cross_accurate<T>(cx, cy, p0x, p0y, p1x, p1y) / dsel(Lpos, L, cone),
               cpx * bx + cpy * by);
  D y_c = cpx * tx + cpy * ty;
  D y[4], u[4];
  for (int i = 0; i < 4; ++i) {
    y[i] = scale(qx[i], tx) + scale(qy[i], ty);
    u[i] = (scale(qx[i], bx) + scale(qy[i], by) + x_c) / w;
  }
  D y_lo = -y_c, y_hi = L - y_c;
  // `ndf._groove`: orientation and groove half-width X = x_max / w.
  V area2 = zero;
  for (int i = 0; i < 4; ++i) area2 += qx[i] * qy[(i + 1) % 4] - qx[(i + 1) % 4] * qy[i];
  V sign = sel<V>(area2 >= 0, one, -one);
  D ratio = scale(splat<V>(-2), dep) / w;
  D em;
  for (int l = 0; l < Vec<T>::L; ++l) em.v[l] = std::expm1(ratio.v[l]);
  for (int i = 0; i < N; ++i) em.d[i] = ratio.d[i] * (em.v + 1);
  D X = (scale(half, w) * dsafe_sqrt<T>(-em)) / w;

  // `ndf._strip_pieces`: the edges clipped to y_lo <= y <= y_hi and the two chains.
  D e_ua[4], e_ub[4], e_ya[4], e_yb[4];
  D lo_in = czero, lo_out = czero, hi_in = czero, hi_out = czero;
  V sw = zero, swy = zero;
  auto hi_touch = zero > one;  // the boundary crosses or touches y_hi (`ndf._strip_pieces`)
  for (int i = 0; i < 4; ++i) {
    const int j = (i + 1) % 4;
    D du = u[j] - u[i], dyd = y[j] - y[i];
    const V d0 = dyd.v, a = y[i].v, lo = y_lo.v, hi = y_hi.v;
    V r_lo = ratio_clipped<T>(lo - a, d0), r_hi = ratio_clipped<T>(hi - a, d0);
    auto inside = (a >= lo) & (a <= hi);
    V tin = sel<V>(d0 > 0, r_lo, sel<V>(d0 < 0, r_hi, sel<V>(inside, -splat<V>(2), splat<V>(2))));
    V tout = sel<V>(d0 > 0, r_hi, sel<V>(d0 < 0, r_lo, sel<V>(inside, splat<V>(2), -splat<V>(2))));
    V t0 = vmax<T>(tin, zero), t1 = vmin<T>(tout, one);
    auto empty = t1 <= t0;
    t1 = vmax<T>(t1, t0);
    auto vert0 = t0 <= 0, vert1 = t1 >= 1;
    auto up = d0 > 0;
    D bound0 = dsel(up, y_lo, y_hi), bound1 = dsel(up, y_hi, y_lo);
    // `ndf._implicit`: the root of the constraint that sets each end.
    const V slope = sel<V>(d0 == 0, one, d0);
    D T0 = cst<N>(t0), T1 = cst<N>(t1);
    D r0 = y[i] + scale(t0, dyd) - bound0, r1 = y[i] + scale(t1, dyd) - bound1;
    for (int k = 0; k < N; ++k) {
      T0.d[k] = sel<V>(vert0, zero, -r0.d[k] / slope);
      T1.d[k] = sel<V>(vert1, zero, -r1.d[k] / slope);
    }
    e_ua[i] = dlerp(u[i], u[j], du, T0);
    e_ya[i] = dsel(vert0, y[i], bound0);
    e_ub[i] = dsel(empty, e_ua[i], dlerp(u[i], u[j], du, T1));
    e_yb[i] = dsel(empty, e_ya[i], dsel(vert1, y[j], bound1));
    const V yi = y[i].v, yj = y[j].v;
    lo_in = lo_in + dsel((yi >= lo) & (yj < lo), e_ub[i], czero);
    lo_out = lo_out + dsel((yi < lo) & (yj >= lo), e_ua[i], czero);
    hi_in = hi_in + dsel((yi <= hi) & (yj > hi), e_ub[i], czero);
    hi_out = hi_out + dsel((yi > hi) & (yj <= hi), e_ua[i], czero);
    hi_touch = hi_touch | ((yi <= hi) & (yj > hi)) | ((yi > hi) & (yj <= hi));
    V wgt = vabs<T>(e_ub[i].v - e_ua[i].v) + vabs<T>(e_yb[i].v - e_ya[i].v);
    sw += wgt;
    swy += wgt * (e_ya[i].v + e_yb[i].v) / 2;
  }
  // y_ref carries no derivative; a strip that holds one point of the footprint, at y_hi,
  // takes y_hi (`ndf._strip_pieces`).
  const D y_ref = cst<N>(sel<V>(sw > 0, swy / sel<V>(sw > 0, sw, one),
                                sel<V>(hi_touch, y_hi.v, y_lo.v)));
  D pu[kPieces] = {e_ua[0], e_ua[1], e_ua[2], e_ua[3], lo_in, hi_in};
  D pv[kPieces] = {e_ub[0], e_ub[1], e_ub[2], e_ub[3], lo_out, hi_out};
  D pa[kPieces] = {e_ya[0] - y_ref, e_ya[1] - y_ref, e_ya[2] - y_ref, e_ya[3] - y_ref,
                   y_lo - y_ref, y_hi - y_ref};
  D pb[kPieces] = {e_yb[0] - y_ref, e_yb[1] - y_ref, e_yb[2] - y_ref, e_yb[3] - y_ref,
                   y_lo - y_ref, y_hi - y_ref};

  // `ndf._cut` to the groove [-X, X] (its forward mode is `_cut_transpose`'s transpose), then
  // `_centre` (no derivative).
  const D lo = -X, hi = X;
  sw = zero;
  swy = zero;
  for (int i = 0; i < kPieces; ++i) {
    D du = pv[i] - pu[i], dY = pb[i] - pa[i];
    auto lo_a = pu[i].v < lo.v, hi_a = pu[i].v > hi.v;
    auto lo_b = pv[i].v < lo.v, hi_b = pv[i].v > hi.v;
    auto moved_a = lo_a | hi_a, moved_b = lo_b | hi_b;
    D ca = dsel(lo_a, lo, dsel(hi_a, hi, pu[i]));
    D cb = dsel(lo_b, lo, dsel(hi_b, hi, pv[i]));
    auto nz = du.v != 0;
    D inv = cone / dsel(nz, du, cone);
    auto param = [&](const D& c, decltype(nz) moved, const D& dflt) {
      D r = (c - pu[i]) * inv;
      auto m = moved & nz;
      return dsel(m, dsel(r.v <= 0, czero, dsel(r.v >= 1, cone, r)), dflt);
    };
    D ta = param(ca, moved_a, czero), tb = param(cb, moved_b, cone);
    D Ya2 = dlerp(pa[i], pb[i], dY, ta), Yb2 = dlerp(pa[i], pb[i], dY, tb);
    auto point = (nz & (ca.v == cb.v)) | (~nz & moved_a);
    cb = dsel(point, ca, cb);
    Yb2 = dsel(point, Ya2, Yb2);
    g->ua[i] = ca;
    g->ub[i] = cb;
    g->Ya[i] = Ya2;
    g->Yb[i] = Yb2;
    V wgt = vabs<T>(cb.v - ca.v) + vabs<T>(Yb2.v - Ya2.v);
    sw += wgt;
    swy += wgt * (Ya2.v + Yb2.v) / 2;
  }
  const D ref = cst<N>(sel<V>(sw > 0, swy / sel<V>(sw > 0, sw, one), zero));
  D sum = czero;
  for (int i = 0; i < kPieces; ++i) {
    g->Ya[i] = g->Ya[i] - ref;
    g->Yb[i] = g->Yb[i] - ref;
    sum = sum + scale(half, g->Ya[i] + g->Yb[i]) * (g->ub[i] - g->ua[i]);
  }
  g->scale = scale(sign, -w);
  g->area = g->scale * sum;
  g->X = X;
  g->tx = tx;
  g->ty = ty;
  g->bx = bx;
  g->by = by;
}

// The inputs and outputs of the pair kernels (flat, row-major). n pairs, nv views.
template <typename T>
struct PairArgs {
  size_t n = 0, nv = 0;
  const T *fp, *p0, *p1, *w, *d, *alpha, *h, *ctD = nullptr, *ctA = nullptr;
  const bool* valid;
  double skip_eps = 0;  // > 0: skip the pair-views `skip_bound` puts below it (`cull.view_keep`)
  T *D = nullptr, *A = nullptr;                               // values
  T *dp0 = nullptr, *dp1 = nullptr, *dw = nullptr, *dd = nullptr, *dalpha = nullptr,
    *dh = nullptr;                                            // reverse pass
  T *JD = nullptr, *JA = nullptr;                             // Jacobians (kJac)
};

// Pairs per chunk of work (a multiple of every vector width).
constexpr size_t kPairChunk = 256;

// `ndf.piece_count_estimate` of the pairs i0 .. i0 + L - 1 (one lane each; lanes past i1 and
// padding give 0): the footprint edges whose part within the scratch's length reaches into the
// groove, and the chains along its ends whose crossing does. It orders the pairs alone
// (`pairs_in_order`), so it needs neither the geometry's compensated arithmetic nor its exact
// ties, and the groove's half-width X = sqrt(1 - exp(-r)) / 2 (r = 2 d / w) takes
// exp(-r) ~ 1 / (1 + r + r^2/2 + r^3/6 + r^4/24) (X within 0.5 %).
template <typename T>
typename Vec<T>::type piece_estimate(const PairArgs<T>& a, size_t i0, size_t i1) {
  typedef typename Vec<T>::type V;
  constexpr int L = Vec<T>::L;
  const V zero = V{}, one = splat<V>(1);
  V p0x, p0y, ex, ey, w, d, fx[4], fy[4];
  decltype(V{} < V{}) ok;
  for (int l = 0; l < L; ++l) {
    const size_t i = std::min(i0 + l, i1 - 1);
    const bool use = i0 + l < i1 && a.valid[i];
    ok[l] = use ? -1 : 0;
    p0x[l] = a.p0[2 * i];
    p0y[l] = a.p0[2 * i + 1];
    ex[l] = a.p1[2 * i] - p0x[l];
    ey[l] = a.p1[2 * i + 1] - p0y[l];
    w[l] = use ? a.w[i] : T(1);
    d[l] = use ? a.d[i] : T(1);
    for (int k = 0; k < 4; ++k) {
      fx[k][l] = a.fp[i * 8 + 2 * k] - p0x[l];
      fy[k][l] = a.fp[i * 8 + 2 * k + 1] - p0y[l];
    }
  }
  const V len = vsqrt<T>(ex * ex + ey * ey);
  ok = ok & (len > 0) & (w > 0);
  const V il = one / sel<V>(len > 0, len, one), tx = ex * il, ty = ey * il;
  const V r = 2 * d / w, taylor = 1 + r * (1 + r * (splat<V>(0.5) + r * (splat<V>(1.0 / 6) +
                                                                        r * splat<V>(1.0 / 24))));
  const V X = splat<V>(0.5) * vsqrt<T>(vmax<T>(1 - one / taylor, zero)), iw = one / w;
  V u[4], y[4];
  for (int k = 0; k < 4; ++k) {
    u[k] = (fx[k] * ty - fy[k] * tx) * iw;  // b = (t_y, -t_x)
    y[k] = fx[k] * tx + fy[k] * ty;
  }
  V count = zero;
  for (int lev = 0; lev < 2; ++lev) {  // the chains along y = 0 and y = len
    const V level = lev ? len : zero;
    V crossings = zero, lo = splat<V>(1e30), hi = splat<V>(-1e30);
    for (int k = 0; k < 4; ++k) {
      const int j = (k + 1) % 4;
      const auto cr = (y[k] - level) * (y[j] - level) < 0;
      const V dy = sel<V>(cr, y[j] - y[k], one);
      const V uc = u[k] + (level - y[k]) / dy * (u[j] - u[k]);
      crossings += sel<V>(cr, one, zero);
      lo = sel<V>(cr, vmin<T>(lo, uc), lo);
      hi = sel<V>(cr, vmax<T>(hi, uc), hi);
    }
    count += sel<V>((crossings >= 2) & (lo <= X) & (hi >= -X) & (hi > lo), one, zero);
  }
  for (int k = 0; k < 4; ++k) {  // the edges, clipped to 0 <= y <= len
    const int j = (k + 1) % 4;
    const V dy = y[j] - y[k], du = u[j] - u[k];
    const auto flat = dy == 0;
    const auto inside = (y[k] >= 0) & (y[k] <= len);
    const V idy = one / sel<V>(flat, one, dy);
    const V ta = (zero - y[k]) * idy, tb = (len - y[k]) * idy;
    const V t0 = sel<V>(flat, sel<V>(inside, zero, one), vmax<T>(zero, vmin<T>(ta, tb)));
    const V t1 = sel<V>(flat, sel<V>(inside, one, zero), vmin<T>(one, vmax<T>(ta, tb)));
    const V ua = u[k] + t0 * du, ub = u[k] + t1 * du;
    count += sel<V>((t1 > t0) & (vmin<T>(ua, ub) <= X) & (vmax<T>(ua, ub) >= -X), one, zero);
  }
  return sel<V>(ok, count, zero);
}

// The positions [i0, i1) (at most kPairChunk) into `ord` by increasing `piece_estimate`, the
// padding (valid false) last, each group in position order; returns i1 - i0.
template <typename T>
size_t pairs_in_order(size_t i0, size_t i1, const PairArgs<T>& a, size_t* ord) {
  constexpr int kGroups = 8;  // estimates 0..6, then padding
  constexpr int L = Vec<T>::L;
  const size_t m = i1 - i0;
  unsigned char key[kPairChunk];
  size_t start[kGroups + 1] = {0};
  for (size_t j = 0; j < m; j += L) {
    const auto c = piece_estimate(a, i0 + j, i1);
    for (int l = 0; l < L && j + l < m; ++l) {
      const size_t i = i0 + j + l;
      key[j + l] = static_cast<unsigned char>(a.valid[i] ? std::min(static_cast<int>(c[l]), 6)
                                                         : 7);
      ++start[key[j + l] + 1];
    }
  }
  for (int g = 0; g < kGroups; ++g) start[g + 1] += start[g];
  for (size_t j = 0; j < m; ++j) ord[start[key[j]]++] = i0 + j;
  return m;
}

// Views whose skipping bounds a block keeps (more views: computed again when used).
constexpr size_t kKeptBounds = 8;

// `cull.cull_ratio`'s bound rho of view v's pair-view in each lane (padding lanes: the board
// normal): the GGX at the largest n.h over the groove's fan of normals, whose widest wall has
// cosine `wc` and sine `ws`, as a fraction of its peak; 4 ulps added to n.h and 8 ulps of
// itself to rho against rounding; 0 for a scratch of zero length (`has_len` false: D_hat = 0).
// A NaN input gives NaN, which nothing skips.
template <typename T, typename V, typename M>
V skip_bound(const PairArgs<T>& a, size_t v, const size_t* id, M valid, M has_len, V bx, V by,
             V wc, V ws, V al) {
  constexpr int L = Vec<T>::L;
  const V zero = V{}, one = splat<V>(1);
  const T ulp = std::numeric_limits<T>::epsilon();
  V h[3];
  for (int l = 0; l < L; ++l)
    for (int c = 0; c < 3; ++c) h[c][l] = valid[l] ? a.h[(v * a.n + id[l]) * 3 + c] : T(c == 2);
  const V inv = one / vsqrt<T>(h[0] * h[0] + h[1] * h[1] + h[2] * h[2]);
  const V hx = (h[0] * bx + h[1] * by) * inv, hz = h[2] * inv, ax = vabs<T>(hx);
  const auto peak_on_fan = (hz > 0) & (ax * wc <= hz * ws);  // n.h peaks inside the fan
  V c = sel<V>(peak_on_fan, vsqrt<T>(hx * hx + hz * hz), hz * wc + ax * ws);
  c = c + 4 * ulp;
  c = sel<V>(c > one, one, c);  // (min, keeping a NaN)
  const V a2 = al * al;
  const auto smooth = al < one;  // GGX increases in n.h (else it peaks at n.h -> 0: alpha^4)
  const V den = sel<V>(smooth, c * c * (a2 - 1) + 1, one);
  const V rho = sel<V>(c <= 0, zero, a2 * a2 / (den * den)) * (1 + 8 * ulp);
  return sel<V>(smooth, sel<V>(has_len, sel<V>(rho > one, one, rho), zero), rho);
}

// Pairs [i0, i1) (at most kPairChunk), `L` at a time in the order of `pairs_in_order` (a tail
// repeats its last pair in the spare lanes; padding slots are evaluated as a benign dummy pair
// and give exact zeros). Values (`kGrad` false): D, A; the reverse pass: the cotangents ctD, ctA
// times the pair's Jacobian; `kJac` (with `kGrad`): the values and the Jacobian itself, per view
// JD (V, n, 7) = dD/d(p0x, p0y, p1x, p1y, w, d, alpha) and dh (V, n, 3) = dD/dh, and
// JA (n, 6) = dA/d(p0x, p0y, p1x, p1y, w, d).
template <typename T, bool kGrad, bool kJac = false>
void pairs_chunk(int n_gl, const double* xs, const double* ws, size_t i0, size_t i1,
                 const PairArgs<T>& a, bool arc) {
  typedef typename Vec<T>::type V;
  constexpr int L = Vec<T>::L;
  constexpr int N = kGrad ? kGeo : 0;
  typedef Dual<V, N> D;
  const V zero = V{};
  const T dummy_fp[8] = {0, 0, T(1e-3), 0, T(1e-3), T(1e-3), 0, T(1e-3)};
  const T four_pi = static_cast<T>(4 * 3.14159265358979323846);
  // The pairs in order of their estimated piece count (`piece_estimate`), padding last: a block
  // integrates as many pieces as its busiest lane, and each pair's results are its own, so the
  // order changes the time alone. ord: positions in [i0, i1), at most kPairChunk of them.
  size_t ord[kPairChunk];
  const size_t m = pairs_in_order(i0, i1, a, ord);
  for (size_t b = 0; b < m; b += L) {
    const int lanes = static_cast<int>(std::min<size_t>(L, m - b));
    size_t id[L];  // the pair of each lane (a tail repeats its last pair in the spare lanes)
    for (int l = 0; l < L; ++l) id[l] = ord[b + std::min(l, lanes - 1)];
    V fp[4][2], p[6], al;
    decltype(V{} < V{}) valid;
    bool any = false;
    for (int l = 0; l < L; ++l) {
      const size_t i = id[l];
      const bool ok = a.valid[i];
      any = any || ok;
      valid[l] = ok ? -1 : 0;
      for (int c = 0; c < 8; ++c) fp[c / 2][c % 2][l] = ok ? a.fp[i * 8 + c] : dummy_fp[c];
      p[0][l] = ok ? a.p0[i * 2] : T(-1);
      p[1][l] = ok ? a.p0[i * 2 + 1] : T(-1);
      p[2][l] = ok ? a.p1[i * 2] : T(-0.99);
      p[3][l] = ok ? a.p1[i * 2 + 1] : T(-1);
      p[4][l] = ok ? a.w[i] : T(1e-4);
      p[5][l] = ok ? a.d[i] : T(1e-4);
      al[l] = ok ? a.alpha[i] : T(0.5);
    }
    if (!any) {  // padding only
      for (int l = 0; l < lanes; ++l) {
        const size_t i = id[l];
        if constexpr (!kGrad || kJac) {
          a.A[i] = 0;
          for (size_t v = 0; v < a.nv; ++v) a.D[v * a.n + i] = 0;
        }
        if constexpr (kJac) {
          for (int t = 0; t < kGeo; ++t) a.JA[i * kGeo + t] = 0;
          for (size_t v = 0; v < a.nv; ++v) {
            for (int t = 0; t <= kGeo; ++t) a.JD[(v * a.n + i) * (kGeo + 1) + t] = 0;
            for (int c = 0; c < 3; ++c) a.dh[(v * a.n + i) * 3 + c] = 0;
          }
        } else if constexpr (kGrad) {
          a.dp0[2 * i] = a.dp0[2 * i + 1] = a.dp1[2 * i] = a.dp1[2 * i + 1] = 0;
          a.dw[i] = a.dd[i] = a.dalpha[i] = 0;
          for (size_t v = 0; v < a.nv; ++v)
            for (int c = 0; c < 3; ++c) a.dh[(v * a.n + i) * 3 + c] = 0;
        }
      }
      continue;
    }
    Geo<V, N> g;
    geometry<T>(fp, var<N>(p[0], 0), var<N>(p[1], 1), var<N>(p[2], 2), var<N>(p[3], 3),
                var<N>(p[4], 4), var<N>(p[5], 5), &g);
    // The pieces that are not points, first, per lane (`ndf._compact`); k of them in all lanes.
    int idx[L][kPieces], cnt[L], k = 0;
    for (int l = 0; l < L; ++l) {
      cnt[l] = 0;
      for (int i = 0; i < kPieces; ++i)
        if (!(g.ua[i].v[l] == g.ub[i].v[l] && g.Ya[i].v[l] == g.Yb[i].v[l])) idx[l][cnt[l]++] = i;
      if (valid[l]) k = std::max(k, cnt[l]);
    }
    V cu[kPieces], cv[kPieces], cya[kPieces], cyb[kPieces];
    for (int j = 0; j < k; ++j)
      for (int l = 0; l < L; ++l) {
        const bool in = j < cnt[l];
        const int i = in ? idx[l][j] : 0;
        cu[j][l] = in ? g.ua[i].v[l] : T(0);
        cv[j][l] = in ? g.ub[i].v[l] : T(0);
        cya[j][l] = in ? g.Ya[i].v[l] : T(0);
        cyb[j][l] = in ? g.Yb[i].v[l] : T(0);
      }
    const V pref = al * al / four_pi, sp = g.scale.v * pref;
    const V sv[kTan] = {g.X.v, zero, zero, zero, g.bx.v, g.by.v, g.tx.v, g.ty.v, al};
    // Skipping (`skip_eps` > 0, `cull.view_keep`): a pair-view is skipped when its bound is
    // below skip_eps and below the pair's largest over the views. The fan of normals from the
    // groove's half-width X: sin^2 of the arc's widest wall, or tan^2 of half the paper
    // groove's, is s = 4 X^2.
    const bool skipping = a.skip_eps > 0;
    V wall_c = zero, wall_s = zero, rho_max = zero, rho_v[kKeptBounds];
    const V ex = p[2] - p[0], ey = p[3] - p[1];
    const auto has_len = ex * ex + ey * ey > 0;
    if (skipping) {
      const V s = 4 * g.X.v * g.X.v;
      if (arc) {
        wall_s = vsqrt<T>(s);
        wall_c = vsqrt<T>(vmax<T>(1 - s, zero));
      } else {
        const V r = 1 / (1 + s);
        wall_c = (1 - s) * r;
        wall_s = 2 * vsqrt<T>(s) * r;
      }
      for (size_t v = 0; v < a.nv; ++v) {
        const V rho = skip_bound<T>(a, v, id, valid, has_len, g.bx.v, g.by.v, wall_c, wall_s, al);
        if (v < kKeptBounds) rho_v[v] = rho;
        rho_max = sel<V>((rho > rho_max) | (rho != rho), rho, rho_max);  // (a NaN sticks)
      }
    }
    V gt[kGeo], ga = zero;
    for (int t = 0; t < kGeo; ++t) gt[t] = zero;
    for (size_t v = 0; v < a.nv; ++v) {
      // The lanes that evaluate this view: valid and not skipped.
      decltype(V{} < V{}) on = valid;
      if (skipping) {
        const V rho = v < kKeptBounds ? rho_v[v]
                                      : skip_bound<T>(a, v, id, valid, has_len, g.bx.v, g.by.v,
                                                      wall_c, wall_s, al);
        on = valid & ~((rho < splat<V>(a.skip_eps)) & (rho < rho_max));
      }
      bool any_on = false;
      for (int l = 0; l < L; ++l) any_on = any_on || on[l];
      if (!any_on) {  // every lane skips this view: exact zeros, nothing evaluated
        for (int l = 0; l < lanes; ++l) {
          const size_t r = v * a.n + id[l];
          if constexpr (!kGrad || kJac) a.D[r] = 0;
          if constexpr (kJac)
            for (int t = 0; t <= kGeo; ++t) a.JD[r * (kGeo + 1) + t] = 0;
          if constexpr (kGrad)
            for (int c = 0; c < 3; ++c) a.dh[r * 3 + c] = 0;
        }
        continue;
      }
      V hv[3], ct = zero;
      for (int l = 0; l < L; ++l) {
        const size_t i = id[l];
        for (int c = 0; c < 3; ++c) hv[c][l] = valid[l] ? a.h[(v * a.n + i) * 3 + c] : T(c == 2);
        if constexpr (kJac) ct[l] = on[l] ? T(1) : T(0);
        else if constexpr (kGrad) ct[l] = on[l] ? a.ctD[v * a.n + i] : T(0);
      }
      V s[kTan];
      for (int c = 0; c < kTan; ++c) s[c] = sv[c];
      for (int c = 0; c < 3; ++c) s[1 + c] = hv[c];
      V lit = zero, gp[4][kMaxPieces], gs[kTan];
      for (int c = 0; c < kTan; ++c) gs[c] = zero;
      if (k > 0 && arc)
        arc_lit_lanes<T, V, kGrad>(n_gl, xs, ws, k, cu, cv, cya, cyb, s, &lit, gp[0], gp[1],
                                   gp[2], gp[3], gs);
      else if (k > 0)
        lit_lanes<T, V, kGrad>(n_gl, xs, ws, k, cu, cv, cya, cyb, s, &lit, gp[0], gp[1], gp[2],
                               gp[3], gs);
      if constexpr (!kGrad) {
        V Dv = sel<V>(on, sp * lit, zero);
        for (int l = 0; l < lanes; ++l) a.D[v * a.n + id[l]] = Dv[l];
      } else {
        // dD/d(geometry) through the pieces (back to their uncompacted slots), X and the frame.
        V gpc[4][kPieces];
        for (int f = 0; f < 4; ++f)
          for (int i = 0; i < kPieces; ++i) gpc[f][i] = zero;
        for (int l = 0; l < L; ++l)
          for (int j = 0; j < cnt[l] && j < k; ++j)
            for (int f = 0; f < 4; ++f) gpc[f][idx[l][j]][l] = gp[f][j][l];
        const V cs = ct * sp;
        const size_t row = v * a.n;  // (lane l's row: row + id[l])
        for (int t = 0; t < kGeo; ++t) {
          V sum = gs[0] * g.X.d[t] + gs[4] * g.bx.d[t] + gs[5] * g.by.d[t] + gs[6] * g.tx.d[t] +
                  gs[7] * g.ty.d[t];
          for (int i = 0; i < kPieces; ++i)
            sum += gpc[0][i] * g.ua[i].d[t] + gpc[1][i] * g.ub[i].d[t] +
                   gpc[2][i] * g.Ya[i].d[t] + gpc[3][i] * g.Yb[i].d[t];
          const V jt = cs * sum + ct * (g.scale.d[t] * pref * lit);
          if constexpr (kJac) {
            for (int l = 0; l < lanes; ++l)
              a.JD[(row + id[l]) * (kGeo + 1) + t] = on[l] ? jt[l] : T(0);
          } else {
            gt[t] += jt;
          }
        }
        const V jal = ct * (g.scale.v * ((2 * al / four_pi) * lit) + sp * gs[8]);
        if constexpr (kJac) {
          const V Dv = sel<V>(on, sp * lit, zero);
          for (int l = 0; l < lanes; ++l) {
            a.JD[(row + id[l]) * (kGeo + 1) + kGeo] = on[l] ? jal[l] : T(0);
            a.D[row + id[l]] = Dv[l];
          }
        } else {
          ga += jal;
        }
        for (int l = 0; l < lanes; ++l)
          for (int c = 0; c < 3; ++c)
            a.dh[(v * a.n + id[l]) * 3 + c] = on[l] ? cs[l] * gs[1 + c][l] : T(0);
      }
    }
    if constexpr (!kGrad) {
      for (int l = 0; l < lanes; ++l) a.A[id[l]] = valid[l] ? g.area.v[l] : T(0);
    } else if constexpr (kJac) {
      for (int l = 0; l < lanes; ++l) {
        a.A[id[l]] = valid[l] ? g.area.v[l] : T(0);
        for (int t = 0; t < kGeo; ++t) a.JA[id[l] * kGeo + t] = valid[l] ? g.area.d[t][l] : T(0);
      }
    } else {
      V ctA;
      for (int l = 0; l < L; ++l) {
        const size_t i = id[l];
        ctA[l] = valid[l] ? a.ctA[i] : T(0);
      }
      for (int t = 0; t < kGeo; ++t) gt[t] += ctA * g.area.d[t];
      for (int l = 0; l < lanes; ++l) {
        const size_t i = id[l];
        const bool ok = valid[l];
        a.dp0[2 * i] = ok ? gt[0][l] : T(0);
        a.dp0[2 * i + 1] = ok ? gt[1][l] : T(0);
        a.dp1[2 * i] = ok ? gt[2][l] : T(0);
        a.dp1[2 * i + 1] = ok ? gt[3][l] : T(0);
        a.dw[i] = ok ? gt[4][l] : T(0);
        a.dd[i] = ok ? gt[5][l] : T(0);
        a.dalpha[i] = ok ? ga[l] : T(0);
      }
    }
  }
}

// `pairs_chunk` over [i0, i1), kPairChunk pairs at a time.
template <typename T, bool kGrad, bool kJac = false>
void pairs_range(int n_gl, const double* xs, const double* ws, size_t i0, size_t i1,
                 const PairArgs<T>& a, bool arc) {
  for (size_t c0 = i0; c0 < i1; c0 += kPairChunk)
    pairs_chunk<T, kGrad, kJac>(n_gl, xs, ws, c0, std::min(i1, c0 + kPairChunk), a, arc);
}

template <typename T, bool kGrad, bool kJac = false>
ffi::Error run_pairs(ffi::ThreadPool& pool, int64_t n_gl, int64_t profile, double skip_eps,
                     int64_t threads, size_t n_fp, size_t n_h, size_t n_ct, PairArgs<T>& a,
                     const size_t* counts) {
  // counts: p0, p1, w, d, alpha, valid (ctA for the reverse pass: counts[6]).
  const size_t n = a.n;
  if (n == 0) return ffi::Error::Success();
  bool ok = n_fp == 8 * n && counts[0] == 2 * n && counts[1] == 2 * n && n_gl >= 1 &&
            n_gl <= kMaxNodes && n_h % (3 * n) == 0 && (profile == 0 || profile == 1) &&
            skip_eps >= 0 && skip_eps <= 1;
  a.skip_eps = skip_eps;
  for (int f = 2; f < (kGrad && !kJac ? 7 : 6); ++f) ok = ok && counts[f] == n;
  a.nv = n_h / (3 * n);
  if (kGrad && !kJac) ok = ok && n_ct == a.nv * n;
  if (!ok)
    return ffi::Error(ffi::ErrorCode::kInvalidArgument,
                      "jscratch pairs: inputs must be (n, 4, 2) footprints, (n, 2) p0 and p1, "
                      "(n,) width, depth, alpha and valid, (V, n, 3) h (and (V, n) ctD, (n,) ctA), "
                      "profile 0 (paper) or 1 (arc), skip_eps in [0, 1]");
  // The n_gl-point rule, then (for the arc's far pieces, `arc_piece`) the n_gl / 2-point rule.
  double xs[2 * kMaxNodes], ws[2 * kMaxNodes];
  gauss_legendre(static_cast<int>(n_gl), xs, ws);
  if (n_gl % 2 == 0) gauss_legendre(static_cast<int>(n_gl / 2), xs + n_gl, ws + n_gl);
  parallel(pool, n, kPairChunk, threads, [&](size_t i0, size_t i1) {
    pairs_range<T, kGrad, kJac>(static_cast<int>(n_gl), xs, ws, i0, i1, a, profile == 1);
  });
  return ffi::Error::Success();
}

// The whole-pair kernels' common inputs into `a`.
template <ffi::DataType DT>
void pair_inputs(ffi::Buffer<DT>& fp, ffi::Buffer<DT>& p0, ffi::Buffer<DT>& p1,
                 ffi::Buffer<DT>& w, ffi::Buffer<DT>& d, ffi::Buffer<DT>& alpha,
                 ffi::Buffer<ffi::DataType::PRED>& valid, ffi::Buffer<DT>& h,
                 PairArgs<ffi::NativeType<DT>>* a) {
  a->n = w.element_count();
  a->fp = fp.typed_data(); a->p0 = p0.typed_data(); a->p1 = p1.typed_data();
  a->w = w.typed_data(); a->d = d.typed_data(); a->alpha = alpha.typed_data();
  a->valid = valid.typed_data(); a->h = h.typed_data();
}

template <ffi::DataType DT>
ffi::Error PairsImpl(ffi::ThreadPool pool, ffi::Buffer<DT> fp, ffi::Buffer<DT> p0,
                     ffi::Buffer<DT> p1, ffi::Buffer<DT> w, ffi::Buffer<DT> d,
                     ffi::Buffer<DT> alpha, ffi::Buffer<ffi::DataType::PRED> valid,
                     ffi::Buffer<DT> h, int64_t n_gl, int64_t profile, double skip_eps,
                     int64_t threads, ffi::ResultBuffer<DT> D,
                     ffi::ResultBuffer<DT> A) {
  using T = ffi::NativeType<DT>;
  PairArgs<T> a;
  pair_inputs(fp, p0, p1, w, d, alpha, valid, h, &a);
  a.D = D->typed_data(); a.A = A->typed_data();
  const size_t counts[6] = {p0.element_count(), p1.element_count(), w.element_count(),
                            d.element_count(), alpha.element_count(), valid.element_count()};
  return run_pairs<T, false>(pool, n_gl, profile, skip_eps, threads, fp.element_count(),
                             h.element_count(), 0, a, counts);
}

template <ffi::DataType DT>
ffi::Error PairsVjpImpl(ffi::ThreadPool pool, ffi::Buffer<DT> fp, ffi::Buffer<DT> p0,
                        ffi::Buffer<DT> p1, ffi::Buffer<DT> w, ffi::Buffer<DT> d,
                        ffi::Buffer<DT> alpha, ffi::Buffer<ffi::DataType::PRED> valid,
                        ffi::Buffer<DT> h, ffi::Buffer<DT> ctD, ffi::Buffer<DT> ctA,
                        int64_t n_gl, int64_t profile, double skip_eps, int64_t threads,
                        ffi::ResultBuffer<DT> dp0,
                        ffi::ResultBuffer<DT> dp1, ffi::ResultBuffer<DT> dw,
                        ffi::ResultBuffer<DT> dd, ffi::ResultBuffer<DT> dalpha,
                        ffi::ResultBuffer<DT> dh) {
  using T = ffi::NativeType<DT>;
  PairArgs<T> a;
  pair_inputs(fp, p0, p1, w, d, alpha, valid, h, &a);
  a.ctD = ctD.typed_data(); a.ctA = ctA.typed_data();
  a.dp0 = dp0->typed_data(); a.dp1 = dp1->typed_data(); a.dw = dw->typed_data();
  a.dd = dd->typed_data(); a.dalpha = dalpha->typed_data(); a.dh = dh->typed_data();
  const size_t counts[7] = {p0.element_count(), p1.element_count(), w.element_count(),
                            d.element_count(), alpha.element_count(), valid.element_count(),
                            ctA.element_count()};
  return run_pairs<T, true>(pool, n_gl, profile, skip_eps, threads, fp.element_count(),
                            h.element_count(), ctD.element_count(), a, counts);
}

template <ffi::DataType DT>
ffi::Error PairsJacImpl(ffi::ThreadPool pool, ffi::Buffer<DT> fp, ffi::Buffer<DT> p0,
                        ffi::Buffer<DT> p1, ffi::Buffer<DT> w, ffi::Buffer<DT> d,
                        ffi::Buffer<DT> alpha, ffi::Buffer<ffi::DataType::PRED> valid,
                        ffi::Buffer<DT> h, int64_t n_gl, int64_t profile, double skip_eps,
                        int64_t threads, ffi::ResultBuffer<DT> D, ffi::ResultBuffer<DT> A,
                        ffi::ResultBuffer<DT> JD, ffi::ResultBuffer<DT> dh,
                        ffi::ResultBuffer<DT> JA) {
  using T = ffi::NativeType<DT>;
  PairArgs<T> a;
  pair_inputs(fp, p0, p1, w, d, alpha, valid, h, &a);
  a.D = D->typed_data(); a.A = A->typed_data(); a.JD = JD->typed_data();
  a.dh = dh->typed_data(); a.JA = JA->typed_data();
  const size_t counts[6] = {p0.element_count(), p1.element_count(), w.element_count(),
                            d.element_count(), alpha.element_count(), valid.element_count()};
  return run_pairs<T, true, true>(pool, n_gl, profile, skip_eps, threads, fp.element_count(),
                                  h.element_count(), 0, a, counts);
}

}  // namespace

#define JSCRATCH_LIT_ARGS(DT)                                                              \
  ffi::Ffi::Bind()                                                                         \
      .Ctx<ffi::ThreadPool>()                                                              \
      .Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>()                \
      .Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>()                \
      .Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>()                \
      .Attr<int64_t>("n_gl").Attr<int64_t>("threads")

#define JSCRATCH_LIT_BIND(DT)                                                              \
  JSCRATCH_LIT_ARGS(DT)                                                                    \
      .Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>()                \
      .Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>()                \
      .Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>()                \
      .Ret<ffi::Buffer<DT>>()

#ifdef JSCRATCH_DTYPE_F32
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchLitF32, LitImpl<ffi::DataType::F32>,
                              JSCRATCH_LIT_BIND(ffi::DataType::F32));
#endif
#ifdef JSCRATCH_DTYPE_F64
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchLitF64, LitImpl<ffi::DataType::F64>,
                              JSCRATCH_LIT_BIND(ffi::DataType::F64));
#endif
#ifdef JSCRATCH_DTYPE_F32
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchLitValuesF32, LitValuesImpl<ffi::DataType::F32>,
                              JSCRATCH_LIT_ARGS(ffi::DataType::F32)
                                  .Ret<ffi::Buffer<ffi::DataType::F32>>());
#endif
#ifdef JSCRATCH_DTYPE_F64
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchLitValuesF64, LitValuesImpl<ffi::DataType::F64>,
                              JSCRATCH_LIT_ARGS(ffi::DataType::F64)
                                  .Ret<ffi::Buffer<ffi::DataType::F64>>());
#endif

#define JSCRATCH_PAIRS_ARGS(DT)                                                            \
  ffi::Ffi::Bind()                                                                         \
      .Ctx<ffi::ThreadPool>()                                                              \
      .Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>()                \
      .Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>()                \
      .Arg<ffi::Buffer<ffi::DataType::PRED>>().Arg<ffi::Buffer<DT>>()

#define JSCRATCH_PAIRS_BIND(DT)                                                            \
  JSCRATCH_PAIRS_ARGS(DT)                                                                  \
      .Attr<int64_t>("n_gl").Attr<int64_t>("profile").Attr<double>("skip_eps")             \
      .Attr<int64_t>("threads").Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>()

#define JSCRATCH_PAIRS_VJP_BIND(DT)                                                        \
  JSCRATCH_PAIRS_ARGS(DT)                                                                  \
      .Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>()                                       \
      .Attr<int64_t>("n_gl").Attr<int64_t>("profile").Attr<double>("skip_eps")             \
      .Attr<int64_t>("threads")                                                            \
      .Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>()                \
      .Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>()

#ifdef JSCRATCH_DTYPE_F32
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchPairsF32, PairsImpl<ffi::DataType::F32>,
                              JSCRATCH_PAIRS_BIND(ffi::DataType::F32));
#endif
#ifdef JSCRATCH_DTYPE_F64
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchPairsF64, PairsImpl<ffi::DataType::F64>,
                              JSCRATCH_PAIRS_BIND(ffi::DataType::F64));
#endif
#ifdef JSCRATCH_DTYPE_F32
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchPairsVjpF32, PairsVjpImpl<ffi::DataType::F32>,
                              JSCRATCH_PAIRS_VJP_BIND(ffi::DataType::F32));
#endif
#ifdef JSCRATCH_DTYPE_F64
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchPairsVjpF64, PairsVjpImpl<ffi::DataType::F64>,
                              JSCRATCH_PAIRS_VJP_BIND(ffi::DataType::F64));
#endif

#define JSCRATCH_PAIRS_JAC_BIND(DT)                                                        \
  JSCRATCH_PAIRS_ARGS(DT)                                                                  \
      .Attr<int64_t>("n_gl").Attr<int64_t>("profile").Attr<double>("skip_eps")             \
      .Attr<int64_t>("threads")                                                            \
      .Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>()                \
      .Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>()

#ifdef JSCRATCH_DTYPE_F32
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchPairsJacF32, PairsJacImpl<ffi::DataType::F32>,
                              JSCRATCH_PAIRS_JAC_BIND(ffi::DataType::F32));
#endif
#ifdef JSCRATCH_DTYPE_F64
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchPairsJacF64, PairsJacImpl<ffi::DataType::F64>,
                              JSCRATCH_PAIRS_JAC_BIND(ffi::DataType::F64));
#endif

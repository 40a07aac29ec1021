// The per-view stage of the scratch NDF's pair integral with its partial derivatives, as one
// XLA FFI custom call for the CPU (`jscratch.native`). It is a line-by-line port of the jnp code
// it replaces in a reverse pass (`jscratch.ndf._view`, `lit_interval`, `jscratch.lobe.lobe`,
// `lobe_params`, `ndf._cut`, `lobe.piece_values(..., with_partials=True)`, `ndf._cut_transpose`
// and the autodiff of the view algebra), evaluated per pair-view in registers instead of
// through XLA's fusions. The jnp code stays the reference: tests compare the two in float64
// (equal to rounding) and float32.
//
// Inputs per pair-view (leading axes flattened, n pair-views; the pieces have a trailing axis
// of k): ua, ub, Ya, Yb (n, k) the boundary pieces cut to the groove (`ndf.PairGeometry`), X (n)
// the groove half-width in widths, h (n, 3) the board-frame half vector (normalised here), b, t
// (n, 2) the scratch's across and along unit vectors, alpha (n). Attributes: n_gl Gauss-Legendre
// nodes per piece, threads (the most workers one call uses, the calling thread included).
//
// Threads: the pair-views are cut into chunks of `kChunk` (whole vectors; the cut depends on n
// alone) that the calling thread and up to threads - 1 tasks on XLA's intra-op thread pool (the
// FFI execution context's `ThreadPool`, alive as long as the client) claim one at a time. The
// lanes are independent, so the results are the same bits for any thread count; a task that
// starts after the last chunk was claimed returns at once, and the caller never waits for a task
// that has not started (no deadlock when the pool is busy or runs tasks inline).
// Outputs: lit (n) = sum over pieces of the integral of Y (F1 + F2) du over the piece cut to the
// lit slab, and its partial derivatives with respect to every input (`JscratchLit*`), or the
// value alone (`JscratchLitValues*`).

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <condition_variable>
#include <functional>
#include <memory>
#include <mutex>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

constexpr int kMaxNodes = 32;
constexpr int kMaxPieces = 8;
constexpr int kTan = 9;  // tangents of the view algebra: X, h (3), b (2), t (2), alpha

// One lane per pair-view: GCC/Clang vector extensions (32 bytes: 8 floats or 4 doubles); the
// compiler emits SIMD code for every operation below, branches become selects (`sel`).
template <typename T>
struct Vec {
  typedef T type __attribute__((vector_size(32)));
  static constexpr int L = 32 / sizeof(T);
};

template <typename V>
inline V sel(decltype(V{} < V{}) m, V a, V b) {
  return m ? a : b;
}
template <typename V>
inline V splat(double x) {
  return V{} + static_cast<decltype(V{}[0])>(x);
}

template <typename T, typename V>
inline V vsqrt(V x) {
  V r;
  for (int l = 0; l < Vec<T>::L; ++l) r[l] = std::sqrt(x[l]);
  return r;
}
template <typename T, typename V>
inline V vabs(V x) {
  return sel<V>(x < 0, -x, x);
}
template <typename T, typename V>
inline V vmax(V a, V b) {
  return sel<V>(a > b, a, b);
}
template <typename T, typename V>
inline V vmin(V a, V b) {
  return sel<V>(a < b, a, b);
}

// Forward-mode number with kTan tangents: the view algebra's Jacobian (a few dozen operations
// per pair-view, as jax's autodiff of the same jnp code computes it).
template <typename V>
struct Dual {
  V v;
  V d[kTan];
};

template <typename V>
Dual<V> cst(V v) {
  Dual<V> r;
  r.v = v;
  for (int i = 0; i < kTan; ++i) r.d[i] = V{};
  return r;
}
template <typename V>
Dual<V> var(V v, int i) {
  Dual<V> r = cst(v);
  r.d[i] = splat<V>(1);
  return r;
}
template <typename V>
Dual<V> operator+(const Dual<V>& a, const Dual<V>& b) {
  Dual<V> r;
  r.v = a.v + b.v;
  for (int i = 0; i < kTan; ++i) r.d[i] = a.d[i] + b.d[i];
  return r;
}
template <typename V>
Dual<V> operator-(const Dual<V>& a, const Dual<V>& b) {
  Dual<V> r;
  r.v = a.v - b.v;
  for (int i = 0; i < kTan; ++i) r.d[i] = a.d[i] - b.d[i];
  return r;
}
template <typename V>
Dual<V> operator-(const Dual<V>& a) {
  Dual<V> r;
  r.v = -a.v;
  for (int i = 0; i < kTan; ++i) r.d[i] = -a.d[i];
  return r;
}
template <typename V>
Dual<V> operator*(const Dual<V>& a, const Dual<V>& b) {
  Dual<V> r;
  r.v = a.v * b.v;
  for (int i = 0; i < kTan; ++i) r.d[i] = a.d[i] * b.v + a.v * b.d[i];
  return r;
}
template <typename V>
Dual<V> scale(V s, const Dual<V>& a) {
  Dual<V> r;
  r.v = s * a.v;
  for (int i = 0; i < kTan; ++i) r.d[i] = s * a.d[i];
  return r;
}
template <typename V>
Dual<V> operator/(const Dual<V>& a, const Dual<V>& b) {
  Dual<V> r;
  r.v = a.v / b.v;
  const V inv = 1 / b.v;
  for (int i = 0; i < kTan; ++i) r.d[i] = (a.d[i] - r.v * b.d[i]) * inv;
  return r;
}
template <typename V>
Dual<V> dsel(decltype(V{} < V{}) m, const Dual<V>& a, const Dual<V>& b) {
  Dual<V> r;
  r.v = sel<V>(m, a.v, b.v);
  for (int i = 0; i < kTan; ++i) r.d[i] = sel<V>(m, a.d[i], b.d[i]);
  return r;
}
template <typename T, typename V>
Dual<V> dsqrt(const Dual<V>& a) {
  Dual<V> r;
  r.v = vsqrt<T>(a.v);
  const V inv = splat<V>(0.5) / r.v;
  for (int i = 0; i < kTan; ++i) r.d[i] = a.d[i] * inv;
  return r;
}
// `ndf._safe_sqrt`: 0 with derivative 0 where the argument is not positive.
template <typename T, typename V>
Dual<V> dsafe_sqrt(const Dual<V>& a) {
  auto pos = a.v > 0;
  Dual<V> safe = dsel(pos, a, cst(splat<V>(1)));
  return dsel(pos, dsqrt<T>(safe), cst(V{}));
}
template <typename T, typename V>
Dual<V> dabs(const Dual<V>& a) {
  V s = sel<V>(a.v > 0, splat<V>(1), sel<V>(a.v < 0, splat<V>(-1), V{}));
  Dual<V> r;
  r.v = vabs<T>(a.v);
  for (int i = 0; i < kTan; ++i) r.d[i] = s * a.d[i];
  return r;
}
// jax's max/min: at a tie each argument gets half the derivative.
template <typename T, typename V>
Dual<V> dmax(const Dual<V>& a, const Dual<V>& b) {
  V wa = sel<V>(a.v > b.v, splat<V>(1), sel<V>(a.v == b.v, splat<V>(0.5), V{}));
  Dual<V> r;
  r.v = vmax<T>(a.v, b.v);
  for (int i = 0; i < kTan; ++i) r.d[i] = wa * a.d[i] + (1 - wa) * b.d[i];
  return r;
}
template <typename T, typename V>
Dual<V> dmin(const Dual<V>& a, const Dual<V>& b) {
  V wa = sel<V>(a.v < b.v, splat<V>(1), sel<V>(a.v == b.v, splat<V>(0.5), V{}));
  Dual<V> r;
  r.v = vmin<T>(a.v, b.v);
  for (int i = 0; i < kTan; ++i) r.d[i] = wa * a.d[i] + (1 - wa) * b.d[i];
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
    for (int l = 0; l < Vec<T>::L; ++l) {
      I0[l] = std::atan2(s_d[l], y0[l]);
      lg[l] = std::log1p(larg[l]);
    }
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

// One lane per pair-view: `L` pair-views from lanes of the inputs (pieces `k` per lane).
template <typename T, typename V, bool kPartials>
void lit_lanes(int n_gl, const double* xs, const double* ws, int k, const V* ua, const V* ub,
               const V* Ya, const V* Yb, const V* sv, V* out, V* g_ua, V* g_ub, V* g_Ya,
               V* g_Yb, V* gs) {
  const V zero = V{}, one = splat<V>(1), two = splat<V>(2);
  // The view algebra with its Jacobian (`ndf._lit_integral`'s half vector in the scratch frame,
  // `_view`, `lit_interval`, `lobe.lobe`, `lobe_params`), from sv = (X, h (3), b (2), t (2),
  // alpha): computed here with IEEE operations, not in an XLA fusion (whose rewrites, such as
  // x / sqrt(y) -> x * rsqrt(y), move a sharp peak by an ulp or two).
  Dual<V> Xd = var(sv[0], 0), h0 = var(sv[1], 1), h1 = var(sv[2], 2), h2 = var(sv[3], 3),
          b0 = var(sv[4], 4), b1 = var(sv[5], 5), t0 = var(sv[6], 6), t1 = var(sv[7], 7),
          al = var(sv[8], 8);
  Dual<V> nrm = dsqrt<T>(h0 * h0 + h1 * h1 + h2 * h2);
  Dual<V> hn0 = h0 / nrm, hn1 = h1 / nrm, hz = h2 / nrm;
  Dual<V> hx = hn0 * b0 + hn1 * b1, hy = hn0 * t0 + hn1 * t1;
  Dual<V> r = dsqrt<T>(hx * hx + hz * hz);
  Dual<V> rp = r + dabs<T>(hx);
  Dual<V> near = hz / scale(two, rp), far = rp / scale(two, hz);
  auto hx_pos = hx.v >= 0;
  Dual<V> u_p = dsel(hx_pos, near, far);
  Dual<V> u_m = dsel(hx_pos, -far, -near);
  Dual<V> lo = dmax<T>(-Xd, u_m);
  Dual<V> hi = dmax<T>(dmin<T>(Xd, u_p), lo);
  Dual<V> a2 = al * al;
  Dual<V> kk = dsafe_sqrt<T>(cst(one) - a2);
  Dual<V> g = cst(one) / (cst(one) + kk * hz);
  Dual<V> beta2 = a2 + kk * kk * hy * hy;
  Dual<V> beta = dsqrt<T>(beta2);
  Dual<V> u1 = -(g * kk * hx) / cst(two);
  Dual<V> q1 = g * beta / cst(two);
  Dual<V> a = -(scale(two, g) * kk * hx) / beta;
  Dual<V> m = scale(two, kk) * (hz + g * kk * hx * hx) / beta2;
  Dual<V> g21 = scale(two, g) + cst(one);
  Dual<V> pd[11] = {g * g + g, g21 * m + a * a, g21 * a, m * m - a * a, scale(two, a) * m,
                    u1, q1, g, kk, hx, hz};
  V p[11];
  for (int i = 0; i < 11; ++i) p[i] = pd[i].v;

  // `ndf._cut` of the pieces to the slab [lo, hi].
  const V Lo = lo.v, Hi = hi.v;
  typedef decltype(V{} < V{}) M;
  V ca[kMaxPieces], cb[kMaxPieces], Ya2[kMaxPieces], Yb2[kMaxPieces], ta[kMaxPieces],
      tb[kMaxPieces], dYs[kMaxPieces], inv_du[kMaxPieces];
  M ta_free[kMaxPieces], tb_free[kMaxPieces], lo_a[kMaxPieces], hi_a[kMaxPieces],
      lo_b[kMaxPieces], hi_b[kMaxPieces], pt[kMaxPieces];
  V sw = zero, swy = zero;
  for (int i = 0; i < k; ++i) {
    V du = ub[i] - ua[i], dY = Yb[i] - Ya[i];
    lo_a[i] = ua[i] < Lo; hi_a[i] = ua[i] > Hi; lo_b[i] = ub[i] < Lo; hi_b[i] = ub[i] > Hi;
    M moved_a = lo_a[i] | hi_a[i], moved_b = lo_b[i] | hi_b[i];
    V c_a = sel<V>(lo_a[i], Lo, sel<V>(hi_a[i], Hi, ua[i]));
    V c_b = sel<V>(lo_b[i], Lo, sel<V>(hi_b[i], Hi, ub[i]));
    M nz = du != 0;
    V inv = 1 / sel<V>(nz, du, one);
    auto param = [&](V c, M moved, V dflt, M* fr) {
      V rr = (c - ua[i]) * inv;
      M mm = moved & nz;
      *fr = mm & (rr > 0) & (rr < 1);
      return sel<V>(mm, sel<V>(rr <= 0, zero, sel<V>(rr >= 1, one, rr)), dflt);
    };
    ta[i] = param(c_a, moved_a, zero, &ta_free[i]);
    tb[i] = param(c_b, moved_b, one, &tb_free[i]);
    V y_a = lerp(Ya[i], Yb[i], dY, ta[i]);
    V y_b = lerp(Ya[i], Yb[i], dY, tb[i]);
    pt[i] = (nz & (c_a == c_b)) | (~nz & moved_a);
    c_b = sel<V>(pt[i], c_a, c_b);
    y_b = sel<V>(pt[i], y_a, y_b);
    ca[i] = c_a; cb[i] = c_b; Ya2[i] = y_a; Yb2[i] = y_b; dYs[i] = dY; inv_du[i] = inv;
    V wgt = vabs<T>(c_b - c_a) + vabs<T>(y_b - y_a);
    sw += wgt;
    swy += wgt * (y_a + y_b) / 2;
  }
  // `ndf._centre` (it carries no derivative).
  V ref = sel<V>(sw > 0, swy / sel<V>(sw > 0, sw, one), zero);

  V value = zero, dp[11], g_lo = zero, g_hi = zero;
  for (int i = 0; i < 11; ++i) dp[i] = zero;
  for (int i = 0; i < k; ++i) {
    V dca, dcb, dYa, dYb;
    value += piece<T, V, kPartials>(n_gl, xs, ws, ca[i], cb[i], Ya2[i] - ref, Yb2[i] - ref, p,
                                    &dca, &dcb, &dYa, &dYb, dp);
    if constexpr (!kPartials) continue;
    // `ndf._cut_transpose`.
    dca = dca + sel<V>(pt[i], dcb, zero);
    dYa = dYa + sel<V>(pt[i], dYb, zero);
    dcb = sel<V>(pt[i], zero, dcb);
    dYb = sel<V>(pt[i], zero, dYb);
    g_Ya[i] = dYa * (1 - ta[i]) + dYb * (1 - tb[i]);
    g_Yb[i] = dYa * ta[i] + dYb * tb[i];
    V ga = sel<V>(ta_free[i], dYa * dYs[i] * inv_du[i], zero);
    V gb = sel<V>(tb_free[i], dYb * dYs[i] * inv_du[i], zero);
    dca += ga;
    dcb += gb;
    V gua = ga * (ta[i] - 1) + gb * (tb[i] - 1);
    V gub = -(ga * ta[i] + gb * tb[i]);
    gua += sel<V>(lo_a[i] | hi_a[i], zero, dca);
    gub += sel<V>(lo_b[i] | hi_b[i], zero, dcb);
    g_ua[i] = gua;
    g_ub[i] = gub;
    g_lo += sel<V>(lo_a[i], dca, zero) + sel<V>(lo_b[i], dcb, zero);
    g_hi += sel<V>(hi_a[i], dca, zero) + sel<V>(hi_b[i], dcb, zero);
  }
  *out = value;
  if constexpr (!kPartials) return;
  // Chain the slab bounds' and the lobe parameters' partials through the view algebra.
  for (int t = 0; t < kTan; ++t) {
    V s = g_lo * lo.d[t] + g_hi * hi.d[t];
    for (int i = 0; i < 11; ++i) s += dp[i] * pd[i].d[t];
    gs[t] = s;
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
  auto work = [&](size_t i0, size_t i1) {
    lit_range<T, kPartials>(static_cast<int>(n_gl), xs, ws, k, i0, i1, in, res);
  };
  const size_t chunks = (n + kChunk - 1) / kChunk;
  size_t workers = std::min<size_t>(chunks, static_cast<size_t>(std::max<int64_t>(1, threads)));
  if (workers > 1) workers = std::min<size_t>(workers, std::max<int64_t>(1, pool.num_threads()));
  if (workers <= 1) {
    work(0, n);
    return ffi::Error::Success();
  }
  auto job = std::make_shared<Job>();
  job->chunks = chunks;
  job->body = [&](size_t c) { work(c * kChunk, std::min(n, (c + 1) * kChunk)); };
  for (size_t w = 1; w < workers; ++w) pool.Schedule([job] { job->drain(); });
  job->drain();
  job->wait();
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

XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchLitF32, LitImpl<ffi::DataType::F32>,
                              JSCRATCH_LIT_BIND(ffi::DataType::F32));
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchLitF64, LitImpl<ffi::DataType::F64>,
                              JSCRATCH_LIT_BIND(ffi::DataType::F64));
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchLitValuesF32, LitValuesImpl<ffi::DataType::F32>,
                              JSCRATCH_LIT_ARGS(ffi::DataType::F32)
                                  .Ret<ffi::Buffer<ffi::DataType::F32>>());
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchLitValuesF64, LitValuesImpl<ffi::DataType::F64>,
                              JSCRATCH_LIT_ARGS(ffi::DataType::F64)
                                  .Ret<ffi::Buffer<ffi::DataType::F64>>());

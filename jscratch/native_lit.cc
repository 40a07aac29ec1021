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
// the groove half-width in widths, hx, hy, hz (n) the normalised half vector in the scratch
// frame, alpha (n). Attribute n_gl: Gauss-Legendre nodes per piece.
// Outputs: lit (n) = sum over pieces of the integral of Y (F1 + F2) du over the piece cut to the
// lit slab, and its partial derivatives with respect to every input.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <thread>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

constexpr int kMaxNodes = 32;
constexpr int kMaxPieces = 8;
constexpr int kTan = 5;  // tangents of the view algebra: hx, hy, hz, alpha, X

// Forward-mode number with kTan tangents: the view algebra's Jacobian (a few dozen operations
// per pair-view, as jax's autodiff of the same jnp code computes it).
template <typename T>
struct Dual {
  T v;
  T d[kTan];
};

template <typename T>
Dual<T> cst(T v) {
  Dual<T> r;
  r.v = v;
  for (int i = 0; i < kTan; ++i) r.d[i] = 0;
  return r;
}
template <typename T>
Dual<T> var(T v, int i) {
  Dual<T> r = cst(v);
  r.d[i] = 1;
  return r;
}
template <typename T>
Dual<T> operator+(const Dual<T>& a, const Dual<T>& b) {
  Dual<T> r;
  r.v = a.v + b.v;
  for (int i = 0; i < kTan; ++i) r.d[i] = a.d[i] + b.d[i];
  return r;
}
template <typename T>
Dual<T> operator-(const Dual<T>& a, const Dual<T>& b) {
  Dual<T> r;
  r.v = a.v - b.v;
  for (int i = 0; i < kTan; ++i) r.d[i] = a.d[i] - b.d[i];
  return r;
}
template <typename T>
Dual<T> operator-(const Dual<T>& a) {
  Dual<T> r;
  r.v = -a.v;
  for (int i = 0; i < kTan; ++i) r.d[i] = -a.d[i];
  return r;
}
template <typename T>
Dual<T> operator*(const Dual<T>& a, const Dual<T>& b) {
  Dual<T> r;
  r.v = a.v * b.v;
  for (int i = 0; i < kTan; ++i) r.d[i] = a.d[i] * b.v + a.v * b.d[i];
  return r;
}
template <typename T>
Dual<T> operator*(T s, const Dual<T>& a) {
  Dual<T> r;
  r.v = s * a.v;
  for (int i = 0; i < kTan; ++i) r.d[i] = s * a.d[i];
  return r;
}
template <typename T>
Dual<T> operator/(const Dual<T>& a, const Dual<T>& b) {
  Dual<T> r;
  r.v = a.v / b.v;
  for (int i = 0; i < kTan; ++i) r.d[i] = (a.d[i] - r.v * b.d[i]) / b.v;
  return r;
}
template <typename T>
Dual<T> dsqrt(const Dual<T>& a) {
  Dual<T> r;
  r.v = std::sqrt(a.v);
  for (int i = 0; i < kTan; ++i) r.d[i] = a.d[i] / (2 * r.v);
  return r;
}
// `ndf._safe_sqrt`: 0 with derivative 0 where the argument is not positive.
template <typename T>
Dual<T> dsafe_sqrt(const Dual<T>& a) {
  return a.v > 0 ? dsqrt(a) : cst(T(0));
}
template <typename T>
Dual<T> dabs(const Dual<T>& a) {
  T s = a.v > 0 ? T(1) : (a.v < 0 ? T(-1) : T(0));
  Dual<T> r;
  r.v = std::abs(a.v);
  for (int i = 0; i < kTan; ++i) r.d[i] = s * a.d[i];
  return r;
}
// jax's max/min: at a tie each argument gets half the derivative.
template <typename T>
Dual<T> dmax(const Dual<T>& a, const Dual<T>& b) {
  T wa = a.v > b.v ? T(1) : (a.v == b.v ? T(0.5) : T(0));
  Dual<T> r;
  r.v = std::max(a.v, b.v);
  for (int i = 0; i < kTan; ++i) r.d[i] = wa * a.d[i] + (1 - wa) * b.d[i];
  return r;
}
template <typename T>
Dual<T> dmin(const Dual<T>& a, const Dual<T>& b) {
  T wa = a.v < b.v ? T(1) : (a.v == b.v ? T(0.5) : T(0));
  Dual<T> r;
  r.v = std::min(a.v, b.v);
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
template <typename T>
T lerp(T a, T b, T d, T t) {
  return t <= T(0.5) ? a + t * d : b - (1 - t) * d;
}

// `lobe._lobes` at one abscissa.
template <typename T>
struct Lobes {
  T F1, T2, inv2, B, N, e, se, ee, see;
};

template <typename T>
Lobes<T> lobes(T u, const T* p) {
  const T u1 = p[5], q1 = p[6], g = p[7], k = p[8], hx = p[9], hz = p[10];
  Lobes<T> r;
  T u2 = u * u;
  r.B = 1 + 4 * u2;
  r.N = hz * (1 - 4 * u2) - 4 * hx * u;
  T d = u - u1;
  T inv1 = 1 / (q1 * q1 + d * d);
  T T1 = g * r.B * inv1 / 4;
  r.inv2 = 1 / (r.B + k * r.N);
  r.e = q1 * q1 * inv1;
  r.se = q1 * d * inv1;
  r.F1 = T1 * T1 + T1;
  r.T2 = r.B * r.inv2;
  r.ee = r.e * r.e;
  r.see = r.se * r.e;
  return r;
}

// `lobe.piece_values(..., with_partials=True)` for one piece: the value, the partials with
// respect to the ends (ua, ub, Ya, Yb) and (accumulated into dp) the 11 lobe parameters.
template <typename T>
T piece(int n_gl, const double* xs, const double* ws, T ua, T ub, T Ya, T Yb, const T* p, T* d_ua,
        T* d_ub, T* d_Ya, T* d_Yb, T* dp) {
  const T c0 = p[0], u1 = p[5], q1 = p[6], k = p[8];
  const T ct[4] = {p[1], p[2], p[3], p[4]};
  T du = ub - ua, half = du / 2, um = ua + half, Ym = (Ya + Yb) / 2, dY = Yb - Ya;
  T ds = du / q1, sa = (ua - u1) / q1, sm = sa + ds / 2;
  bool use_cf = std::abs(ds) >= std::max(T(1), T(0.5) * std::abs(sm));
  T ds_s = use_cf ? ds : T(1), sa_s = use_cf ? sa : T(0), sb_s = sa_s + ds_s;
  T ea = 1 / (1 + sa_s * sa_s), eb = 1 / (1 + sb_s * sb_s);
  // `lobe._t1_closed`.
  T B0[5], B1[5], E0, E1, Et0;
  {
    T s_a = sa_s, s_d = ds_s, s_b = s_a + s_d, s_m = s_a + s_d / 2;
    T I0 = std::atan2(s_d, 1 + s_a * s_b);
    T ps = s_d * (s_a + s_b);
    bool up = ps >= 0;
    T I1 = T(0.5) * (up ? T(1) : T(-1)) * std::log1p(up ? ps * ea : -ps * eb);
    T K1 = T(0.5) * (s_d * ea) * ((s_a + s_b) * eb);
    T K0 = T(0.5) * I0 + T(0.5) * (s_d * ea) * ((1 - s_a * s_b) * eb);
    B0[0] = s_d; B0[1] = I0; B0[2] = I1; B0[3] = K0; B0[4] = K1;
    B1[0] = 0;
    B1[1] = I1 - s_m * I0;
    B1[2] = s_d - I0 - s_m * I1;
    B1[3] = K1 - s_m * K0;
    B1[4] = (I0 - K0) - s_m * K1;
    E0 = c0 * B0[0] + ct[0] * B0[1] + ct[1] * B0[2] + ct[2] * B0[3] + ct[3] * B0[4];
    E1 = ct[0] * B1[1] + ct[1] * B1[2] + ct[2] * B1[3] + ct[3] * B1[4];
    Et0 = ct[0] * B0[1] + ct[1] * B0[2] + ct[2] * B0[3] + ct[3] * B0[4];
  }
  T cf = q1 * (Ym * E0 + (dY / ds_s) * E1);
  T gl_t1 = 0, gl_t2 = 0, m0_2 = 0, mc_2 = 0, m0t_gl = 0, mc_gl = 0, bas[4] = {0, 0, 0, 0};
  T ft_wy = 0, dk = 0, dhx = 0, dhz = 0;
  for (int j = 0; j < n_gl; ++j) {
    T x = T(xs[j]), w = T(ws[j]);
    T uu = um + half * x;
    Lobes<T> at = lobes(uu, p);
    T F2 = at.T2 * at.T2 + at.T2;
    T wy = w * (Ym + (dY / 2) * x);
    gl_t2 += wy * F2;
    gl_t1 += wy * at.F1;
    m0_2 += w * F2;
    mc_2 += w * x * F2;
    T Ft = ct[0] * at.e + ct[1] * at.se + ct[2] * at.ee + ct[3] * at.see;
    m0t_gl += w * Ft;
    mc_gl += w * x * at.F1;
    bas[0] += wy * at.e;
    bas[1] += wy * at.se;
    bas[2] += wy * at.ee;
    bas[3] += wy * at.see;
    ft_wy += wy * Ft;
    T f = half * wy * (-(2 * at.T2 + 1) * at.T2 * at.inv2);
    dk += f * at.N;
    dhx += f * (-4 * k * uu);
    dhz += f * (k * (1 - 4 * uu * uu));
  }
  gl_t2 *= half;
  gl_t1 *= half;
  T value = (use_cf ? cf : gl_t1) + gl_t2;
  m0_2 /= 2;
  mc_2 /= 4;
  m0t_gl /= 2;
  mc_gl /= 4;
  T m0t_1 = use_cf ? Et0 / ds_s : m0t_gl;
  T mc_1 = use_cf ? E1 / (ds_s * ds_s) : mc_gl;
  T m0 = m0t_1 + c0 + m0_2, mc = mc_1 + mc_2;
  T ma = m0 / 2 - mc, mb = m0 / 2 + mc;
  Lobes<T> ea_ = lobes(ua, p), eb_ = lobes(ub, p);
  T Da = ea_.F1 + ea_.T2 * ea_.T2 + ea_.T2;
  T Db = eb_.F1 + eb_.T2 * eb_.T2 + eb_.T2;
  bool point = (ua == ub) && (Ya == Yb);
  *d_ua = point ? T(0) : -Ya * Da - dY * ma;
  *d_ub = point ? T(0) : Yb * Db - dY * mb;
  *d_Ya = du * ma;
  *d_Yb = du * mb;
  if (point) return value;
  T d_c[4];
  for (int i = 0; i < 4; ++i)
    d_c[i] = use_cf ? q1 * (Ym * B0[i + 1] + (dY / ds_s) * B1[i + 1]) : half * bas[i];
  T sb = sa + ds;
  T Fta = ct[0] * ea_.e + ct[1] * ea_.se + ct[2] * ea_.ee + ct[3] * ea_.see;
  T Ftb = ct[0] * eb_.e + ct[1] * eb_.se + ct[2] * eb_.ee + ct[3] * eb_.see;
  T d_u1 = -(Yb * Ftb - Ya * Fta) + dY * m0t_1;
  T It_over_q1 = use_cf ? Ym * Et0 + (dY / ds_s) * E1 : (ds / 2) * ft_wy;
  T d_q1 = -(Yb * sb * Ftb - Ya * sa * Fta) + dY * (mc_1 * ds + sm * m0t_1) + It_over_q1;
  dp[0] += Ym * du;
  for (int i = 0; i < 4; ++i) dp[1 + i] += d_c[i];
  dp[5] += d_u1;
  dp[6] += d_q1;
  dp[8] += dk;
  dp[9] += dhx;
  dp[10] += dhz;
  return value;
}

template <typename T>
void lit_one(int n_gl, const double* xs, const double* ws, int k, const T* ua, const T* ub,
             const T* Ya, const T* Yb, T X, T hx_, T hy_, T hz_, T alpha_, T* out, T* g_ua,
             T* g_ub, T* g_Ya, T* g_Yb, T* g_X, T* g_hx, T* g_hy, T* g_hz, T* g_alpha) {
  // The view algebra with its Jacobian (`ndf._view`, `lit_interval`, `lobe.lobe`, `lobe_params`).
  Dual<T> hx = var(hx_, 0), hy = var(hy_, 1), hz = var(hz_, 2), al = var(alpha_, 3),
          Xd = var(X, 4);
  Dual<T> r = dsqrt(hx * hx + hz * hz);
  Dual<T> rp = r + dabs(hx);
  Dual<T> near = hz / (T(2) * rp), far = rp / (T(2) * hz);
  Dual<T> u_p = hx.v >= 0 ? near : far;
  Dual<T> u_m = hx.v >= 0 ? -far : -near;
  Dual<T> lo = dmax(-Xd, u_m);
  Dual<T> hi = dmax(dmin(Xd, u_p), lo);
  Dual<T> a2 = al * al;
  Dual<T> kk = dsafe_sqrt(cst(T(1)) - a2);
  Dual<T> g = cst(T(1)) / (cst(T(1)) + kk * hz);
  Dual<T> beta2 = a2 + kk * kk * hy * hy;
  Dual<T> beta = dsqrt(beta2);
  Dual<T> u1 = -(g * kk * hx) / cst(T(2));
  Dual<T> q1 = g * beta / cst(T(2));
  Dual<T> a = -(T(2) * g * kk * hx) / beta;
  Dual<T> m = T(2) * kk * (hz + g * kk * hx * hx) / beta2;
  Dual<T> pd[11] = {g * g + g, (T(2) * g + cst(T(1))) * m + a * a, (T(2) * g + cst(T(1))) * a,
                    m * m - a * a, T(2) * a * m, u1, q1, g, kk, hx, hz};
  T p[11];
  for (int i = 0; i < 11; ++i) p[i] = pd[i].v;

  // `ndf._cut` of the pieces to the slab [lo, hi].
  T L = lo.v, H = hi.v;
  T ca[kMaxPieces], cb[kMaxPieces], Ya2[kMaxPieces], Yb2[kMaxPieces], ta[kMaxPieces],
      tb[kMaxPieces], dYs[kMaxPieces], inv_du[kMaxPieces];
  bool ta_free[kMaxPieces], tb_free[kMaxPieces], lo_a[kMaxPieces], hi_a[kMaxPieces],
      lo_b[kMaxPieces], hi_b[kMaxPieces], pt[kMaxPieces];
  T sw = 0, swy = 0;
  for (int i = 0; i < k; ++i) {
    T du = ub[i] - ua[i], dY = Yb[i] - Ya[i];
    lo_a[i] = ua[i] < L; hi_a[i] = ua[i] > H; lo_b[i] = ub[i] < L; hi_b[i] = ub[i] > H;
    bool moved_a = lo_a[i] || hi_a[i], moved_b = lo_b[i] || hi_b[i];
    T c_a = lo_a[i] ? L : (hi_a[i] ? H : ua[i]);
    T c_b = lo_b[i] ? L : (hi_b[i] ? H : ub[i]);
    bool nz = du != 0;
    T inv = 1 / (nz ? du : T(1));
    auto param = [&](T c, bool moved, T dflt, bool* fr) {
      T rr = (c - ua[i]) * inv;
      bool mm = moved && nz;
      *fr = mm && rr > 0 && rr < 1;
      return mm ? (rr <= 0 ? T(0) : (rr >= 1 ? T(1) : rr)) : dflt;
    };
    ta[i] = param(c_a, moved_a, T(0), &ta_free[i]);
    tb[i] = param(c_b, moved_b, T(1), &tb_free[i]);
    T y_a = lerp(Ya[i], Yb[i], dY, ta[i]);
    T y_b = lerp(Ya[i], Yb[i], dY, tb[i]);
    pt[i] = nz ? (c_a == c_b) : moved_a;
    if (pt[i]) {
      c_b = c_a;
      y_b = y_a;
    }
    ca[i] = c_a; cb[i] = c_b; Ya2[i] = y_a; Yb2[i] = y_b; dYs[i] = dY; inv_du[i] = inv;
    T wgt = std::abs(c_b - c_a) + std::abs(y_b - y_a);
    sw += wgt;
    swy += wgt * (y_a + y_b) / 2;
  }
  T ref = sw > 0 ? swy / sw : T(0);  // `ndf._centre` (it carries no derivative)

  T value = 0, dp[11] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0}, g_lo = 0, g_hi = 0;
  for (int i = 0; i < k; ++i) {
    T dca, dcb, dYa, dYb;
    value += piece(n_gl, xs, ws, ca[i], cb[i], Ya2[i] - ref, Yb2[i] - ref, p, &dca, &dcb, &dYa,
                   &dYb, dp);
    // `ndf._cut_transpose`.
    if (pt[i]) {
      dca += dcb;
      dYa += dYb;
      dcb = 0;
      dYb = 0;
    }
    g_Ya[i] = dYa * (1 - ta[i]) + dYb * (1 - tb[i]);
    g_Yb[i] = dYa * ta[i] + dYb * tb[i];
    T ga = ta_free[i] ? dYa * dYs[i] * inv_du[i] : T(0);
    T gb = tb_free[i] ? dYb * dYs[i] * inv_du[i] : T(0);
    dca += ga;
    dcb += gb;
    T gua = ga * (ta[i] - 1) + gb * (tb[i] - 1);
    T gub = -(ga * ta[i] + gb * tb[i]);
    gua += (lo_a[i] || hi_a[i]) ? T(0) : dca;
    gub += (lo_b[i] || hi_b[i]) ? T(0) : dcb;
    g_ua[i] = gua;
    g_ub[i] = gub;
    g_lo += (lo_a[i] ? dca : T(0)) + (lo_b[i] ? dcb : T(0));
    g_hi += (hi_a[i] ? dca : T(0)) + (hi_b[i] ? dcb : T(0));
  }
  *out = value;
  // Chain the slab bounds' and the lobe parameters' partials through the view algebra.
  T gt[kTan];
  for (int t = 0; t < kTan; ++t) {
    T s = g_lo * lo.d[t] + g_hi * hi.d[t];
    for (int i = 0; i < 11; ++i) s += dp[i] * pd[i].d[t];
    gt[t] = s;
  }
  *g_hx = gt[0];
  *g_hy = gt[1];
  *g_hz = gt[2];
  *g_alpha = gt[3];
  *g_X = gt[4];
}

template <ffi::DataType DT>
ffi::Error LitImpl(ffi::Buffer<DT> ua, ffi::Buffer<DT> ub, ffi::Buffer<DT> Ya, ffi::Buffer<DT> Yb,
                   ffi::Buffer<DT> X, ffi::Buffer<DT> hx, ffi::Buffer<DT> hy, ffi::Buffer<DT> hz,
                   ffi::Buffer<DT> alpha, int64_t n_gl, int64_t threads, ffi::ResultBuffer<DT> out,
                   ffi::ResultBuffer<DT> g_ua, ffi::ResultBuffer<DT> g_ub,
                   ffi::ResultBuffer<DT> g_Ya, ffi::ResultBuffer<DT> g_Yb,
                   ffi::ResultBuffer<DT> g_X, ffi::ResultBuffer<DT> g_hx,
                   ffi::ResultBuffer<DT> g_hy, ffi::ResultBuffer<DT> g_hz,
                   ffi::ResultBuffer<DT> g_alpha) {
  using T = ffi::NativeType<DT>;
  const size_t n = X.element_count();
  if (n == 0) return ffi::Error::Success();
  const size_t k = ua.element_count() / n;
  if (k * n != ua.element_count() || k > kMaxPieces || n_gl < 1 || n_gl > kMaxNodes)
    return ffi::Error(ffi::ErrorCode::kInvalidArgument, "jscratch lit: bad shapes");
  double xs[kMaxNodes], ws[kMaxNodes];
  gauss_legendre(static_cast<int>(n_gl), xs, ws);
  const T *pua = ua.typed_data(), *pub = ub.typed_data(), *pYa = Ya.typed_data(),
          *pYb = Yb.typed_data(), *pX = X.typed_data(), *phx = hx.typed_data(),
          *phy = hy.typed_data(), *phz = hz.typed_data(), *pal = alpha.typed_data();
  T *o = out->typed_data(), *oua = g_ua->typed_data(), *oub = g_ub->typed_data(),
    *oYa = g_Ya->typed_data(), *oYb = g_Yb->typed_data(), *oX = g_X->typed_data(),
    *ohx = g_hx->typed_data(), *ohy = g_hy->typed_data(), *ohz = g_hz->typed_data(),
    *oal = g_alpha->typed_data();
  auto work = [&](size_t i0, size_t i1) {
    for (size_t i = i0; i < i1; ++i) {
      const size_t j = i * k;
      lit_one<T>(static_cast<int>(n_gl), xs, ws, static_cast<int>(k), pua + j, pub + j, pYa + j,
                 pYb + j, pX[i], phx[i], phy[i], phz[i], pal[i], o + i, oua + j, oub + j, oYa + j,
                 oYb + j, oX + i, ohx + i, ohy + i, ohz + i, oal + i);
    }
  };
  size_t nt = static_cast<size_t>(std::max<int64_t>(1, threads));
  nt = std::min(nt, std::max<size_t>(1, n / 2048));
  if (nt <= 1) {
    work(0, n);
  } else {
    std::vector<std::thread> pool;
    size_t step = (n + nt - 1) / nt;
    for (size_t t = 1; t < nt; ++t)
      pool.emplace_back(work, std::min(n, t * step), std::min(n, (t + 1) * step));
    work(0, std::min(n, step));
    for (auto& th : pool) th.join();
  }
  return ffi::Error::Success();
}

}  // namespace

#define JSCRATCH_LIT_BIND(DT)                                                              \
  ffi::Ffi::Bind()                                                                         \
      .Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>()                \
      .Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>()                \
      .Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>().Arg<ffi::Buffer<DT>>()                \
      .Attr<int64_t>("n_gl").Attr<int64_t>("threads")                                      \
      .Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>()                \
      .Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>()                \
      .Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>().Ret<ffi::Buffer<DT>>()                \
      .Ret<ffi::Buffer<DT>>()

XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchLitF32, LitImpl<ffi::DataType::F32>,
                              JSCRATCH_LIT_BIND(ffi::DataType::F32));
XLA_FFI_DEFINE_HANDLER_SYMBOL(JscratchLitF64, LitImpl<ffi::DataType::F64>,
                              JSCRATCH_LIT_BIND(ffi::DataType::F64));

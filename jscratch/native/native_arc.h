// The ball cutter's groove (`jscratch.arc`, docs/model.md §13) in the whole-pair kernels: the
// per-view stage of `arc.arc_lit_integral` with its partial derivatives, one SIMD lane per pair.
// Included by native_lit.cc inside its namespace (it uses that file's `Vec`, `Dual`, `View`,
// `Cut` and their helpers); the geometry stage is the paper profile's, unchanged, at
// (width, depth) = `arc.arc_groove(plunge, radius)`.
//
// Per view: the groove's half-width in u is U = u_of_v(2 X); the lit slab [u_lo, u_hi] is cut in
// the geometry's coordinate x / 2R = v / 2 (`cut`), the ends are mapped to u (slab bounds and
// groove edges exactly), and each piece's J = ∫ Y(v(u)) v'(u) (F1 + F2) du
// (`arc._piece_integrals`: the sharp lobe's poles subtracted by the Hermite cubic H and
// integrated in closed form, the rest by n_gl-point Gauss-Legendre in u). lit = sum of J / 2
// (so that D = scale * pref * lit, as for the paper's profile).
//
// Partial derivatives, all by hand, from one pass over the nodes:
// - J is affine in the sharp lobe's coefficients (c0, c10, c11, c20, c21): their partials are the
//   same rule applied to the basis functions (1, e, s e, e^2, s e^2) with the Hermite data of each;
// - J is linear in the piece's Y, which is linear in mu = (v(u) - v(ua)) / (ub - ua): with
//   J_1 (Y = 1) and J_mu (Y = mu), d J / d Yb = J_mu / den, d J / d Ya = J_1 - J_mu / den
//   (den = (v(ub) - v(ua)) / (ub - ua));
// - the ends: the derivatives of the integral itself,
//   d J / d ub = v'(ub) (Yb D(ub) - Y_v J_lambda),
//   d J / d ua = -v'(ua) (Ya D(ua) + Y_v J_(1-lambda))
//   (Y_v = dY / (v(ub) - v(ua)), lambda = mu / den), which differ from the rule's own
//   derivative by that rule's error on smooth integrands;
// - u1 and q1 (the peak's position and width): the rule's derivative, the nodes' s moving
//   (d/ds of the basis functions), the Hermite data moving with z = u1 + i q1 (w', w'' at z) and
//   the closed form's ends (its integrands at the ends);
// - k, hx, hz: the smooth lobe F2 at the nodes, as for the paper's profile.

constexpr double kQSub = 0.375;  // `arc.Q_SUB`

// Complex numbers per lane (the Hermite data at z = u1 + i q1).
template <typename V>
struct Cx {
  V re, im;
};
template <typename V>
inline Cx<V> operator+(const Cx<V>& a, const Cx<V>& b) {
  return {a.re + b.re, a.im + b.im};
}
template <typename V>
inline Cx<V> operator-(const Cx<V>& a, const Cx<V>& b) {
  return {a.re - b.re, a.im - b.im};
}
template <typename V>
inline Cx<V> operator*(const Cx<V>& a, const Cx<V>& b) {
  return {a.re * b.re - a.im * b.im, a.re * b.im + a.im * b.re};
}
template <typename V>
inline Cx<V> rmul(V s, const Cx<V>& a) {
  return {s * a.re, s * a.im};
}
template <typename V>
inline Cx<V> radd(V s, const Cx<V>& a) {
  return {s + a.re, a.im};
}
template <typename V>
inline Cx<V> times_i(const Cx<V>& a) {
  return {-a.im, a.re};
}
template <typename V>
inline Cx<V> cinv(const Cx<V>& a) {
  V m = 1 / (a.re * a.re + a.im * a.im);
  return {a.re * m, -a.im * m};
}

// One piece per lane: J (value), and with kPartials its partials with respect to the ends (u),
// the ends' Y and (accumulated into dp) the lobe parameters (`lobe.lobe_params`' layout; g has
// none). A point (ua == ub, Ya == Yb) has zero partials.
//
// `kSub` false: no lane subtracts (`sub` false in all of them), so H, its closed form and their
// partials are zero and are not computed (the same results: only zeros are left out of sums).
//
// The rule, per lane: the n_s-point one (xs_s, ws_s) where `short_rule`, else the full one (xs,
// ws); the loop runs over n nodes (the full rule's, or n_s where every lane takes the short one),
// a short-rule lane's nodes past n_s weighing 0. Every sum is weighted, so those nodes add exact
// zeros: a lane's result is its own, whatever rule its block's other lanes take.
template <typename T, typename V, bool kPartials, bool kSub>
V arc_piece_impl(int n, const double* xs, const double* ws, int n_s,
                 const double* xs_s, const double* ws_s, decltype(V{} < V{}) short_rule, V ua,
                 V ub, V Ya, V Yb, const V* p, decltype(V{} < V{}) sub, V* d_ua, V* d_ub,
                 V* d_Ya, V* d_Yb, V* dp) {
  const V c0 = p[0], c10 = p[1], c11 = p[2], c20 = p[3], c21 = p[4], u1 = p[5], q1 = p[6],
          k = p[8], hx = p[9], hz = p[10];
  const V zero = V{}, one = splat<V>(1), two = splat<V>(2), four = splat<V>(4);
  const V du = ub - ua, half = du / 2, um = ua + half, dY = Yb - Ya;
  const V Ba = 1 + 4 * ua * ua;
  const V den = 4 * (1 - 4 * ub * ua) / ((1 + 4 * ub * ub) * Ba);  // `arc._vdd(ub, ua)`
  const auto denp = den > 0;
  const V den1 = sel<V>(denp, den, one), dYden = dY / den1;
  const V ds = du / q1, sa = (ua - u1) / q1;
  const V ds_s = sel<V>(sub, ds, one), sa_s = sel<V>(sub, sa, zero), du_s = sel<V>(sub, du, one);
  const V q1_s = sel<V>(sub, q1, splat<V>(kQSub / 2)), idu = 1 / du_s;
  const V dYdv = dYden * idu;
  const Cx<V> Pi{c20, c21}, dPi{c21 - 2 * c11, 2 * c10};
  // H's coefficients (al0, al1, ga0, ga1) from Φ(i) = F and Φ'(i) = G; zero where nothing is
  // subtracted.
  auto coef = [&](const Cx<V>& F, const Cx<V>& G, V* a) {
    a[0] = sel<V>(sub, F.re, zero);
    a[1] = sel<V>(sub, F.im, zero);
    a[2] = sel<V>(sub, G.im / 2, zero);
    a[3] = sel<V>(sub, -(G.re - F.im) / 2, zero);
  };
  // Hermite data at z: v' (vp), v'' (vpp), v''' (vppp); Y(z) = Ya + dYden mu(z).
  Cx<V> z{u1, q1_s}, z2{}, iB{}, iB2{}, vp{}, vpp{}, muz{}, Yz{}, wz{}, wpz{};
  V h[4] = {zero, zero, zero, zero};
  // The closed form's basis integrals (`arc._basis`).
  const V sb_s = sa_s + ds_s, ea = 1 / (1 + sa_s * sa_s), eb = 1 / (1 + sb_s * sb_s);
  V I0 = zero, I1 = zero, K0 = zero, K1 = zero;
  if constexpr (kSub) {
    z2 = z * z;
    iB = cinv(radd(one, rmul(four, z2)));
    iB2 = iB * iB;
    vp = rmul(four, radd(one, rmul(splat<V>(-4), z2))) * iB2;
    vpp = rmul(splat<V>(-32), z * radd(splat<V>(3), rmul(splat<V>(-4), z2))) * iB2 * iB;
    muz = rmul(idu, (z - Cx<V>{ua, zero}) * rmul(four / Ba, radd(one, rmul(-4 * ua, z)) * iB));
    Yz = radd(Ya, rmul(dYden, muz));
    wz = Yz * vp;
    wpz = rmul(dYdv, vp * vp) + Yz * vpp;
    coef(wz * Pi, rmul(q1_s, wpz * Pi) + wz * dPi, h);
    const V y0 = 1 + sa_s * sb_s, ps = ds_s * (sa_s + sb_s);
    const auto up = ps >= 0;
    const V larg = sel<V>(up, ps * ea, -ps * eb);
    I0 = vatan2<T>(ds_s, y0);
    const V lg = vlog1p<T>(larg);
    I1 = splat<V>(0.5) * sel<V>(up, lg, -lg);
    K0 = splat<V>(0.5) * I0 + splat<V>(0.5) * (ds_s * ea) * ((1 - sa_s * sb_s) * eb);
    K1 = splat<V>(0.5) * (ds_s * ea) * ((sa_s + sb_s) * eb);
  }
  auto closed = [&](const V* a) {
    if constexpr (kSub) return q1_s * (a[0] * K0 + a[1] * K1 + a[2] * I0 + a[3] * I1);
    return zero;
  };

  // Gauss-Legendre in u on the rest: r = w (c0 + F2) + (w P - H) e^2 at the nodes.
  V gl = zero;
  V S_vD = zero, S_mD = zero, S_w = zero, S_we = zero, S_wse = zero, S_wee = zero,
    S_wsee = zero, S_Rp = zero, S_sRp = zero, S_e = zero, S_se = zero, S_ee = zero,
    S_see = zero, S_k = zero, S_hx = zero, S_hz = zero;
  const V iBa = 1 / Ba, iq1 = 1 / q1;
  // (vfma: the sums and the polynomials in one rounding per term, where the CPU can)
  for (int j = 0; j < n; ++j) {
    const int js = j < n_s ? j : n_s - 1;
    const V x = sel<V>(short_rule, splat<V>(xs_s[js]), splat<V>(xs[j]));
    const V w = sel<V>(short_rule, j < n_s ? splat<V>(ws_s[j]) : zero, splat<V>(ws[j]));
    const V tau = (1 + x) / 2;
    const V uu = vfma(half, x, um), u2 = uu * uu, B = vfma(four, u2, one), iBu = 1 / B;
    const V m4u2 = vfma(splat<V>(-4), u2, one), vpj = 4 * m4u2 * iBu * iBu;
    // mu = (v(u) - v(ua)) / (ub - ua) at the node, by the divided difference.
    const V mu = sel<V>(denp, tau * (4 * vfma(-4 * uu, ua, one) * iBu * iBa), tau);
    const V wu = vfma(dYden, mu, Ya) * vpj;
    const V N = vfma(hz, m4u2, -4 * hx * uu), inv2 = 1 / vfma(k, N, B), T2 = B * inv2;
    const V F2 = vfma(T2, T2, T2);
    const V s = (uu - u1) * iq1, e = 1 / vfma(s, s, one), se = s * e, ee = e * e, see = se * e;
    const V A0 = vfma(wu, c10, -h[2]), A1 = vfma(wu, c11, -h[3]), B0 = vfma(wu, c20, -h[0]),
            B1 = vfma(wu, c21, -h[1]);
    const V Rs = vfma(vfma(A1, s, A0), e, vfma(B1, s, B0) * ee);
    gl = vfma(w, vfma(wu, c0 + F2, Rs), gl);
    if constexpr (kPartials) {
      const V eee = ee * e, seee = see * e;
      const V Dt = vfma(c21, see, vfma(c20, ee, vfma(c11, se, vfma(c10, e, c0 + F2))));
      // d/ds of the remainder (w P - H) e^2 at fixed w, term by term as Rs.
      const V Rp = vfma(B1, 4 * eee - 3 * ee,
                        vfma(-4 * B0, seee, vfma(A1, 2 * ee - e, -2 * A0 * see)));
      const V ww = w * wu, wv = w * vpj;
      S_vD = vfma(wv, Dt, S_vD);
      S_mD = vfma(wv * mu, Dt, S_mD);
      S_w += ww;
      S_we = vfma(ww, e, S_we);
      S_wse = vfma(ww, se, S_wse);
      S_wee = vfma(ww, ee, S_wee);
      S_wsee = vfma(ww, see, S_wsee);
      S_Rp = vfma(w, Rp, S_Rp);
      S_sRp = vfma(w * s, Rp, S_sRp);
      S_e = vfma(w, e, S_e);
      S_se = vfma(w, se, S_se);
      S_ee = vfma(w, ee, S_ee);
      S_see = vfma(w, see, S_see);
      const V f = ww * (-vfma(two, T2, one) * T2 * inv2);
      S_k = vfma(f, N, S_k);
      S_hx = vfma(f, -4 * k * uu, S_hx);
      S_hz = vfma(f, k * m4u2, S_hz);
    }
  }
  V value = half * gl;
  if constexpr (kSub) value = value + sel<V>(sub, closed(h), zero);
  if constexpr (!kPartials) return value;

  // H's share of the rule's sum, and of its derivative in s (times s for q1).
  auto hsum = [&](const V* a) { return a[2] * S_e + a[3] * S_se + a[0] * S_ee + a[1] * S_see; };
  // ∫ of the Hermite-subtracted integrand whose H has Φ(i) = F, Φ'(i) = G, less the rule's
  // share of H (the rule's share of the rest is added by the caller).
  auto lfull = [&](const Cx<V>& F, const Cx<V>& G) {
    V a[4];
    coef(F, G, a);
    return closed(a) - half * hsum(a);
  };
  // The two bases of Y: 1 and mu.
  V J1 = half * S_vD, Jm = half * S_mD, M1 = S_vD / 2, Mm = S_mD / 2;
  V gu1 = half * (-S_Rp / q1), gq1 = half * (-S_sRp / q1);
  V gc[5] = {half * S_w, half * S_we, half * S_wse, half * S_wee, half * S_wsee};
  Cx<V> dFu{}, dGu{};
  if constexpr (kSub) {
    const Cx<V> F1 = vp * Pi, G1 = rmul(q1_s, vpp * Pi) + vp * dPi;
    const Cx<V> wm = muz * vp, wmp = rmul(idu, vp * vp) + muz * vpp;
    const Cx<V> Fm = wm * Pi, Gm = rmul(q1_s, wmp * Pi) + wm * dPi;
    V a1[4], am[4];
    coef(F1, G1, a1);
    coef(Fm, Gm, am);
    J1 = closed(a1) - half * hsum(a1) + half * S_vD;
    Jm = closed(am) - half * hsum(am) + half * S_mD;
    // The ends: J_1 / du and J_mu / du, then the integral's derivatives.
    M1 = sel<V>(sub, closed(a1) * idu, zero) + (S_vD - hsum(a1)) / 2;
    Mm = sel<V>(sub, closed(am) * idu, zero) + (S_mD - hsum(am)) / 2;
    // u1 and q1: H moves with z (w' and w'' at z), the nodes' s and the closed form's ends
    // move.
    const Cx<V> vppp =
        rmul(splat<V>(-96), radd(one, rmul(splat<V>(-24), z2) + rmul(splat<V>(16), z2 * z2))) *
        iB2 * iB2;
    const Cx<V> wppz = rmul(3 * dYdv, vp * vpp) + Yz * vppp;
    const V eb2 = eb * eb, ea2 = ea * ea;
    const V kin_sa = q1_s * (h[0] * (eb2 - ea2) + h[1] * (sb_s * eb2 - sa_s * ea2) +
                             h[2] * (eb - ea) + h[3] * (sb_s * eb - sa_s * ea));
    const V kin_ds = q1_s * (h[0] * eb2 + h[1] * sb_s * eb2 + h[2] * eb + h[3] * sb_s * eb);
    dFu = wpz * Pi;
    dGu = rmul(q1_s, wppz * Pi) + wpz * dPi;
    gu1 = lfull(dFu, dGu) + sel<V>(sub, -kin_sa / q1, zero) + half * (-S_Rp / q1);
    gq1 = lfull(times_i(dFu), dFu + times_i(dGu)) +
          sel<V>(sub, closed(h) / q1_s + (-sa_s * kin_sa - ds_s * kin_ds) / q1, zero) +
          half * (-S_sRp / q1);
    // The sharp lobe's coefficients.
    const Cx<V> zc{zero, zero};
    gc[1] = lfull(zc, rmul(splat<V>(2), times_i(wz))) + half * S_we;
    gc[2] = lfull(zc, rmul(splat<V>(-2), wz)) + half * S_wse;
    gc[3] = lfull(wz, rmul(q1_s, wpz)) + half * S_wee;
    gc[4] = lfull(times_i(wz), times_i(rmul(q1_s, wpz)) + wz) + half * S_wsee;
  }
  V gYb = Jm / den1, gYa = J1 - gYb;
  auto at_end = [&](V u, V* vpe) {
    const V B = 1 + 4 * u * u, N = hz * (1 - 4 * u * u) - 4 * hx * u, T2 = B / (B + k * N);
    const V s = (u - u1) / q1, e = 1 / (1 + s * s);
    *vpe = 4 * (1 - 4 * u * u) / (B * B);
    return c0 + T2 * T2 + T2 + c10 * e + c11 * s * e + c20 * e * e + c21 * s * e * e;
  };
  V vpa, vpb;
  const V Da = at_end(ua, &vpa), Db = at_end(ub, &vpb);
  V gub = vpb * (Yb * Db - dYden * Mm / den1);
  V gua = -vpa * (Ya * Da + dYden * (M1 - Mm / den1));
  // A point's partials are zero.
  const auto point = (ua == ub) & (Ya == Yb);
  *d_ua = sel<V>(point, zero, gua);
  *d_ub = sel<V>(point, zero, gub);
  *d_Ya = sel<V>(point, zero, gYa);
  *d_Yb = sel<V>(point, zero, gYb);
  for (int i = 0; i < 5; ++i) dp[i] += sel<V>(point, zero, gc[i]);
  dp[5] += sel<V>(point, zero, gu1);
  dp[6] += sel<V>(point, zero, gq1);
  dp[8] += sel<V>(point, zero, half * S_k);
  dp[9] += sel<V>(point, zero, half * S_hx);
  dp[10] += sel<V>(point, zero, half * S_hz);
  return value;
}

// The Bernstein-ellipse test for the shorter rule: whether the pole z = (zr, zi) is at least
// kFar piece lengths away in summed distance, |z - ua| + |z - ub| >= kFar |ub - ua|, i.e. it
// lies outside the ellipse E_rho with foci ua, ub and rho + 1 / rho = 2 kFar (rho ~ 10.3), which
// holds E_5, all the error bound needs (docs/model.md §13; kFar = 2.6, E_5 itself, would make a
// step at most 2-3 % faster: benchmarks/RESULTS.md).
constexpr double kFar = 5.2;
template <typename T, typename V>
inline decltype(V{} < V{}) far_pole(V zr, V zi, V ua, V ub, V len) {
  const V a = zr - ua, b = zr - ub, z2 = zi * zi;
  return vsqrt<T>(a * a + z2) + vsqrt<T>(b * b + z2) >= splat<V>(kFar) * len;
}

// `arc_piece_impl` with the subtraction's work only where a lane subtracts, and with the
// n_gl / 2-point rule (stored after the n_gl-point one in xs, ws: `run_pairs`) in each lane whose
// integrand is analytic in E_5 of its piece: the poles of w (+-i/2), of F2 and, where nothing is
// subtracted, of F1 lie outside it. The rule's error bound (docs/model.md §13) then has
// 5^(-2 n / 2) = 5^(-n) < 2^(-2 n), below the full rule's at the worst pieces (rho = 2). The
// choice is per lane, so a pair's result does not depend on the pairs beside it in its block.
template <typename T, typename V, bool kPartials>
V arc_piece(int n_gl, const double* xs, const double* ws, V ua, V ub, V Ya, V Yb, const V* p,
            V* d_ua, V* d_ub, V* d_Ya, V* d_Yb, V* dp) {
  const V q1 = p[6], one = splat<V>(1);
  const V ds = (ub - ua) / q1, sa = (ua - p[5]) / q1, sm = sa + ds / 2;
  // Where the sharp lobe's poles are subtracted (`arc._piece_integrals`).
  const auto sub = (q1 < splat<V>(kQSub)) &
                   (vabs<T>(ds) >= vmax<T>(one, splat<V>(0.5) * vabs<T>(sm)));
  bool any = false;
  for (int l = 0; l < Vec<T>::L; ++l) any = any || sub[l];
  decltype(V{} < V{}) far{};  // (no lane)
  int n = n_gl, n_s = n_gl;
  const double *xs_s = xs, *ws_s = ws;
  if (n_gl >= 8 && n_gl % 2 == 0) {
    const V k = p[8], hx = p[9], hz = p[10], len = vabs<T>(ub - ua), zero = V{};
    // F2's poles: (k hx +- i beta) / (2 (1 - k hz)), beta^2 = 1 - k^2 (hx^2 + hz^2) (complex
    // poles only where beta^2 > 0 and 1 - k hz > 0; else the full rule).
    const V b2 = 1 - k * k * (hx * hx + hz * hz), den = 2 * (1 - k * hz);
    const auto ok2 = (b2 > 0) & (den > 0);
    const V iden = 1 / sel<V>(ok2, den, one);
    const V zr = k * hx * iden, zi = vsqrt<T>(sel<V>(ok2, b2, one)) * iden;
    far = far_pole<T>(zero, splat<V>(0.5), ua, ub, len) & ok2 &
          far_pole<T>(zr, zi, ua, ub, len) & (sub | far_pole<T>(p[5], q1, ua, ub, len));
    xs_s = xs + n_gl;
    ws_s = ws + n_gl;
    n_s = n_gl / 2;
    bool all = true;
    for (int l = 0; l < Vec<T>::L; ++l) all = all && far[l];
    if (all) n = n_s;
  }
  if (any)
    return arc_piece_impl<T, V, kPartials, true>(n, xs, ws, n_s, xs_s, ws_s, far, ua, ub,
                                                 Ya, Yb, p, sub, d_ua, d_ub, d_Ya, d_Yb, dp);
  return arc_piece_impl<T, V, kPartials, false>(n, xs, ws, n_s, xs_s, ws_s, far, ua, ub,
                                                Ya, Yb, p, sub, d_ua, d_ub, d_Ya, d_Yb, dp);
}

// `arc.u_of_v(2 c)` and its derivative in c (as autodiff of `u_of_v` gives it: 1 where the
// square root is 0).
template <typename T, typename V>
inline V u_of_c(V c, V* dudc) {
  const V v = 2 * c, a = (1 - v) * (1 + v);
  const auto pos = a > 0;
  const V r = sel<V>(pos, vsqrt<T>(sel<V>(pos, a, splat<V>(1))), V{});
  const V d = 1 + r;
  *dudc = 2 * (1 / (2 * d) + sel<V>(pos, v * v / (2 * r * d * d), V{}));
  return v / (2 * d);
}

// The arc's per-view stage, one lane per pair-view; inputs and outputs as `lit_lanes` (the
// pieces in x / 2R, sv = (X, h, b, t, alpha)), lit = sum of J / 2.
template <typename T, typename V, bool kPartials>
void arc_lit_lanes(int n_gl, const double* xs, const double* ws, int k, const V* ua,
                   const V* ub, const V* Ya, const V* Yb, const V* sv, V* out, V* g_ua, V* g_ub,
                   V* g_Ya, V* g_Yb, V* gs) {
  typedef typename Cut<V>::M M;
  const V zero = V{}, one = splat<V>(1), two = splat<V>(2), four = splat<V>(4);
  constexpr int NV = kPartials ? kTan : 0;  // (the value alone needs no tangents)
  View<V, NV> vw;
  view_algebra<T, V, NV>(sv, &vw);
  // U = u_of_v(2 X), the slab in u and in x / 2R = v(u) / 2.
  const Dual<V, NV> v2 = scale(two, vw.X);
  const Dual<V, NV> U = v2 / scale(two, cst<NV>(one) + dsafe_sqrt<T>((cst<NV>(one) - v2) *
                                                                      (cst<NV>(one) + v2)));
  const Dual<V, NV> lo_u = dmax<T>(-U, vw.u_m);
  const Dual<V, NV> hi_u = dmax<T>(dmin<T>(U, vw.u_p), lo_u);
  auto half_v = [&](const Dual<V, NV>& u) {
    return scale(splat<V>(0.5), scale(four, u) / (cst<NV>(one) + scale(four, u) * u));
  };
  const Dual<V, NV> lo_c = half_v(lo_u), hi_c = half_v(hi_u);
  V p[11];
  for (int i = 0; i < 11; ++i) p[i] = vw.pd[i].v;
  Cut<V> c;
  cut<T>(k, ua, ub, Ya, Yb, lo_c.v, hi_c.v, &c);
  const V X = vw.X.v, Uv = U.v;
  // An end in u: the slab bound where the cut clamped it, the groove edge +-U where it is there,
  // else mapped.
  auto to_u = [&](V x, M lo, M hi, V* dudc, M* mapped, M* at_m, M* at_p) {
    const V m = u_of_c<T>(x, dudc);
    *at_m = ~lo & ~hi & (x == -X);
    *at_p = ~lo & ~hi & ~*at_m & (x == X);
    *mapped = ~lo & ~hi & ~*at_m & ~*at_p;
    return sel<V>(lo, lo_u.v, sel<V>(hi, hi_u.v, sel<V>(x == -X, -Uv, sel<V>(x == X, Uv, m))));
  };
  V value = zero, dp[11], g_lo = zero, g_hi = zero, g_ulo = zero, g_uhi = zero, g_U = zero;
  for (int i = 0; i < 11; ++i) dp[i] = zero;
  for (int i = 0; i < k; ++i) {
    V da, db;
    M ma, mb, am, ap, bm, bp;
    const V ua_u = to_u(c.ca[i], c.lo_a[i], c.hi_a[i], &da, &ma, &am, &ap);
    const M same = c.ca[i] == c.cb[i];
    const V ub_u = sel<V>(same, ua_u, to_u(c.cb[i], c.lo_b[i], c.hi_b[i], &db, &mb, &bm, &bp));
    V gua, gub, gYa, gYb;
    value += arc_piece<T, V, kPartials>(n_gl, xs, ws, ua_u, ub_u, c.Ya2[i] - c.ref,
                                        c.Yb2[i] - c.ref, p, &gua, &gub, &gYa, &gYb, dp);
    if constexpr (!kPartials) continue;
    // The ends' mapping, transposed (a point's second end is its first).
    gua += sel<V>(same, gub, zero);
    gub = sel<V>(same, zero, gub);
    g_ulo += sel<V>(c.lo_a[i], gua, zero) + sel<V>(c.lo_b[i], gub, zero);
    g_uhi += sel<V>(~c.lo_a[i] & c.hi_a[i], gua, zero) + sel<V>(~c.lo_b[i] & c.hi_b[i], gub, zero);
    g_U += sel<V>(ap, gua, zero) - sel<V>(am, gua, zero) + sel<V>(bp, gub, zero) -
           sel<V>(bm, gub, zero);
    const V gca = sel<V>(ma, gua * da, zero), gcb = sel<V>(mb, gub * db, zero);
    cut_transpose(c, i, gca, gcb, gYa, gYb, &g_ua[i], &g_ub[i], &g_Ya[i], &g_Yb[i], &g_lo, &g_hi);
  }
  const V h2 = splat<V>(0.5);
  *out = h2 * value;
  if constexpr (kPartials) {
    for (int i = 0; i < k; ++i) {
      g_ua[i] *= h2;
      g_ub[i] *= h2;
      g_Ya[i] *= h2;
      g_Yb[i] *= h2;
    }
    for (int t = 0; t < kTan; ++t) {
      V s = g_lo * lo_c.d[t] + g_hi * hi_c.d[t] + g_ulo * lo_u.d[t] + g_uhi * hi_u.d[t] +
            g_U * U.d[t];
      for (int i = 0; i < 11; ++i) s += dp[i] * vw.pd[i].d[t];
      gs[t] = h2 * s;
    }
  }
}

// SIMD vectors for the native kernels (`native_lit.cc`, which includes this file inside its
// namespace, after <cmath> and <cstdint>): the vector type, selects, and the elementary functions
// the kernels need per lane. `tests/test_native.py` compiles this file alone and checks
// `vatan2` and `vlog1p` against libm.

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
// a * b + c with one rounding (a fused multiply-add) where the CPU has one; the build's
// -ffp-contract=off keeps every other product and sum rounded on its own. (A file that includes
// this one inside a namespace includes <immintrin.h> first, so the line below adds nothing there.)
#if defined(__FMA__) && defined(__AVX__)
#include <immintrin.h>
#endif
template <typename V>
inline V vfma(V a, V b, V c) {
#if defined(__FMA__) && defined(__AVX__)
  if constexpr (sizeof(a[0]) == 4)
    return reinterpret_cast<V>(_mm256_fmadd_ps(reinterpret_cast<__m256>(a),
                                               reinterpret_cast<__m256>(b),
                                               reinterpret_cast<__m256>(c)));
  else
    return reinterpret_cast<V>(_mm256_fmadd_pd(reinterpret_cast<__m256d>(a),
                                               reinterpret_cast<__m256d>(b),
                                               reinterpret_cast<__m256d>(c)));
#else
  return a * b + c;
#endif
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

// atan2 and log1p per lane. In float32, SIMD versions of the Cephes single-precision algorithms
// (atanf after reduction to |t| <= tan(pi/8), logf on a mantissa in [sqrt(1/2), sqrt(2)) with
// log1p's correction term): atan2 within 3 ulps and log1p within 1 ulp of libm
// (docs/model.md §12), instead of one libm call
// per lane. In float64, libm per lane (the kernels' float64 results are the tests' references).
template <typename T, typename V>
inline V vatan2(V y, V x) {
  V r;
  if constexpr (sizeof(T) == 8) {
    for (int l = 0; l < Vec<T>::L; ++l) r[l] = std::atan2(y[l], x[l]);
  } else {
    typedef typename Vec<int32_t>::type VI;  // (V is Vec<float>::type here)
    const V zero = V{}, one = splat<V>(1);
    const V ax = vabs<T>(x), ay = vabs<T>(y);
    const auto swap = ay > ax;
    const V num = sel<V>(swap, ax, ay), den = sel<V>(swap, ay, ax);
    const V a = sel<V>(den > 0, num / sel<V>(den > 0, den, one), zero);  // in [0, 1]
    const auto big = a > splat<V>(0.41421356237309504880);             // tan(pi/8)
    const V t = sel<V>(big, (a - one) / (a + one), a);
    const V z = t * t;
    V p = ((splat<V>(8.05374449538e-2) * z - splat<V>(1.38776856032e-1)) * z +
           splat<V>(1.99777106478e-1)) * z - splat<V>(3.33329491539e-1);
    r = (p * z) * t + t + sel<V>(big, splat<V>(0.78539816339744830962), zero);
    r = sel<V>(swap, splat<V>(1.57079632679489661923) - r, r);
    r = sel<V>((x < 0) | ((x == 0) & ((VI)x < 0)), splat<V>(3.14159265358979323846) - r, r);
    // the sign of y (also for y = -0), as atan2's
    r = (V)(((VI)r & splat<VI>(0x7fffffff)) | ((VI)y & splat<VI>(int32_t(0x80000000))));
    r = sel<V>((x != x) | (y != y), x + y, r);
  }
  return r;
}
template <typename T, typename V>
inline V vlog1p(V x) {
  V r;
  if constexpr (sizeof(T) == 8) {
    for (int l = 0; l < Vec<T>::L; ++l) r[l] = std::log1p(x[l]);
  } else {
    typedef typename Vec<int32_t>::type VI;  // (V is Vec<float>::type here)
    const V one = splat<V>(1);
    const V u = one + x;
    // u = m 2^e with m in [sqrt(1/2), sqrt(2)) (u >= 1/2 and finite here; other lanes below)
    const VI bits = (VI)u;
    VI e = ((bits >> 23) & 0xff) - 126;
    V m = (V)((bits & 0x007fffff) | 0x3f000000);  // in [1/2, 1)
    const auto lo = m < splat<V>(0.70710678118654752440);
    e = e + (VI)lo;  // (a mask is -1 where true)
    const V f = sel<V>(lo, m + m - one, m - one);
    const V ef = __builtin_convertvector(e, V);
    const V z = f * f;
    V p = splat<V>(7.0376836292e-2);
    p = p * f - splat<V>(1.1514610310e-1);
    p = p * f + splat<V>(1.1676998740e-1);
    p = p * f - splat<V>(1.2420140846e-1);
    p = p * f + splat<V>(1.4249322787e-1);
    p = p * f - splat<V>(1.6668057665e-1);
    p = p * f + splat<V>(2.0000714765e-1);
    p = p * f - splat<V>(2.4999993993e-1);
    p = p * f + splat<V>(3.3333331174e-1);
    V y = f * (z * p) - splat<V>(2.12194440e-4) * ef - splat<V>(0.5) * z;
    // log(u) + (x - (u - 1)) / u: the rounding of 1 + x, to first order
    y = (f + y) + splat<V>(0.693359375) * ef + (x - (u - one)) / u;
    const auto tiny = vabs<T>(x) < splat<V>(5.9604644775390625e-8);  // 2^-24: log1p(x) = x
    r = sel<V>(tiny, x, y);
        for (int l = 0; l < Vec<T>::L; ++l)  // outside the fast range (never on the kernels' path)
      if (!(u[l] > 0.5f) || !(x[l] < 3.4e38f)) r[l] = std::log1p(x[l]);
  }
  return r;
}

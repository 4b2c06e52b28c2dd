
#include <type_traits>
@COMMON@
// libm's functions without <cmath>: its header alone is about half the time of a quick (-O0)
// build of a small tree's program, and of every build's parsing. sqrt, fabs, atan2 and pow are
// the compiler's builtins (the same instructions and libm calls std:: makes of them); sincos,
// a GNU extension with no builtin in every compiler, is declared as glibc declares it.
extern "C" {
void sincos(double, double*, double*) noexcept;
void sincosf(float, float*, float*) noexcept;
}
#ifndef INFINITY
#define INFINITY (__builtin_inff())  // as <math.h> defines it
#endif
static inline double jb_sqrt(double x) { return __builtin_sqrt(x); }
static inline float jb_sqrt(float x) { return __builtin_sqrtf(x); }
static inline double jb_fabs(double x) { return __builtin_fabs(x); }
static inline float jb_fabs(float x) { return __builtin_fabsf(x); }
static inline double jb_atan2(double y, double x) { return __builtin_atan2(y, x); }
static inline float jb_atan2(float y, float x) { return __builtin_atan2f(y, x); }
static inline double jb_pow(double x, double p) { return __builtin_pow(x, p); }
static inline float jb_pow(float x, float p) { return __builtin_powf(x, p); }
// an owned array of n values (std::unique_ptr<X[]> without <memory>, whose header alone takes
// about half a second to compile): the reverse sweeps' kept steps
template <typename X>
struct Owned {
  X* data;
  explicit Owned(int64_t n) : data(new X[n]) {}
  ~Owned() { delete[] data; }
  Owned(const Owned&) = delete;
  Owned& operator=(const Owned&) = delete;
  X& operator[](int64_t i) { return data[i]; }
};
// states per block: one vector register of lanes, VECTOR_BYTES wide (jaxbody.backends.native.BUILDS):
// scalar code for a single state (a vector build would carry every value in a whole register,
// and the long derivative programs keep most of them on the stack), 256-bit lanes for small
// batches, 512-bit lanes (with AVX-512) for larger ones
#define JB_VECTOR_BYTES @VECTOR_BYTES@
constexpr int VECTOR_BYTES = JB_VECTOR_BYTES == 0 ? int(sizeof(T)) : JB_VECTOR_BYTES;
constexpr int W = VECTOR_BYTES / sizeof(T);
typedef T V __attribute__((vector_size(sizeof(T) * W)));
typedef std::conditional<sizeof(T) == 8, int64_t, int32_t>::type IntT;
typedef IntT I __attribute__((vector_size(sizeof(T) * W)));

// 512-bit blocks read a batched operand and write a result with one gather or scatter
// instruction per scalar (lane l: row b0 + l of a row-major (batch, n) array): per-lane loads
// and stores would cost the same per state in either precision, a larger share of float32's
// shorter time per state. Only an optimised build: <immintrin.h> is most of a quick build's
// compile time, and a quick build only serves until its optimised one is ready (per-lane loads
// and stores read and write the same values)
#if JB_VECTOR_BYTES == 64 && defined(__AVX512F__) && defined(__OPTIMIZE__)
#include <immintrin.h>
#define JB_GATHER 1
static inline V gather_rows(const float* base, int64_t stride, int n) {
  const __m512i lane = _mm512_min_epi32(_mm512_set_epi32(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0),
                                        _mm512_set1_epi32(n - 1));
  return (V)_mm512_i32gather_ps(_mm512_mullo_epi32(lane, _mm512_set1_epi32(int(stride))), base, 4);
}
static inline V gather_rows(const double* base, int64_t stride, int n) {
  const __m256i lane = _mm256_min_epi32(_mm256_set_epi32(7, 6, 5, 4, 3, 2, 1, 0), _mm256_set1_epi32(n - 1));
  return (V)_mm512_i32gather_pd(_mm256_mullo_epi32(lane, _mm256_set1_epi32(int(stride))), base, 8);
}
static inline void scatter_rows(float* base, int64_t stride, int n, V x) {
  const __m512i row = _mm512_mullo_epi32(_mm512_set_epi32(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0),
                                         _mm512_set1_epi32(int(stride)));
  _mm512_mask_i32scatter_ps(base, __mmask16((1u << n) - 1u), row, (__m512)x, 4);
}
static inline void scatter_rows(double* base, int64_t stride, int n, V x) {
  const __m256i row = _mm256_mullo_epi32(_mm256_set_epi32(7, 6, 5, 4, 3, 2, 1, 0), _mm256_set1_epi32(int(stride)));
  _mm512_mask_i32scatter_pd(base, __mmask8((1u << n) - 1u), row, (__m512d)x, 8);
}
#else
#define JB_GATHER 0
#endif

// sine and cosine of every lane: Cody-Waite reduction by pi/2 (two-part constant, fused
// multiply-adds) and Cephes' minimax polynomials on [-pi/4, pi/4] (six terms in double, three in
// single precision), about 1 ulp for the angles
// of joints (|x| < 1e5); larger angles (and NaN) go lane by lane through libm
static inline void sincos_(double x, double* s, double* c) { sincos(x, s, c); }
static inline void sincos_(float x, float* s, float* c) { sincosf(x, s, c); }

static inline void sincos_lanes(V x, V& s, V& c, int n) {
  T sl = 0, cl = 0;
  for (int l = 0; l < W; ++l) {
    if (l < n) {
      sincos_(x[l], &sl, &cl);
    }
    s[l] = sl;
    c[l] = cl;
  }
}

static inline void vsincos(V x, V& s, V& c, int n) {
  {
    bool small = true;
    for (int l = 0; l < W; ++l) small &= jb_fabs(x[l]) < T(1e5);  // false for NaN: libm's NaN
    if (small) {
      // 1.5 * 2^(mantissa bits): adding it rounds to an integer, held in the low bits
      const T magic = sizeof(T) == 8 ? T(6755399441055744.0) : T(12582912.0f);
      const T pio2_hi = sizeof(T) == 8 ? T(1.5707963267948966) : T(1.57079637f);
      const T pio2_lo = sizeof(T) == 8 ? T(6.123233995736766e-17) : T(-4.37113883e-8f);
      const V shifted = x * T(0.63661977236758134308) + magic;
      const V k = shifted - magic;
      I quadrant;
      __builtin_memcpy(&quadrant, &shifted, sizeof(V));
      quadrant &= 3;
      V r = x - k * pio2_hi;  // contracted to a fused multiply-add
      r = r - k * pio2_lo;
      const V z = r * r;
      V ps, pc;
      if constexpr (sizeof(T) == 4) {
        // Cephes' single-precision polynomials (sinf, cosf): three terms each suffice
        ps = V{} + T(-1.9515295891e-4f);
        ps = ps * z + T(8.3321608736e-3f);
        ps = ps * z + T(-1.6666654611e-1f);
        pc = V{} + T(2.443315711809948e-5f);
        pc = pc * z + T(-1.388731625493765e-3f);
        pc = pc * z + T(4.166664568298827e-2f);
      } else {
        ps = V{} + T(1.58962301576546568060e-10);
        ps = ps * z + T(-2.50507477628578072866e-8);
        ps = ps * z + T(2.75573136213857245213e-6);
        ps = ps * z + T(-1.98412698295895385996e-4);
        ps = ps * z + T(8.33333333332211858878e-3);
        ps = ps * z + T(-1.66666666666666307295e-1);
        pc = V{} + T(-1.13585365213876817300e-11);
        pc = pc * z + T(2.08757008419747316778e-9);
        pc = pc * z + T(-2.75573141792967388112e-7);
        pc = pc * z + T(2.48015872888517045348e-5);
        pc = pc * z + T(-1.38888888888730564116e-3);
        pc = pc * z + T(4.16666666666665929218e-2);
      }
      const V sr = r + r * z * ps;
      const V cr = T(1.0) - T(0.5) * z + z * z * pc;
      const I swap = (quadrant & 1) != 0;
      const V s0 = swap ? cr : sr, c0 = swap ? sr : cr;
      s = ((quadrant & 2) != 0) ? -s0 : s0;
      c = (((quadrant + 1) & 2) != 0) ? -c0 : c0;
      return;
    }
  }
  sincos_lanes(x, s, c, n);
}

// square root and two-argument arc tangent of every lane (the springs of quaternion joints)
static inline V vsqrt(V x) {
  V r;
  for (int l = 0; l < W; ++l) r[l] = jb_sqrt(x[l]);
  return r;
}
static inline V vatan2(V y, V x) {
  V r;
  for (int l = 0; l < W; ++l) r[l] = jb_atan2(y[l], x[l]);
  return r;
}

// the generated function of the states b0 .. b0 + n - 1 (n <= W); lane l is state b0 + min(l, n - 1)
static void fd_block(const Inputs& in, int64_t b0, int n) {
@ACCESS@
@BODY@
}

extern "C" void jaxbody_range(const Inputs* in, int64_t b0, int64_t b1) {
  for (int64_t b = b0; b < b1; b += W) fd_block(*in, b, b1 - b < W ? int(b1 - b) : W);
}

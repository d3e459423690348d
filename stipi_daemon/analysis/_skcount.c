/*
 * Single-pass occluded-pixel counting, Eqs. (1)-(2) of the STIP-I paper.
 *
 * S_k = number of ROI pixels whose 8-bit gray value is <= p (Eq. (1) marks them 1, Eq. (2)
 * sums the marks). OpenCV needs two passes for that (cv2.threshold writes a 0/1 image,
 * cv2.countNonZero reads it back), so it moves three frames' worth of memory per frame.
 * This module reads each pixel once and writes nothing: compare, accumulate in 8-bit lanes,
 * widen every 255 vectors. The same pass can also count saturated pixels (gray == 255) for
 * the frame-quality check, at no extra memory traffic.
 *
 * Pixel layouts (the gray value is computed on the fly, in the same single pass):
 *   - gray: 2-D (H, W) or (H, W, 1) bytes; the gray value is the byte.
 *   - YUYV (YUY2, packed 4:2:2): (H, W, 2) bytes Y0 U0 Y1 V0 ...; the gray value is the Y
 *     byte (channel 0 of each pixel), as cv2.cvtColor(COLOR_YUV2GRAY_YUYV) gives it.
 *   - BGR: (H, W, 3) bytes; the gray value is Y = (cb*B + cg*G + cr*R + d) >> s with the
 *     integer weights passed by the caller (bgr_weights = (cb, cg, cr, d, s)), which must be
 *     the fixed-point formula cv2.cvtColor(COLOR_BGR2GRAY) uses on the caller's OpenCV build
 *     (OpenCV's own code: 1868, 9617, 4899, 8192, 14; its Intel IPP path: 3735, 19235,
 *     9798, 16384, 15). The kernel never rounds differently: Y <= p is evaluated exactly as
 *     S = cb*B + cg*G + cr*R < ((p + 1) << s) - d, and Y == 255 as S >= (255 << s) - d, in
 *     32-bit integers.
 *
 * Domain: any buffer of unsigned bytes whose pixels are contiguous (channel stride 1, pixel
 * stride = channels) and whose rows do not overlap (the row stride may be larger than the
 * row, e.g. a crop of a larger frame). Counts are exact (64-bit) for any frame size. A
 * row-span table restricts each row to pixel columns [x0, x1) (a circular ROI); an empty
 * span (x0 >= x1) counts nothing.
 *
 * Kernels: AVX2 (chosen at run time when the CPU has it), SSE2 (every x86-64 CPU) and a
 * portable C loop (other CPUs). All give identical counts for every layout; `kernel()` names
 * the one in use. The GIL is released while counting.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#if defined(__x86_64__) || defined(_M_X64) || defined(__i386__) || defined(_M_IX86)
#define SK_X86 1
#include <emmintrin.h>
#if defined(__GNUC__) || defined(__clang__)
#define SK_HAVE_AVX2 1
#include <immintrin.h>
#endif
#endif

#if defined(__GNUC__) || defined(__clang__)
#define SK_PREFETCH(addr) __builtin_prefetch((addr), 0, 2)
#elif defined(SK_X86)
#define SK_PREFETCH(addr) _mm_prefetch((const char *)(addr), _MM_HINT_T1)
#else
#define SK_PREFETCH(addr) ((void)(addr))
#endif

typedef struct {
    uint64_t le;  /* pixels with gray value <= p */
    uint64_t sat; /* pixels with gray value == 255 */
} sk_counts;

/* What is counted: the threshold and, for BGR, the integer gray formula as thresholds. */
typedef struct {
    int channels; /* 1 gray, 2 YUYV, 3 BGR */
    uint8_t p;
    int32_t cb, cg, cr; /* BGR weights */
    int32_t t_le;       /* BGR: gray <= p  <=>  S < t_le */
    int32_t t_sat;      /* BGR: gray == 255 <=> S >= t_sat */
} sk_params;

/* Count n pixels starting at s (pixel stride = channels). */
typedef void (*sk_row_fn)(const uint8_t *, Py_ssize_t, const sk_params *, int, sk_counts *);
/* Sum n bytes starting at s. */
typedef uint64_t (*sk_sum_fn)(const uint8_t *, Py_ssize_t);

/* ---------------------------------------------------------------------------------------- */
/* Portable kernels                                                                         */
/* ---------------------------------------------------------------------------------------- */

/* Byte-lane accumulators in plain C, so the compiler can vectorize them on any CPU: each
 * of the 32 lanes sees at most 255 pixels per block before it is widened. `step` is the
 * distance between gray bytes (1 gray, 2 YUYV). */
#define SK_LANES 32
static inline void strided_counts_c(const uint8_t *s, Py_ssize_t n, const int step, uint8_t p,
                                    int want_sat, sk_counts *c)
{
    uint64_t le = 0, sat = 0;
    Py_ssize_t i = 0;
    while (n - i >= SK_LANES) {
        Py_ssize_t steps = (n - i) / SK_LANES;
        if (steps > 255)
            steps = 255;
        uint8_t a_le[SK_LANES] = {0}, a_sat[SK_LANES] = {0};
        for (Py_ssize_t b = 0; b < steps; b++, i += SK_LANES) {
            for (int k = 0; k < SK_LANES; k++) {
                a_le[k] += s[step * (i + k)] <= p;
                a_sat[k] += s[step * (i + k)] == 255;
            }
        }
        for (int k = 0; k < SK_LANES; k++) {
            le += a_le[k];
            sat += a_sat[k];
        }
    }
    for (; i < n; i++) {
        le += s[step * i] <= p;
        sat += s[step * i] == 255;
    }
    c->le += le;
    if (want_sat)
        c->sat += sat;
}

static void gray_counts_c(const uint8_t *s, Py_ssize_t n, const sk_params *k, int want_sat,
                          sk_counts *c)
{
    strided_counts_c(s, n, 1, k->p, want_sat, c);
}

static void yuyv_counts_c(const uint8_t *s, Py_ssize_t n, const sk_params *k, int want_sat,
                          sk_counts *c)
{
    strided_counts_c(s, n, 2, k->p, want_sat, c);
}

/* BGR: S = cb*B + cg*G + cr*R in 32 bits (at most 32767 * 3 * 255 < 2^31), compared with
 * the two thresholds; 32-bit block counters (65536 pixels per block) widened to 64 bits.
 * Written with a counted inner loop over unsigned values so that compilers vectorize it
 * (stride-3 loads become shuffles): about 10x faster than the scalar loop. */
#define SK_BGR_BLOCK 65536
static void bgr_counts_c(const uint8_t *s, Py_ssize_t n, const sk_params *k, int want_sat,
                         sk_counts *c)
{
    const uint32_t cb = (uint32_t)k->cb, cg = (uint32_t)k->cg, cr = (uint32_t)k->cr;
    const uint32_t t_le = (uint32_t)k->t_le, t_sat = (uint32_t)k->t_sat;
    for (Py_ssize_t i = 0; i < n; i += SK_BGR_BLOCK) {
        const int len = (int)(n - i < SK_BGR_BLOCK ? n - i : SK_BGR_BLOCK);
        const uint8_t *q = s + 3 * i;
        uint32_t le = 0, sat = 0;
        for (int j = 0; j < len; j++) {
            uint32_t v = cb * q[3 * j] + cg * q[3 * j + 1] + cr * q[3 * j + 2];
            le += v < t_le;
            sat += v >= t_sat;
        }
        c->le += le;
        if (want_sat)
            c->sat += sat;
    }
}

static uint64_t row_sum_c(const uint8_t *s, Py_ssize_t n)
{
    uint64_t t = 0;
    for (Py_ssize_t i = 0; i < n; i++)
        t += s[i];
    return t;
}

/* ---------------------------------------------------------------------------------------- */
/* SSE2                                                                                     */
/* ---------------------------------------------------------------------------------------- */

#ifdef SK_X86
static inline uint64_t hsum_epi64_128(__m128i v)
{
    uint64_t lanes[2];
    _mm_storeu_si128((__m128i *)lanes, v);
    return lanes[0] + lanes[1];
}

/* n bytes; x <= p on unsigned bytes: min(x, p) == x. Each match subtracts -1 (adds 1) to a
 * byte lane; at most 255 vectors go into a lane before _mm_sad_epu8 widens it to 64 bits.
 * yuyv: only the even bytes (the Y of each pixel) count; n is then even and so is every
 * vector's offset, so the even lanes are always the Y bytes. */
static inline void byte_counts_sse2_impl(const uint8_t *s, Py_ssize_t n, uint8_t p,
                                         const int want_sat, const int yuyv, sk_counts *c)
{
    const __m128i vp = _mm_set1_epi8((char)p);
    const __m128i vmax = _mm_set1_epi8((char)0xFF);
    const __m128i even = _mm_set1_epi16(0x00FF);
    const __m128i zero = _mm_setzero_si128();
    __m128i tot_le = zero, tot_sat = zero;
    Py_ssize_t i = 0;
    while (n - i >= 16) {
        Py_ssize_t blocks = (n - i) / 16;
        if (blocks > 255)
            blocks = 255;
        __m128i a_le = zero, a_sat = zero;
        for (Py_ssize_t b = 0; b < blocks; b++, i += 16) {
            __m128i x = _mm_loadu_si128((const __m128i *)(s + i));
            __m128i m = _mm_cmpeq_epi8(_mm_min_epu8(x, vp), x);
            if (yuyv)
                m = _mm_and_si128(m, even);
            a_le = _mm_sub_epi8(a_le, m);
            if (want_sat) {
                __m128i q = _mm_cmpeq_epi8(x, vmax);
                if (yuyv)
                    q = _mm_and_si128(q, even);
                a_sat = _mm_sub_epi8(a_sat, q);
            }
        }
        tot_le = _mm_add_epi64(tot_le, _mm_sad_epu8(a_le, zero));
        if (want_sat)
            tot_sat = _mm_add_epi64(tot_sat, _mm_sad_epu8(a_sat, zero));
    }
    c->le += hsum_epi64_128(tot_le);
    if (want_sat)
        c->sat += hsum_epi64_128(tot_sat);
    if (yuyv)
        strided_counts_c(s + i, (n - i) / 2, 2, p, want_sat, c);
    else
        strided_counts_c(s + i, n - i, 1, p, want_sat, c);
}

static void gray_counts_sse2(const uint8_t *s, Py_ssize_t n, const sk_params *k, int want_sat,
                             sk_counts *c)
{
    if (want_sat)
        byte_counts_sse2_impl(s, n, k->p, 1, 0, c);
    else
        byte_counts_sse2_impl(s, n, k->p, 0, 0, c);
}

static void yuyv_counts_sse2(const uint8_t *s, Py_ssize_t n, const sk_params *k, int want_sat,
                             sk_counts *c)
{
    if (want_sat)
        byte_counts_sse2_impl(s, 2 * n, k->p, 1, 1, c);
    else
        byte_counts_sse2_impl(s, 2 * n, k->p, 0, 1, c);
}

/* BGR with SSE2 alone (no byte shuffle): 16 pixels (48 bytes) are split into B, G and R
 * planes by five rounds of byte unpacking (the deinterleave OpenCV's SSE2 fallback uses),
 * widened to 16-bit words, paired (B, G) and (R, 0) for _mm_madd_epi16, compared as int32
 * and the masks packed to bytes. Pixel order within the planes is permuted, identically
 * for B, G and R, which a count does not see. */
static inline void bgr16_planes_sse2(const uint8_t *q, __m128i *b, __m128i *g, __m128i *r)
{
    __m128i t00 = _mm_loadu_si128((const __m128i *)q);
    __m128i t01 = _mm_loadu_si128((const __m128i *)(q + 16));
    __m128i t02 = _mm_loadu_si128((const __m128i *)(q + 32));
    __m128i t10 = _mm_unpacklo_epi8(t00, _mm_unpackhi_epi64(t01, t01));
    __m128i t11 = _mm_unpacklo_epi8(_mm_unpackhi_epi64(t00, t00), t02);
    __m128i t12 = _mm_unpacklo_epi8(t01, _mm_unpackhi_epi64(t02, t02));
    __m128i t20 = _mm_unpacklo_epi8(t10, _mm_unpackhi_epi64(t11, t11));
    __m128i t21 = _mm_unpacklo_epi8(_mm_unpackhi_epi64(t10, t10), t12);
    __m128i t22 = _mm_unpacklo_epi8(t11, _mm_unpackhi_epi64(t12, t12));
    __m128i t30 = _mm_unpacklo_epi8(t20, _mm_unpackhi_epi64(t21, t21));
    __m128i t31 = _mm_unpacklo_epi8(_mm_unpackhi_epi64(t20, t20), t22);
    __m128i t32 = _mm_unpacklo_epi8(t21, _mm_unpackhi_epi64(t22, t22));
    *b = _mm_unpacklo_epi8(t30, _mm_unpackhi_epi64(t31, t31));
    *g = _mm_unpacklo_epi8(_mm_unpackhi_epi64(t30, t30), t32);
    *r = _mm_unpacklo_epi8(t31, _mm_unpackhi_epi64(t32, t32));
}

/* S of 4 pixels from 16-bit words b16, g16, r16 (lanes 0-3 when lo, 4-7 when hi). */
#define SK_BGR4_SSE2(UNPACK, b16, g16, r16)                                                   \
    _mm_add_epi32(_mm_madd_epi16(UNPACK(b16, g16), w_bg),                                  \
                  _mm_madd_epi16(UNPACK(r16, zero), w_r))

static inline void bgr_counts_sse2_impl(const uint8_t *s, Py_ssize_t n, const sk_params *k,
                                        const int want_sat, sk_counts *c)
{
    const __m128i w_bg = _mm_set1_epi32((int32_t)((uint32_t)k->cb | ((uint32_t)k->cg << 16)));
    const __m128i w_r = _mm_set1_epi32(k->cr);
    const __m128i t_le = _mm_set1_epi32(k->t_le);
    const __m128i t_sat = _mm_set1_epi32(k->t_sat - 1);
    const __m128i zero = _mm_setzero_si128();
    __m128i tot_le = zero, tot_sat = zero;
    Py_ssize_t i = 0;
    while (n - i >= 16) {
        Py_ssize_t steps = (n - i) / 16;
        if (steps > 255)
            steps = 255;
        __m128i a_le = zero, a_sat = zero;
        for (Py_ssize_t st = 0; st < steps; st++, i += 16) {
            __m128i b, g, r;
            bgr16_planes_sse2(s + 3 * i, &b, &g, &r);
            __m128i bl = _mm_unpacklo_epi8(b, zero), bh = _mm_unpackhi_epi8(b, zero);
            __m128i gl = _mm_unpacklo_epi8(g, zero), gh = _mm_unpackhi_epi8(g, zero);
            __m128i rl = _mm_unpacklo_epi8(r, zero), rh = _mm_unpackhi_epi8(r, zero);
            __m128i v0 = SK_BGR4_SSE2(_mm_unpacklo_epi16, bl, gl, rl);
            __m128i v1 = SK_BGR4_SSE2(_mm_unpackhi_epi16, bl, gl, rl);
            __m128i v2 = SK_BGR4_SSE2(_mm_unpacklo_epi16, bh, gh, rh);
            __m128i v3 = SK_BGR4_SSE2(_mm_unpackhi_epi16, bh, gh, rh);
            __m128i m = _mm_packs_epi16(
                _mm_packs_epi32(_mm_cmpgt_epi32(t_le, v0), _mm_cmpgt_epi32(t_le, v1)),
                _mm_packs_epi32(_mm_cmpgt_epi32(t_le, v2), _mm_cmpgt_epi32(t_le, v3)));
            a_le = _mm_sub_epi8(a_le, m);
            if (want_sat) {
                __m128i q8 = _mm_packs_epi16(
                    _mm_packs_epi32(_mm_cmpgt_epi32(v0, t_sat), _mm_cmpgt_epi32(v1, t_sat)),
                    _mm_packs_epi32(_mm_cmpgt_epi32(v2, t_sat), _mm_cmpgt_epi32(v3, t_sat)));
                a_sat = _mm_sub_epi8(a_sat, q8);
            }
        }
        tot_le = _mm_add_epi64(tot_le, _mm_sad_epu8(a_le, zero));
        if (want_sat)
            tot_sat = _mm_add_epi64(tot_sat, _mm_sad_epu8(a_sat, zero));
    }
    c->le += hsum_epi64_128(tot_le);
    if (want_sat)
        c->sat += hsum_epi64_128(tot_sat);
    bgr_counts_c(s + 3 * i, n - i, k, want_sat, c);
}

static void bgr_counts_sse2(const uint8_t *s, Py_ssize_t n, const sk_params *k, int want_sat,
                            sk_counts *c)
{
    if (want_sat)
        bgr_counts_sse2_impl(s, n, k, 1, c);
    else
        bgr_counts_sse2_impl(s, n, k, 0, c);
}

static uint64_t row_sum_sse2(const uint8_t *s, Py_ssize_t n)
{
    const __m128i zero = _mm_setzero_si128();
    __m128i tot = zero;
    Py_ssize_t i = 0;
    for (; n - i >= 16; i += 16)
        tot = _mm_add_epi64(tot, _mm_sad_epu8(_mm_loadu_si128((const __m128i *)(s + i)), zero));
    return hsum_epi64_128(tot) + row_sum_c(s + i, n - i);
}
#endif

/* ---------------------------------------------------------------------------------------- */
/* AVX2 (compiled for the target, chosen at run time)                                       */
/* ---------------------------------------------------------------------------------------- */

#ifdef SK_HAVE_AVX2
#define SK_AVX2 __attribute__((target("avx2")))

/* Tail masks: 32 bytes loaded at sk_tail8 + r have their last r bytes set; 8 int32 loaded
 * at sk_tail32 + r their last r lanes. A row's last partial vector is read overlapping the
 * previous one (never outside the span's row) and masked, instead of a scalar loop: a
 * circle ROI is hundreds of short rows, and scalar tails cost more than the vectors. */
static const uint8_t sk_tail8[64] = {
    0,    0,    0,    0,    0,    0,    0,    0,    0,    0,    0,    0,    0,    0,    0,    0,
    0,    0,    0,    0,    0,    0,    0,    0,    0,    0,    0,    0,    0,    0,    0,    0,
    0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF,
    0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF};
static const int32_t sk_tail32[16] = {0, 0, 0, 0, 0, 0, 0, 0, -1, -1, -1, -1, -1, -1, -1, -1};

SK_AVX2 static inline uint64_t hsum_epi64_256(__m256i v)
{
    uint64_t lanes[4];
    _mm256_storeu_si256((__m256i *)lanes, v);
    return lanes[0] + lanes[1] + lanes[2] + lanes[3];
}

/* n bytes (gray, or YUYV with only the even bytes counted). Two vectors (64 bytes, one
 * cache line) per step, each with its own 8-bit accumulator: 255 steps fill an accumulator
 * lane at most to 255. */
SK_AVX2 static inline void byte_counts_avx2_impl(const uint8_t *s, Py_ssize_t n, uint8_t p,
                                                 const int want_sat, const int yuyv,
                                                 sk_counts *c)
{
    const __m256i vp = _mm256_set1_epi8((char)p);
    const __m256i vmax = _mm256_set1_epi8((char)0xFF);
    const __m256i even = _mm256_set1_epi16(0x00FF);
    const __m256i zero = _mm256_setzero_si256();
    __m256i tot_le = zero, tot_sat = zero;
    Py_ssize_t i = 0;
    while (n - i >= 64) {
        Py_ssize_t steps = (n - i) / 64;
        if (steps > 255)
            steps = 255;
        __m256i a0 = zero, a1 = zero, s0 = zero, s1 = zero;
        for (Py_ssize_t b = 0; b < steps; b++, i += 64) {
            __m256i x0 = _mm256_loadu_si256((const __m256i *)(s + i));
            __m256i x1 = _mm256_loadu_si256((const __m256i *)(s + i + 32));
            __m256i m0 = _mm256_cmpeq_epi8(_mm256_min_epu8(x0, vp), x0);
            __m256i m1 = _mm256_cmpeq_epi8(_mm256_min_epu8(x1, vp), x1);
            if (yuyv) {
                m0 = _mm256_and_si256(m0, even);
                m1 = _mm256_and_si256(m1, even);
            }
            a0 = _mm256_sub_epi8(a0, m0);
            a1 = _mm256_sub_epi8(a1, m1);
            if (want_sat) {
                __m256i q0 = _mm256_cmpeq_epi8(x0, vmax);
                __m256i q1 = _mm256_cmpeq_epi8(x1, vmax);
                if (yuyv) {
                    q0 = _mm256_and_si256(q0, even);
                    q1 = _mm256_and_si256(q1, even);
                }
                s0 = _mm256_sub_epi8(s0, q0);
                s1 = _mm256_sub_epi8(s1, q1);
            }
        }
        tot_le = _mm256_add_epi64(tot_le, _mm256_sad_epu8(a0, zero));
        tot_le = _mm256_add_epi64(tot_le, _mm256_sad_epu8(a1, zero));
        if (want_sat) {
            tot_sat = _mm256_add_epi64(tot_sat, _mm256_sad_epu8(s0, zero));
            tot_sat = _mm256_add_epi64(tot_sat, _mm256_sad_epu8(s1, zero));
        }
    }
    /* The rest (< 64 bytes): whole 32-byte vectors, then the last r bytes as a masked
     * vector overlapping the previous one (needs n >= 32); shorter spans go to SSE2. */
    if (n >= 32 && n - i > 0) {
        __m256i a_le = zero, a_sat = zero;
        while (n - i > 0) {
            const Py_ssize_t r = n - i >= 32 ? 32 : n - i;
            __m256i x = _mm256_loadu_si256((const __m256i *)(s + i + r - 32));
            __m256i keep = _mm256_loadu_si256((const __m256i *)(sk_tail8 + r));
            if (yuyv)
                keep = _mm256_and_si256(keep, even);
            a_le = _mm256_sub_epi8(a_le, _mm256_and_si256(keep, _mm256_cmpeq_epi8(_mm256_min_epu8(x, vp), x)));
            if (want_sat)
                a_sat = _mm256_sub_epi8(a_sat, _mm256_and_si256(keep, _mm256_cmpeq_epi8(x, vmax)));
            i += r;
        }
        tot_le = _mm256_add_epi64(tot_le, _mm256_sad_epu8(a_le, zero));
        if (want_sat)
            tot_sat = _mm256_add_epi64(tot_sat, _mm256_sad_epu8(a_sat, zero));
    }
    c->le += hsum_epi64_256(tot_le);
    if (want_sat)
        c->sat += hsum_epi64_256(tot_sat);
    if (n - i > 0)
        byte_counts_sse2_impl(s + i, n - i, p, want_sat, yuyv, c);
}

SK_AVX2 static void gray_counts_avx2(const uint8_t *s, Py_ssize_t n, const sk_params *k,
                                     int want_sat, sk_counts *c)
{
    if (want_sat)
        byte_counts_avx2_impl(s, n, k->p, 1, 0, c);
    else
        byte_counts_avx2_impl(s, n, k->p, 0, 0, c);
}

SK_AVX2 static void yuyv_counts_avx2(const uint8_t *s, Py_ssize_t n, const sk_params *k,
                                     int want_sat, sk_counts *c)
{
    if (want_sat)
        byte_counts_avx2_impl(s, 2 * n, k->p, 1, 1, c);
    else
        byte_counts_avx2_impl(s, 2 * n, k->p, 0, 1, c);
}

/* S = cb*B + cg*G + cr*R of 8 BGR pixels (24 bytes at q) as 8 int32 (pixel order within
 * the vector does not matter: only counts are taken). Lane 0 holds bytes q[0..15] (pixels
 * 0-3 in bytes 0-11), lane 1 bytes q[8..23] (pixels 4-7 in bytes 4-15): no byte outside the
 * 24 is read. One shuffle makes the words (B, G) of each pixel, one the words (R, 0);
 * _mm256_madd_epi16 with (cb, cg) and (cr, 0) sums each pair to 32 bits, exactly. */
SK_AVX2 static inline __m256i bgr8_sums(const uint8_t *q, __m256i sh_bg, __m256i sh_r,
                                        __m256i w_bg, __m256i w_r)
{
    __m256i x = _mm256_inserti128_si256(
        _mm256_castsi128_si256(_mm_loadu_si128((const __m128i *)q)),
        _mm_loadu_si128((const __m128i *)(q + 8)), 1);
    __m256i bg = _mm256_madd_epi16(_mm256_shuffle_epi8(x, sh_bg), w_bg);
    return _mm256_add_epi32(bg, _mm256_madd_epi16(_mm256_shuffle_epi8(x, sh_r), w_r));
}

/* The same from one plain 32-byte load at q - 4: lane 0 then holds pixels 0-3 in bytes 4-15,
 * lane 1 pixels 4-7 in bytes 0-11 (no lane insert). Reads 4 bytes before q and 4 after the
 * 24: the caller keeps those inside the row. */
SK_AVX2 static inline __m256i bgr8_sums_shifted(const uint8_t *q, __m256i sh_bg, __m256i sh_r,
                                                __m256i w_bg, __m256i w_r)
{
    __m256i x = _mm256_loadu_si256((const __m256i *)(q - 4));
    __m256i bg = _mm256_madd_epi16(_mm256_shuffle_epi8(x, sh_bg), w_bg);
    return _mm256_add_epi32(bg, _mm256_madd_epi16(_mm256_shuffle_epi8(x, sh_r), w_r));
}

/* 32 pixels (96 bytes) per step: four 8-pixel sums compared with the thresholds as int32,
 * each all-ones mask subtracted (1 added) into 32-bit lane counters (no packing: the byte
 * shuffles are this loop's bottleneck, the adds are not); a lane gains at most 4 per step,
 * and the counters are widened to 64 bits every 2^24 steps. */
SK_AVX2 static inline uint64_t hsum_epi32_256(__m256i v)
{
    __m128i s = _mm_add_epi32(_mm256_castsi256_si128(v), _mm256_extracti128_si256(v, 1));
    s = _mm_add_epi32(s, _mm_shuffle_epi32(s, 0x4E));
    s = _mm_add_epi32(s, _mm_shuffle_epi32(s, 0xB1));
    return (uint32_t)_mm_cvtsi128_si32(s);
}

SK_AVX2 static inline void bgr_counts_avx2_impl(const uint8_t *s, Py_ssize_t n,
                                                const sk_params *k, const int want_sat,
                                                sk_counts *c)
{
    const char Z = (char)0x80; /* pshufb: zero this byte */
    const __m256i sh_bg = _mm256_setr_epi8(0, Z, 1, Z, 3, Z, 4, Z, 6, Z, 7, Z, 9, Z, 10, Z,   /**/
                                           4, Z, 5, Z, 7, Z, 8, Z, 10, Z, 11, Z, 13, Z, 14, Z);
    const __m256i sh_r = _mm256_setr_epi8(2, Z, Z, Z, 5, Z, Z, Z, 8, Z, Z, Z, 11, Z, Z, Z, /**/
                                          6, Z, Z, Z, 9, Z, Z, Z, 12, Z, Z, Z, 15, Z, Z, Z);
    /* The same shuffles for bgr8_sums_shifted (lane 0 four bytes later, lane 1 four earlier). */
    const __m256i sh_bg4 = _mm256_setr_epi8(4, Z, 5, Z, 7, Z, 8, Z, 10, Z, 11, Z, 13, Z, 14, Z, /**/
                                            0, Z, 1, Z, 3, Z, 4, Z, 6, Z, 7, Z, 9, Z, 10, Z);
    const __m256i sh_r4 = _mm256_setr_epi8(6, Z, Z, Z, 9, Z, Z, Z, 12, Z, Z, Z, 15, Z, Z, Z, /**/
                                           2, Z, Z, Z, 5, Z, Z, Z, 8, Z, Z, Z, 11, Z, Z, Z);
    const __m256i w_bg = _mm256_set1_epi32((int32_t)((uint32_t)k->cb | ((uint32_t)k->cg << 16)));
    const __m256i w_r = _mm256_set1_epi32(k->cr);
    const __m256i t_le = _mm256_set1_epi32(k->t_le);
    const __m256i t_sat = _mm256_set1_epi32(k->t_sat - 1);
    const __m256i zero = _mm256_setzero_si256();
    Py_ssize_t i = 0;
    /* A lane gains at most 4 per 32 pixels: blocks of at most 2^29 pixels keep it < 2^26. */
    while (n - i >= 8) {
        const Py_ssize_t end = n - i > ((Py_ssize_t)1 << 29) ? i + ((Py_ssize_t)1 << 29) : n;
        __m256i a_le = zero, a_sat = zero;
        if (i == 0 && end - i >= 40) { /* the first 8 pixels: no byte before them to read */
            __m256i v = bgr8_sums(s, sh_bg, sh_r, w_bg, w_r);
            a_le = _mm256_sub_epi32(a_le, _mm256_cmpgt_epi32(t_le, v));
            if (want_sat)
                a_sat = _mm256_sub_epi32(a_sat, _mm256_cmpgt_epi32(v, t_sat));
            i = 8;
        }
        /* 32 pixels with one plain load per 8 (bytes q - 4 .. q + 99: i >= 8 before, and at
         * least 2 more pixels after the 32) */
        for (; i >= 8 && end - i >= 34; i += 32) {
            const uint8_t *q = s + 3 * i;
            __m256i v0 = bgr8_sums_shifted(q, sh_bg4, sh_r4, w_bg, w_r);
            __m256i v1 = bgr8_sums_shifted(q + 24, sh_bg4, sh_r4, w_bg, w_r);
            __m256i v2 = bgr8_sums_shifted(q + 48, sh_bg4, sh_r4, w_bg, w_r);
            __m256i v3 = bgr8_sums_shifted(q + 72, sh_bg4, sh_r4, w_bg, w_r);
            a_le = _mm256_sub_epi32(a_le, _mm256_add_epi32(
                _mm256_add_epi32(_mm256_cmpgt_epi32(t_le, v0), _mm256_cmpgt_epi32(t_le, v1)),
                _mm256_add_epi32(_mm256_cmpgt_epi32(t_le, v2), _mm256_cmpgt_epi32(t_le, v3))));
            if (want_sat)
                a_sat = _mm256_sub_epi32(a_sat, _mm256_add_epi32(
                    _mm256_add_epi32(_mm256_cmpgt_epi32(v0, t_sat), _mm256_cmpgt_epi32(v1, t_sat)),
                    _mm256_add_epi32(_mm256_cmpgt_epi32(v2, t_sat), _mm256_cmpgt_epi32(v3, t_sat))));
        }
        for (; end - i >= 32; i += 32) {
            const uint8_t *q = s + 3 * i;
            __m256i v0 = bgr8_sums(q, sh_bg, sh_r, w_bg, w_r);
            __m256i v1 = bgr8_sums(q + 24, sh_bg, sh_r, w_bg, w_r);
            __m256i v2 = bgr8_sums(q + 48, sh_bg, sh_r, w_bg, w_r);
            __m256i v3 = bgr8_sums(q + 72, sh_bg, sh_r, w_bg, w_r);
            a_le = _mm256_sub_epi32(a_le, _mm256_add_epi32(
                _mm256_add_epi32(_mm256_cmpgt_epi32(t_le, v0), _mm256_cmpgt_epi32(t_le, v1)),
                _mm256_add_epi32(_mm256_cmpgt_epi32(t_le, v2), _mm256_cmpgt_epi32(t_le, v3))));
            if (want_sat)
                a_sat = _mm256_sub_epi32(a_sat, _mm256_add_epi32(
                    _mm256_add_epi32(_mm256_cmpgt_epi32(v0, t_sat), _mm256_cmpgt_epi32(v1, t_sat)),
                    _mm256_add_epi32(_mm256_cmpgt_epi32(v2, t_sat), _mm256_cmpgt_epi32(v3, t_sat))));
        }
        /* The block's rest (< 32 pixels, only in the last block): groups of 8, the last r
         * pixels as a group overlapping the previous one, its first 8 - r lanes masked off
         * (n >= 8 here, so the group starts inside the row). */
        while (end == n && end - i > 0) {
            const Py_ssize_t r = end - i >= 8 ? 8 : end - i;
            __m256i v = bgr8_sums(s + 3 * (i + r - 8), sh_bg, sh_r, w_bg, w_r);
            __m256i keep = _mm256_loadu_si256((const __m256i *)(sk_tail32 + r));
            a_le = _mm256_sub_epi32(a_le, _mm256_and_si256(keep, _mm256_cmpgt_epi32(t_le, v)));
            if (want_sat)
                a_sat = _mm256_sub_epi32(a_sat, _mm256_and_si256(keep, _mm256_cmpgt_epi32(v, t_sat)));
            i += r;
        }
        c->le += hsum_epi32_256(a_le);
        if (want_sat)
            c->sat += hsum_epi32_256(a_sat);
    }
    if (n - i > 0)
        bgr_counts_c(s + 3 * i, n - i, k, want_sat, c);
}

SK_AVX2 static void bgr_counts_avx2(const uint8_t *s, Py_ssize_t n, const sk_params *k,
                                    int want_sat, sk_counts *c)
{
    if (want_sat)
        bgr_counts_avx2_impl(s, n, k, 1, c);
    else
        bgr_counts_avx2_impl(s, n, k, 0, c);
}

SK_AVX2 static uint64_t row_sum_avx2(const uint8_t *s, Py_ssize_t n)
{
    const __m256i zero = _mm256_setzero_si256();
    __m256i t0 = zero, t1 = zero;
    Py_ssize_t i = 0;
    for (; n - i >= 64; i += 64) {
        t0 = _mm256_add_epi64(
            t0, _mm256_sad_epu8(_mm256_loadu_si256((const __m256i *)(s + i)), zero));
        t1 = _mm256_add_epi64(
            t1, _mm256_sad_epu8(_mm256_loadu_si256((const __m256i *)(s + i + 32)), zero));
    }
    if (n >= 32) { /* the last < 64 bytes: vectors, the last one overlapping and masked */
        while (n - i > 0) {
            const Py_ssize_t r = n - i >= 32 ? 32 : n - i;
            __m256i x = _mm256_loadu_si256((const __m256i *)(s + i + r - 32));
            __m256i keep = _mm256_loadu_si256((const __m256i *)(sk_tail8 + r));
            t0 = _mm256_add_epi64(t0, _mm256_sad_epu8(_mm256_and_si256(x, keep), zero));
            i += r;
        }
    }
    return hsum_epi64_256(_mm256_add_epi64(t0, t1)) + row_sum_sse2(s + i, n - i);
}
#endif

/* ---------------------------------------------------------------------------------------- */
/* Dispatch                                                                                 */
/* ---------------------------------------------------------------------------------------- */

typedef struct {
    const char *name;
    sk_row_fn gray, yuyv, bgr;
    sk_sum_fn sum;
} sk_kernel_set;

static const sk_kernel_set k_c = {"c", gray_counts_c, yuyv_counts_c, bgr_counts_c, row_sum_c};
#ifdef SK_X86
static const sk_kernel_set k_sse2 = {"sse2", gray_counts_sse2, yuyv_counts_sse2, bgr_counts_sse2,
                                     row_sum_sse2};
#endif
#ifdef SK_HAVE_AVX2
static const sk_kernel_set k_avx2 = {"avx2", gray_counts_avx2, yuyv_counts_avx2,
                                     bgr_counts_avx2, row_sum_avx2};
#endif

static const sk_kernel_set *g_k = &k_c;

static int select_kernel(const char *name)
{
    if (strcmp(name, "c") == 0) {
        g_k = &k_c;
        return 0;
    }
#ifdef SK_X86
    if (strcmp(name, "sse2") == 0) {
        g_k = &k_sse2;
        return 0;
    }
#endif
#ifdef SK_HAVE_AVX2
    if (strcmp(name, "avx2") == 0) {
        __builtin_cpu_init();
        if (!__builtin_cpu_supports("avx2"))
            return -1;
        g_k = &k_avx2;
        return 0;
    }
#endif
    return -1;
}

static void select_best_kernel(void)
{
    if (select_kernel("avx2") == 0)
        return;
    if (select_kernel("sse2") == 0)
        return;
    select_kernel("c");
}

/* ---------------------------------------------------------------------------------------- */
/* Buffer handling                                                                          */
/* ---------------------------------------------------------------------------------------- */

/* An image of byte pixels with contiguous pixels (1, 2 or 3 bytes each) and rows. */
typedef struct {
    Py_buffer view;
    const uint8_t *data;
    Py_ssize_t rows, cols, row_stride;
    int channels;
} sk_image;

static int get_image(PyObject *obj, sk_image *img)
{
    if (PyObject_GetBuffer(obj, &img->view, PyBUF_STRIDES | PyBUF_FORMAT) < 0)
        return -1;
    Py_buffer *v = &img->view;
    const char *fmt = v->format ? v->format : "B";
    if (v->itemsize != 1 || (strcmp(fmt, "B") != 0 && strcmp(fmt, "=B") != 0 &&
                             strcmp(fmt, "<B") != 0 && strcmp(fmt, "|B") != 0)) {
        PyErr_Format(PyExc_TypeError, "image must hold unsigned bytes (uint8), got format '%s'",
                     fmt);
        goto fail;
    }
    if (v->ndim != 2 && v->ndim != 3) {
        PyErr_Format(PyExc_ValueError,
                     "image must be 2-D (gray) or 3-D (H, W, 1|2|3), got %d dimensions",
                     v->ndim);
        goto fail;
    }
    img->rows = v->shape[0];
    img->cols = v->shape[1];
    img->row_stride = v->strides[0];
    img->channels = v->ndim == 2 ? 1 : (int)v->shape[2];
    if (v->ndim == 3 && (v->shape[2] < 1 || v->shape[2] > 3)) {
        PyErr_Format(PyExc_ValueError,
                     "image must have 1 (gray), 2 (YUYV) or 3 (BGR) channels, got %zd",
                     v->shape[2]);
        goto fail;
    }
    if (v->ndim == 3 && img->channels > 1 && v->strides[2] != 1) {
        PyErr_Format(PyExc_ValueError,
                     "image channels must be contiguous (channel stride %zd, expected 1)",
                     v->strides[2]);
        goto fail;
    }
    if (img->cols > 1 && v->strides[1] != img->channels) {
        PyErr_Format(PyExc_ValueError,
                     "image rows must be contiguous (column stride %zd, expected %d)",
                     v->strides[1], img->channels);
        goto fail;
    }
    if (img->rows > 1 && img->cols > 0 && img->row_stride < img->cols * img->channels) {
        PyErr_Format(PyExc_ValueError,
                     "image rows must not overlap or run backwards (row stride %zd, row %zd "
                     "bytes)",
                     img->row_stride, img->cols * img->channels);
        goto fail;
    }
    img->data = (const uint8_t *)v->buf;
    return 0;
fail:
    PyBuffer_Release(v);
    return -1;
}

/* Row spans of an ROI: int32 pairs (x0, x1) in pixel columns, one pair per image row. */
typedef struct {
    Py_buffer view;
    const int32_t *xy;
    int present;
} sk_spans;

static int get_spans(PyObject *obj, const sk_image *img, sk_spans *sp)
{
    sp->present = 0;
    if (obj == NULL || obj == Py_None)
        return 0;
    if (PyObject_GetBuffer(obj, &sp->view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return -1;
    Py_buffer *v = &sp->view;
    const char *fmt = v->format ? v->format : "B";
    char code = fmt[0] == '=' || fmt[0] == '<' || fmt[0] == '@' ? fmt[1] : fmt[0];
    if (v->itemsize != 4 || (code != 'i' && code != 'l')) {
        PyErr_Format(PyExc_TypeError, "spans must be int32, got format '%s' (itemsize %zd)",
                     fmt, v->itemsize);
        goto fail;
    }
    if (v->len / 4 != 2 * img->rows) {
        PyErr_Format(PyExc_ValueError, "spans must hold 2 x %zd int32 (x0, x1 per row), got %zd",
                     img->rows, v->len / 4);
        goto fail;
    }
    sp->xy = (const int32_t *)v->buf;
    for (Py_ssize_t r = 0; r < img->rows; r++) {
        int32_t x0 = sp->xy[2 * r], x1 = sp->xy[2 * r + 1];
        if (x0 < 0 || x1 > img->cols || (x1 > x0 && x0 >= img->cols)) {
            PyErr_Format(PyExc_ValueError,
                         "span of row %zd is [%d, %d), outside the image's %zd columns", r,
                         (int)x0, (int)x1, img->cols);
            goto fail;
        }
    }
    sp->present = 1;
    return 0;
fail:
    PyBuffer_Release(v);
    return -1;
}

/* How far ahead row-by-row reading prefetches [bytes], and where to: into L2 (locality 2,
 * prefetcht1). Measured on cold 640x480 and 1920x1080 frames with the simulator's circle ROI
 * (the span bytes read in place, gray/YUYV/BGR): no prefetch -> up to 3.5x the time of
 * 16 KB into L2; 6 KB into L1 (prefetcht0, limited by the L1's few outstanding misses) ->
 * 1.1-1.9x; 12-48 KB into L2 -> within 5 % of each other (best); 96 KB -> slower again. */
static const Py_ssize_t sk_prefetch_bytes = 16384;

/* Pixel columns [x0, x1) of row r (the whole row without spans; empty: x1 == x0). */
static inline void row_span(const sk_image *img, const sk_spans *sp, Py_ssize_t r,
                            Py_ssize_t *x0, Py_ssize_t *x1)
{
    if (sp->present) {
        *x0 = sp->xy[2 * r];
        *x1 = sp->xy[2 * r + 1] > sp->xy[2 * r] ? sp->xy[2 * r + 1] : sp->xy[2 * r];
    } else {
        *x0 = 0;
        *x1 = img->cols;
    }
}

/* Row-by-row reading with software prefetch: each row (span) starts at an address the
 * hardware prefetcher does not predict, and without this every row begins with a full
 * memory latency. Keeps about sk_prefetch_bytes of the coming rows' spans in flight. */
typedef struct {
    Py_ssize_t row, ahead; /* next row to prefetch, bytes prefetched but not yet read */
} sk_prefetcher;

static inline void prefetch_rows(const sk_image *img, const sk_spans *sp, sk_prefetcher *pf)
{
    const Py_ssize_t ps = img->channels;
    Py_ssize_t x0, x1;
    while (pf->row < img->rows && pf->ahead < sk_prefetch_bytes) {
        row_span(img, sp, pf->row, &x0, &x1);
        const uint8_t *a = img->data + pf->row * img->row_stride + x0 * ps;
        const Py_ssize_t nb = (x1 - x0) * ps;
        for (Py_ssize_t x = 0; x < nb; x += 64)
            SK_PREFETCH(a + x);
        if (nb > 0)
            SK_PREFETCH(a + nb - 1); /* the span's last line when it starts mid-line */
        pf->ahead += nb;
        pf->row++;
    }
}

static inline int whole_is_one_run(const sk_image *img, const sk_spans *sp)
{
    return !sp->present && (img->rows == 1 || img->row_stride == img->cols * img->channels);
}

static sk_row_fn row_fn_for(int channels)
{
    return channels == 3 ? g_k->bgr : channels == 2 ? g_k->yuyv : g_k->gray;
}

static void count_image(const sk_image *img, const sk_spans *sp, const sk_params *k,
                        sk_row_fn fn, int want_sat, sk_counts *c)
{
    const Py_ssize_t ps = img->channels;
    if (whole_is_one_run(img, sp)) {
        fn(img->data, img->rows * img->cols, k, want_sat, c);
        return;
    }
    sk_prefetcher pf = {0, 0};
    Py_ssize_t x0, x1;
    for (Py_ssize_t r = 0; r < img->rows; r++) {
        prefetch_rows(img, sp, &pf);
        row_span(img, sp, r, &x0, &x1);
        pf.ahead -= (x1 - x0) * ps;
        if (x1 > x0)
            fn(img->data + r * img->row_stride + x0 * ps, x1 - x0, k, want_sat, c);
    }
}

static uint64_t sum_image(const sk_image *img, const sk_spans *sp, sk_sum_fn fn)
{
    const Py_ssize_t ps = img->channels;
    if (whole_is_one_run(img, sp))
        return fn(img->data, img->rows * img->cols * ps);
    uint64_t total = 0;
    sk_prefetcher pf = {0, 0};
    Py_ssize_t x0, x1;
    for (Py_ssize_t r = 0; r < img->rows; r++) {
        prefetch_rows(img, sp, &pf);
        row_span(img, sp, r, &x0, &x1);
        pf.ahead -= (x1 - x0) * ps;
        if (x1 > x0)
            total += fn(img->data + r * img->row_stride + x0 * ps, (x1 - x0) * ps);
    }
    return total;
}

static int parse_threshold(PyObject *obj, uint8_t *p)
{
    long v = PyLong_AsLong(obj);
    if (v == -1 && PyErr_Occurred())
        return -1;
    if (v < 0 || v > 255) {
        PyErr_Format(PyExc_ValueError, "threshold p must be in 0..255, got %ld", v);
        return -1;
    }
    *p = (uint8_t)v;
    return 0;
}

/* bgr_weights = (cb, cg, cr, d, s): gray = (cb*B + cg*G + cr*R + d) >> s. Accepted when
 * every weight is in 0..32767 (the 16-bit multipliers of the SIMD kernels), cb + cg + cr ==
 * 2**s (so white stays 255 and the gray value never exceeds it) and 0 <= d < 2**s. */
static int parse_weights(PyObject *obj, int channels, uint8_t p, sk_params *k)
{
    memset(k, 0, sizeof(*k));
    k->channels = channels;
    k->p = p;
    if (channels != 3) {
        if (obj != NULL && obj != Py_None) {
            PyErr_SetString(PyExc_ValueError,
                            "bgr_weights apply to 3-channel (BGR) images only");
            return -1;
        }
        return 0;
    }
    if (obj == NULL || obj == Py_None) {
        PyErr_SetString(PyExc_ValueError,
                        "a 3-channel (BGR) image needs bgr_weights=(cb, cg, cr, d, s): the "
                        "fixed-point gray formula of cv2.cvtColor(COLOR_BGR2GRAY)");
        return -1;
    }
    long w[5];
    if (!PyArg_ParseTuple(obj, "lllll;bgr_weights must be 5 integers (cb, cg, cr, d, s)", &w[0],
                          &w[1], &w[2], &w[3], &w[4]))
        return -1;
    if (w[4] < 0 || w[4] > 15 || w[0] < 0 || w[1] < 0 || w[2] < 0 || w[0] > 32767 ||
        w[1] > 32767 || w[2] > 32767 || w[0] + w[1] + w[2] != (1L << w[4]) || w[3] < 0 ||
        w[3] >= (1L << w[4])) {
        PyErr_Format(PyExc_ValueError,
                     "bgr_weights (%ld, %ld, %ld, %ld, %ld) are not a fixed-point gray formula: "
                     "need 0 <= s <= 15, weights in 0..32767 summing to 2**s, 0 <= d < 2**s",
                     w[0], w[1], w[2], w[3], w[4]);
        return -1;
    }
    k->cb = (int32_t)w[0];
    k->cg = (int32_t)w[1];
    k->cr = (int32_t)w[2];
    k->t_le = (int32_t)(((long)p + 1) << w[4]) - (int32_t)w[3];
    k->t_sat = (int32_t)(255L << w[4]) - (int32_t)w[3];
    return 0;
}

/* ---------------------------------------------------------------------------------------- */
/* Python functions                                                                         */
/* ---------------------------------------------------------------------------------------- */

static PyObject *run_counts(PyObject *args, PyObject *kwargs, int want_sat)
{
    static char *kwlist[] = {"image", "p", "spans", "bgr_weights", NULL};
    PyObject *image, *p_obj, *spans_obj = Py_None, *w_obj = Py_None;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "OO|OO", kwlist, &image, &p_obj, &spans_obj,
                                     &w_obj))
        return NULL;
    uint8_t p;
    if (parse_threshold(p_obj, &p) < 0)
        return NULL;
    sk_image img;
    if (get_image(image, &img) < 0)
        return NULL;
    sk_params k;
    if (parse_weights(w_obj, img.channels, p, &k) < 0) {
        PyBuffer_Release(&img.view);
        return NULL;
    }
    sk_spans sp;
    if (get_spans(spans_obj, &img, &sp) < 0) {
        PyBuffer_Release(&img.view);
        return NULL;
    }
    sk_counts c = {0, 0};
    const sk_row_fn fn = row_fn_for(img.channels);
    Py_BEGIN_ALLOW_THREADS
    count_image(&img, &sp, &k, fn, want_sat, &c);
    Py_END_ALLOW_THREADS
    if (sp.present)
        PyBuffer_Release(&sp.view);
    PyBuffer_Release(&img.view);
    if (want_sat)
        return Py_BuildValue("(KK)", (unsigned long long)c.le, (unsigned long long)c.sat);
    return PyLong_FromUnsignedLongLong(c.le);
}

static PyObject *sk_count_le(PyObject *self, PyObject *args, PyObject *kwargs)
{
    (void)self;
    return run_counts(args, kwargs, 0);
}

static PyObject *sk_count_le_and_saturated(PyObject *self, PyObject *args, PyObject *kwargs)
{
    (void)self;
    return run_counts(args, kwargs, 1);
}

static PyObject *sk_read_sum(PyObject *self, PyObject *args, PyObject *kwargs)
{
    (void)self;
    static char *kwlist[] = {"image", "spans", NULL};
    PyObject *image, *spans_obj = Py_None;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "O|O", kwlist, &image, &spans_obj))
        return NULL;
    sk_image img;
    if (get_image(image, &img) < 0)
        return NULL;
    sk_spans sp;
    if (get_spans(spans_obj, &img, &sp) < 0) {
        PyBuffer_Release(&img.view);
        return NULL;
    }
    uint64_t total = 0;
    const sk_sum_fn fn = g_k->sum;
    Py_BEGIN_ALLOW_THREADS
    total = sum_image(&img, &sp, fn);
    Py_END_ALLOW_THREADS
    if (sp.present)
        PyBuffer_Release(&sp.view);
    PyBuffer_Release(&img.view);
    return PyLong_FromUnsignedLongLong(total);
}

static PyObject *sk_kernel(PyObject *self, PyObject *unused)
{
    (void)self;
    (void)unused;
    return PyUnicode_FromString(g_k->name);
}

static PyObject *sk_available_kernels(PyObject *self, PyObject *unused)
{
    (void)self;
    (void)unused;
    PyObject *out = PyList_New(0);
    if (out == NULL)
        return NULL;
    const sk_kernel_set *saved = g_k;
    const char *names[] = {"c", "sse2", "avx2"};
    for (size_t k = 0; k < sizeof(names) / sizeof(names[0]); k++) {
        if (select_kernel(names[k]) == 0) {
            PyObject *s = PyUnicode_FromString(names[k]);
            if (s == NULL || PyList_Append(out, s) < 0) {
                Py_XDECREF(s);
                Py_DECREF(out);
                g_k = saved;
                return NULL;
            }
            Py_DECREF(s);
        }
    }
    g_k = saved;
    return out;
}

static PyObject *sk_use_kernel(PyObject *self, PyObject *arg)
{
    (void)self;
    const char *name = PyUnicode_AsUTF8(arg);
    if (name == NULL)
        return NULL;
    if (strcmp(name, "best") == 0) {
        select_best_kernel();
    } else if (select_kernel(name) < 0) {
        PyErr_Format(PyExc_ValueError,
                     "kernel '%s' is not available on this CPU or build (see "
                     "available_kernels())",
                     name);
        return NULL;
    }
    return PyUnicode_FromString(g_k->name);
}

static PyMethodDef sk_methods[] = {
    {"count_le", (PyCFunction)(void (*)(void))sk_count_le, METH_VARARGS | METH_KEYWORDS,
     "count_le(image, p, spans=None, bgr_weights=None) -> int\n\n"
     "Number of pixels with gray value <= p (Eqs. (1)-(2)). image: uint8 gray (H, W) or\n"
     "(H, W, 1), YUYV (H, W, 2) (gray = Y byte) or BGR (H, W, 3) (gray = (cb*B + cg*G +\n"
     "cr*R + d) >> s with bgr_weights = (cb, cg, cr, d, s)); contiguous pixels and rows.\n"
     "spans (int32, shape (rows, 2)) limits row r to pixel columns [x0, x1)."},
    {"count_le_and_saturated", (PyCFunction)(void (*)(void))sk_count_le_and_saturated,
     METH_VARARGS | METH_KEYWORDS,
     "count_le_and_saturated(image, p, spans=None, bgr_weights=None) -> (int, int)\n\n"
     "(pixels with gray <= p, pixels with gray == 255) in one pass; arguments as count_le."},
    {"read_sum", (PyCFunction)(void (*)(void))sk_read_sum, METH_VARARGS | METH_KEYWORDS,
     "read_sum(image, spans=None) -> int\n\nSum of the bytes of the image's pixels (within "
     "the row spans when given): the fastest read of those bytes once, in place (the memory "
     "floor of the benchmarks)."},
    {"kernel", sk_kernel, METH_NOARGS, "kernel() -> str\n\nName of the kernel in use."},
    {"available_kernels", sk_available_kernels, METH_NOARGS,
     "available_kernels() -> list[str]\n\nKernels this CPU and build can run."},
    {"use_kernel", sk_use_kernel, METH_O,
     "use_kernel(name) -> str\n\nSelect 'c', 'sse2', 'avx2' or 'best' (for tests and "
     "benchmarks); returns the kernel now in use."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef sk_module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "_skcount",
    .m_doc = "Single-pass occluded-pixel counting (Eqs. (1)-(2)); see _skcount.c.",
    .m_size = -1,
    .m_methods = sk_methods,
};

PyMODINIT_FUNC PyInit__skcount(void)
{
    select_best_kernel();
    return PyModule_Create(&sk_module);
}

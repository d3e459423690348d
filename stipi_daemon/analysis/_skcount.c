/*
 * Single-pass occluded-pixel counting, Eqs. (1)-(2) of the STIP-I paper.
 *
 * S_k = number of ROI pixels whose 8-bit gray value is <= p (Eq. (1) marks them 1, Eq. (2)
 * sums the marks). OpenCV needs two passes for that (cv2.threshold writes a 0/1 image,
 * cv2.countNonZero reads it back), so it moves three frames' worth of memory per frame.
 * This module reads each pixel once and writes nothing: compare, accumulate in 8-bit lanes,
 * widen every 255 vectors. The same pass can also count saturated pixels (== 255) for the
 * frame-quality check, at no extra memory traffic.
 *
 * Domain: any 2-D buffer of unsigned bytes whose rows are contiguous (item stride 1; the row
 * stride may be larger than the width, e.g. a crop of a larger frame). Counts are exact
 * (64-bit) for any frame size. A row-span table restricts each row to [x0, x1) for a
 * circular ROI; an empty span (x0 >= x1) counts nothing.
 *
 * Kernels: AVX2 (chosen at run time when the CPU has it), SSE2 (every x86-64 CPU) and a
 * portable C loop (other CPUs). All give identical counts; `kernel()` names the one in use.
 * The GIL is released while counting.
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
#define SK_PREFETCH(addr) __builtin_prefetch((addr), 0, 3)
#elif defined(SK_X86)
#define SK_PREFETCH(addr) _mm_prefetch((const char *)(addr), _MM_HINT_T0)
#else
#define SK_PREFETCH(addr) ((void)(addr))
#endif

typedef struct {
    uint64_t le;  /* pixels with value <= p */
    uint64_t sat; /* pixels with value == 255 */
} sk_counts;

typedef void (*sk_row_fn)(const uint8_t *, Py_ssize_t, uint8_t, int, sk_counts *);
typedef uint64_t (*sk_sum_fn)(const uint8_t *, Py_ssize_t);

/* ---------------------------------------------------------------------------------------- */
/* Portable kernels                                                                         */
/* ---------------------------------------------------------------------------------------- */

/* Byte-lane accumulators in plain C, so the compiler can vectorize them on any CPU: each
 * of the 32 lanes sees at most 255 bytes per block before it is widened. */
#define SK_LANES 32
static void row_counts_c(const uint8_t *s, Py_ssize_t n, uint8_t p, int want_sat, sk_counts *c)
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
                a_le[k] += s[i + k] <= p;
                a_sat[k] += s[i + k] == 255;
            }
        }
        for (int k = 0; k < SK_LANES; k++) {
            le += a_le[k];
            sat += a_sat[k];
        }
    }
    for (; i < n; i++) {
        le += s[i] <= p;
        sat += s[i] == 255;
    }
    c->le += le;
    if (want_sat)
        c->sat += sat;
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

/* x <= p on unsigned bytes: min(x, p) == x. Each match subtracts -1 (adds 1) to a byte
 * lane; at most 255 vectors go into a lane before _mm_sad_epu8 widens it to 64 bits. */
static inline void row_counts_sse2_impl(const uint8_t *s, Py_ssize_t n, uint8_t p,
                                        const int want_sat, sk_counts *c)
{
    const __m128i vp = _mm_set1_epi8((char)p);
    const __m128i vmax = _mm_set1_epi8((char)0xFF);
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
            a_le = _mm_sub_epi8(a_le, _mm_cmpeq_epi8(_mm_min_epu8(x, vp), x));
            if (want_sat)
                a_sat = _mm_sub_epi8(a_sat, _mm_cmpeq_epi8(x, vmax));
        }
        tot_le = _mm_add_epi64(tot_le, _mm_sad_epu8(a_le, zero));
        if (want_sat)
            tot_sat = _mm_add_epi64(tot_sat, _mm_sad_epu8(a_sat, zero));
    }
    c->le += hsum_epi64_128(tot_le);
    if (want_sat)
        c->sat += hsum_epi64_128(tot_sat);
    row_counts_c(s + i, n - i, p, want_sat, c);
}

static void row_counts_sse2(const uint8_t *s, Py_ssize_t n, uint8_t p, int want_sat,
                            sk_counts *c)
{
    if (want_sat)
        row_counts_sse2_impl(s, n, p, 1, c);
    else
        row_counts_sse2_impl(s, n, p, 0, c);
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
__attribute__((target("avx2"))) static inline uint64_t hsum_epi64_256(__m256i v)
{
    uint64_t lanes[4];
    _mm256_storeu_si256((__m256i *)lanes, v);
    return lanes[0] + lanes[1] + lanes[2] + lanes[3];
}

/* Two vectors (64 bytes, one cache line) per step, each with its own 8-bit accumulator:
 * 255 steps fill an accumulator lane at most to 255. */
__attribute__((target("avx2"))) static inline void
row_counts_avx2_impl(const uint8_t *s, Py_ssize_t n, uint8_t p, const int want_sat,
                     sk_counts *c)
{
    const __m256i vp = _mm256_set1_epi8((char)p);
    const __m256i vmax = _mm256_set1_epi8((char)0xFF);
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
            a0 = _mm256_sub_epi8(a0, _mm256_cmpeq_epi8(_mm256_min_epu8(x0, vp), x0));
            a1 = _mm256_sub_epi8(a1, _mm256_cmpeq_epi8(_mm256_min_epu8(x1, vp), x1));
            if (want_sat) {
                s0 = _mm256_sub_epi8(s0, _mm256_cmpeq_epi8(x0, vmax));
                s1 = _mm256_sub_epi8(s1, _mm256_cmpeq_epi8(x1, vmax));
            }
        }
        tot_le = _mm256_add_epi64(tot_le, _mm256_sad_epu8(a0, zero));
        tot_le = _mm256_add_epi64(tot_le, _mm256_sad_epu8(a1, zero));
        if (want_sat) {
            tot_sat = _mm256_add_epi64(tot_sat, _mm256_sad_epu8(s0, zero));
            tot_sat = _mm256_add_epi64(tot_sat, _mm256_sad_epu8(s1, zero));
        }
    }
    c->le += hsum_epi64_256(tot_le);
    if (want_sat)
        c->sat += hsum_epi64_256(tot_sat);
    row_counts_sse2_impl(s + i, n - i, p, want_sat, c);
}

__attribute__((target("avx2"))) static void row_counts_avx2(const uint8_t *s, Py_ssize_t n,
                                                            uint8_t p, int want_sat,
                                                            sk_counts *c)
{
    if (want_sat)
        row_counts_avx2_impl(s, n, p, 1, c);
    else
        row_counts_avx2_impl(s, n, p, 0, c);
}

__attribute__((target("avx2"))) static uint64_t row_sum_avx2(const uint8_t *s, Py_ssize_t n)
{
    const __m256i zero = _mm256_setzero_si256();
    __m256i t0 = zero, t1 = zero;
    Py_ssize_t i = 0;
    for (; n - i >= 64; i += 64) {
        t0 = _mm256_add_epi64(t0, _mm256_sad_epu8(_mm256_loadu_si256((const __m256i *)(s + i)), zero));
        t1 = _mm256_add_epi64(
            t1, _mm256_sad_epu8(_mm256_loadu_si256((const __m256i *)(s + i + 32)), zero));
    }
    return hsum_epi64_256(_mm256_add_epi64(t0, t1)) + row_sum_sse2(s + i, n - i);
}
#endif

/* ---------------------------------------------------------------------------------------- */
/* Dispatch                                                                                 */
/* ---------------------------------------------------------------------------------------- */

static sk_row_fn g_row_counts = row_counts_c;
static sk_sum_fn g_row_sum = row_sum_c;
static const char *g_kernel = "c";

static int select_kernel(const char *name)
{
    if (strcmp(name, "c") == 0) {
        g_row_counts = row_counts_c;
        g_row_sum = row_sum_c;
        g_kernel = "c";
        return 0;
    }
#ifdef SK_X86
    if (strcmp(name, "sse2") == 0) {
        g_row_counts = row_counts_sse2;
        g_row_sum = row_sum_sse2;
        g_kernel = "sse2";
        return 0;
    }
#endif
#ifdef SK_HAVE_AVX2
    if (strcmp(name, "avx2") == 0) {
        __builtin_cpu_init();
        if (!__builtin_cpu_supports("avx2"))
            return -1;
        g_row_counts = row_counts_avx2;
        g_row_sum = row_sum_avx2;
        g_kernel = "avx2";
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

/* A 2-D byte image with contiguous rows. */
typedef struct {
    Py_buffer view;
    const uint8_t *data;
    Py_ssize_t rows, cols, row_stride;
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
    if (v->ndim != 2) {
        PyErr_Format(PyExc_ValueError, "image must be 2-D, got %d dimensions", v->ndim);
        goto fail;
    }
    img->rows = v->shape[0];
    img->cols = v->shape[1];
    img->row_stride = v->strides[0];
    if (img->rows > 1 && img->cols > 0 && img->row_stride < img->cols) {
        PyErr_Format(PyExc_ValueError,
                     "image rows must not overlap or run backwards (row stride %zd, width %zd)",
                     img->row_stride, img->cols);
        goto fail;
    }
    if (img->cols > 1 && v->strides[1] != 1) {
        PyErr_Format(PyExc_ValueError,
                     "image rows must be contiguous (column stride %zd, expected 1)",
                     v->strides[1]);
        goto fail;
    }
    img->data = (const uint8_t *)v->buf;
    return 0;
fail:
    PyBuffer_Release(v);
    return -1;
}

/* Row spans of an ROI: int32 pairs (x0, x1), one pair per image row. */
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

/* How far ahead row-by-row counting prefetches [bytes]. Measured on cold 480p-1080p frames
 * with the simulator's circle ROI: 0 -> 1.6-2.2x the whole frame's read time, 2 KB -> 1.0-1.2x,
 * 4-8 KB -> 0.7-1.1x (best), 16 KB -> 0.8-1.4x (prefetches start evicting each other). */
static const Py_ssize_t sk_prefetch_bytes = 6144;

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

static void count_image(const sk_image *img, const sk_spans *sp, uint8_t p, int want_sat,
                        sk_counts *c)
{
    const sk_row_fn fn = g_row_counts;
    if (!sp->present && (img->rows == 1 || img->row_stride == img->cols)) {
        fn(img->data, img->rows * img->cols, p, want_sat, c); /* one contiguous run */
        return;
    }
    /* Row by row (a circle's spans, or a crop whose rows are not adjacent), prefetching
     * about sk_prefetch_bytes of the rows ahead: each row starts at an address the hardware
     * prefetcher does not predict, and without this every row begins with a full memory
     * latency (measured: a circle ROI took up to 2x the time of reading the whole frame). */
    Py_ssize_t pf_row = 0, pf_ahead = 0, x0, x1;
    for (Py_ssize_t r = 0; r < img->rows; r++) {
        while (pf_row < img->rows && pf_ahead < sk_prefetch_bytes) {
            const uint8_t *ahead = img->data + pf_row * img->row_stride;
            row_span(img, sp, pf_row, &x0, &x1);
            for (Py_ssize_t x = x0; x < x1; x += 64)
                SK_PREFETCH(ahead + x);
            pf_ahead += x1 - x0;
            pf_row++;
        }
        row_span(img, sp, r, &x0, &x1);
        pf_ahead -= x1 - x0;
        if (x1 > x0)
            fn(img->data + r * img->row_stride + x0, x1 - x0, p, want_sat, c);
    }
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

/* ---------------------------------------------------------------------------------------- */
/* Python functions                                                                         */
/* ---------------------------------------------------------------------------------------- */

static PyObject *run_counts(PyObject *args, PyObject *kwargs, int want_sat)
{
    static char *kwlist[] = {"image", "p", "spans", NULL};
    PyObject *image, *p_obj, *spans_obj = Py_None;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "OO|O", kwlist, &image, &p_obj, &spans_obj))
        return NULL;
    uint8_t p;
    if (parse_threshold(p_obj, &p) < 0)
        return NULL;
    sk_image img;
    if (get_image(image, &img) < 0)
        return NULL;
    sk_spans sp;
    if (get_spans(spans_obj, &img, &sp) < 0) {
        PyBuffer_Release(&img.view);
        return NULL;
    }
    sk_counts c = {0, 0};
    Py_BEGIN_ALLOW_THREADS
    count_image(&img, &sp, p, want_sat, &c);
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

static PyObject *sk_read_sum(PyObject *self, PyObject *arg)
{
    (void)self;
    sk_image img;
    if (get_image(arg, &img) < 0)
        return NULL;
    uint64_t total = 0;
    const sk_sum_fn fn = g_row_sum;
    Py_BEGIN_ALLOW_THREADS
    if (img.rows == 1 || img.row_stride == img.cols) {
        total = fn(img.data, img.rows * img.cols);
    } else {
        for (Py_ssize_t r = 0; r < img.rows; r++)
            total += fn(img.data + r * img.row_stride, img.cols);
    }
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&img.view);
    return PyLong_FromUnsignedLongLong(total);
}

static PyObject *sk_kernel(PyObject *self, PyObject *unused)
{
    (void)self;
    (void)unused;
    return PyUnicode_FromString(g_kernel);
}

static PyObject *sk_available_kernels(PyObject *self, PyObject *unused)
{
    (void)self;
    (void)unused;
    PyObject *out = PyList_New(0);
    if (out == NULL)
        return NULL;
    const char *saved = g_kernel;
    const char *names[] = {"c", "sse2", "avx2"};
    for (size_t k = 0; k < sizeof(names) / sizeof(names[0]); k++) {
        if (select_kernel(names[k]) == 0) {
            PyObject *s = PyUnicode_FromString(names[k]);
            if (s == NULL || PyList_Append(out, s) < 0) {
                Py_XDECREF(s);
                Py_DECREF(out);
                select_kernel(saved);
                return NULL;
            }
            Py_DECREF(s);
        }
    }
    select_kernel(saved);
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
    return PyUnicode_FromString(g_kernel);
}

static PyMethodDef sk_methods[] = {
    {"count_le", (PyCFunction)(void (*)(void))sk_count_le, METH_VARARGS | METH_KEYWORDS,
     "count_le(image, p, spans=None) -> int\n\n"
     "Number of pixels with value <= p (Eqs. (1)-(2)) in a 2-D uint8 image with contiguous\n"
     "rows; spans (int32, shape (rows, 2)) limits row r to columns [x0, x1)."},
    {"count_le_and_saturated", (PyCFunction)(void (*)(void))sk_count_le_and_saturated,
     METH_VARARGS | METH_KEYWORDS,
     "count_le_and_saturated(image, p, spans=None) -> (int, int)\n\n"
     "(pixels <= p, pixels == 255) in one pass; arguments as count_le."},
    {"read_sum", sk_read_sum, METH_O,
     "read_sum(image) -> int\n\nSum of all pixel values: the fastest read of the image once "
     "(the memory floor of the benchmarks)."},
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

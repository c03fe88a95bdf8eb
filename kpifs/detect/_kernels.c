/* Fused elementwise loops of the binary tests (kpifs.detect._elementwise).
 *
 * numpy makes each step of these loops a pass over memory: clipping the
 * projections of the null's draws and adding their powers takes seven passes
 * per channel, more than the matrix product that made them. Here each element
 * is read once. The operations are numpy's, in numpy's order, in single
 * precision and without contraction into fused multiply-adds (built with
 * -ffp-contract=off), so that the results are those of the numpy loops in
 * kpifs.detect._elementwise, which are used where this module is not built.
 *
 * Only the buffer protocol is used (no numpy headers); the Python wrappers
 * check shapes, types and contiguity before calling. The GIL is released.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

/* On x86-64 with GCC or Clang, the loops are compiled for AVX2 and AVX-512 too and the
 * widest the processor has is chosen when the module loads (function multi-versioning;
 * the same operations, so the same numbers, on wider registers). */
#if defined(__x86_64__) && defined(__linux__) && (defined(__GNUC__) || defined(__clang__)) \
    && defined(__has_attribute)
#if __has_attribute(target_clones)
#define WIDEST __attribute__((target_clones("avx512f", "avx2", "default")))
#endif
#endif
#ifndef WIDEST
#define WIDEST
#endif

/* numpy.maximum(v, 0) and numpy.minimum(v, 0): NaN propagates. */
static inline float clip_low(float v) { return (v > 0.0f || v != v) ? v : 0.0f; }
static inline float clip_high(float v) { return (v < 0.0f || v != v) ? v : 0.0f; }

/* Buffers of the arguments: *n* objects, each a contiguous float32 array (or None where
 * *optional*), read-only or *writable*; on failure, an exception set and none held. */
typedef struct {
    PyObject *obj;
    const char *name;
    int writable, optional;
    Py_buffer view;
    int held;
} Arg;

static void release(Arg *args, int n)
{
    for (int k = 0; k < n; k++)
        if (args[k].held) {
            PyBuffer_Release(&args[k].view);
            args[k].held = 0;
        }
}

static int acquire(Arg *args, int n)
{
    for (int k = 0; k < n; k++) {
        Arg *a = &args[k];
        a->held = 0;
        if (a->obj == Py_None && a->optional)
            continue;
        int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (a->writable ? PyBUF_WRITABLE : 0);
        if (PyObject_GetBuffer(a->obj, &a->view, flags) < 0) {
            release(args, k);
            return -1;
        }
        a->held = 1;
        const char *f = a->view.format;
        if (a->view.itemsize != 4 || f == NULL || !(f[0] == 'f' || (f[0] && f[1] == 'f'))) {
            PyErr_Format(PyExc_TypeError, "%s: a contiguous float32 array is needed", a->name);
            release(args, k + 1);
            return -1;
        }
    }
    return 0;
}

static float *data(Arg *a) { return a->held ? (float *)a->view.buf : NULL; }
static Py_ssize_t floats(Arg *a) { return a->held ? a->view.len / 4 : 0; }

/* w = max(z, 0); pos += w; sq += w * w; neg += min(z, 0)^2, element by element (any of the
 * three may be NULL). */
WIDEST static void forms_loop(const float *z, Py_ssize_t n, float *pos, float *sq, float *neg)
{
    if (pos && sq && neg) {
        for (Py_ssize_t i = 0; i < n; i++) {
            float w = clip_low(z[i]), v = clip_high(z[i]);
            pos[i] += w;
            sq[i] += w * w;
            neg[i] += v * v;
        }
    } else if (sq && neg) {
        for (Py_ssize_t i = 0; i < n; i++) {
            float w = clip_low(z[i]), v = clip_high(z[i]);
            sq[i] += w * w;
            neg[i] += v * v;
        }
    } else {
        if (pos)
            for (Py_ssize_t i = 0; i < n; i++)
                pos[i] += clip_low(z[i]);
        if (sq)
            for (Py_ssize_t i = 0; i < n; i++) {
                float w = clip_low(z[i]);
                sq[i] += w * w;
            }
        if (neg)
            for (Py_ssize_t i = 0; i < n; i++) {
                float v = clip_high(z[i]);
                neg[i] += v * v;
            }
    }
}

/* The sums of a Newton step of the binary limits, for draws z (k, q, n), signal per unit
 * contrast m (k, q) and contrasts c (k, n), with u_j = max(z_j + m_j c, 0):
 *   power 2: f = sum_j u_j^2,  g = sum_j m_j u_j;
 *   power 1: f = sum_j u_j,    g = sum_j m_j [u_j > 0];
 * summed over j in order, into f and g (k, n). */
WIDEST static void crossing_loop(const float *z, const float *m, const float *c, int power,
                                 float *f, float *g, Py_ssize_t k, Py_ssize_t q, Py_ssize_t n)
{
    for (Py_ssize_t a = 0; a < k; a++) {
        const float *ca = c + a * n;
        float *fa = f + a * n, *ga = g + a * n;
        for (Py_ssize_t i = 0; i < n; i++)
            fa[i] = ga[i] = 0.0f;
        for (Py_ssize_t j = 0; j < q; j++) {
            const float mj = m[a * q + j];
            const float *zj = z + (a * q + j) * n;
            if (power == 2) {
                for (Py_ssize_t i = 0; i < n; i++) {
                    float u = clip_low(mj * ca[i] + zj[i]);
                    fa[i] += u * u;
                    ga[i] += mj * u;
                }
            } else {
                for (Py_ssize_t i = 0; i < n; i++) {
                    float u = clip_low(mj * ca[i] + zj[i]);
                    fa[i] += u;
                    ga[i] += mj * (u > 0.0f ? 1.0f : 0.0f);
                }
            }
        }
    }
}

/* numpy's max over an array: NaN wins. */
static inline float nanmax(float m, float x) { return (x > m || x != x) ? x : m; }

/* Positions summed side by side: their sums and maxima stay in registers. */
#define LANES 16

/* Per draw d of z (n, q, npos), with sums over the channels j in order from 0:
 *   out[d] = (max_p sum_j max(z,0)^2, max_p sum_j min(z,0)^2, max_p sum_j max(z,0),
 *             max_p (sum_j max(z,0) - tot[d, p]))     (the last -inf without tot). */
WIDEST static void maxima_loop(const float *z, const float *tot, Py_ssize_t n, Py_ssize_t q,
                               Py_ssize_t npos, float *out)
{
    for (Py_ssize_t d = 0; d < n; d++) {
        const float *zd = z + d * q * npos, *td = tot ? tot + d * npos : NULL;
        float m0[LANES], m1[LANES], m2[LANES], m3[LANES];
        for (int p = 0; p < LANES; p++)
            m0[p] = m1[p] = m2[p] = m3[p] = -INFINITY;
        Py_ssize_t p0 = 0;
        for (; p0 + LANES <= npos; p0 += LANES) {
            float sq[LANES] = {0.0f}, neg[LANES] = {0.0f}, pos[LANES] = {0.0f};
            for (Py_ssize_t j = 0; j < q; j++) {
                const float *zj = zd + j * npos + p0;
                for (int p = 0; p < LANES; p++) {
                    float w = clip_low(zj[p]), v = clip_high(zj[p]);
                    pos[p] += w;
                    sq[p] += w * w;
                    neg[p] += v * v;
                }
            }
            for (int p = 0; p < LANES; p++) {
                m0[p] = nanmax(m0[p], sq[p]);
                m1[p] = nanmax(m1[p], neg[p]);
                m2[p] = nanmax(m2[p], pos[p]);
            }
            if (td)
                for (int p = 0; p < LANES; p++)
                    m3[p] = nanmax(m3[p], pos[p] - td[p0 + p]);
        }
        float best[4] = {-INFINITY, -INFINITY, -INFINITY, -INFINITY};
        for (int p = 0; p < LANES; p++) {
            best[0] = nanmax(best[0], m0[p]);
            best[1] = nanmax(best[1], m1[p]);
            best[2] = nanmax(best[2], m2[p]);
            best[3] = nanmax(best[3], m3[p]);
        }
        for (; p0 < npos; p0++) {                          /* the last positions */
            float sq = 0.0f, neg = 0.0f, pos = 0.0f;
            for (Py_ssize_t j = 0; j < q; j++) {
                float w = clip_low(zd[j * npos + p0]), v = clip_high(zd[j * npos + p0]);
                pos += w;
                sq += w * w;
                neg += v * v;
            }
            best[0] = nanmax(best[0], sq);
            best[1] = nanmax(best[1], neg);
            best[2] = nanmax(best[2], pos);
            if (td)
                best[3] = nanmax(best[3], pos - td[p0]);
        }
        for (int k = 0; k < 4; k++)
            out[4 * d + k] = best[k];
    }
}

/* numpy's min over an array: NaN wins. */
static inline float nanmin(float m, float x) { return (x < m || x != x) ? x : m; }

/* `_crossings` of kpifs.detect.limits, chunk of positions by chunk: Newton steps of every
 * draw of a chunk until all have converged (or n_iter steps), as numpy does them:
 *   new = max(c - (f - thr) / g', 0), g' = 2 g (power 2) or g (power 1), with f, g the
 *   crossing sums at c; where g' <= 0, new = max(min_{j: m_j > 0} (root - z_j) / m_j, c);
 *   converged where |new - c| <= rtol max(new, 1e-30).
 * f and g (n floats each) are work space. */
WIDEST static void newton_loop(const float *z, const float *m, float *c, float thr, float root,
                               int power, int n_iter, float rtol, Py_ssize_t chunk,
                               Py_ssize_t k, Py_ssize_t q, Py_ssize_t n, float *f, float *g)
{
    for (Py_ssize_t a0 = 0; a0 < k; a0 += chunk) {
        const Py_ssize_t a1 = a0 + chunk < k ? a0 + chunk : k;
        for (int it = 0; it < n_iter; it++) {
            int converged = 1;
            for (Py_ssize_t a = a0; a < a1; a++) {
                crossing_loop(z + a * q * n, m + a * q, c + a * n, power, f, g, 1, q, n);
                float *ca = c + a * n;
                const float *za = z + a * q * n, *ma = m + a * q;
                for (Py_ssize_t i = 0; i < n; i++) {
                    const float gi = power == 2 ? 2.0f * g[i] : g[i];
                    float v = clip_low(ca[i] - (f[i] - thr) / gi);
                    if (gi <= 0.0f) {
                        float alone = INFINITY;
                        for (Py_ssize_t j = 0; j < q; j++)
                            alone = nanmin(alone, ma[j] > 0.0f ? (root - za[j * n + i]) / ma[j]
                                                               : INFINITY);
                        v = (alone > ca[i] || alone != alone) ? alone : ca[i];
                    }
                    const float d = v - ca[i];
                    const float big = (v > 1e-30f || v != v) ? v : 1e-30f;
                    if (!((d < 0.0f ? -d : d) <= rtol * big))
                        converged = 0;
                    ca[i] = v;
                }
            }
            if (converged)
                break;
        }
    }
}

/* binary_forms(z, positive, square, negative): for every element,
 *   w = max(z, 0); positive += w; square += w * w; negative += min(z, 0)^2
 * (each accumulator may be None, and is of z's size). */
static PyObject *binary_forms(PyObject *self, PyObject *args)
{
    Arg a[4] = {{.name = "z"}, {.name = "positive", .writable = 1, .optional = 1},
                {.name = "square", .writable = 1, .optional = 1},
                {.name = "negative", .writable = 1, .optional = 1}};
    if (!PyArg_ParseTuple(args, "OOOO", &a[0].obj, &a[1].obj, &a[2].obj, &a[3].obj))
        return NULL;
    if (acquire(a, 4) < 0)
        return NULL;
    const Py_ssize_t n = floats(&a[0]);
    for (int k = 1; k < 4; k++)
        if (a[k].held && floats(&a[k]) != n) {
            PyErr_SetString(PyExc_ValueError, "binary_forms: an accumulator is not z's size");
            release(a, 4);
            return NULL;
        }
    Py_BEGIN_ALLOW_THREADS
    forms_loop(data(&a[0]), n, data(&a[1]), data(&a[2]), data(&a[3]));
    Py_END_ALLOW_THREADS
    release(a, 4);
    Py_RETURN_NONE;
}

/* binary_maxima(z, tot, out, n, q, npos): `maxima_loop` (tot may be None). */
static PyObject *binary_maxima(PyObject *self, PyObject *args)
{
    Arg a[3] = {{.name = "z"}, {.name = "tot", .optional = 1}, {.name = "out", .writable = 1}};
    Py_ssize_t n, q, npos;
    if (!PyArg_ParseTuple(args, "OOOnnn", &a[0].obj, &a[1].obj, &a[2].obj, &n, &q, &npos))
        return NULL;
    if (acquire(a, 3) < 0)
        return NULL;
    if (n < 0 || q < 1 || npos < 1 || floats(&a[0]) != n * q * npos || floats(&a[2]) != 4 * n
        || (a[1].held && floats(&a[1]) != n * npos)) {
        PyErr_SetString(PyExc_ValueError, "binary_maxima: inconsistent sizes");
        release(a, 3);
        return NULL;
    }
    Py_BEGIN_ALLOW_THREADS
    maxima_loop(data(&a[0]), data(&a[1]), n, q, npos, data(&a[2]));
    Py_END_ALLOW_THREADS
    release(a, 3);
    Py_RETURN_NONE;
}

/* newton_crossings(z, m, c, thr, root, power, n_iter, rtol, chunk, k, q, n): `newton_loop`,
 * in place on c. */
static PyObject *newton_crossings(PyObject *self, PyObject *args)
{
    Arg a[3] = {{.name = "z"}, {.name = "m"}, {.name = "c", .writable = 1}};
    float thr, root, rtol;
    int power, n_iter;
    Py_ssize_t chunk, k, q, n;
    if (!PyArg_ParseTuple(args, "OOOffiifnnnn", &a[0].obj, &a[1].obj, &a[2].obj, &thr, &root,
                          &power, &n_iter, &rtol, &chunk, &k, &q, &n))
        return NULL;
    if (acquire(a, 3) < 0)
        return NULL;
    if (floats(&a[0]) != k * q * n || floats(&a[1]) != k * q || floats(&a[2]) != k * n ||
        (power != 1 && power != 2) || chunk < 1 || n < 1) {
        PyErr_SetString(PyExc_ValueError, "newton_crossings: inconsistent sizes or options");
        release(a, 3);
        return NULL;
    }
    float *work = PyMem_RawMalloc(2 * n * sizeof(float));
    if (work == NULL) {
        release(a, 3);
        return PyErr_NoMemory();
    }
    Py_BEGIN_ALLOW_THREADS
    newton_loop(data(&a[0]), data(&a[1]), data(&a[2]), thr, root, power, n_iter, rtol, chunk,
                k, q, n, work, work + n);
    Py_END_ALLOW_THREADS
    PyMem_RawFree(work);
    release(a, 3);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"binary_forms", binary_forms, METH_VARARGS,
     "binary_forms(z, positive, square, negative): add max(z,0), max(z,0)^2, min(z,0)^2."},
    {"binary_maxima", binary_maxima, METH_VARARGS,
     "binary_maxima(z, tot, out, n, q, npos): per draw, the grid maxima of the binary forms."},
    {"newton_crossings", newton_crossings, METH_VARARGS,
     "newton_crossings(z, m, c, thr, root, power, n_iter, rtol, chunk, k, q, n): in place."},
    {NULL, NULL, 0, NULL}
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, .m_name = "_kernels",
    .m_doc = "Fused elementwise loops of the binary tests (see kpifs.detect._elementwise).",
    .m_size = -1, .m_methods = methods,
};

PyMODINIT_FUNC PyInit__kernels(void)
{
    return PyModule_Create(&module);
}

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

static int get_floats(PyObject *obj, Py_buffer *view, int writable, const char *what)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) < 0)
        return -1;
    if (view->itemsize != 4 || view->format == NULL ||
        !(view->format[0] == 'f' || (view->format[0] != '\0' && view->format[1] == 'f'))) {
        PyErr_Format(PyExc_TypeError, "%s: a contiguous float32 array is needed", what);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

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

/* binary_maxima(z, tot, out, n, q, npos): `maxima_loop` (tot may be None). */
static PyObject *binary_maxima(PyObject *self, PyObject *args)
{
    PyObject *oz, *ot, *oo;
    Py_ssize_t n, q, npos;
    if (!PyArg_ParseTuple(args, "OOOnnn", &oz, &ot, &oo, &n, &q, &npos))
        return NULL;
    Py_buffer vz, vt, vo;
    int have_t = ot != Py_None;
    if (get_floats(oz, &vz, 0, "z") < 0)
        return NULL;
    if (have_t && get_floats(ot, &vt, 0, "tot") < 0) {
        PyBuffer_Release(&vz);
        return NULL;
    }
    if (get_floats(oo, &vo, 1, "out") < 0) {
        PyBuffer_Release(&vz);
        if (have_t)
            PyBuffer_Release(&vt);
        return NULL;
    }
    PyObject *result = NULL;
    if (n < 0 || q < 1 || npos < 1 || vz.len != 4 * n * q * npos || vo.len != 16 * n ||
        (have_t && vt.len != 4 * n * npos)) {
        PyErr_SetString(PyExc_ValueError, "binary_maxima: inconsistent sizes");
        goto done;
    }
    {
        const float *z = (const float *)vz.buf, *tot = have_t ? (const float *)vt.buf : NULL;
        float *out = (float *)vo.buf;
        Py_BEGIN_ALLOW_THREADS
        maxima_loop(z, tot, n, q, npos, out);
        Py_END_ALLOW_THREADS
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&vz);
    if (have_t)
        PyBuffer_Release(&vt);
    PyBuffer_Release(&vo);
    return result;
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

/* newton_crossings(z, m, c, thr, root, power, n_iter, rtol, chunk, k, q, n): in place on c. */
static PyObject *newton_crossings(PyObject *self, PyObject *args)
{
    PyObject *oz, *om, *oc;
    float thr, root, rtol;
    int power, n_iter;
    Py_ssize_t chunk, k, q, n;
    if (!PyArg_ParseTuple(args, "OOOffiifnnnn", &oz, &om, &oc, &thr, &root, &power, &n_iter,
                          &rtol, &chunk, &k, &q, &n))
        return NULL;
    Py_buffer vz, vm, vc;
    if (get_floats(oz, &vz, 0, "z") < 0)
        return NULL;
    if (get_floats(om, &vm, 0, "m") < 0) {
        PyBuffer_Release(&vz);
        return NULL;
    }
    if (get_floats(oc, &vc, 1, "c") < 0) {
        PyBuffer_Release(&vz); PyBuffer_Release(&vm);
        return NULL;
    }
    PyObject *result = NULL;
    float *work = NULL;
    if (vz.len != 4 * k * q * n || vm.len != 4 * k * q || vc.len != 4 * k * n ||
        (power != 1 && power != 2) || chunk < 1 || n < 1) {
        PyErr_SetString(PyExc_ValueError, "newton_crossings: inconsistent sizes or options");
        goto done;
    }
    work = PyMem_RawMalloc(2 * n * sizeof(float));
    if (work == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    {
        const float *z = (const float *)vz.buf, *m = (const float *)vm.buf;
        float *c = (float *)vc.buf;
        Py_BEGIN_ALLOW_THREADS
        newton_loop(z, m, c, thr, root, power, n_iter, rtol, chunk, k, q, n, work, work + n);
        Py_END_ALLOW_THREADS
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyMem_RawFree(work);
    PyBuffer_Release(&vz); PyBuffer_Release(&vm); PyBuffer_Release(&vc);
    return result;
}

/* binary_forms(z, positive, square, negative): for every element,
 *   w = max(z, 0); positive += w; square += w * w; negative += min(z, 0)^2
 * (each accumulator may be None). */
static PyObject *binary_forms(PyObject *self, PyObject *args)
{
    PyObject *objs[4];
    Py_buffer views[4];
    int have[4] = {0, 0, 0, 0};
    if (!PyArg_ParseTuple(args, "OOOO", &objs[0], &objs[1], &objs[2], &objs[3]))
        return NULL;
    PyObject *result = NULL;
    for (int k = 0; k < 4; k++) {
        if (objs[k] == Py_None)
            continue;
        if (get_floats(objs[k], &views[k], k > 0, k ? "accumulator" : "z") < 0)
            goto done;
        have[k] = 1;
        if (k && views[k].len != views[0].len) {
            PyErr_SetString(PyExc_ValueError, "accumulators and z differ in size");
            goto done;
        }
    }
    if (!have[0]) {
        PyErr_SetString(PyExc_TypeError, "z is needed");
        goto done;
    }
    {
        const Py_ssize_t n = views[0].len / 4;
        const float *z = (const float *)views[0].buf;
        float *pos = have[1] ? (float *)views[1].buf : NULL;
        float *sq = have[2] ? (float *)views[2].buf : NULL;
        float *neg = have[3] ? (float *)views[3].buf : NULL;
        Py_BEGIN_ALLOW_THREADS
        forms_loop(z, n, pos, sq, neg);
        Py_END_ALLOW_THREADS
    }
    result = Py_None;
    Py_INCREF(result);
done:
    for (int k = 0; k < 4; k++)
        if (have[k])
            PyBuffer_Release(&views[k]);
    return result;
}

/* crossing_sums(z, m, c, power, f, g): for draws z (k, q, n), signal per unit
 * contrast m (k, q) and contrasts c (k, n), with u_j = max(z_j + m_j c, 0):
 *   power 2: f = sum_j u_j^2,  g = sum_j m_j u_j;
 *   power 1: f = sum_j u_j,    g = sum_j m_j [u_j > 0];
 * summed over j in order, into f and g (k, n). */
static PyObject *crossing_sums(PyObject *self, PyObject *args)
{
    PyObject *oz, *om, *oc, *of, *og;
    int power;
    Py_ssize_t k, q, n;
    if (!PyArg_ParseTuple(args, "OOOiOOnnn", &oz, &om, &oc, &power, &of, &og, &k, &q, &n))
        return NULL;
    Py_buffer vz, vm, vc, vf, vg;
    if (get_floats(oz, &vz, 0, "z") < 0)
        return NULL;
    if (get_floats(om, &vm, 0, "m") < 0) {
        PyBuffer_Release(&vz);
        return NULL;
    }
    if (get_floats(oc, &vc, 0, "c") < 0) {
        PyBuffer_Release(&vz); PyBuffer_Release(&vm);
        return NULL;
    }
    if (get_floats(of, &vf, 1, "f") < 0) {
        PyBuffer_Release(&vz); PyBuffer_Release(&vm); PyBuffer_Release(&vc);
        return NULL;
    }
    if (get_floats(og, &vg, 1, "g") < 0) {
        PyBuffer_Release(&vz); PyBuffer_Release(&vm); PyBuffer_Release(&vc);
        PyBuffer_Release(&vf);
        return NULL;
    }
    PyObject *result = NULL;
    if (vz.len != 4 * k * q * n || vm.len != 4 * k * q || vc.len != 4 * k * n ||
        vf.len != 4 * k * n || vg.len != 4 * k * n || (power != 1 && power != 2)) {
        PyErr_SetString(PyExc_ValueError, "crossing_sums: inconsistent sizes or power");
        goto done;
    }
    {
        const float *z = (const float *)vz.buf, *m = (const float *)vm.buf;
        const float *c = (const float *)vc.buf;
        float *f = (float *)vf.buf, *g = (float *)vg.buf;
        Py_BEGIN_ALLOW_THREADS
        crossing_loop(z, m, c, power, f, g, k, q, n);
        Py_END_ALLOW_THREADS
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&vz); PyBuffer_Release(&vm); PyBuffer_Release(&vc);
    PyBuffer_Release(&vf); PyBuffer_Release(&vg);
    return result;
}

static PyMethodDef methods[] = {
    {"binary_forms", binary_forms, METH_VARARGS,
     "binary_forms(z, positive, square, negative): add max(z,0), max(z,0)^2, min(z,0)^2."},
    {"binary_maxima", binary_maxima, METH_VARARGS,
     "binary_maxima(z, tot, out, n, q, npos): per draw, the grid maxima of the binary forms."},
    {"newton_crossings", newton_crossings, METH_VARARGS,
     "newton_crossings(z, m, c, thr, root, power, n_iter, rtol, chunk, k, q, n): in place."},
    {"crossing_sums", crossing_sums, METH_VARARGS,
     "crossing_sums(z, m, c, power, f, g, k, q, n): the binary forms' Newton sums."},
    {NULL, NULL, 0, NULL}
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_kernels",
    "Fused elementwise loops of the binary tests (see kpifs.detect._elementwise).", -1, methods
};

PyMODINIT_FUNC PyInit__kernels(void)
{
    return PyModule_Create(&module);
}

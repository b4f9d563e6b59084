/* The Kalman step of pd_service.estimation.linear.LinearBackend.advance, in C.

   The same formulas as the numpy form in linear.py (the reference, which the tests compare
   this against), for a step of m <= M jumps; one call does the whole step where numpy would
   make a few dozen calls on tiny arrays:

       jump:    x- = A^m x + [A^{m-1}B ... B] [u(a); ...; u(a+m-1)]
                P- = A^m P (A^m)^T + Qs(m)          (upper triangle computed, mirrored:
                                                     exactly symmetric)
       update:  one row h:  s = h P- h^T + r,  w = P- h / sqrt(s),  c = 1 / sqrt(s)
                            x+ = x- + w (c (z - h x-)),  P+ = P- - w w^T   (w = 0 if s <= 0)
                r rows H:   S = H P- H^T + R = L L^T (Cholesky),  W = P- H^T L^{-T},
                            K = W L^{-1},  x+ = x- + K (z - H x-),  P+ = P- - W W^T

   Entry points (one step's arithmetic, advance_impl, behind both):
       advance: LinearBackend.advance's step (the reuse rule for a step's previous result,
                jump, remean, update, the new Gaussian)
       replay:  ReplayEstimator._replay's loop, advance after advance over the measured
                steps, the inputs read from the input buffer in place
   and two helpers of the input buffer and the window:
       fill:    InputBuffer.set's rows, buf[start:end] = u
       freeze:  arrays made read-only (ndarray.setflags(write=False)) in one call
       untrack: states kept unchanged taken out of the cycle collector

   A step it does not take (a Cholesky pivot not above 1e-10 of its diagonal entry: S
   singular or nearly so; a sensor beyond MAXR rows) makes advance() return None and replay()
   stop: the caller then runs the numpy form for that step (LU, or the pseudo-inverse). The
   calls are METH_FASTCALL and build their tuples directly (no format string to parse).
   Arrays are read as float64 and C-contiguous (converted if not); results are new arrays.
   Sums run in index order, so results are deterministic but not bit for bit numpy's
   (BLAS orders its sums otherwise): they agree to rounding. No state, no GIL release. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include <numpy/arrayobject.h>
#include <math.h>
#include <string.h>

#define PIVOT 1e-10
#define MAXN 64  /* state dimension handled here (MAX_N); a larger model: the numpy form */
#define MAXR 16  /* rows of one sensor handled here (MAX_R); larger: the numpy form */

/* A float64 C-contiguous view of obj (a new reference), or NULL with an exception. The
   backend's arrays are such already: taken as they are, without numpy's conversion. */
static PyArrayObject *as_f64(PyObject *obj) {
    if (PyArray_CheckExact(obj)) {
        PyArrayObject *a = (PyArrayObject *)obj;
        if (PyArray_TYPE(a) == NPY_DOUBLE && PyArray_ISCARRAY_RO(a) && PyArray_ISNOTSWAPPED(a)) {
            Py_INCREF(obj);
            return a;
        }
    }
    return (PyArrayObject *)PyArray_FROM_OTF(obj, NPY_DOUBLE, NPY_ARRAY_IN_ARRAY);
}

static PyObject *new_vec(npy_intp n, double **data) {
    npy_intp dims[1] = {n};
    PyObject *a = PyArray_SimpleNew(1, dims, NPY_DOUBLE);
    if (a) *data = (double *)PyArray_DATA((PyArrayObject *)a);
    return a;
}

static PyObject *new_mat(npy_intp r, npy_intp c, double **data) {
    npy_intp dims[2] = {r, c};
    PyObject *a = PyArray_SimpleNew(2, dims, NPY_DOUBLE);
    if (a) *data = (double *)PyArray_DATA((PyArrayObject *)a);
    return a;
}

static int check_size(PyArrayObject *a, npy_intp size, const char *what) {
    if (PyArray_SIZE(a) != size) {
        PyErr_Format(PyExc_ValueError, "_kalman: %s has %zd values, expected %zd", what,
                     (Py_ssize_t)PyArray_SIZE(a), (Py_ssize_t)size);
        return -1;
    }
    return 0;
}

/* nargs == want, or a TypeError naming the function (the calls are METH_FASTCALL: no
   argument tuple, no format string to parse). */
static int check_nargs(const char *name, Py_ssize_t nargs, Py_ssize_t want) {
    if (nargs == want) return 0;
    PyErr_Format(PyExc_TypeError, "_kalman.%s: %zd arguments, expected %zd", name, nargs, want);
    return -1;
}

/* untrack_note: the tuples made here (a step's sensors, the Gaussian) are taken out of the
   cyclic garbage collector's lists. They are immutable and hold only numbers, bytes, numpy
   arrays of float64 and other such tuples, so they can be in no reference cycle and
   reference counting frees them; tracked, a session's window of them fills the collector's
   young generation and its collections stop the worker (docs/performance.md). (CPython
   untracks such exact tuples itself, but only when a collection first scans them, and never
   a tuple subclass such as the Gaussian.) */

/* The jump: (x (n,), P (n, n) or None, A (n, n), Qs (n, n), G (n, >= k) or None, u (k
   values)) -> (x-, P- or None). G is the tables' full stacked input matrix [A^{M-1}B ... B]:
   its last k columns multiply u (m steps of nu inputs, k = m nu). P None: the mean only. */
static PyObject *jump_impl(PyObject *ox, PyObject *oP, PyObject *oA, PyObject *oQ,
                           PyObject *oG, const double *u, npy_intp k) {
    PyArrayObject *x = NULL, *P = NULL, *A = NULL, *Q = NULL, *G = NULL;
    PyObject *xo = NULL, *Po = NULL, *res = NULL;
    x = as_f64(ox);
    A = as_f64(oA);
    if (!x || !A) goto done;
    npy_intp n = PyArray_SIZE(x);
    if (n > MAXN || check_size(A, n * n, "A")) {
        if (!PyErr_Occurred()) PyErr_SetString(PyExc_ValueError, "_kalman: state too large");
        goto done;
    }
    const double *a = PyArray_DATA(A), *xv = PyArray_DATA(x);
    double *xn;
    xo = new_vec(n, &xn);
    if (!xo) goto done;
    for (npy_intp i = 0; i < n; i++) {
        double acc = 0.0;
        for (npy_intp k = 0; k < n; k++) acc += a[i * n + k] * xv[k];
        xn[i] = acc;
    }
    if (oG != Py_None) {
        G = as_f64(oG);
        if (!G) goto done;
        npy_intp cols = PyArray_NDIM(G) == 2 ? PyArray_DIM(G, 1) : -1;
        if (PyArray_NDIM(G) != 2 || PyArray_DIM(G, 0) != n || cols < k) {
            PyErr_SetString(PyExc_ValueError, "_kalman: G is not (n, >= U.size)");
            goto done;
        }
        const double *g = (const double *)PyArray_DATA(G) + (cols - k);
        for (npy_intp i = 0; i < n; i++) {  /* the last k columns: [A^{m-1}B ... B] */
            double acc = 0.0;
            for (npy_intp l = 0; l < k; l++) acc += g[i * cols + l] * u[l];
            xn[i] += acc;
        }
    }
    if (oP == Py_None) {
        Po = Py_None;
        Py_INCREF(Po);
    } else {
        P = as_f64(oP);
        Q = as_f64(oQ);
        if (!P || !Q || check_size(P, n * n, "P") || check_size(Q, n * n, "Qs")) goto done;
        const double *p = PyArray_DATA(P), *q = PyArray_DATA(Q);
        double t[MAXN * MAXN];  /* T = A P */
        for (npy_intp i = 0; i < n; i++)
            for (npy_intp j = 0; j < n; j++) {
                double acc = 0.0;
                for (npy_intp k = 0; k < n; k++) acc += a[i * n + k] * p[k * n + j];
                t[i * n + j] = acc;
            }
        double *pn;
        Po = new_mat(n, n, &pn);
        if (!Po) goto done;
        for (npy_intp i = 0; i < n; i++)  /* (T A^T)_ij, j >= i, + Qs_ij; mirrored */
            for (npy_intp j = i; j < n; j++) {
                double acc = 0.0;
                for (npy_intp k = 0; k < n; k++) acc += t[i * n + k] * a[j * n + k];
                pn[i * n + j] = pn[j * n + i] = acc + q[i * n + j];
            }
    }
    res = PyTuple_Pack(2, xo, Po);
done:
    Py_XDECREF(x); Py_XDECREF(P); Py_XDECREF(A); Py_XDECREF(Q); Py_XDECREF(G);
    Py_XDECREF(xo); Py_XDECREF(Po);
    return res;
}

/* x += K (z - H x) in place: x (n,), H (r, n), K (n, r), z (r,), r <= MAXR. */
static void mean_update(double *x, npy_intp n, const double *H, const double *K,
                        const double *z, npy_intp r) {
    double innov[MAXR];
    for (npy_intp c = 0; c < r; c++) {
        double acc = 0.0;
        for (npy_intp k = 0; k < n; k++) acc += H[c * n + k] * x[k];
        innov[c] = z[c] - acc;
    }
    for (npy_intp i = 0; i < n; i++) {
        double acc = 0.0;
        for (npy_intp c = 0; c < r; c++) acc += K[i * r + c] * innov[c];
        x[i] += acc;
    }
}

/* x += K (c (z - h x)) in place: one row's mean step (kinds 1 and 2 of linear.Stage), with
   h x = x[j] for a unit row (h NULL) or the dot product h (n,) x. */
static void mean_row(double *x, npy_intp n, const double *h, long j, const double *K,
                     double z, double c) {
    double hx = 0.0;
    if (h == NULL) {
        hx = x[j];
    } else {
        for (npy_intp l = 0; l < n; l++) hx += h[l] * x[l];
    }
    double ci = c * (z - hx);
    for (npy_intp l = 0; l < n; l++) x[l] += K[l] * ci;
}

/* One Kalman update in place on x (n,) and P (n, n) with r rows H (r, n), R (r, r), z (r,).
   Writes K (n, r). Returns 0, or 1 when a Cholesky pivot is not clearly positive. */
static int update_rows(double *x, double *P, npy_intp n, const double *H, const double *R,
                       const double *z, npy_intp r, double *K) {
    double PHt[MAXN * MAXR], S[MAXR * MAXR], L[MAXR * MAXR], Li[MAXR * MAXR];
    double W[MAXN * MAXR];
    for (npy_intp i = 0; i < n; i++)  /* P H^T (n, r) */
        for (npy_intp c = 0; c < r; c++) {
            double acc = 0.0;
            for (npy_intp k = 0; k < n; k++) acc += P[i * n + k] * H[c * n + k];
            PHt[i * r + c] = acc;
        }
    for (npy_intp a = 0; a < r; a++)  /* S = H P H^T + R, lower triangle read */
        for (npy_intp b = 0; b <= a; b++) {
            double acc = 0.0;
            for (npy_intp k = 0; k < n; k++) acc += H[a * n + k] * PHt[k * r + b];
            S[a * r + b] = acc + R[a * r + b];
        }
    memset(L, 0, sizeof(double) * (size_t)(r * r));
    for (npy_intp k = 0; k < r; k++) {  /* S = L L^T */
        double d = S[k * r + k], q = d;
        for (npy_intp l = 0; l < k; l++) q -= L[k * r + l] * L[k * r + l];
        if (!(d > 0.0) || !(q > PIVOT * d)) return 1;
        double lkk = sqrt(q);
        L[k * r + k] = lkk;
        for (npy_intp i = k + 1; i < r; i++) {
            double acc = S[i * r + k];
            for (npy_intp l = 0; l < k; l++) acc -= L[i * r + l] * L[k * r + l];
            L[i * r + k] = acc / lkk;
        }
    }
    memset(Li, 0, sizeof(double) * (size_t)(r * r));
    for (npy_intp j = 0; j < r; j++) {  /* L^{-1} by forward substitution, column j */
        Li[j * r + j] = 1.0 / L[j * r + j];
        for (npy_intp i = j + 1; i < r; i++) {
            double acc = 0.0;
            for (npy_intp l = j; l < i; l++) acc -= L[i * r + l] * Li[l * r + j];
            Li[i * r + j] = acc / L[i * r + i];
        }
    }
    for (npy_intp i = 0; i < n; i++)  /* W = P H^T L^{-T} */
        for (npy_intp c = 0; c < r; c++) {
            double acc = 0.0;
            for (npy_intp l = 0; l <= c; l++) acc += PHt[i * r + l] * Li[c * r + l];
            W[i * r + c] = acc;
        }
    for (npy_intp i = 0; i < n; i++)  /* K = W L^{-1} */
        for (npy_intp c = 0; c < r; c++) {
            double acc = 0.0;
            for (npy_intp l = c; l < r; l++) acc += W[i * r + l] * Li[l * r + c];
            K[i * r + c] = acc;
        }
    mean_update(x, n, H, K, z, r);
    for (npy_intp i = 0; i < n; i++)  /* P - W W^T, exactly symmetric */
        for (npy_intp j = i; j < n; j++) {
            double acc = 0.0;
            for (npy_intp c = 0; c < r; c++) acc += W[i * r + c] * W[j * r + c];
            P[i * n + j] = P[j * n + i] = P[i * n + j] - acc;
        }
    return 0;
}

/* Stages (linear.Gaussian.stages, the one format the numpy form writes too): a bytes object
   holding one record of float64 values per packet applied, in order,

       sensor, kind, j, c, r, z (r values), K (n x r, row-major), H (r x n; not for kind 1)

   with kind, j, c, K and z as linear.read_stages describes (kind 1 / 2: r = 1, K = w;
   kind 3: K (n, r), j = -1, c = 0): one object per step, not one per packet and array. */

static Py_ssize_t record_len(long kind, npy_intp n, npy_intp r) {
    return 5 + r + n * r + (kind == 1 ? 0 : r * n);
}

/* A growable array of doubles: the records being written (on the stack while they fit). */
typedef struct {
    double *d;
    Py_ssize_t len, cap;
    double local[512];
} Records;

static void records_init(Records *b) { b->d = b->local; b->len = 0; b->cap = 512; }

static void records_free(Records *b) { if (b->d != b->local) PyMem_Free(b->d); }

static double *records_add(Records *b, Py_ssize_t k) {
    if (b->len + k > b->cap) {
        Py_ssize_t cap = 2 * (b->len + k);
        double *d = PyMem_Malloc(sizeof(double) * (size_t)cap);
        if (!d) { PyErr_NoMemory(); return NULL; }
        memcpy(d, b->d, sizeof(double) * (size_t)b->len);
        records_free(b);
        b->d = d;
        b->cap = cap;
    }
    double *at = b->d + b->len;
    b->len += k;
    return at;
}

/* Applies packets[start:] to xv (n,) and pv (n, n) in place, in turn, each appending its
   stage's record to ``rec``. 0, 1 (hand back: a Cholesky pivot not clearly positive, or a
   packet beyond this kernel's sizes), or -1 with an exception. */
static int apply_packets(double *xv, double *pv, npy_intp n, PyObject *packets,
                         PyObject *rows, Py_ssize_t start, Py_ssize_t stop, Records *rec) {
    Py_ssize_t np_ = stop;
    for (Py_ssize_t i = start; i < np_; i++) {
        PyObject *pk = PyList_GET_ITEM(packets, i);
        if (!PyTuple_Check(pk) || PyTuple_GET_SIZE(pk) < 3) {
            PyErr_SetString(PyExc_TypeError, "_kalman: a packet is not (sensor, z, R)");
            return -1;
        }
        Py_ssize_t sensor = PyLong_AsSsize_t(PyTuple_GET_ITEM(pk, 0));
        if (sensor == -1 && PyErr_Occurred()) return -1;
        if (sensor < 0 || sensor >= PyList_GET_SIZE(rows)) {
            PyErr_SetString(PyExc_IndexError, "_kalman: sensor index out of range");
            return -1;
        }
        PyObject *row = PyList_GET_ITEM(rows, sensor);
        if (!PyTuple_Check(row) || PyTuple_GET_SIZE(row) != 6) {
            PyErr_SetString(PyExc_TypeError, "_kalman: a sensor row is not a 6-tuple");
            return -1;
        }
        long kind = PyLong_AsLong(PyTuple_GET_ITEM(row, 0));
        if (kind == -1 && PyErr_Occurred()) return -1;
        PyObject *oH = PyTuple_GET_ITEM(row, 1);
        PyObject *oR = PyTuple_GET_ITEM(pk, 2);
        if (oR == Py_None) oR = PyTuple_GET_ITEM(row, 3);
        PyArrayObject *H = as_f64(oH), *R = as_f64(oR), *Z = as_f64(PyTuple_GET_ITEM(pk, 1));
        int fail = 0;
        long j = -1;
        double c = 0.0, K[MAXN * MAXR];
        npy_intp r = 1;
        if (!H || !R || !Z) {
            fail = -1;
        } else if (kind == 1 || kind == 2) {
            const double *h = PyArray_DATA(H);
            j = PyLong_AsLong(PyTuple_GET_ITEM(row, 5));
            if ((j == -1 && PyErr_Occurred()) || check_size(H, n, "h") || check_size(Z, 1, "z")
                || check_size(R, 1, "R") || (kind == 1 && (j < 0 || j >= n))) {
                if (!PyErr_Occurred()) PyErr_SetString(PyExc_ValueError, "_kalman: bad row");
                fail = -1;
            } else {
                double zs = *(const double *)PyArray_DATA(Z), rr = *(const double *)PyArray_DATA(R);
                double *w = K, s, innov;
                if (kind == 1) {
                    for (npy_intp k = 0; k < n; k++) w[k] = pv[k * n + j];
                    s = pv[j * n + j] + rr;
                    innov = zs - xv[j];
                } else {
                    double hph = 0.0, hx = 0.0;
                    for (npy_intp k = 0; k < n; k++) {
                        double acc = 0.0;
                        for (npy_intp l = 0; l < n; l++) acc += pv[k * n + l] * h[l];
                        w[k] = acc;
                    }
                    for (npy_intp k = 0; k < n; k++) { hph += h[k] * w[k]; hx += h[k] * xv[k]; }
                    s = hph + rr;
                    innov = zs - hx;
                }
                if (!(s > 0.0)) {  /* h P- h^T + r = 0: nothing new (K = 0) */
                    for (npy_intp k = 0; k < n; k++) w[k] = 0.0;
                } else {
                    c = 1.0 / sqrt(s);
                    double ci = c * innov;
                    for (npy_intp k = 0; k < n; k++) w[k] *= c;
                    for (npy_intp k = 0; k < n; k++) xv[k] += w[k] * ci;
                    for (npy_intp a = 0; a < n; a++)
                        for (npy_intp b = a; b < n; b++)
                            pv[a * n + b] = pv[b * n + a] = pv[a * n + b] - w[a] * w[b];
                }
            }
        } else {
            r = PyArray_SIZE(Z);
            if (r > MAXR) {
                fail = 1;
            } else if (check_size(H, r * n, "H") || check_size(R, r * r, "R")) {
                fail = -1;
            } else if (update_rows(xv, pv, n, PyArray_DATA(H), PyArray_DATA(R),
                                   PyArray_DATA(Z), r, K)) {
                fail = 1;
            } else {
                kind = 3;
            }
        }
        if (!fail) {  /* the stage's record */
            double *d = records_add(rec, record_len(kind, n, r));
            if (!d) {
                fail = -1;
            } else {
                d[0] = (double)sensor; d[1] = (double)kind; d[2] = (double)j; d[3] = c;
                d[4] = (double)r;
                memcpy(d + 5, PyArray_DATA(Z), sizeof(double) * (size_t)r);
                memcpy(d + 5 + r, K, sizeof(double) * (size_t)(n * r));
                if (kind != 1)
                    memcpy(d + 5 + r + n * r, PyArray_DATA(H), sizeof(double) * (size_t)(r * n));
            }
        }
        Py_XDECREF(H); Py_XDECREF(R); Py_XDECREF(Z);
        if (fail) return fail;
    }
    return 0;
}

/* (x+, P+, stages + the new ones' records) for xo, Po updated by packets[start:]
   (apply_packets); stages: bytes. xo and Po are the result's arrays (their data written in
   place); on any failure released. None: handed back. */
static PyObject *finish_update(PyObject *xo, PyObject *Po, npy_intp n, PyObject *packets,
                               PyObject *rows, Py_ssize_t start, PyObject *stages) {
    PyObject *res = NULL, *all = NULL;
    Records rec;
    records_init(&rec);
    int got = apply_packets(PyArray_DATA((PyArrayObject *)xo), PyArray_DATA((PyArrayObject *)Po),
                            n, packets, rows, start, PyList_GET_SIZE(packets), &rec);
    if (got < 0) goto done;
    if (got > 0) { res = Py_NewRef(Py_None); goto done; }
    Py_ssize_t old = PyBytes_GET_SIZE(stages);
    all = PyBytes_FromStringAndSize(NULL, old + (Py_ssize_t)sizeof(double) * rec.len);
    if (!all) goto done;
    char *to = PyBytes_AS_STRING(all);
    if (old) memcpy(to, PyBytes_AS_STRING(stages), (size_t)old);
    memcpy(to + old, rec.d, sizeof(double) * (size_t)rec.len);
    res = PyTuple_New(3);
    if (!res) goto done;
    PyTuple_SET_ITEM(res, 0, xo);
    PyTuple_SET_ITEM(res, 1, Po);
    PyTuple_SET_ITEM(res, 2, all);
    xo = Po = all = NULL;  /* the result holds them */
done:
    records_free(&rec);
    Py_XDECREF(all); Py_XDECREF(xo); Py_XDECREF(Po);
    return res;
}

/* The next record of stages d[0..nd) at *at for a state of n values: its kind, j,
   c, r and pointers to its z, K and H (NULL for kind 1); advances *at. -1 with a ValueError
   if the bytes are not such records. */
static int next_record(const double *d, Py_ssize_t nd, Py_ssize_t *at, npy_intp n, long *kind,
                       long *j, double *c, npy_intp *r, const double **z, const double **K,
                       const double **H, Py_ssize_t *sensor) {
    Py_ssize_t i = *at;
    if (nd - i < 5) goto bad;
    *sensor = (Py_ssize_t)d[i];
    *kind = (long)d[i + 1];
    *j = (long)d[i + 2];
    *c = d[i + 3];
    *r = (npy_intp)d[i + 4];
    if (*kind < 1 || *kind > 3 || *r < 1 || *r > MAXR || (*kind != 3 && *r != 1)
        || (*kind == 1 && (*j < 0 || *j >= n)))
        goto bad;
    Py_ssize_t len = record_len(*kind, n, *r);
    if (nd - i < len) goto bad;
    *z = d + i + 5;
    *K = *z + *r;
    *H = *kind == 1 ? NULL : *K + n * *r;
    *at = i + len;
    return 0;
bad:
    PyErr_SetString(PyExc_ValueError, "_kalman: stages that do not fit this state");
    return -1;
}

/* The float64 values of stages (a bytes object) and their count; NULL with a ValueError if
   the bytes hold a partial value. */
static const double *packed_values(PyObject *stages, Py_ssize_t *nd) {
    Py_ssize_t size = PyBytes_GET_SIZE(stages);
    if (size % (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "_kalman: stages of a partial value");
        return NULL;
    }
    *nd = size / (Py_ssize_t)sizeof(double);
    return (const double *)PyBytes_AS_STRING(stages);
}

/* The mean recursion of stages (bytes) on xv (n,) in place (linear.LinearBackend._remean);
   -1 with an exception. */
static int remean_packed(double *xv, npy_intp n, PyObject *stages) {
    Py_ssize_t nd, at = 0, sensor;
    const double *d = packed_values(stages, &nd);
    if (!d) return -1;
    while (at < nd) {
        long kind, j;
        double c;
        npy_intp r;
        const double *z, *K, *H;
        if (next_record(d, nd, &at, n, &kind, &j, &c, &r, &z, &K, &H, &sensor)) return -1;
        if (kind == 3)
            mean_update(xv, n, H, K, z, r);
        else
            mean_row(xv, n, kind == 1 ? NULL : H, j, K, z[0], c);
    }
    return 0;
}

/* An array with a's values that the caller may write: a itself where the caller holds the
   only reference to it (an array just made here, float64 and C-contiguous), else a new
   copy. Steals a; NULL with an exception. */
static PyObject *writable(PyObject *a) {
    if (Py_REFCNT(a) == 1 && PyArray_CheckExact(a)) {
        PyArrayObject *arr = (PyArrayObject *)a;
        if (PyArray_TYPE(arr) == NPY_DOUBLE && PyArray_ISCARRAY(arr) && PyArray_ISNOTSWAPPED(arr))
            return a;
    }
    PyArrayObject *c = as_f64(a);
    Py_DECREF(a);
    if (!c) return NULL;
    PyObject *copy = PyArray_NewCopy(c, NPY_CORDER);
    Py_DECREF(c);
    return copy;
}

/* A new state of type T (a tuple subclass of 6 fields: linear.Gaussian) (x, P, src, m,
   sensors, stages). Steals x and P; src, sensors and stages borrowed. NULL with an
   exception (x and P then released). */
static PyObject *new_gaussian(PyTypeObject *T, PyObject *x, PyObject *P, PyObject *src,
                              Py_ssize_t m, PyObject *sensors, PyObject *stages) {
    PyObject *mo = PyLong_FromSsize_t(m);
    PyObject *g = mo ? T->tp_alloc(T, 6) : NULL;
    if (!g) {
        Py_XDECREF(mo); Py_DECREF(x); Py_DECREF(P);
        return NULL;
    }
    PyTuple_SET_ITEM(g, 0, x);
    PyTuple_SET_ITEM(g, 1, P);
    PyTuple_SET_ITEM(g, 2, Py_NewRef(src));
    PyTuple_SET_ITEM(g, 3, mo);
    PyTuple_SET_ITEM(g, 4, Py_NewRef(sensors));
    PyTuple_SET_ITEM(g, 5, Py_NewRef(stages));
    PyObject_GC_UnTrack(g);  /* see untrack_note */
    return g;
}

/* A packet's sensor index (its first field), borrowed; NULL with an exception. */
static PyObject *sensor_of(PyObject *packet) {
    if (!PyTuple_Check(packet) || PyTuple_GET_SIZE(packet) < 3) {
        PyErr_SetString(PyExc_TypeError, "_kalman: a packet is not (sensor, z, R)");
        return NULL;
    }
    return PyTuple_GET_ITEM(packet, 0);
}

/* The empty stages (b""), made once at import: a step without packets holds it. */
static PyObject *no_stages;

/* One step: a Gaussian, or None (not taken), or NULL with an exception.

   LinearBackend.advance's step for m <= the tables' M: the numpy form's steps in the same
   order (the jump, the reuse of ``old``, remean, the updates), the same formulas. Its
   docstring has them and the rule for reusing ``old`` (this step's previous result: same
   covariance object and m, its packets the first of ``packets``). None: a packet this
   kernel does not take (a nearly singular S, or sizes beyond the kernel's): the caller runs
   the numpy form for the whole step. gt: the state type (linear.Gaussian, a 6-field tuple
   subclass); jumps: tables.jumps (a tuple), entry m a tuple (A^m, ., Qs(m), .); G: the
   stacked input matrix or None; rows: linear._rows per sensor; state: (x, P, ...); u: the
   k_u inputs u(a), ..., u(a+m-1); packets: a list of Packet; old: a Gaussian or None. */
static PyObject *advance_impl(PyObject *gt, PyObject *jumps, PyObject *G, PyObject *rows,
                              PyObject *state, Py_ssize_t m, const double *u, npy_intp k_u,
                              PyObject *packets, PyObject *old) {
    if (!PyType_Check(gt) || !PyType_IsSubtype((PyTypeObject *)gt, &PyTuple_Type)
        || !PyTuple_Check(jumps) || !PyList_Check(packets) || !PyTuple_Check(state)
        || PyTuple_GET_SIZE(state) < 2
        || (old != Py_None && (!PyTuple_Check(old) || PyTuple_GET_SIZE(old) != 6
                               || !PyTuple_Check(PyTuple_GET_ITEM(old, 4))
                               || !PyBytes_Check(PyTuple_GET_ITEM(old, 5))))) {
        PyErr_SetString(PyExc_TypeError, "_kalman.advance: arguments of the wrong types");
        return NULL;
    }
    if (m < 0 || m >= PyTuple_GET_SIZE(jumps)) {
        PyErr_SetString(PyExc_ValueError, "_kalman.advance: m outside the tables");
        return NULL;
    }
    PyTypeObject *T = (PyTypeObject *)gt;
    PyObject *x = PyTuple_GET_ITEM(state, 0), *P = PyTuple_GET_ITEM(state, 1);
    PyObject *empty = PyTuple_New(0);  /* the () singleton */
    if (!empty) return NULL;
    Py_ssize_t npk = PyList_GET_SIZE(packets);
    PyObject *done = empty;
    int reuse = 0;
    if (old != Py_None && PyTuple_GET_ITEM(old, 2) == P) {
        Py_ssize_t om = PyLong_AsSsize_t(PyTuple_GET_ITEM(old, 3));
        if (om == -1 && PyErr_Occurred()) goto error;
        if (om == m) {
            done = PyTuple_GET_ITEM(old, 4);
            Py_ssize_t k = PyTuple_GET_SIZE(done);
            reuse = k == 0;
            if (k > 0 && k <= npk) {  /* old's packets are the first of these, in order */
                reuse = 1;
                for (Py_ssize_t i = 0; i < k && reuse; i++) {
                    PyObject *sn = sensor_of(PyList_GET_ITEM(packets, i));
                    if (!sn) goto error;
                    int eq = PyObject_RichCompareBool(sn, PyTuple_GET_ITEM(done, i), Py_EQ);
                    if (eq < 0) goto error;
                    reuse = eq;
                }
            }
            if (!reuse) done = empty;  /* old applied other packets first: from the prior */
        }
    }
    PyObject *xp, *Pp;  /* new references from here on */
    if (m == 0) {
        xp = Py_NewRef(x);
        Pp = Py_NewRef(P);
    } else {
        PyObject *jt = PyTuple_GET_ITEM(jumps, m);
        if (!PyTuple_Check(jt) || PyTuple_GET_SIZE(jt) < 3) {
            PyErr_SetString(PyExc_TypeError, "_kalman.advance: a jump is not (A, ., Qs, ...)");
            goto error;
        }
        PyObject *r = jump_impl(x, reuse ? Py_None : P, PyTuple_GET_ITEM(jt, 0),
                                PyTuple_GET_ITEM(jt, 2), G, u, k_u);
        if (!r) goto error;
        xp = Py_NewRef(PyTuple_GET_ITEM(r, 0));
        Pp = Py_NewRef(reuse ? P : PyTuple_GET_ITEM(r, 1));
        Py_DECREF(r);
    }
    PyObject *stages = no_stages;
    if (reuse) {  /* the covariance after old's packets is unchanged: their means only */
        stages = PyTuple_GET_ITEM(old, 5);
        if (PyBytes_GET_SIZE(stages)) {
            xp = writable(xp);  /* the jump's new array, or a copy of a shared one */
            if (!xp || remean_packed(PyArray_DATA((PyArrayObject *)xp),
                                     PyArray_SIZE((PyArrayObject *)xp), stages)) {
                Py_XDECREF(xp); Py_DECREF(Pp);
                goto error;
            }
        }
        Py_SETREF(Pp, Py_NewRef(PyTuple_GET_ITEM(old, 1)));
        if (PyTuple_GET_SIZE(done) == npk) {
            PyObject *g = new_gaussian(T, xp, Pp, P, m, done, stages);
            Py_DECREF(empty);
            return g;
        }
    }
    if (npk == 0) {
        PyObject *g = new_gaussian(T, xp, Pp, P, m, empty, no_stages);
        Py_DECREF(empty);
        return g;
    }
    /* the packets' sensor indices: old's tuple where it holds the same ones (a step the
       replay redoes with its packets unchanged: no new tuple to make and later free) */
    PyObject *sensors = NULL;
    if (old != Py_None && PyTuple_GET_SIZE(PyTuple_GET_ITEM(old, 4)) == npk) {
        PyObject *os = PyTuple_GET_ITEM(old, 4);
        int same = 1;
        for (Py_ssize_t i = 0; i < npk && same; i++) {
            PyObject *sn = sensor_of(PyList_GET_ITEM(packets, i));
            if (!sn) goto fail_sensors;
            same = PyObject_RichCompareBool(sn, PyTuple_GET_ITEM(os, i), Py_EQ);
            if (same < 0) goto fail_sensors;
        }
        if (same) sensors = Py_NewRef(os);
    }
    if (!sensors) {
        sensors = PyTuple_New(npk);
        if (!sensors) goto fail_sensors;
        for (Py_ssize_t i = 0; i < npk; i++) {
            PyObject *sn = sensor_of(PyList_GET_ITEM(packets, i));
            if (!sn) goto fail_sensors;
            PyTuple_SET_ITEM(sensors, i, Py_NewRef(sn));
        }
        PyObject_GC_UnTrack(sensors);  /* see untrack_note */
    }
    {
        /* the jump's (or remean's) new arrays are updated in place; x or P shared with
           another state (no jump, or old's covariance) is copied first */
        PyObject *xo = writable(xp), *Po = xo ? writable(Pp) : NULL;
        if (!xo) Py_DECREF(Pp);
        PyObject *g = NULL;
        if (xo && Po) {
            npy_intp n = PyArray_SIZE((PyArrayObject *)xo);
            if (n > MAXN) {
                Py_DECREF(xo); Py_DECREF(Po);
                g = Py_NewRef(Py_None);
            } else if (check_size((PyArrayObject *)Po, n * n, "P")) {
                Py_DECREF(xo); Py_DECREF(Po);
            } else {
                PyObject *got = finish_update(xo, Po, n, packets, rows, PyTuple_GET_SIZE(done),
                                              stages);
                if (got == Py_None) {
                    g = got;  /* not taken: the caller runs the numpy form */
                } else if (got) {
                    g = new_gaussian(T, Py_NewRef(PyTuple_GET_ITEM(got, 0)),
                                     Py_NewRef(PyTuple_GET_ITEM(got, 1)), P, m, sensors,
                                     PyTuple_GET_ITEM(got, 2));
                    Py_DECREF(got);
                }
            }
        } else {
            Py_XDECREF(xo);
        }
        Py_DECREF(sensors);
        Py_DECREF(empty);
        return g;
    }
fail_sensors:
    Py_XDECREF(sensors); Py_DECREF(xp); Py_DECREF(Pp);
error:
    Py_DECREF(empty);
    return NULL;
}

static PyObject *advance(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (check_nargs("advance", nargs, 9)) return NULL;
    Py_ssize_t m = PyLong_AsSsize_t(args[5]);
    if (m == -1 && PyErr_Occurred()) return NULL;
    if (args[2] == Py_None)
        return advance_impl(args[0], args[1], Py_None, args[3], args[4], m, NULL, 0, args[7],
                            args[8]);
    PyArrayObject *U = as_f64(args[6]);
    if (!U) return NULL;
    PyObject *g = advance_impl(args[0], args[1], args[2], args[3], args[4], m,
                               (const double *)PyArray_DATA(U), PyArray_SIZE(U), args[7],
                               args[8]);
    Py_DECREF(U);
    return g;
}

/* ---- steps with events inside them (LinearBackend.split_step's C form) ------------------

   split(Gaussian, jumps, G, rows, state, m, U, packets, cuts, coef, period, mean_only) ->
   Gaussian, or None (not taken: the numpy form then runs); mean_only (no packets): the
   mean walked alone, P the state's

   The walk of LinearBackend.split_step: from x(a), whole steps by the tables (as the jump
   above), the intervals between events by the model's Taylor polynomials (coef (K+1,
   2 n^2 + n nu): row j multiplies tau^(j+1); A = I + its first n^2 columns, B the next
   n nu, Q the last n^2, made exactly symmetric), each packet's Kalman update at its own
   time (apply_packets), the input before a cut's offset its u_before:

       x(t + tau) = A(tau) x + B(tau) u,   P(t + tau) = A(tau) P A(tau)^T + Q(tau)

   U (rows, nu) the span's inputs; packets sorted by offset (field 3, s); cuts a list of
   (row, offset, u_before (nu,)) rising. The result is at row m + 1 if a packet lies after
   its step's start, else at row m; it records no parent (src None, m 0, no stages): never
   reused. None for a packet the update does not take (as advance). */

#define MAXCUT 64

/* A command taking effect inside row ``row`` of a span at ``d`` s; before it: ``u``. */
typedef struct { Py_ssize_t row; double d; const double *u; } CutAt;

static void taylor_at(const double *coef, npy_intp K1, npy_intp n, npy_intp nu, double tau,
                      double *A, double *B, double *Q) {
    npy_intp nn = n * n, nb = n * nu, w = 2 * nn + nb;
    for (npy_intp c = 0; c < nn; c++) A[c] = Q[c] = 0.0;
    for (npy_intp c = 0; c < nb; c++) B[c] = 0.0;
    double p = 1.0;
    for (npy_intp j = 0; j < K1; j++) {  /* sum_j tau^(j+1) coef[j] */
        p *= tau;
        const double *row = coef + j * w;
        for (npy_intp c = 0; c < nn; c++) A[c] += p * row[c];
        for (npy_intp c = 0; c < nb; c++) B[c] += p * row[nn + c];
        for (npy_intp c = 0; c < nn; c++) Q[c] += p * row[nn + nb + c];
    }
    for (npy_intp i = 0; i < n; i++) A[i * n + i] += 1.0;
    for (npy_intp i = 0; i < n; i++)  /* exactly symmetric: (Q + Q^T) / 2 */
        for (npy_intp j = i + 1; j < n; j++)
            Q[i * n + j] = Q[j * n + i] = 0.5 * (Q[i * n + j] + Q[j * n + i]);
}

/* x <- A x + (Bu: NULL, or added), P <- A P A^T + Q (upper triangle, mirrored) in place
   (P NULL: the mean alone). */
static void propagate_raw(double *x, double *P, npy_intp n, const double *A, const double *Q,
                          const double *Bu) {
    double t[MAXN * MAXN], xn[MAXN];
    for (npy_intp i = 0; i < n; i++) {
        double acc = 0.0;
        for (npy_intp k = 0; k < n; k++) acc += A[i * n + k] * x[k];
        xn[i] = acc + (Bu ? Bu[i] : 0.0);
    }
    memcpy(x, xn, sizeof(double) * (size_t)n);
    if (!P) return;
    for (npy_intp i = 0; i < n; i++)
        for (npy_intp j = 0; j < n; j++) {
            double acc = 0.0;
            for (npy_intp k = 0; k < n; k++) acc += A[i * n + k] * P[k * n + j];
            t[i * n + j] = acc;
        }
    for (npy_intp i = 0; i < n; i++)
        for (npy_intp j = i; j < n; j++) {
            double acc = 0.0;
            for (npy_intp k = 0; k < n; k++) acc += t[i * n + k] * A[j * n + k];
            P[i * n + j] = P[j * n + i] = acc + Q[i * n + j];
        }
}

/* x, P (NULL: the mean alone) over tau s from f s into row r by the Taylor polynomials, the
   input u_r held (a cut's u_before in row r before its offset). */
static void segment_raw(double *x, double *P, npy_intp n, npy_intp nu, const double *coef,
                        npy_intp K1, double tau, const double *u_r, const CutAt *cuts,
                        Py_ssize_t ncut, Py_ssize_t r, double f) {
    double A[MAXN * MAXN], B[MAXN * MAXR], Q[MAXN * MAXN], Bu[MAXN];
    const double *uu = u_r;
    for (Py_ssize_t c = 0; c < ncut; c++)
        if (cuts[c].row == r && f < cuts[c].d) uu = cuts[c].u;
    taylor_at(coef, K1, n, nu, tau, A, B, Q);
    for (npy_intp i = 0; i < n; i++) {
        double acc = 0.0;
        for (npy_intp l = 0; l < nu; l++) acc += B[i * nu + l] * uu[l];
        Bu[i] = acc;
    }
    propagate_raw(x, P, n, A, Q, nu ? Bu : NULL);
}

/* The walk itself on a state (x, P): a new Gaussian, None (not taken), or NULL with an
   exception. u: the span's inputs, urows rows of nu; cuts[ncut] rising; G the tables'
   stacked input matrix (NULL without inputs); coef (K1, 2 n^2 + n nu). */
static PyObject *split_impl(PyObject *gt, PyObject *jumps, PyArrayObject *G, PyObject *rows,
                            PyObject *state, Py_ssize_t m, const double *u, npy_intp urows,
                            npy_intp nu, PyObject *packets, const CutAt *cuts, Py_ssize_t ncut,
                            const double *coef, npy_intp K1, npy_intp coef_w, double period,
                            int mean_only) {
    if (!PyType_Check(gt) || !PyTuple_Check(jumps) || !PyList_Check(packets)
        || !PyTuple_Check(state) || PyTuple_GET_SIZE(state) < 2 || m < 0
        || m + 1 >= PyTuple_GET_SIZE(jumps)) {
        PyErr_SetString(PyExc_TypeError, "_kalman.split: arguments of the wrong types");
        return NULL;
    }
    PyArrayObject *X = as_f64(PyTuple_GET_ITEM(state, 0)), *PP = as_f64(PyTuple_GET_ITEM(state, 1));
    PyObject *res = NULL, *empty = NULL;
    Records rec;
    records_init(&rec);
    if (!X || !PP) goto done;
    npy_intp n = PyArray_SIZE(X);
    if (mean_only && PyList_GET_SIZE(packets)) {
        PyErr_SetString(PyExc_ValueError, "_kalman.split: the mean alone only without packets");
        goto done;
    }
    if (n > MAXN || nu > MAXR || check_size(PP, n * n, "P") || coef_w != 2 * n * n + n * nu) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_ValueError, "_kalman.split: sizes that do not fit");
        goto done;
    }
    double x[MAXN], P[MAXN * MAXN];
    memcpy(x, PyArray_DATA(X), sizeof(double) * (size_t)n);
    memcpy(P, PyArray_DATA(PP), sizeof(double) * (size_t)(n * n));
    {
        Py_ssize_t npk = PyList_GET_SIZE(packets);
        double last = 0.0;
        if (npk) {
            PyObject *pk = PyList_GET_ITEM(packets, npk - 1);
            if (!PyTuple_Check(pk) || PyTuple_GET_SIZE(pk) < 4) {
                PyErr_SetString(PyExc_TypeError, "_kalman.split: a packet has no offset");
                goto done;
            }
            last = PyFloat_AsDouble(PyTuple_GET_ITEM(pk, 3));
            if (last == -1.0 && PyErr_Occurred()) goto done;
        }
        Py_ssize_t end = last > 0.0 ? m + 1 : m;
        if (urows < end) {
            PyErr_SetString(PyExc_ValueError, "_kalman.split: U has too few rows");
            goto done;
        }
        for (Py_ssize_t c = 0; c < ncut; c++)
            if (cuts[c].row < 0 || cuts[c].row >= end) {
                PyErr_SetString(PyExc_ValueError, "_kalman.split: a cut outside the span");
                goto done;
            }
        Py_ssize_t r = 0, ci = 0, pi = 0;
        double f = 0.0;
        double Bu[MAXN];
        for (;;) {
            /* the next event: a cut (first at a tie), a packet, or the end */
            Py_ssize_t row;
            double off;
            int what;
            double poff = 0.0;
            if (pi < npk) {
                PyObject *pk = PyList_GET_ITEM(packets, pi);
                if (!PyTuple_Check(pk) || PyTuple_GET_SIZE(pk) < 4) {
                    PyErr_SetString(PyExc_TypeError, "_kalman.split: a packet has no offset");
                    goto done;
                }
                poff = PyFloat_AsDouble(PyTuple_GET_ITEM(pk, 3));
                if (poff == -1.0 && PyErr_Occurred()) goto done;
            }
            if (ci < ncut && (pi >= npk || cuts[ci].row < m
                              || (cuts[ci].row == m && cuts[ci].d <= poff))) {
                row = cuts[ci].row; off = cuts[ci].d; what = 0;
            } else if (pi < npk) {
                row = m; off = poff; what = 1;
            } else {
                row = end; off = 0.0; what = 2;
            }
            if (row > r) {
                if (f > 0.0) {  /* the rest of row r */
                    segment_raw(x, mean_only ? NULL : P, n, nu, coef, K1, period - f, u + r * nu,
                                cuts, ncut, r, f);
                    r += 1;
                    f = 0.0;
                }
                if (row > r) {  /* whole steps: the tables' jump of row - r */
                    Py_ssize_t k = row - r;
                    PyObject *jt = PyTuple_GET_ITEM(jumps, k);
                    if (!PyTuple_Check(jt) || PyTuple_GET_SIZE(jt) < 3) {
                        PyErr_SetString(PyExc_TypeError, "_kalman.split: a jump is not (A, ., Qs, ...)");
                        goto done;
                    }
                    PyArrayObject *Aj = as_f64(PyTuple_GET_ITEM(jt, 0));
                    PyArrayObject *Qj = as_f64(PyTuple_GET_ITEM(jt, 2));
                    int bad = !Aj || !Qj || check_size(Aj, n * n, "A") || check_size(Qj, n * n, "Qs");
                    if (!bad && G && nu) {
                        npy_intp kk = k * nu;
                        npy_intp cols = PyArray_NDIM(G) == 2 ? PyArray_DIM(G, 1) : -1;
                        if (PyArray_NDIM(G) != 2 || PyArray_DIM(G, 0) != n || cols < kk) {
                            PyErr_SetString(PyExc_ValueError, "_kalman: G is not (n, >= U.size)");
                            bad = 1;
                        } else {
                            const double *g = (const double *)PyArray_DATA(G) + (cols - kk);
                            const double *uu = u + r * nu;
                            for (npy_intp i = 0; i < n; i++) {
                                double acc = 0.0;
                                for (npy_intp l = 0; l < kk; l++) acc += g[i * cols + l] * uu[l];
                                Bu[i] = acc;
                            }
                        }
                    }
                    if (!bad)
                        propagate_raw(x, mean_only ? NULL : P, n, PyArray_DATA(Aj),
                                      PyArray_DATA(Qj), G && nu ? Bu : NULL);
                    Py_XDECREF(Aj); Py_XDECREF(Qj);
                    if (bad) goto done;
                    r = row;
                }
            }
            if (off > f) {
                segment_raw(x, mean_only ? NULL : P, n, nu, coef, K1, off - f, u + r * nu, cuts,
                            ncut, r, f);
                f = off;
            }
            if (what == 0) {
                ci++;
            } else if (what == 1) {
                rec.len = 0;
                int got = apply_packets(x, P, n, packets, rows, pi, pi + 1, &rec);
                if (got < 0) goto done;
                if (got > 0) { res = Py_NewRef(Py_None); goto done; }
                pi++;
            } else {
                break;
            }
        }
    }
    {
        double *xd, *pd;
        PyObject *xo = new_vec(n, &xd), *Po = xo ? new_mat(n, n, &pd) : NULL;
        empty = PyTuple_New(0);
        if (!xo || !Po || !empty) { Py_XDECREF(xo); Py_XDECREF(Po); goto done; }
        memcpy(xd, x, sizeof(double) * (size_t)n);
        memcpy(pd, P, sizeof(double) * (size_t)(n * n));
        res = new_gaussian((PyTypeObject *)gt, xo, Po, Py_None, 0, empty, no_stages);
    }
done:
    records_free(&rec);
    Py_XDECREF(X); Py_XDECREF(PP); Py_XDECREF(empty);
    return res;
}

/* replay(Gaussian, jumps, G, rows, state, a, steps, buf, off, packets, chk, noreuse,
          cut_steps, cut_offsets, u_before, origin, coef, period) -> (state, a, done)

   ReplayEstimator._replay's loop over the measured steps ``steps`` (a list of ints, rising,
   after ``a``) for a LinearBackend with the kernel, one step each as that loop makes it,
   without a Python call, a slice of the input buffer and two dict operations per step:

       for s in steps:
           e = s + 1 if packets[s] end off the grid else s
           cuts = the commands taking effect inside steps a .. e - 1
           old = chk.get(s) if noreuse is None or s < noreuse else None
           state = advance(state, s - a, buf[a - off : e - off], packets[s], old, cuts)
           chk[s] = state;  a = e

   (a grid step without cuts: advance_impl, with the reuse of ``old``; otherwise the split
   walk, split_impl). buf (rows, nu) float64 C-contiguous (InputBuffer's; u(t) = buf[t -
   off]); packets and chk dicts from step to a list of packets / a Gaussian; cut_steps the
   input buffer's sorted command steps with an offset, cut_offsets step -> offset (s),
   u_before u(origin - 1); coef the model's Taylor coefficients (None: split steps are not
   taken here), period the step (s). Stops before a step it does not take (a jump longer
   than the tables, a step advance() or split hands back, a split step without coef):
   ``done`` steps were made and stored, ``state`` is the last, ``a`` its end step; the
   caller goes on from there with LinearBackend.advance. Same calls in the same order: the
   same bits. */
static PyObject *replay(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (check_nargs("replay", nargs, 18)) return NULL;
    PyObject *gt = args[0], *jumps = args[1], *G = args[2], *rows = args[3];
    PyObject *steps = args[6], *ob = args[7], *packets = args[9], *chk = args[10];
    PyObject *nr = args[11], *cut_steps = args[12], *cut_offsets = args[13];
    PyObject *ocoef = args[16];
    Py_ssize_t a = PyLong_AsSsize_t(args[5]), off = PyLong_AsSsize_t(args[8]);
    Py_ssize_t origin = PyLong_AsSsize_t(args[15]);
    double period = PyFloat_AsDouble(args[17]);
    if ((a == -1 || off == -1 || origin == -1 || period == -1.0) && PyErr_Occurred())
        return NULL;
    Py_ssize_t noreuse = 0;
    if (nr != Py_None) {
        noreuse = PyLong_AsSsize_t(nr);
        if (noreuse == -1 && PyErr_Occurred()) return NULL;
    }
    if (!PyTuple_Check(jumps) || !PyList_Check(steps) || !PyDict_Check(packets)
        || !PyDict_Check(chk) || !PyArray_CheckExact(ob) || !PyList_Check(cut_steps)
        || !PyDict_Check(cut_offsets)) {
        PyErr_SetString(PyExc_TypeError, "_kalman.replay: arguments of the wrong types");
        return NULL;
    }
    PyArrayObject *buf = (PyArrayObject *)ob;
    if (PyArray_TYPE(buf) != NPY_DOUBLE || !PyArray_ISCARRAY_RO(buf)
        || !PyArray_ISNOTSWAPPED(buf) || PyArray_NDIM(buf) != 2) {
        PyErr_SetString(PyExc_TypeError, "_kalman.replay: buf is not a C-contiguous float64 "
                                         "(rows, nu) array");
        return NULL;
    }
    npy_intp nbuf = PyArray_DIM(buf, 0), nu = PyArray_DIM(buf, 1);
    const double *bd = (const double *)PyArray_DATA(buf);
    Py_ssize_t ntab = PyTuple_GET_SIZE(jumps);
    PyArrayObject *ub = as_f64(args[14]), *coef = NULL, *Ga = NULL;
    if (!ub) return NULL;
    if (check_size(ub, nu, "u_before")) { Py_DECREF(ub); return NULL; }
    if (ocoef != Py_None && !(coef = as_f64(ocoef))) { Py_DECREF(ub); return NULL; }
    if (coef && PyArray_NDIM(coef) != 2) {
        PyErr_SetString(PyExc_ValueError, "_kalman.replay: coef is not a matrix");
        Py_DECREF(ub); Py_DECREF(coef);
        return NULL;
    }
    if (G != Py_None && !(Ga = as_f64(G))) { Py_DECREF(ub); Py_XDECREF(coef); return NULL; }
    Py_ssize_t ncs = PyList_GET_SIZE(cut_steps);
    PyObject *state = Py_NewRef(args[4]);
    Py_ssize_t done = 0, nsteps = PyList_GET_SIZE(steps);
    for (; done < nsteps; done++) {
        Py_ssize_t s = PyLong_AsSsize_t(PyList_GET_ITEM(steps, done));
        if (s == -1 && PyErr_Occurred()) goto error;
        Py_ssize_t m = s - a;
        if (m < 0 || m >= ntab) break;  /* the numpy form: its error, or table-sized jumps */
        PyObject *key = PyList_GET_ITEM(steps, done);
        PyObject *pk = PyDict_GetItemWithError(packets, key);  /* borrowed */
        if (!pk) {
            if (!PyErr_Occurred()) PyErr_SetObject(PyExc_KeyError, key);
            goto error;
        }
        if (!PyList_Check(pk)) {
            PyErr_SetString(PyExc_TypeError, "_kalman.replay: packets of a step are not a list");
            goto error;
        }
        Py_ssize_t npk = PyList_GET_SIZE(pk), e = s;
        if (npk) {
            PyObject *lp = PyList_GET_ITEM(pk, npk - 1);
            if (PyTuple_Check(lp) && PyTuple_GET_SIZE(lp) >= 4) {
                double lo = PyFloat_AsDouble(PyTuple_GET_ITEM(lp, 3));
                if (lo == -1.0 && PyErr_Occurred()) goto error;
                if (lo > 0.0) e = s + 1;
            }
        }
        if (a - off < 0 || e - off > nbuf || (e - off) * nu > PyArray_SIZE(buf)) {
            PyErr_SetString(PyExc_IndexError, "_kalman.replay: steps outside the input buffer");
            goto error;
        }
        /* the cuts inside steps a .. e - 1 */
        CutAt cuts[MAXCUT];
        Py_ssize_t ncut = 0;
        int too_many = 0;
        for (Py_ssize_t c = 0; c < ncs; c++) {
            Py_ssize_t j = PyLong_AsSsize_t(PyList_GET_ITEM(cut_steps, c));
            if (j == -1 && PyErr_Occurred()) goto error;
            if (j < a) continue;
            if (j >= e) break;
            if (ncut == MAXCUT) { too_many = 1; break; }
            PyObject *dv = PyDict_GetItemWithError(cut_offsets, PyList_GET_ITEM(cut_steps, c));
            if (!dv) {
                if (!PyErr_Occurred()) PyErr_SetString(PyExc_KeyError, "_kalman.replay: a cut step without its offset");
                goto error;
            }
            double d = PyFloat_AsDouble(dv);
            if (d == -1.0 && PyErr_Occurred()) goto error;
            if (j - 1 >= origin && j - 1 - off < 0) {
                PyErr_SetString(PyExc_IndexError, "_kalman.replay: a cut outside the input buffer");
                goto error;
            }
            cuts[ncut].row = j - a;
            cuts[ncut].d = d;
            cuts[ncut].u = j - 1 >= origin ? bd + (j - 1 - off) * nu
                                           : (const double *)PyArray_DATA(ub);
            ncut++;
        }
        if (too_many) break;
        PyObject *old = Py_None;
        PyObject *g;
        if (e == s && ncut == 0) {
            if (nr == Py_None || s < noreuse) {
                old = PyDict_GetItemWithError(chk, key);  /* borrowed; chk[s] replaced below */
                if (!old) {
                    if (PyErr_Occurred()) goto error;
                    old = Py_None;
                }
            }
            Py_INCREF(old);  /* held across chk[s] = g, which drops the dict's reference */
            g = advance_impl(gt, jumps, G, rows, state, m, bd + (a - off) * nu, m * nu, pk, old);
            Py_DECREF(old);
        } else {
            /* no Taylor polynomials (Van Loan: the numpy form's), or a jump past the tables */
            if (!coef || m + 1 >= ntab) break;
            g = split_impl(gt, jumps, Ga, rows, state, m, bd + (a - off) * nu, e - a, nu, pk,
                           cuts, ncut, PyArray_DATA(coef), PyArray_DIM(coef, 0),
                           PyArray_DIM(coef, 1), period, 0);
        }
        if (!g) goto error;
        if (g == Py_None) {  /* not taken: the numpy form makes this step */
            Py_DECREF(g);
            break;
        }
        if (PyDict_SetItem(chk, key, g) < 0) { Py_DECREF(g); goto error; }
        Py_SETREF(state, g);
        a = e;
    }
    Py_DECREF(ub); Py_XDECREF(coef); Py_XDECREF(Ga);
    {
        PyObject *ao = PyLong_FromSsize_t(a), *dn = PyLong_FromSsize_t(done);
        PyObject *res = ao && dn ? PyTuple_New(3) : NULL;
        if (!res) { Py_XDECREF(ao); Py_XDECREF(dn); Py_DECREF(state); return NULL; }
        PyTuple_SET_ITEM(res, 0, state);
        PyTuple_SET_ITEM(res, 1, ao);
        PyTuple_SET_ITEM(res, 2, dn);
        return res;
    }
error:
    Py_DECREF(ub); Py_XDECREF(coef); Py_XDECREF(Ga);
    Py_DECREF(state);
    return NULL;
}

static PyObject *split(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (check_nargs("split", nargs, 12)) return NULL;
    int mean_only = PyObject_IsTrue(args[11]);
    if (mean_only < 0) return NULL;
    PyObject *cutl = args[8];
    Py_ssize_t m = PyLong_AsSsize_t(args[5]);
    double period = PyFloat_AsDouble(args[10]);
    if ((m == -1 || period == -1.0) && PyErr_Occurred()) return NULL;
    if (!PyList_Check(cutl)) {
        PyErr_SetString(PyExc_TypeError, "_kalman.split: cuts is not a list");
        return NULL;
    }
    Py_ssize_t ncut = PyList_GET_SIZE(cutl);
    if (ncut > MAXCUT) Py_RETURN_NONE;
    PyArrayObject *U = as_f64(args[6]), *C = as_f64(args[9]), *G = NULL;
    PyArrayObject *held[MAXCUT];
    CutAt cuts[MAXCUT];
    Py_ssize_t nheld = 0;
    PyObject *res = NULL;
    if (!U || !C) goto done;
    if (args[2] != Py_None && !(G = as_f64(args[2]))) goto done;
    npy_intp nu = PyArray_NDIM(U) == 2 ? PyArray_DIM(U, 1) : 0;
    npy_intp urows = PyArray_NDIM(U) == 2 ? PyArray_DIM(U, 0) : 0;
    if (PyArray_NDIM(C) != 2) {
        PyErr_SetString(PyExc_ValueError, "_kalman.split: coef is not a matrix");
        goto done;
    }
    for (Py_ssize_t c = 0; c < ncut; c++) {
        PyObject *ct = PyList_GET_ITEM(cutl, c);
        if (!PyTuple_Check(ct) || PyTuple_GET_SIZE(ct) != 3) {
            PyErr_SetString(PyExc_TypeError, "_kalman.split: a cut is not (row, offset, u)");
            goto done;
        }
        cuts[c].row = PyLong_AsSsize_t(PyTuple_GET_ITEM(ct, 0));
        cuts[c].d = PyFloat_AsDouble(PyTuple_GET_ITEM(ct, 1));
        if (PyErr_Occurred()) goto done;
        if (!(held[nheld] = as_f64(PyTuple_GET_ITEM(ct, 2)))) goto done;
        nheld++;
        if (check_size(held[nheld - 1], nu, "u_before")) goto done;
        cuts[c].u = PyArray_DATA(held[nheld - 1]);
    }
    res = split_impl(args[0], args[1], G, args[3], args[4], m, PyArray_DATA(U), urows, nu,
                     args[7], cuts, ncut, PyArray_DATA(C), PyArray_DIM(C, 0), PyArray_DIM(C, 1),
                     period, mean_only);
done:
    for (Py_ssize_t c = 0; c < nheld; c++) Py_DECREF(held[c]);
    Py_XDECREF(U); Py_XDECREF(C); Py_XDECREF(G);
    return res;
}

/* freeze(a, ...) -> None: each numpy array made read-only, as a.setflags(write=False) does
   without parsing keyword arguments. TypeError, with nothing changed, if an argument is not
   a numpy array. */
static PyObject *freeze(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    for (Py_ssize_t i = 0; i < nargs; i++)
        if (!PyArray_Check(args[i])) {
            PyErr_SetString(PyExc_TypeError, "_kalman.freeze: arguments must be numpy arrays");
            return NULL;
        }
    for (Py_ssize_t i = 0; i < nargs; i++)
        PyArray_CLEARFLAGS((PyArrayObject *)args[i], NPY_ARRAY_WRITEABLE);
    Py_RETURN_NONE;
}

/* fill(buf, start, end, u) -> bool: rows [start, end) of buf (rows, nu) set to u (nu,), as
   numpy's buf[start:end] = u does for these (inputs.InputBuffer.set), without numpy's
   general indexing. False, with nothing written, for anything else (buf not a
   writeable C-contiguous float64 matrix, u not float64 (nu,), rows out of range): the caller
   then assigns with numpy, the reference. */
static PyObject *fill(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (check_nargs("fill", nargs, 4)) return NULL;
    PyObject *ob = args[0], *ou = args[3];
    Py_ssize_t start = PyLong_AsSsize_t(args[1]), end = PyLong_AsSsize_t(args[2]);
    if ((start == -1 || end == -1) && PyErr_Occurred()) return NULL;
    if (!PyArray_CheckExact(ob) || !PyArray_CheckExact(ou)) Py_RETURN_FALSE;
    PyArrayObject *b = (PyArrayObject *)ob, *u = (PyArrayObject *)ou;
    if (PyArray_TYPE(b) != NPY_DOUBLE || PyArray_NDIM(b) != 2 || !PyArray_ISCARRAY(b)
        || !PyArray_ISNOTSWAPPED(b) || PyArray_TYPE(u) != NPY_DOUBLE || PyArray_NDIM(u) != 1
        || !PyArray_ISCARRAY_RO(u) || !PyArray_ISNOTSWAPPED(u))
        Py_RETURN_FALSE;
    npy_intp rows = PyArray_DIM(b, 0), nu = PyArray_DIM(b, 1);
    if (PyArray_DIM(u, 0) != nu || start < 0 || start > end || end > rows) Py_RETURN_FALSE;
    double *d = (double *)PyArray_DATA(b) + start * nu;
    const double *v = PyArray_DATA(u);
    for (npy_intp i = start; i < end; i++, d += nu)  /* a few values a row: no memcpy call */
        for (npy_intp j = 0; j < nu; j++) d[j] = v[j];
    Py_RETURN_TRUE;
}

/* untrack(obj) -> obj: obj and the tuples, lists and dicts it holds, at any depth, leave
   the cyclic garbage collector, each where everything it references is then untracked or
   atomic (numbers, strings, numpy arrays, types). For states kept unchanged for seconds, as
   a session's snapshot (an EstimatorState, replaced every second), which would otherwise
   fill the collector's young generation (see untrack_note). Only for objects nobody changes
   afterwards: a list or an instance untracked here is not tracked again when a container is
   put in it (a dict is). Recursion
   below the root goes only into exact tuples, lists and dicts, at most 16 deep. */
static int holds_tracked(PyObject *ref, void *arg) {
    (void)arg;
    return PyObject_IS_GC(ref) && PyObject_GC_IsTracked(ref) && !PyType_Check(ref);
}

static void untrack_tree(PyObject *o, int depth, int root);

static int untrack_child(PyObject *ref, void *arg) {
    untrack_tree(ref, *(int *)arg, 0);
    return 0;
}

static void untrack_tree(PyObject *o, int depth, int root) {
    if (!PyObject_IS_GC(o) || !PyObject_GC_IsTracked(o) || PyType_Check(o)) return;
    if (!root && !PyTuple_CheckExact(o) && !PyList_CheckExact(o) && !PyDict_CheckExact(o))
        return;
    traverseproc traverse = Py_TYPE(o)->tp_traverse;
    if (!traverse) return;
    if (depth < 16) {
        int below = depth + 1;
        traverse(o, untrack_child, &below);
    }
    if (!traverse(o, holds_tracked, NULL)) PyObject_GC_UnTrack(o);
}

static PyObject *untrack(PyObject *self, PyObject *obj) {
    (void)self;
    untrack_tree(obj, 0, 1);
    return Py_NewRef(obj);
}

static PyMethodDef methods[] = {
    {"advance", (PyCFunction)(void (*)(void))advance, METH_FASTCALL,
     "advance(Gaussian, jumps, G, rows, state, m, U, packets, old) -> Gaussian, or None (not "
     "taken: the numpy form then runs): LinearBackend.advance's step for m <= M."},
    {"replay", (PyCFunction)(void (*)(void))replay, METH_FASTCALL,
     "replay(Gaussian, jumps, G, rows, state, a, steps, buf, off, packets, chk, noreuse, "
     "cut_steps, cut_offsets, u_before, origin, coef, period) -> (state, a, done): "
     "ReplayEstimator._replay's loop of advance calls, in one call."},
    {"split", (PyCFunction)(void (*)(void))split, METH_FASTCALL,
     "split(Gaussian, jumps, G, rows, state, m, U, packets, cuts, coef, period, mean_only) -> "
     "Gaussian, or None (not taken): LinearBackend.split_step's walk of a step with events "
     "inside it (mean_only, no packets: x walked, P the state's)."},
    {"freeze", (PyCFunction)(void (*)(void))freeze, METH_FASTCALL,
     "freeze(a, ...) -> None: a.setflags(write=False) for each array, in one call."},
    {"fill", (PyCFunction)(void (*)(void))fill, METH_FASTCALL,
     "fill(buf, start, end, u) -> True: buf[start:end] = u done; False: not taken (use numpy)."},
    {"untrack", untrack, METH_O,
     "untrack(obj) -> obj: obj and the tuples, lists and dicts it holds leave the cycle "
     "collector where they reference nothing tracked (for states not changed afterwards)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_kalman",
    "The Kalman step of LinearBackend.advance in C (pd_service/estimation/_kalman.c).",
    -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__kalman(void) {
    import_array();
    if (!no_stages && !(no_stages = PyBytes_FromStringAndSize(NULL, 0))) return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m && (PyModule_AddIntConstant(m, "MAX_N", MAXN) || PyModule_AddIntConstant(m, "MAX_R", MAXR))) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}

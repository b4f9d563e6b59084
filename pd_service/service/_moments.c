/* A prediction's health check and its arrays' msgpack form, in C: one call where the
   Python form (pd_service.service.health.inspect, then msgpack's packing of the values it
   read) makes two lists of Python floats, two fsums and two packs.

       moments(x, P) -> (verdict, x_data, P_data)

   x (n,) and P (n, n), float64. verdict: 0 healthy, 1 a non-finite entry in x or P, 2 a
   negative diagonal entry of P (finite); as inspect() decides, in that order. x_data and
   P_data: x and P (row-major) as msgpack arrays of float64, byte for byte what
   msgpack.packb(list_of_floats) writes (an array header, then 0xcb and the 8 bytes of
   each IEEE double, big-endian). Any other argument (another dtype, rank or shape):
   TypeError, and the caller takes the Python form. No state, no GIL release.

       clearly_psd(P, margin_rel) -> bool

   the thorough test's shortcut (health.thoroughly_healthy): True when a Cholesky
   factorisation shows that no eigenvalue of (P + P^T) / 2 is below -margin; False leaves
   the verdict to numpy's eigenvalues. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include <numpy/arrayobject.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

/* a float64 array of rank `rank`, native byte order (any strides), or NULL */
static PyArrayObject *f64(PyObject *obj, int rank) {
    if (!PyArray_Check(obj)) return NULL;
    PyArrayObject *a = (PyArrayObject *)obj;
    if (PyArray_TYPE(a) != NPY_DOUBLE || PyArray_NDIM(a) != rank || !PyArray_ISNOTSWAPPED(a))
        return NULL;
    return a;
}

/* bytes of the msgpack array header for `count` items */
static Py_ssize_t header_len(uint64_t count) {
    return count <= 15 ? 1 : (count <= 0xFFFF ? 3 : 5);
}

/* the msgpack array header for `count` items at out */
static void header(unsigned char *out, uint64_t count) {
    if (count <= 15) {
        out[0] = (unsigned char)(0x90 | count);
    } else if (count <= 0xFFFF) {
        out[0] = 0xdc;
        out[1] = (unsigned char)(count >> 8);
        out[2] = (unsigned char)count;
    } else {
        out[0] = 0xdd;
        for (int i = 0; i < 4; i++) out[1 + i] = (unsigned char)(count >> (24 - 8 * i));
    }
}

/* The rows x cols float64 values at base (strides s0, s1; any alignment), row-major, as a
   msgpack array (a new bytes object, or NULL with an exception). Clears *finite if a value
   is not finite, sets *negative if a diagonal entry (i == j) is below 0. */
static PyObject *pack(const char *base, npy_intp rows, npy_intp cols, npy_intp s0,
                      npy_intp s1, int *finite, int *negative) {
    uint64_t count = (uint64_t)rows * (uint64_t)cols;
    Py_ssize_t h = header_len(count);
    PyObject *b = PyBytes_FromStringAndSize(NULL, h + 9 * (Py_ssize_t)count);
    if (b == NULL) return NULL;
    unsigned char *out = (unsigned char *)PyBytes_AS_STRING(b);
    header(out, count);
    out += h;
    for (npy_intp i = 0; i < rows; i++) {
        for (npy_intp j = 0; j < cols; j++) {
            double v;
            memcpy(&v, base + i * s0 + j * s1, 8);
            *finite &= isfinite(v) != 0;
            if (i == j && v < 0.0) *negative = 1;
            /* 0xcb and the IEEE double's 8 bytes, big-endian */
            uint64_t bits;
            memcpy(&bits, &v, 8);
            out[0] = 0xcb;
            for (int k = 0; k < 8; k++) out[1 + k] = (unsigned char)(bits >> (56 - 8 * k));
            out += 9;
        }
    }
    return b;
}

static PyObject *moments(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 2) {
        PyErr_Format(PyExc_TypeError, "moments: %zd arguments, expected 2", nargs);
        return NULL;
    }
    PyObject *ox = args[0], *oP = args[1];
    PyArrayObject *x = f64(ox, 1), *P = f64(oP, 2);
    if (x == NULL || P == NULL) {
        PyErr_SetString(PyExc_TypeError, "moments: x (n,) and P (n, n) must be float64 arrays");
        return NULL;
    }
    npy_intp n = PyArray_DIM(x, 0);
    if (PyArray_DIM(P, 0) != n || PyArray_DIM(P, 1) != n) {
        PyErr_SetString(PyExc_TypeError, "moments: x (n,) and P (n, n) do not fit");
        return NULL;
    }
    if ((uint64_t)n > 0xFFFFFFFFu / ((uint64_t)n ? (uint64_t)n : 1u)) {
        PyErr_SetString(PyExc_TypeError, "moments: too many values for one msgpack array");
        return NULL;
    }
    int finite = 1, negative = 0, ignored = 0;
    /* x as n rows of one column: its "diagonal" is not a variance */
    PyObject *xb = pack(PyArray_BYTES(x), n, 1, PyArray_STRIDE(x, 0), 0, &finite, &ignored);
    if (xb == NULL) return NULL;
    PyObject *pb = pack(PyArray_BYTES(P), n, n, PyArray_STRIDE(P, 0), PyArray_STRIDE(P, 1),
                        &finite, &negative);
    if (pb == NULL) {
        Py_DECREF(xb);
        return NULL;
    }
    int verdict = !finite ? 1 : (negative ? 2 : 0);
    PyObject *res = PyTuple_New(3);  /* (verdict, xb, pb), without a format to parse */
    if (res == NULL) {
        Py_DECREF(xb);
        Py_DECREF(pb);
        return NULL;
    }
    PyTuple_SET_ITEM(res, 0, PyLong_FromLong(verdict));  /* 0, 1, 2: cached small ints */
    PyTuple_SET_ITEM(res, 1, xb);
    PyTuple_SET_ITEM(res, 2, pb);
    return res;
}

#define MAXN_PSD 64

/* clearly_psd(P, margin_rel) -> bool. True iff P (n, n) float64 is finite and the Cholesky
   factorisation of (P + P^T) / 2 + margin I succeeds (every pivot > 0), where margin =
   margin_rel * max(1, max_i |P_ii|): then every eigenvalue of (P + P^T) / 2 exceeds -margin
   less the factorisation's rounding (~n^2 eps max(1, max |P_ii|)). False says nothing: the
   caller decides with the eigenvalues. TypeError for another dtype, rank or shape, or n
   above 64. */
static PyObject *clearly_psd(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 2) {
        PyErr_Format(PyExc_TypeError, "clearly_psd: %zd arguments, expected 2", nargs);
        return NULL;
    }
    PyObject *oP = args[0];
    double margin_rel = PyFloat_AsDouble(args[1]);
    if (margin_rel == -1.0 && PyErr_Occurred()) return NULL;
    PyArrayObject *P = f64(oP, 2);
    if (P == NULL || PyArray_DIM(P, 0) != PyArray_DIM(P, 1) || PyArray_DIM(P, 0) > MAXN_PSD) {
        PyErr_SetString(PyExc_TypeError, "clearly_psd: P must be a float64 (n, n) array, n <= 64");
        return NULL;
    }
    npy_intp n = PyArray_DIM(P, 0), s0 = PyArray_STRIDE(P, 0), s1 = PyArray_STRIDE(P, 1);
    const char *base = PyArray_BYTES(P);
    double L[MAXN_PSD * MAXN_PSD];
    double scale = 1.0;
    for (npy_intp i = 0; i < n; i++) {
        for (npy_intp j = 0; j < n; j++) {
            double a, b;
            memcpy(&a, base + i * s0 + j * s1, 8);
            memcpy(&b, base + j * s0 + i * s1, 8);
            if (!isfinite(a)) Py_RETURN_FALSE;
            L[i * n + j] = 0.5 * (a + b);
        }
        if (fabs(L[i * n + i]) > scale) scale = fabs(L[i * n + i]);
    }
    double margin = margin_rel * scale;
    for (npy_intp j = 0; j < n; j++) {  /* lower triangle, in place, row by row */
        for (npy_intp i = j; i < n; i++) {
            double v = L[i * n + j] + (i == j ? margin : 0.0);
            for (npy_intp k = 0; k < j; k++) v -= L[i * n + k] * L[j * n + k];
            if (i == j) {
                if (!(v > 0.0)) Py_RETURN_FALSE;
                L[j * n + j] = sqrt(v);
            } else {
                L[i * n + j] = v / L[j * n + j];
            }
        }
    }
    Py_RETURN_TRUE;
}

static PyMethodDef methods[] = {
    {"clearly_psd", (PyCFunction)(void (*)(void))clearly_psd, METH_FASTCALL,
     "clearly_psd(P, margin_rel) -> True if P is finite and (P + P^T)/2 + margin I has a "
     "Cholesky factor (margin = margin_rel * max(1, max |P_ii|)); False: undecided."},
    {"moments", (PyCFunction)(void (*)(void))moments, METH_FASTCALL,
     "moments(x, P) -> (verdict, x_data, P_data): 0 healthy, 1 non-finite, 2 negative "
     "variance; x and P (row-major) as msgpack float64 arrays."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_moments",
    "A prediction's health check and msgpack form (pd_service.service.health).", -1, methods,
};

PyMODINIT_FUNC PyInit__moments(void) {
    import_array();
    return PyModule_Create(&module);
}

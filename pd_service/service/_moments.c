/* A prediction's health check and its arrays' msgpack form, in C: one call where the
   Python form (pd_service.service.health.inspect, then msgpack's packing of the values it
   read) makes two lists of Python floats, two fsums and two packs.

       moments(x, P) -> (verdict, x_data, P_data)

   x (n,) and P (n, n), float64. verdict: 0 healthy, 1 a non-finite entry in x or P, 2 a
   negative diagonal entry of P (finite); as inspect() decides, in that order. x_data and
   P_data: x and P (row-major) as msgpack arrays of float64, byte for byte what
   msgpack.packb(list_of_floats) writes (an array header, then 0xcb and the 8 bytes of
   each IEEE double, big-endian). Any other argument (another dtype, rank or shape):
   TypeError, and the caller takes the Python form. No state, no GIL release. */

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

/* msgpack array header for `count` items at out; returns the bytes written */
static Py_ssize_t header(unsigned char *out, uint64_t count) {
    if (count <= 15) {
        out[0] = (unsigned char)(0x90 | count);
        return 1;
    }
    if (count <= 0xFFFF) {
        out[0] = 0xdc;
        out[1] = (unsigned char)(count >> 8);
        out[2] = (unsigned char)count;
        return 3;
    }
    out[0] = 0xdd;
    for (int i = 0; i < 4; i++) out[1 + i] = (unsigned char)(count >> (24 - 8 * i));
    return 5;
}

/* 0xcb and the big-endian bytes of v at out (9 bytes) */
static void put_double(unsigned char *out, double v) {
    uint64_t bits;
    memcpy(&bits, &v, 8);
    out[0] = 0xcb;
    for (int i = 0; i < 8; i++) out[1 + i] = (unsigned char)(bits >> (56 - 8 * i));
}

static PyObject *moments(PyObject *self, PyObject *args) {
    PyObject *ox, *oP;
    if (!PyArg_ParseTuple(args, "OO", &ox, &oP)) return NULL;
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
    uint64_t nn = (uint64_t)n * (uint64_t)n;
    PyObject *xb = PyBytes_FromStringAndSize(NULL, 5 + 9 * (Py_ssize_t)n);
    PyObject *pb = PyBytes_FromStringAndSize(NULL, 5 + 9 * (Py_ssize_t)nn);
    if (xb == NULL || pb == NULL) {
        Py_XDECREF(xb);
        Py_XDECREF(pb);
        return NULL;
    }
    int finite = 1, negative = 0;
    unsigned char *out = (unsigned char *)PyBytes_AS_STRING(xb);
    Py_ssize_t len = header(out, (uint64_t)n);
    const char *base = PyArray_BYTES(x);
    npy_intp sx = PyArray_STRIDE(x, 0);
    for (npy_intp i = 0; i < n; i++) {
        double v;
        memcpy(&v, base + i * sx, 8);  /* any alignment */
        finite &= isfinite(v) != 0;
        put_double(out + len, v);
        len += 9;
    }
    if (_PyBytes_Resize(&xb, len) < 0) {
        Py_DECREF(pb);
        return NULL;
    }
    out = (unsigned char *)PyBytes_AS_STRING(pb);
    len = header(out, nn);
    base = PyArray_BYTES(P);
    npy_intp s0 = PyArray_STRIDE(P, 0), s1 = PyArray_STRIDE(P, 1);
    for (npy_intp i = 0; i < n; i++) {
        for (npy_intp j = 0; j < n; j++) {
            double v;
            memcpy(&v, base + i * s0 + j * s1, 8);
            finite &= isfinite(v) != 0;
            if (i == j && v < 0.0) negative = 1;
            put_double(out + len, v);
            len += 9;
        }
    }
    if (_PyBytes_Resize(&pb, len) < 0) {
        Py_DECREF(xb);
        return NULL;
    }
    int verdict = !finite ? 1 : (negative ? 2 : 0);
    return Py_BuildValue("(iNN)", verdict, xb, pb);
}

static PyMethodDef methods[] = {
    {"moments", moments, METH_VARARGS,
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

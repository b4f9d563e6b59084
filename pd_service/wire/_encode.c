/* The per-message part of pd_service.wire.convert.PredictionEncoder.encode_packed, in C: one
   call where the Python form makes six msgpack packs, a join of fifteen parts and the
   counters' map.

       prediction(parts, seq, step, t_ns, x_data, P_data, newest_step, made_ns, counters,
                  term) -> bytes or None

   parts: the encoder's 9 constant pieces (bytes): the map header with v and session and the
   key of seq, then the keys of step, t_ns, x (with x's shape), P (with P's shape),
   newest_step, made_ns, counters and term. The message is

       parts[0] seq parts[1] step parts[2] t_ns parts[3] x_data parts[4] P_data
       parts[5] newest_step parts[6] made_ns parts[7] counters parts[8] term

   with each int packed as msgpack-python's Packer packs a Python int (the smallest form:
   positive fixint, uint 8/16/32/64 for the others >= 0; negative fixint, int 8/16/32/64
   below), newest_step None as nil, and counters (a dict of str -> int, in its order) as a
   map of str (fixstr, str 8/16/32: use_bin_type) to ints. x_data and P_data are copied as
   they are. None for anything else (an int that is not exactly an int, or beyond
   [-2^63, 2^64 - 1]; counters not exactly a dict; a key not a str or not encodable; a
   value not exactly an int): the caller then runs the Python form, the reference, which
   the tests hold this to byte for byte. No state, no GIL release.

       pack(obj) -> bytes or None

   msgpack of a tree of dict, list, tuple, str, int, float, bool and None, byte for byte as
   msgpack-python's ``packb(obj, use_bin_type=True)`` writes it (maps in the dict's order),
   where a float64 numpy array stands for its wire form {"shape": [...], "data": [...]}
   (pd_service.wire.session_state.Tensors: the values in C order). What the checkpoints' encoder
   (pd_service.service.handover.checkpoint.encode_state) builds per session and second, without the Python
   dicts and lists of floats the wire form would need. None (the Python form, the
   reference, then runs) for anything else: another type or a subclass, an array of
   another dtype or byte order, a non-finite value in an array, an int beyond msgpack's
   range, a str that is not UTF-8 encodable, nesting deeper than MAXDEPTH. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include <numpy/arrayobject.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

/* An exact int as a sign and magnitude; 0 if it is not one or is out of msgpack's range. */
typedef struct {
    int neg;        /* < 0: i is the value */
    int64_t i;
    uint64_t u;     /* >= 0: u is the value */
} Int;

static int get_int(PyObject *o, Int *v) {
    if (!PyLong_CheckExact(o)) return 0;
    int overflow = 0;
    long long x = PyLong_AsLongLongAndOverflow(o, &overflow);
    if (overflow == 0) {
        if (x == -1 && PyErr_Occurred()) { PyErr_Clear(); return 0; }
        v->neg = x < 0;
        v->i = x;
        v->u = (uint64_t)x;
        return 1;
    }
    if (overflow < 0) return 0;
    unsigned long long u = PyLong_AsUnsignedLongLong(o);
    if (u == (unsigned long long)-1 && PyErr_Occurred()) { PyErr_Clear(); return 0; }
    v->neg = 0;
    v->u = u;
    return 1;
}

static Py_ssize_t int_len(const Int *v) {
    if (v->neg) {
        int64_t x = v->i;
        if (x >= -32) return 1;
        if (x >= -128) return 2;
        if (x >= -32768) return 3;
        if (x >= -2147483648LL) return 5;
        return 9;
    }
    uint64_t u = v->u;
    if (u < 128) return 1;
    if (u < 256) return 2;
    if (u < 65536) return 3;
    if (u < 4294967296ULL) return 5;
    return 9;
}

static unsigned char *put_be(unsigned char *p, uint64_t v, int k) {
    for (int j = k - 1; j >= 0; j--) {
        p[j] = (unsigned char)(v & 0xff);
        v >>= 8;
    }
    return p + k;
}

static unsigned char *put_int(unsigned char *p, const Int *v) {
    if (v->neg) {
        int64_t x = v->i;
        if (x >= -32) { *p++ = (unsigned char)(x & 0xff); return p; }
        if (x >= -128) { *p++ = 0xd0; return put_be(p, (uint64_t)x, 1); }
        if (x >= -32768) { *p++ = 0xd1; return put_be(p, (uint64_t)x, 2); }
        if (x >= -2147483648LL) { *p++ = 0xd2; return put_be(p, (uint64_t)x, 4); }
        *p++ = 0xd3;
        return put_be(p, (uint64_t)x, 8);
    }
    uint64_t u = v->u;
    if (u < 128) { *p++ = (unsigned char)u; return p; }
    if (u < 256) { *p++ = 0xcc; return put_be(p, u, 1); }
    if (u < 65536) { *p++ = 0xcd; return put_be(p, u, 2); }
    if (u < 4294967296ULL) { *p++ = 0xce; return put_be(p, u, 4); }
    *p++ = 0xcf;
    return put_be(p, u, 8);
}

static Py_ssize_t head_len(Py_ssize_t n, int map) {  /* map or str header */
    if (map) return n <= 15 ? 1 : (n <= 0xffff ? 3 : 5);
    return n <= 31 ? 1 : (n <= 0xff ? 2 : (n <= 0xffff ? 3 : 5));
}

static unsigned char *put_head(unsigned char *p, Py_ssize_t n, int map) {
    if (map) {
        if (n <= 15) { *p++ = (unsigned char)(0x80 | n); return p; }
        if (n <= 0xffff) { *p++ = 0xde; return put_be(p, (uint64_t)n, 2); }
        *p++ = 0xdf;
        return put_be(p, (uint64_t)n, 4);
    }
    if (n <= 31) { *p++ = (unsigned char)(0xa0 | n); return p; }
    if (n <= 0xff) { *p++ = 0xd9; return put_be(p, (uint64_t)n, 1); }
    if (n <= 0xffff) { *p++ = 0xda; return put_be(p, (uint64_t)n, 2); }
    *p++ = 0xdb;
    return put_be(p, (uint64_t)n, 4);
}

#define NPARTS 9
#define MAXCOUNTERS 256 /* more: the Python form */

static PyObject *prediction(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 10) {
        PyErr_Format(PyExc_TypeError, "_encode.prediction: %zd arguments, expected 10", nargs);
        return NULL;
    }
    PyObject *parts = args[0], *xd = args[4], *Pd = args[5], *newest = args[6];
    PyObject *counters = args[8];
    if (!PyTuple_CheckExact(parts) || PyTuple_GET_SIZE(parts) != NPARTS) {
        PyErr_SetString(PyExc_TypeError, "_encode.prediction: parts must be a tuple of 9 bytes");
        return NULL;
    }
    Py_ssize_t size = 0;
    for (int j = 0; j < NPARTS; j++) {
        PyObject *b = PyTuple_GET_ITEM(parts, j);
        if (!PyBytes_CheckExact(b)) {
            PyErr_SetString(PyExc_TypeError, "_encode.prediction: parts must be bytes");
            return NULL;
        }
        size += PyBytes_GET_SIZE(b);
    }
    if (!PyBytes_CheckExact(xd) || !PyBytes_CheckExact(Pd)) {
        PyErr_SetString(PyExc_TypeError, "_encode.prediction: x_data and P_data must be bytes");
        return NULL;
    }
    size += PyBytes_GET_SIZE(xd) + PyBytes_GET_SIZE(Pd);
    Int ints[5]; /* seq, step, t_ns, made_ns, term */
    PyObject *io[5] = {args[1], args[2], args[3], args[7], args[9]};
    for (int j = 0; j < 5; j++) {
        if (!get_int(io[j], &ints[j])) Py_RETURN_NONE;
        size += int_len(&ints[j]);
    }
    Int nw;
    if (newest == Py_None) {
        size += 1;
    } else {
        if (!get_int(newest, &nw)) Py_RETURN_NONE;
        size += int_len(&nw);
    }
    if (!PyDict_CheckExact(counters)) Py_RETURN_NONE;
    Py_ssize_t nc = PyDict_GET_SIZE(counters);
    if (nc > MAXCOUNTERS) Py_RETURN_NONE;
    const char *ks[MAXCOUNTERS];
    Py_ssize_t kl[MAXCOUNTERS];
    Int vs[MAXCOUNTERS];
    size += head_len(nc, 1);
    Py_ssize_t pos = 0, c = 0;
    PyObject *k, *v;
    while (PyDict_Next(counters, &pos, &k, &v)) {
        if (c >= nc || !PyUnicode_CheckExact(k) || !get_int(v, &vs[c])) Py_RETURN_NONE;
        ks[c] = PyUnicode_AsUTF8AndSize(k, &kl[c]);
        if (ks[c] == NULL) { PyErr_Clear(); Py_RETURN_NONE; }
        size += head_len(kl[c], 0) + kl[c] + int_len(&vs[c]);
        c++;
    }
    if (c != nc) Py_RETURN_NONE;
    PyObject *out = PyBytes_FromStringAndSize(NULL, size);
    if (out == NULL) return NULL;
    unsigned char *p = (unsigned char *)PyBytes_AS_STRING(out);
#define PART(j) do { PyObject *b_ = PyTuple_GET_ITEM(parts, j); \
        memcpy(p, PyBytes_AS_STRING(b_), (size_t)PyBytes_GET_SIZE(b_)); \
        p += PyBytes_GET_SIZE(b_); } while (0)
    PART(0); p = put_int(p, &ints[0]);
    PART(1); p = put_int(p, &ints[1]);
    PART(2); p = put_int(p, &ints[2]);
    PART(3); memcpy(p, PyBytes_AS_STRING(xd), (size_t)PyBytes_GET_SIZE(xd));
    p += PyBytes_GET_SIZE(xd);
    PART(4); memcpy(p, PyBytes_AS_STRING(Pd), (size_t)PyBytes_GET_SIZE(Pd));
    p += PyBytes_GET_SIZE(Pd);
    PART(5);
    if (newest == Py_None) *p++ = 0xc0;
    else p = put_int(p, &nw);
    PART(6); p = put_int(p, &ints[3]);
    PART(7);
    p = put_head(p, nc, 1);
    for (Py_ssize_t j = 0; j < nc; j++) {
        p = put_head(p, kl[j], 0);
        memcpy(p, ks[j], (size_t)kl[j]);
        p += kl[j];
        p = put_int(p, &vs[j]);
    }
    PART(8); p = put_int(p, &ints[4]);
#undef PART
    if ((char *)p != PyBytes_AS_STRING(out) + size) {  /* cannot happen: sizes agree */
        Py_DECREF(out);
        PyErr_SetString(PyExc_SystemError, "_encode.prediction: size mismatch");
        return NULL;
    }
    return out;
}

/* --- pack: a growable buffer and a walk over the tree ------------------------------------ */

#define MAXDEPTH 32

typedef struct {
    unsigned char *buf;
    Py_ssize_t len, cap;
} Buf;

/* Room for n more bytes: a pointer to them, NULL (MemoryError set) if it cannot grow. */
static unsigned char *room(Buf *b, Py_ssize_t n) {
    if (b->len + n > b->cap) {
        Py_ssize_t cap = b->cap ? b->cap : 1024;
        while (cap < b->len + n) cap *= 2;
        unsigned char *nb = PyMem_Realloc(b->buf, (size_t)cap);
        if (nb == NULL) { PyErr_NoMemory(); return NULL; }
        b->buf = nb;
        b->cap = cap;
    }
    return b->buf + b->len;
}

/* msgpack's array header (fixarray, array 16, array 32) */
static Py_ssize_t array_head_len(Py_ssize_t n) { return n <= 15 ? 1 : (n <= 0xffff ? 3 : 5); }

static unsigned char *put_array_head(unsigned char *p, Py_ssize_t n) {
    if (n <= 15) { *p++ = (unsigned char)(0x90 | n); return p; }
    if (n <= 0xffff) { *p++ = 0xdc; return put_be(p, (uint64_t)n, 2); }
    *p++ = 0xdd;
    return put_be(p, (uint64_t)n, 4);
}

enum { PACK_OK = 0, PACK_OTHER = 1, PACK_ERROR = -1 };

#define NEED(n) do { p = room(b, (n)); if (p == NULL) return PACK_ERROR; } while (0)

/* The wire form of a float64 array: {"shape": [d0, ...], "data": [v0, ...]} */
static int pack_array(Buf *b, PyArrayObject *a) {
    if (PyArray_TYPE(a) != NPY_DOUBLE || !PyArray_ISNOTSWAPPED(a)) return PACK_OTHER;
    int nd = PyArray_NDIM(a);
    npy_intp size = PyArray_SIZE(a);
    if (size > 0xffffffffLL) return PACK_OTHER;
    PyArrayObject *c = (PyArrayObject *)PyArray_GETCONTIGUOUS(a);
    if (c == NULL) return PACK_ERROR;
    const double *v = (const double *)PyArray_DATA(c);
    for (npy_intp j = 0; j < size; j++) {
        if (!isfinite(v[j])) { Py_DECREF(c); return PACK_OTHER; }
    }
    Int dims[NPY_MAXDIMS];
    Py_ssize_t n = 1 + 6 + array_head_len(nd) + 5 + array_head_len(size) + 9 * size;
    for (int d = 0; d < nd; d++) {
        dims[d].neg = 0;
        dims[d].u = (uint64_t)PyArray_DIM(a, d);
        n += int_len(&dims[d]);
    }
    unsigned char *p = room(b, n);
    if (p == NULL) { Py_DECREF(c); return PACK_ERROR; }
    *p++ = 0x82;
    memcpy(p, "\xa5shape", 6); p += 6;
    p = put_array_head(p, nd);
    for (int d = 0; d < nd; d++) p = put_int(p, &dims[d]);
    memcpy(p, "\xa4" "data", 5); p += 5;
    p = put_array_head(p, size);
    for (npy_intp j = 0; j < size; j++) {
        uint64_t bits;
        memcpy(&bits, &v[j], 8);
        *p++ = 0xcb;
        p = put_be(p, bits, 8);
    }
    b->len = p - b->buf;
    Py_DECREF(c);
    return PACK_OK;
}

static int pack_obj(Buf *b, PyObject *o, int depth) {
    unsigned char *p;
    if (o == Py_None) { NEED(1); *p = 0xc0; b->len += 1; return PACK_OK; }
    if (o == Py_True || o == Py_False) {
        NEED(1); *p = o == Py_True ? 0xc3 : 0xc2; b->len += 1; return PACK_OK;
    }
    if (PyLong_CheckExact(o)) {
        Int v;
        if (!get_int(o, &v)) return PACK_OTHER;
        NEED(9);
        b->len = put_int(p, &v) - b->buf;
        return PACK_OK;
    }
    if (PyFloat_CheckExact(o)) {
        double d = PyFloat_AS_DOUBLE(o);
        uint64_t bits;
        memcpy(&bits, &d, 8);
        NEED(9);
        *p++ = 0xcb;
        b->len = put_be(p, bits, 8) - b->buf;
        return PACK_OK;
    }
    if (PyUnicode_CheckExact(o)) {
        Py_ssize_t k;
        const char *s = PyUnicode_AsUTF8AndSize(o, &k);
        if (s == NULL) { PyErr_Clear(); return PACK_OTHER; }
        if (k > 0xffffffffLL) return PACK_OTHER;
        NEED(head_len(k, 0) + k);
        p = put_head(p, k, 0);
        memcpy(p, s, (size_t)k);
        b->len = p + k - b->buf;
        return PACK_OK;
    }
    if (depth >= MAXDEPTH) return PACK_OTHER;
    if (PyDict_CheckExact(o)) {
        Py_ssize_t n = PyDict_GET_SIZE(o), pos = 0, seen = 0;
        if (n > 0xffffffffLL) return PACK_OTHER;
        NEED(head_len(n, 1));
        b->len = put_head(p, n, 1) - b->buf;
        PyObject *k, *v;
        while (PyDict_Next(o, &pos, &k, &v)) {
            int r = pack_obj(b, k, depth + 1);
            if (r == PACK_OK) r = pack_obj(b, v, depth + 1);
            if (r != PACK_OK) return r;
            seen++;
        }
        return seen == n ? PACK_OK : PACK_OTHER;
    }
    if (PyList_CheckExact(o) || PyTuple_CheckExact(o)) {
        int list = PyList_CheckExact(o);
        Py_ssize_t n = list ? PyList_GET_SIZE(o) : PyTuple_GET_SIZE(o);
        if (n > 0xffffffffLL) return PACK_OTHER;
        NEED(array_head_len(n));
        b->len = put_array_head(p, n) - b->buf;
        for (Py_ssize_t j = 0; j < n; j++) {
            /* the length read again: copying a strided array allocates, which may run
               the garbage collector, whose finalizers may change a list (or a dict: seen) */
            if (list && j >= PyList_GET_SIZE(o)) return PACK_OTHER;
            int r = pack_obj(b, list ? PyList_GET_ITEM(o, j) : PyTuple_GET_ITEM(o, j),
                             depth + 1);
            if (r != PACK_OK) return r;
        }
        return PACK_OK;
    }
    if (PyArray_CheckExact(o)) return pack_array(b, (PyArrayObject *)o);
    return PACK_OTHER;
}

#undef NEED

static PyObject *pack(PyObject *self, PyObject *obj) {
    (void)self;
    Buf b = {NULL, 0, 0};
    int r = pack_obj(&b, obj, 0);
    PyObject *out = NULL;
    if (r == PACK_OK) out = PyBytes_FromStringAndSize((const char *)b.buf, b.len);
    else if (r == PACK_OTHER) out = Py_NewRef(Py_None);
    PyMem_Free(b.buf);
    return out;
}

static PyMethodDef methods[] = {
    {"pack", (PyCFunction)pack, METH_O,
     "pack(obj) -> msgpack bytes of a tree whose float64 arrays stand for their wire form "
     "{shape, data}, or None (the Python form then runs)"},
    {"prediction", (PyCFunction)(void (*)(void))prediction, METH_FASTCALL,
     "prediction(parts, seq, step, t_ns, x_data, P_data, newest_step, made_ns, counters, "
     "term) "
     "-> the Prediction's msgpack bytes, or None (the Python form then runs)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_encode",
    "PredictionEncoder.encode_packed's per-message part (pd_service.wire.convert) and the "
    "checkpoints' msgpack (pd_service.service.handover.checkpoint), in C.", -1,
    methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__encode(void) {
    import_array();
    return PyModule_Create(&module);
}

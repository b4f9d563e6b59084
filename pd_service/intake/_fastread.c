/* The fast path of pd_service/intake (Intake.measurement / Intake.command): read_measurement
   and read_command, straight from the msgpack bytes.

   The full path (pd_service.wire.decode into the validated pydantic model, then
   wire.convert.check_measurement / check_command) is the reference; the tests run both on
   the same payloads (plain messages, re-encoded, mutated, cut and random ones) and demand
   that whatever this accepts, the full path accepts with the same values. This accepts only
   the plainest form of a message that fits its session and returns None for anything else;
   the caller then takes the full path, which names the refusal. It reads the bytes once and
   builds the result only (no dict of the message).

   Accepted (anything else: None):
     top level:  one msgpack map, nothing after it, at most max_bytes bytes in all
     keys:       str, each at most once (a repeated key: None, the full path decides), from
                 Measurement {v, session, sensor, seq, step, t_ns, z, R},
                 Command     {v, session, seq, step, issued_ns, u}
     v:          absent or the int 1          session: the str equal to `session`
     sensor:     the str equal to `sensor`    seq: an int in [0, 2^63 - 1]
     step:       nil (absent) or an int in [0, 2^63 - 1]
     t_ns, issued_ns: nil (absent) or an int in [-2^63, 2^63 - 1]; exactly one of step and
                 t_ns (issued_ns) present
     R:          absent or nil
     z, u:       a map of exactly {"shape": [size], "data": [size values]}, each value a
                 float (32 or 64 bit) or an int (not a bool) with -max_abs <= v <= max_abs
                 (NaN fails the comparison); an int beyond 2^53 in magnitude: None (its
                 comparison with max_abs would need more than a double's precision; with the
                 default max_abs of 1e12 such an int is refused either way)
   Returns (seq, step or None, t_ns or None, float64 array (size,)). Strings are compared as bytes with the UTF-8 of `session` / `sensor`: only valid
   UTF-8 can match. No state, no GIL release. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include <numpy/arrayobject.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#define EXACT_INT (INT64_C(1) << 53) /* ints up to this in magnitude are exact as doubles */

enum { T_NIL, T_BOOL, T_INT, T_FLOAT, T_STR, T_ARRAY, T_MAP };

typedef struct {
    int t;
    int big;             /* T_INT: a uint64 above 2^63 - 1 (i then meaningless) */
    int64_t i;           /* T_INT */
    double f;            /* T_FLOAT */
    const char *s;       /* T_STR */
    uint64_t n;          /* T_STR: bytes; T_ARRAY / T_MAP: entries */
} Val;

typedef struct {
    const unsigned char *p, *end;
} Rd;

static uint64_t be(const unsigned char *p, int k) {
    uint64_t v = 0;
    for (int j = 0; j < k; j++) v = (v << 8) | p[j];
    return v;
}

/* The next value's header (a scalar whole, a str's bytes, an array's or a map's count);
   -1: cut short, or a type no reader accepts (bin, ext, 0xc1). */
static int next(Rd *r, Val *v) {
    if (r->p >= r->end) return -1;
    unsigned b = *r->p++;
    ptrdiff_t left = r->end - r->p;
    int k = 0; /* bytes of a length or value that follow */
    if (b <= 0x7f) { v->t = T_INT; v->big = 0; v->i = b; return 0; }
    if (b >= 0xe0) { v->t = T_INT; v->big = 0; v->i = (int64_t)b - 256; return 0; }
    if (b <= 0x8f) { v->t = T_MAP; v->n = b & 0x0f; return 0; }
    if (b <= 0x9f) { v->t = T_ARRAY; v->n = b & 0x0f; return 0; }
    if (b <= 0xbf) { v->t = T_STR; v->n = b & 0x1f; goto str_body; }
    switch (b) {
    case 0xc0: v->t = T_NIL; return 0;
    case 0xc2: case 0xc3: v->t = T_BOOL; return 0;
    case 0xca: {
        if (left < 4) return -1;
        uint32_t u = (uint32_t)be(r->p, 4);
        float f;
        memcpy(&f, &u, 4);
        v->t = T_FLOAT; v->f = (double)f; r->p += 4; return 0;
    }
    case 0xcb: {
        if (left < 8) return -1;
        uint64_t u = be(r->p, 8);
        double f;
        memcpy(&f, &u, 8);
        v->t = T_FLOAT; v->f = f; r->p += 8; return 0;
    }
    case 0xcc: k = 1; goto uint_body;
    case 0xcd: k = 2; goto uint_body;
    case 0xce: k = 4; goto uint_body;
    case 0xcf: k = 8; goto uint_body;
    case 0xd0: k = 1; goto int_body;
    case 0xd1: k = 2; goto int_body;
    case 0xd2: k = 4; goto int_body;
    case 0xd3: k = 8; goto int_body;
    case 0xd9: k = 1; goto str_len;
    case 0xda: k = 2; goto str_len;
    case 0xdb: k = 4; goto str_len;
    case 0xdc: k = 2; v->t = T_ARRAY; goto count;
    case 0xdd: k = 4; v->t = T_ARRAY; goto count;
    case 0xde: k = 2; v->t = T_MAP; goto count;
    case 0xdf: k = 4; v->t = T_MAP; goto count;
    default: return -1; /* bin, ext, fixext, 0xc1 */
    }
uint_body: {
        if (left < k) return -1;
        uint64_t u = be(r->p, k);
        r->p += k;
        v->t = T_INT;
        v->big = u > (uint64_t)INT64_MAX;
        v->i = v->big ? 0 : (int64_t)u;
        return 0;
    }
int_body: {
        if (left < k) return -1;
        uint64_t u = be(r->p, k);
        r->p += k;
        int64_t i;
        if (k == 1) i = (int8_t)u;
        else if (k == 2) i = (int16_t)u;
        else if (k == 4) i = (int32_t)u;
        else memcpy(&i, &u, 8);
        v->t = T_INT; v->big = 0; v->i = i;
        return 0;
    }
count:
    if (left < k) return -1;
    v->n = be(r->p, k);
    r->p += k;
    return 0;
str_len:
    if (left < k) return -1;
    v->t = T_STR;
    v->n = be(r->p, k);
    r->p += k;
str_body:
    if ((uint64_t)(r->end - r->p) < v->n) return -1;
    v->s = (const char *)r->p;
    r->p += v->n;
    return 0;
}

static int is(const Val *v, const char *name, size_t len) {
    return v->t == T_STR && v->n == len && memcmp(v->s, name, len) == 0;
}

/* {"shape": [size], "data": [size values in [-max_abs, max_abs]]} -> a new float64 array
   (size,), or NULL (no exception: the caller returns None; a Python error only if numpy
   could not allocate). */
static PyObject *vector(Rd *r, Py_ssize_t size, double max_abs) {
    Val v, k;
    if (next(r, &v) || v.t != T_MAP || v.n != 2) return NULL;
    int got_shape = 0;
    npy_intp dims[1] = {size};
    PyObject *out = NULL;
    for (int e = 0; e < 2; e++) {
        if (next(r, &k)) goto fail;
        if (is(&k, "shape", 5) && !got_shape) {
            got_shape = 1;
            if (next(r, &v) || v.t != T_ARRAY || v.n != 1) goto fail;
            if (next(r, &v) || v.t != T_INT || v.big || v.i != size) goto fail;
        } else if (is(&k, "data", 4) && out == NULL) {
            if (next(r, &v) || v.t != T_ARRAY || v.n != (uint64_t)size) goto fail;
            out = PyArray_SimpleNew(1, dims, NPY_DOUBLE);
            if (out == NULL) return NULL;
            double *d = (double *)PyArray_DATA((PyArrayObject *)out);
            for (Py_ssize_t j = 0; j < size; j++) {
                double x;
                if (next(r, &v)) goto fail;
                if (v.t == T_FLOAT) x = v.f;
                else if (v.t == T_INT && !v.big && v.i <= EXACT_INT && v.i >= -EXACT_INT)
                    x = (double)v.i;
                else goto fail;
                if (!(x >= -max_abs && x <= max_abs)) goto fail;
                d[j] = x;
            }
        } else {
            goto fail;
        }
    }
    return out; /* both keys seen: two entries, neither repeated */
fail:
    Py_XDECREF(out);
    return NULL;
}

enum { K_V, K_SESSION, K_SENSOR, K_SEQ, K_STEP, K_TIME, K_VEC, K_R, K_COUNT };

/* The shared reader: `sensor` NULL for a Command. */
static PyObject *read_msg(PyObject *const *args, Py_ssize_t nargs, int command) {
    Py_ssize_t want = command ? 5 : 6;
    if (nargs != want) {
        PyErr_Format(PyExc_TypeError, "_fastread: %zd arguments, expected %zd", nargs, want);
        return NULL;
    }
    /* measurement: payload, session, sensor, size, max_abs, max_bytes
       command:     payload, session, size, max_abs, max_bytes */
    Py_ssize_t a = command ? 1 : 2;
    Py_ssize_t sz_sess, sz_sens = 0;
    const char *sess = PyUnicode_AsUTF8AndSize(args[1], &sz_sess);
    const char *sens = command ? NULL : PyUnicode_AsUTF8AndSize(args[2], &sz_sens);
    Py_ssize_t size = PyLong_AsSsize_t(args[a + 1]);
    double max_abs = PyFloat_AsDouble(args[a + 2]);
    Py_ssize_t max_bytes = PyLong_AsSsize_t(args[a + 3]);
    if (sess == NULL || (!command && sens == NULL) || PyErr_Occurred()) return NULL;
    if (size < 0) {
        PyErr_SetString(PyExc_ValueError, "_fastread: size must be >= 0");
        return NULL;
    }
    Py_buffer buf;
    if (PyObject_GetBuffer(args[0], &buf, PyBUF_SIMPLE) < 0) return NULL;
    PyObject *vec = NULL, *res = NULL;
    int seen[K_COUNT] = {0};
    int64_t seq = 0, step = 0, stamp = 0;
    int has_step = 0, has_stamp = 0;
    if (buf.len > max_bytes) goto none;
    Rd r = {(const unsigned char *)buf.buf, (const unsigned char *)buf.buf + buf.len};
    Val v, k;
    if (next(&r, &v) || v.t != T_MAP) goto none;
    for (uint64_t e = v.n; e > 0; e--) {
        int id;
        if (next(&r, &k) || k.t != T_STR) goto none;
        if (is(&k, "v", 1)) id = K_V;
        else if (is(&k, "session", 7)) id = K_SESSION;
        else if (is(&k, "seq", 3)) id = K_SEQ;
        else if (is(&k, "step", 4)) id = K_STEP;
        else if (!command && is(&k, "sensor", 6)) id = K_SENSOR;
        else if (!command && is(&k, "t_ns", 4)) id = K_TIME;
        else if (!command && is(&k, "z", 1)) id = K_VEC;
        else if (!command && is(&k, "R", 1)) id = K_R;
        else if (command && is(&k, "issued_ns", 9)) id = K_TIME;
        else if (command && is(&k, "u", 1)) id = K_VEC;
        else goto none;
        if (seen[id]++) goto none;
        if (id == K_VEC) {
            vec = vector(&r, size, max_abs);
            if (vec == NULL) goto none;
            continue;
        }
        if (next(&r, &v)) goto none;
        switch (id) {
        case K_V:
            if (v.t != T_INT || v.big || v.i != 1) goto none;
            break;
        case K_SESSION:
            if (v.t != T_STR || v.n != (uint64_t)sz_sess || memcmp(v.s, sess, v.n)) goto none;
            break;
        case K_SENSOR:
            if (v.t != T_STR || v.n != (uint64_t)sz_sens || memcmp(v.s, sens, v.n)) goto none;
            break;
        case K_SEQ:
            if (v.t != T_INT || v.big || v.i < 0) goto none;
            seq = v.i;
            break;
        case K_STEP:
            if (v.t == T_NIL) break;
            if (v.t != T_INT || v.big || v.i < 0) goto none;
            step = v.i;
            has_step = 1;
            break;
        case K_TIME:
            if (v.t == T_NIL) break;
            if (v.t != T_INT || v.big) goto none;
            stamp = v.i;
            has_stamp = 1;
            break;
        case K_R:
            if (v.t != T_NIL) goto none;
            break;
        }
    }
    if (r.p != r.end || !seen[K_SESSION] || !seen[K_SEQ] || vec == NULL
        || (!command && !seen[K_SENSOR]) || has_step == has_stamp) goto none;
    {   /* (seq, step or None, stamp or None, vec), built directly (Py_BuildValue
           would parse its format string at every call) */
        PyObject *s = PyLong_FromLongLong((long long)seq);
        PyObject *o = PyLong_FromLongLong(has_step ? step : stamp);
        if (s == NULL || o == NULL || (res = PyTuple_New(4)) == NULL) {
            Py_XDECREF(s);
            Py_XDECREF(o);
            goto done;
        }
        PyTuple_SET_ITEM(res, 0, s);
        PyTuple_SET_ITEM(res, 1, has_step ? o : Py_NewRef(Py_None));
        PyTuple_SET_ITEM(res, 2, has_step ? Py_NewRef(Py_None) : o);
        PyTuple_SET_ITEM(res, 3, vec);
        vec = NULL; /* the tuple holds it */
    }
    goto done;
none:
    if (!PyErr_Occurred()) res = Py_NewRef(Py_None);
done:
    Py_XDECREF(vec);
    PyBuffer_Release(&buf);
    return res;
}

static PyObject *read_measurement(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    return read_msg(args, nargs, 0);
}

static PyObject *read_command(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    return read_msg(args, nargs, 1);
}

static PyMethodDef methods[] = {
    {"read_measurement", (PyCFunction)(void (*)(void))read_measurement, METH_FASTCALL,
     "read_measurement(payload, session, sensor, m, max_abs, max_bytes) -> "
     "(seq, step, t_ns, z) or None"},
    {"read_command", (PyCFunction)(void (*)(void))read_command, METH_FASTCALL,
     "read_command(payload, session, r, max_abs, max_bytes) -> (seq, step, issued_ns, u) "
     "or None"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_fastread",
    "The fast path of pd_service.intake: plain Measurement / Command readers, in C.", -1,
    methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__fastread(void) {
    import_array();
    return PyModule_Create(&module);
}

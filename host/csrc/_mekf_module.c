/* SPDX-License-Identifier: Apache-2.0 */
/*
 * CPython glue for mekf_likelihood.c: magcal.calib.likelihood._mekf. Arrays arrive through the buffer
 * protocol (no numpy headers needed to build this) and must be C-contiguous native float64:
 * the format and item size are checked, not just the byte count, so an int64 or float32
 * array is an error rather than a wrong result. The Python wrapper in
 * host/src/magcal/calib/likelihood/mekf.py prepares them.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <string.h>

#include "mekf_likelihood.h"

/* A buffer format that means one native-order IEEE double: "d" / "@d" (native), "=d"
 * (native order, standard size: 8 bytes like every platform CPython supports), and "<d"
 * or ">d"/"!d" when that order is the native one. */
static int is_native_float64(const char *fmt, Py_ssize_t itemsize)
{
    if (itemsize != 8 || itemsize != (Py_ssize_t)sizeof(double) || !fmt) return 0;
    const int little = PY_LITTLE_ENDIAN;
    char order = '@';
    if (fmt[0] == '@' || fmt[0] == '=' || fmt[0] == '<' || fmt[0] == '>' || fmt[0] == '!')
        order = *fmt++;
    if (fmt[0] != 'd' || fmt[1] != '\0') return 0;
    if (order == '<') return little;
    if (order == '>' || order == '!') return !little;
    return 1;
}

/* Prefix the pending exception's message with the argument name ("q_filt: ..."), keeping
 * its type. */
static void prefix_error(const char *name)
{
    PyObject *type, *value, *tb;
    PyErr_Fetch(&type, &value, &tb);
    PyErr_NormalizeException(&type, &value, &tb);
    PyObject *msg = value ? PyObject_Str(value) : NULL;
    if (msg) {
        PyErr_Format(type, "%s: %U", name, msg);
        Py_DECREF(msg);
        Py_XDECREF(type);
        Py_XDECREF(value);
        Py_XDECREF(tb);
    } else {
        PyErr_Clear();
        PyErr_Restore(type, value, tb);
    }
}

/* Acquire `obj` as `count` float64 values (count < 0: any number) into `buf`, writable
 * when `writable`. Returns the data, or NULL with an exception set. `buf` must start
 * zeroed; whether this succeeds or not, the caller releases it with release_buffer. */
static double *get_float64(PyObject *obj, Py_buffer *buf, Py_ssize_t count, int writable,
                           const char *name)
{
    const int flags = PyBUF_FORMAT | PyBUF_C_CONTIGUOUS | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, buf, flags) < 0) {
        buf->obj = NULL; /* nothing acquired: nothing to release */
        prefix_error(name);
        return NULL;
    }
    const char *fmt = buf->format ? buf->format : "B";
    if (!is_native_float64(buf->format, buf->itemsize)) {
        PyErr_Format(PyExc_TypeError,
                     "%s: expected float64 values, got buffer format '%s' (item size %zd)",
                     name, fmt, buf->itemsize);
        return NULL;
    }
    const Py_ssize_t got = buf->len / buf->itemsize;
    if (count >= 0 && got != count) {
        PyErr_Format(PyExc_ValueError, "%s: expected %zd float64 values, got %zd", name, count,
                     got);
        return NULL;
    }
    return (double *)buf->buf;
}

/* Acquire `obj` as a mask of `count` one-byte values (numpy bool '?' or uint8 'B'; 0 =
 * absent, anything else present) into `buf`, read-only. Returns the data, or NULL with an
 * exception set; released with release_buffer as get_float64's. */
static const unsigned char *get_mask(PyObject *obj, Py_buffer *buf, Py_ssize_t count,
                                     const char *name)
{
    if (PyObject_GetBuffer(obj, buf, PyBUF_FORMAT | PyBUF_C_CONTIGUOUS) < 0) {
        buf->obj = NULL;
        prefix_error(name);
        return NULL;
    }
    const char *fmt = buf->format ? buf->format : "B";
    if (fmt[0] == '@' || fmt[0] == '=' || fmt[0] == '<' || fmt[0] == '>' || fmt[0] == '!') ++fmt;
    if (buf->itemsize != 1 || (strcmp(fmt, "?") != 0 && strcmp(fmt, "B") != 0)) {
        PyErr_Format(PyExc_TypeError,
                     "%s: expected bool or uint8 values, got buffer format '%s' (item size %zd)",
                     name, buf->format ? buf->format : "B", buf->itemsize);
        return NULL;
    }
    if (buf->len != count) {
        PyErr_Format(PyExc_ValueError, "%s: expected %zd values, got %zd", name, count, buf->len);
        return NULL;
    }
    return (const unsigned char *)buf->buf;
}

static void release_buffer(Py_buffer *buf)
{
    if (buf->obj) PyBuffer_Release(buf); /* also resets buf->obj */
}

/* The buffers of one call: every one starts zeroed and is released at the single exit. */
enum {
    B_MODEL,
    B_DT,
    B_GYR,
    B_ACC,
    B_MAG,
    B_EXTRA,
    B_Q0,
    B_P0,
    B_OUT0, /* cost: q_filt; cost_grad: tape; fisher: info */
    B_OUT1, /* cost: innov;  cost_grad: grad; fisher: grad */
    B_OUT2, /* cost: normalised; fisher: directions */
    B_HAS_ACC,
    B_HAS_MAG,
    B_TURN_VAR,
    B_COUNT
};

typedef struct {
    Py_buffer b[B_COUNT];
} buffers_t;

static void release_all(buffers_t *bufs)
{
    for (int i = 0; i < B_COUNT; ++i) release_buffer(&bufs->b[i]);
}

/* The inputs shared by both entry points. `dt` sets the number of samples n; acc_extra_var
 * (in[5]), the masks has_acc, has_mag (in[8], in[9]) and turn_var (in[10]) may be None (no
 * inflation; present at every sample). Returns 0 with an exception set. */
static int prepare(PyObject *const *in, double g, int use_mag, buffers_t *bufs,
                   mc_mekf_model_t *model, mc_mekf_data_t *data)
{
    const double *v = get_float64(in[0], &bufs->b[B_MODEL], MC_MEKF_MODEL_DOUBLES, 0, "model");
    if (!v) return 0;
    memcpy(model, v, sizeof *model); /* the struct is flat: see mc_mekf_model_is_flat */
    if (!(data->dt = get_float64(in[1], &bufs->b[B_DT], -1, 0, "dt"))) return 0;
    const Py_ssize_t n = bufs->b[B_DT].len / (Py_ssize_t)sizeof(double);
    if (n < 1) {
        PyErr_SetString(PyExc_ValueError, "dt: no samples");
        return 0;
    }
    if (n > PY_SSIZE_T_MAX / MC_MEKF_TAPE_DOUBLES) { /* keeps every count below exact */
        PyErr_Format(PyExc_ValueError, "dt: too many samples (%zd)", n);
        return 0;
    }
    data->n = (size_t)n;
    if (!(data->gyr = get_float64(in[2], &bufs->b[B_GYR], 3 * n, 0, "gyr")) ||
        !(data->acc = get_float64(in[3], &bufs->b[B_ACC], 3 * n, 0, "acc")) ||
        !(data->mag = get_float64(in[4], &bufs->b[B_MAG], 3 * n, 0, "mag")))
        return 0;
    data->acc_extra_var = NULL;
    if (in[5] != Py_None &&
        !(data->acc_extra_var = get_float64(in[5], &bufs->b[B_EXTRA], n, 0, "acc_extra_var")))
        return 0;
    const double *q0 = get_float64(in[6], &bufs->b[B_Q0], 4, 0, "q0");
    const double *P0 = q0 ? get_float64(in[7], &bufs->b[B_P0], 9, 0, "P0") : NULL;
    if (!P0) return 0;
    memcpy(data->q0, q0, sizeof data->q0);
    memcpy(data->P0, P0, sizeof data->P0);
    data->has_acc = data->has_mag = NULL;
    if (in[8] != Py_None && !(data->has_acc = get_mask(in[8], &bufs->b[B_HAS_ACC], n, "has_acc")))
        return 0;
    if (in[9] != Py_None && !(data->has_mag = get_mask(in[9], &bufs->b[B_HAS_MAG], n, "has_mag")))
        return 0;
    data->turn_var = NULL;
    if (in[10] != Py_None &&
        !(data->turn_var = get_float64(in[10], &bufs->b[B_TURN_VAR], n, 0, "turn_var")))
        return 0;
    data->g = g;
    data->use_mag = use_mag;
    return 1;
}

/* An optional output: None gives NULL with *ok untouched. */
static double *optional_output(PyObject *obj, Py_buffer *buf, Py_ssize_t count, const char *name,
                               int *ok)
{
    if (obj == Py_None || !*ok) return NULL;
    double *p = get_float64(obj, buf, count, 1, name);
    if (!p) *ok = 0;
    return p;
}

static PyObject *py_cost(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *in[11], *q_obj, *innov_obj, *norm_obj;
    double g;
    int use_mag;
    in[8] = in[9] = in[10] = Py_None;
    if (!PyArg_ParseTuple(args, "OOOOOOdOOpOOO|OOO", &in[0], &in[1], &in[2], &in[3], &in[4],
                          &in[5], &g, &in[6], &in[7], &use_mag, &q_obj, &innov_obj, &norm_obj,
                          &in[8], &in[9], &in[10]))
        return NULL;
    buffers_t bufs;
    memset(&bufs, 0, sizeof bufs);
    mc_mekf_model_t model;
    mc_mekf_data_t data;
    mc_mekf_outputs_t out;
    int ok = prepare(in, g, use_mag, &bufs, &model, &data);
    if (ok) {
        const Py_ssize_t n = (Py_ssize_t)data.n;
        out.q_filt = optional_output(q_obj, &bufs.b[B_OUT0], 4 * n, "q_filt", &ok);
        out.innov = optional_output(innov_obj, &bufs.b[B_OUT1], 6 * n, "innov", &ok);
        out.normalised = optional_output(norm_obj, &bufs.b[B_OUT2], 6 * n, "normalised", &ok);
    }
    double cost = NAN;
    if (ok) {
        Py_BEGIN_ALLOW_THREADS
        cost = mc_mekf_cost(&model, &data, &out);
        Py_END_ALLOW_THREADS
    }
    release_all(&bufs);
    return ok ? PyFloat_FromDouble(cost) : NULL;
}

static PyObject *py_cost_grad(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *in[11], *tape_obj, *grad_obj;
    double g;
    int use_mag;
    in[8] = in[9] = in[10] = Py_None;
    if (!PyArg_ParseTuple(args, "OOOOOOdOOpOO|OOO", &in[0], &in[1], &in[2], &in[3], &in[4],
                          &in[5], &g, &in[6], &in[7], &use_mag, &tape_obj, &grad_obj, &in[8],
                          &in[9], &in[10]))
        return NULL;
    buffers_t bufs;
    memset(&bufs, 0, sizeof bufs);
    mc_mekf_model_t model, grad;
    mc_mekf_data_t data;
    double *tape = NULL, *grad_out = NULL;
    const int ok =
        prepare(in, g, use_mag, &bufs, &model, &data) &&
        (tape = get_float64(tape_obj, &bufs.b[B_OUT0],
                            MC_MEKF_TAPE_DOUBLES * (Py_ssize_t)data.n, 1, "tape")) != NULL &&
        (grad_out = get_float64(grad_obj, &bufs.b[B_OUT1], MC_MEKF_MODEL_DOUBLES, 1, "grad")) !=
            NULL;
    double cost = NAN;
    if (ok) {
        const size_t tape_len = MC_MEKF_TAPE_DOUBLES * data.n;
        Py_BEGIN_ALLOW_THREADS
        cost = mc_mekf_cost_grad(&model, &data, tape, tape_len, &grad);
        Py_END_ALLOW_THREADS
        memcpy(grad_out, &grad, sizeof grad);
    }
    release_all(&bufs);
    return ok ? PyFloat_FromDouble(cost) : NULL;
}

static PyObject *py_fisher(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *in[11], *dir_obj, *info_obj, *grad_obj;
    double g;
    int use_mag;
    in[8] = in[9] = in[10] = Py_None;
    if (!PyArg_ParseTuple(args, "OOOOOOdOOpOOO|OOO", &in[0], &in[1], &in[2], &in[3], &in[4],
                          &in[5], &g, &in[6], &in[7], &use_mag, &dir_obj, &info_obj, &grad_obj,
                          &in[8], &in[9], &in[10]))
        return NULL;
    buffers_t bufs;
    memset(&bufs, 0, sizeof bufs);
    mc_mekf_model_t model;
    mc_mekf_data_t data;
    const double *dirs = NULL;
    double *info = NULL, *grad = NULL;
    Py_ssize_t k = 0;
    int ok = prepare(in, g, use_mag, &bufs, &model, &data) &&
             (dirs = get_float64(dir_obj, &bufs.b[B_OUT2], -1, 0, "directions")) != NULL;
    if (ok) {
        const Py_ssize_t len = bufs.b[B_OUT2].len / (Py_ssize_t)sizeof(double);
        k = len / MC_MEKF_MODEL_DOUBLES;
        if (k < 1 || k * MC_MEKF_MODEL_DOUBLES != len || k > MC_MEKF_FISHER_MAX_DIRECTIONS) {
            PyErr_Format(PyExc_ValueError,
                         "directions: expected k x %d values with 1 <= k <= %d, got %zd values",
                         MC_MEKF_MODEL_DOUBLES, MC_MEKF_FISHER_MAX_DIRECTIONS, len);
            ok = 0;
        }
    }
    ok = ok && (info = get_float64(info_obj, &bufs.b[B_OUT0], k * k, 1, "info")) != NULL &&
         (grad = get_float64(grad_obj, &bufs.b[B_OUT1], k, 1, "grad")) != NULL;
    double cost = NAN;
    double *work = NULL;
    const size_t work_len = MC_MEKF_FISHER_WORK_DOUBLES((size_t)k);
    if (ok && !(work = PyMem_RawMalloc(work_len * sizeof *work))) {
        PyErr_NoMemory();
        ok = 0;
    }
    if (ok) {
        Py_BEGIN_ALLOW_THREADS
        cost = mc_mekf_fisher(&model, &data, dirs, (size_t)k, work, work_len, info, grad);
        Py_END_ALLOW_THREADS
    }
    PyMem_RawFree(work);
    release_all(&bufs);
    return ok ? PyFloat_FromDouble(cost) : NULL;
}

static PyMethodDef methods[] = {
    {"cost", py_cost, METH_VARARGS,
     "cost(model, dt, gyr, acc, mag, acc_extra_var, g, q0, P0, use_mag, q_out, innov_out, "
     "norm_out[, has_acc, has_mag, turn_var]) -> cost\n\nArrays: C-contiguous float64; "
     "acc_extra_var, turn_var and the outputs may be None. has_acc, has_mag: (n) bool or "
     "uint8, which measurements each sample has; None (the default) means all."},
    {"cost_grad", py_cost_grad, METH_VARARGS,
     "cost_grad(model, dt, gyr, acc, mag, acc_extra_var, g, q0, P0, use_mag, tape, grad_out"
     "[, has_acc, has_mag, turn_var]) -> cost\n\nArrays: C-contiguous float64; tape holds "
     "TAPE_DOUBLES_PER_SAMPLE * n and grad_out MODEL_DOUBLES values; the masks and turn_var "
     "as in cost."},
    {"fisher", py_fisher, METH_VARARGS,
     "fisher(model, dt, gyr, acc, mag, acc_extra_var, g, q0, P0, use_mag, directions, "
     "info_out, grad_out[, has_acc, has_mag, turn_var]) -> cost\n\nThe Fisher information "
     "(k, k) and the cost's derivative (k) along the k rows of directions (k, MODEL_DOUBLES); "
     "the other arguments as in cost."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_mekf",
                                    "Native MEKF likelihood and gradient.", -1, methods,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__mekf(void)
{
    PyObject *mod = PyModule_Create(&module);
    /* The layout sizes, so the Python side never hard-codes them. */
    if (mod && (PyModule_AddIntConstant(mod, "TAPE_DOUBLES_PER_SAMPLE", MC_MEKF_TAPE_DOUBLES) < 0 ||
                PyModule_AddIntConstant(mod, "MODEL_DOUBLES", MC_MEKF_MODEL_DOUBLES) < 0 ||
                PyModule_AddIntConstant(mod, "FISHER_MAX_DIRECTIONS",
                                        MC_MEKF_FISHER_MAX_DIRECTIONS) < 0)) {
        Py_DECREF(mod);
        return NULL;
    }
    return mod;
}

/*
 * CPython glue for mekf_likelihood.c: magcal.calib._mekf. Arrays arrive through the buffer
 * protocol as C-contiguous float64 (the Python wrapper in magcal/calib/native.py prepares
 * them), so no numpy headers are needed to build this.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include "mekf_likelihood.h"

#define MODEL_DOUBLES 45

static int check_len(const Py_buffer *b, Py_ssize_t count, const char *name)
{
    if (b->len != count * (Py_ssize_t)sizeof(double)) {
        PyErr_Format(PyExc_ValueError, "%s: expected %zd float64 values, got %zd bytes", name,
                     count, b->len);
        return 0;
    }
    return 1;
}

static void load_model(const double *v, mc_mekf_model_t *m)
{
    memcpy(m->D, v, 9 * sizeof(double));
    memcpy(m->o, v + 9, 3 * sizeof(double));
    memcpy(m->m, v + 12, 3 * sizeof(double));
    memcpy(m->bias, v + 15, 3 * sizeof(double));
    memcpy(m->Sw, v + 18, 9 * sizeof(double));
    memcpy(m->Sa, v + 27, 9 * sizeof(double));
    memcpy(m->Sm, v + 36, 9 * sizeof(double));
}

static void store_model(const mc_mekf_model_t *m, double *v)
{
    memcpy(v, m->D, 9 * sizeof(double));
    memcpy(v + 9, m->o, 3 * sizeof(double));
    memcpy(v + 12, m->m, 3 * sizeof(double));
    memcpy(v + 15, m->bias, 3 * sizeof(double));
    memcpy(v + 18, m->Sw, 9 * sizeof(double));
    memcpy(v + 27, m->Sa, 9 * sizeof(double));
    memcpy(v + 36, m->Sm, 9 * sizeof(double));
}

typedef struct {
    Py_buffer model, dt, gyr, acc, mag, extra, q0, P0;
} inputs_t;

static void release_inputs(inputs_t *in)
{
    Py_buffer *all[] = {&in->model, &in->dt, &in->gyr, &in->acc,
                        &in->mag,   &in->extra, &in->q0, &in->P0};
    for (size_t i = 0; i < sizeof all / sizeof all[0]; ++i)
        if (all[i]->obj) PyBuffer_Release(all[i]);
}

static int prepare(inputs_t *in, double g, int use_mag, mc_mekf_model_t *model,
                   mc_mekf_data_t *data)
{
    const Py_ssize_t n = in->dt.len / (Py_ssize_t)sizeof(double);
    if (n < 1) {
        PyErr_SetString(PyExc_ValueError, "dt: no samples");
        return 0;
    }
    if (!check_len(&in->model, MODEL_DOUBLES, "model") || !check_len(&in->dt, n, "dt") ||
        !check_len(&in->gyr, 3 * n, "gyr") || !check_len(&in->acc, 3 * n, "acc") ||
        !check_len(&in->mag, 3 * n, "mag") || !check_len(&in->extra, n, "acc_extra_var") ||
        !check_len(&in->q0, 4, "q0") || !check_len(&in->P0, 9, "P0"))
        return 0;
    load_model((const double *)in->model.buf, model);
    data->n = (size_t)n;
    data->dt = (const double *)in->dt.buf;
    data->gyr = (const double *)in->gyr.buf;
    data->acc = (const double *)in->acc.buf;
    data->mag = (const double *)in->mag.buf;
    data->acc_extra_var = (const double *)in->extra.buf;
    data->g = g;
    memcpy(data->q0, in->q0.buf, 4 * sizeof(double));
    memcpy(data->P0, in->P0.buf, 9 * sizeof(double));
    data->use_mag = use_mag;
    return 1;
}

static double *optional_output(PyObject *obj, Py_buffer *buf, Py_ssize_t count, const char *name,
                               int *ok)
{
    if (obj == Py_None) return NULL;
    if (PyObject_GetBuffer(obj, buf, PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS) < 0) {
        *ok = 0;
        return NULL;
    }
    if (!check_len(buf, count, name)) {
        PyBuffer_Release(buf);
        buf->obj = NULL;
        *ok = 0;
        return NULL;
    }
    return (double *)buf->buf;
}

static PyObject *py_cost(PyObject *self, PyObject *args)
{
    (void)self;
    inputs_t in = {0};
    double g;
    int use_mag;
    PyObject *q_obj, *innov_obj, *norm_obj;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*dy*y*pOOO", &in.model, &in.dt, &in.gyr, &in.acc,
                          &in.mag, &in.extra, &g, &in.q0, &in.P0, &use_mag, &q_obj, &innov_obj,
                          &norm_obj))
        return NULL;
    mc_mekf_model_t model;
    mc_mekf_data_t data;
    if (!prepare(&in, g, use_mag, &model, &data)) {
        release_inputs(&in);
        return NULL;
    }
    Py_buffer qb = {0}, ib = {0}, nb = {0};
    int ok = 1;
    mc_mekf_outputs_t out;
    out.q_filt = optional_output(q_obj, &qb, 4 * (Py_ssize_t)data.n, "q_filt", &ok);
    out.innov = ok ? optional_output(innov_obj, &ib, 6 * (Py_ssize_t)data.n, "innov", &ok) : NULL;
    out.normalised =
        ok ? optional_output(norm_obj, &nb, 6 * (Py_ssize_t)data.n, "normalised", &ok) : NULL;
    double cost = NAN;
    if (ok) {
        Py_BEGIN_ALLOW_THREADS
        cost = mc_mekf_cost(&model, &data, &out);
        Py_END_ALLOW_THREADS
    }
    if (qb.obj) PyBuffer_Release(&qb);
    if (ib.obj) PyBuffer_Release(&ib);
    if (nb.obj) PyBuffer_Release(&nb);
    release_inputs(&in);
    if (!ok) return NULL;
    return PyFloat_FromDouble(cost);
}

static PyObject *py_cost_grad(PyObject *self, PyObject *args)
{
    (void)self;
    inputs_t in = {0};
    double g;
    int use_mag;
    Py_buffer tape = {0}, gradb = {0};
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*dy*y*pw*w*", &in.model, &in.dt, &in.gyr, &in.acc,
                          &in.mag, &in.extra, &g, &in.q0, &in.P0, &use_mag, &tape, &gradb))
        return NULL;
    mc_mekf_model_t model, grad;
    mc_mekf_data_t data;
    PyObject *result = NULL;
    if (prepare(&in, g, use_mag, &model, &data) &&
        check_len(&tape, MC_MEKF_TAPE_DOUBLES * (Py_ssize_t)data.n, "tape") &&
        check_len(&gradb, MODEL_DOUBLES, "grad")) {
        double cost;
        double *tape_buf = (double *)tape.buf;
        Py_BEGIN_ALLOW_THREADS
        cost = mc_mekf_cost_grad(&model, &data, tape_buf, &grad);
        Py_END_ALLOW_THREADS
        store_model(&grad, (double *)gradb.buf);
        result = PyFloat_FromDouble(cost);
    }
    PyBuffer_Release(&tape);
    PyBuffer_Release(&gradb);
    release_inputs(&in);
    return result;
}

static PyMethodDef methods[] = {
    {"cost", py_cost, METH_VARARGS,
     "cost(model, dt, gyr, acc, mag, extra, g, q0, P0, use_mag, q_out, innov_out, norm_out)"},
    {"cost_grad", py_cost_grad, METH_VARARGS,
     "cost_grad(model, dt, gyr, acc, mag, extra, g, q0, P0, use_mag, tape, grad_out) "
     "-> cost"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_mekf",
                                    "Native MEKF likelihood and gradient.", -1, methods,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__mekf(void)
{
    PyObject *mod = PyModule_Create(&module);
    /* The tape size per sample, so the Python side never hard-codes the layout. */
    if (mod && PyModule_AddIntConstant(mod, "TAPE_DOUBLES_PER_SAMPLE", MC_MEKF_TAPE_DOUBLES) < 0) {
        Py_DECREF(mod);
        return NULL;
    }
    return mod;
}

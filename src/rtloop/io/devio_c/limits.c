/* The compiled twin of io/limits.py: CommandGuard.apply (with the copies of io/host.py into the commands).
 *
 * Included by ../_devio.c, which builds every part as one translation unit (so each function stays
 * static and inlinable); same arithmetic in the same order as the reference, bit for bit. */

/* An int64 vector of counters held for the object's life (numpy int64: format 'l' or 'q'). */
static int get_counters(PyObject *obj, Py_buffer *view, const char *what) {
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0) {
        return -1;
    }
    if (view->itemsize != 8 || view->format == NULL || (strcmp(view->format, "l") != 0 &&
                                                        strcmp(view->format, "q") != 0)) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_TypeError, "%s: a contiguous int64 vector is needed", what);
        return -1;
    }
    return 0;
}

/* ------------------------------------------------------------------------------------------ */
/* Guard: copies from the task's outputs into a device's commands, then finite, clamp, rate.  */

typedef struct {
    PyObject_HEAD
    Py_buffer u, low, high, step_max, last, out, clamped, rate_hits;
    Py_ssize_t n;
    int rate_limited;
    CopyPairs copies;
    int held; /* how many of the eight vectors are held (for a partial failure) */
} Guard;

static void Guard_release(Guard *self) {
    Py_buffer *vectors[8] = {&self->u,    &self->low, &self->high,    &self->step_max,
                             &self->last, &self->out, &self->clamped, &self->rate_hits};
    for (int i = 0; i < self->held; i++) {
        PyBuffer_Release(vectors[i]);
    }
    self->held = 0;
    CopyPairs_release(&self->copies);
}

static void Guard_dealloc(Guard *self) {
    Guard_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* Guard(u, low, high, step_max, last, out, clamped, rate_hits, copies, rate_limited): copies is a
 * sequence of (source, target) float64 vectors of equal length (task y slice -> device u slice);
 * clamped and rate_hits are int64 counters per command (CommandGuard.clamped, .rate_limited_cycles). */
static int Guard_init(Guard *self, PyObject *args, PyObject *kwargs) {
    PyObject *objects[8], *copies;
    int rate_limited;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOp", &objects[0], &objects[1], &objects[2], &objects[3], &objects[4],
                          &objects[5], &objects[6], &objects[7], &copies, &rate_limited)) {
        return -1;
    }
    Guard_release(self);
    Py_buffer *vectors[8] = {&self->u,    &self->low, &self->high,    &self->step_max,
                             &self->last, &self->out, &self->clamped, &self->rate_hits};
    const char *names[8] = {"u", "low", "high", "step_max", "last", "out", "clamped", "rate_hits"};
    for (int i = 0; i < 8; i++) {
        int got = i < 6 ? get_vector(objects[i], vectors[i], i >= 4, names[i])
                        : get_counters(objects[i], vectors[i], names[i]);
        if (got < 0) {
            goto fail;
        }
        self->held = i + 1;
    }
    self->n = self->u.len / 8;
    for (int i = 1; i < 8; i++) {
        if (vectors[i]->len != self->u.len) {
            PyErr_SetString(PyExc_ValueError, "the guard's vectors differ in length");
            goto fail;
        }
    }
    self->rate_limited = rate_limited;
    if (CopyPairs_get(&self->copies, copies) < 0) {
        goto fail;
    }
    return 0;
fail:
    Guard_release(self);
    return -1;
}

/* apply() -> -1 when the commands in ``out`` are ready, else the index of the first
 * non-finite command (nothing is written then: the caller raises the fault). */
static PyObject *Guard_apply(Guard *self, PyObject *Py_UNUSED(ignored)) {
    if (self->held != 8) {
        PyErr_SetString(PyExc_ValueError, "the guard is released");
        return NULL;
    }
    CopyPairs_run(&self->copies);
    const double *u = self->u.buf, *low = self->low.buf, *high = self->high.buf, *step = self->step_max.buf;
    double *last = self->last.buf, *out = self->out.buf;
    int64_t *clamped = self->clamped.buf, *rate_hits = self->rate_hits.buf;
    Py_ssize_t n = self->n;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (!isfinite(u[i])) {
            return PyLong_FromSsize_t(i);
        }
    }
    for (Py_ssize_t i = 0; i < n; i++) { /* np.minimum(u, high), np.maximum(out, low) */
        double value = u[i] < high[i] ? u[i] : high[i];
        out[i] = value > low[i] ? value : low[i];
        clamped[i] += out[i] != u[i]; /* np.not_equal(out, u), added to the count */
    }
    if (self->rate_limited) { /* delta = out - last, clipped to ±step, out = last + delta: numpy's order */
        for (Py_ssize_t i = 0; i < n; i++) {
            double delta = out[i] - last[i];
            rate_hits[i] += (delta > step[i]) + (delta < -step[i]); /* np.greater, np.less, each added */
            delta = delta < step[i] ? delta : step[i];
            delta = delta > -step[i] ? delta : -step[i];
            out[i] = last[i] + delta;
        }
    }
    memcpy(last, out, (size_t)n * sizeof(double));
    return PyLong_FromLong(-1);
}

static PyObject *Guard_release_method(Guard *self, PyObject *Py_UNUSED(ignored)) {
    Guard_release(self);
    Py_RETURN_NONE;
}

static PyMethodDef Guard_methods[] = {
    {"apply", (PyCFunction)Guard_apply, METH_NOARGS, "Copy, check, clamp, rate limit: -1, or a non-finite index."},
    {"release", (PyCFunction)Guard_release_method, METH_NOARGS, "Let go of the vectors."},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject GuardType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "rtloop.io._devio.Guard",
    .tp_basicsize = sizeof(Guard),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Guard_init,
    .tp_dealloc = (destructor)Guard_dealloc,
    .tp_methods = Guard_methods,
    .tp_doc = "Guard(u, low, high, step_max, last, out, clamped, rate_hits, copies, rate_limited): a device's "
              "commands, guarded and counted.",
};

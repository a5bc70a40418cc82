/* The compiled twin of io/host.py: the copies between a device and its task (DeviceHost, the numpy path), and the
 * float64 vectors every object here holds for its life.
 *
 * Included by ../_devio.c, which builds every part as one translation unit (so each function stays
 * static and inlinable); same arithmetic in the same order as the reference, bit for bit. */

/* rtloop.errors.LibcError, taken at the module's import: a refused ioctl raises what rtloop.linux.rt.ioctl
 * raises in the Python reference, naming the request and the descriptor, with the errno. */
static PyObject *libc_error_type;

static void set_ioctl_error(const char *name, int fd) {
    int saved = errno;
    PyObject *error = PyObject_CallFunction(libc_error_type, "Ni", PyUnicode_FromFormat("ioctl(%s) on fd %d", name, fd),
                                            saved);
    if (error != NULL) {
        PyErr_SetObject((PyObject *)Py_TYPE(error), error);
        Py_DECREF(error);
    }
}

/* A float64 vector held for the object's life (a numpy array or a view of one, contiguous). */
static int get_vector(PyObject *obj, Py_buffer *view, int writable, const char *what) {
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) < 0) {
        return -1;
    }
    if (view->itemsize != 8 || view->format == NULL || strcmp(view->format, "d") != 0) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_TypeError, "%s: a contiguous float64 vector is needed", what);
        return -1;
    }
    return 0;
}

/* ------------------------------------------------------------------------------------------ */
/* Copy pairs: float64 vectors copied source -> target (held for the owner's life).            */

typedef struct {
    Py_ssize_t n; /* how many pairs are held (for a partial failure) */
    Py_buffer *sources, *targets;
} CopyPairs;

static void CopyPairs_release(CopyPairs *pairs) {
    for (Py_ssize_t i = 0; i < pairs->n; i++) {
        PyBuffer_Release(&pairs->sources[i]);
        PyBuffer_Release(&pairs->targets[i]);
    }
    PyMem_Free(pairs->sources);
    PyMem_Free(pairs->targets);
    pairs->sources = pairs->targets = NULL;
    pairs->n = 0;
}

/* Hold each (source, target) of the sequence ``copies``; on failure what was held is let go. */
static int CopyPairs_get(CopyPairs *pairs, PyObject *copies) {
    PyObject *items = PySequence_Fast(copies, "copies: a sequence of (source, target) pairs");
    if (items == NULL) {
        return -1;
    }
    Py_ssize_t count = PySequence_Fast_GET_SIZE(items);
    pairs->sources = PyMem_Calloc(count ? count : 1, sizeof(Py_buffer));
    pairs->targets = PyMem_Calloc(count ? count : 1, sizeof(Py_buffer));
    if (pairs->sources == NULL || pairs->targets == NULL) {
        PyErr_NoMemory();
        goto fail;
    }
    for (Py_ssize_t i = 0; i < count; i++) {
        PyObject *source, *target;
        if (!PyArg_ParseTuple(PySequence_Fast_GET_ITEM(items, i), "OO", &source, &target) ||
            get_vector(source, &pairs->sources[i], 0, "copy source") < 0) {
            goto fail;
        }
        if (get_vector(target, &pairs->targets[i], 1, "copy target") < 0) {
            PyBuffer_Release(&pairs->sources[i]); /* not counted in n yet */
            goto fail;
        }
        pairs->n = i + 1;
        if (pairs->sources[i].len != pairs->targets[i].len) {
            PyErr_SetString(PyExc_ValueError, "a copy's source and target differ in length");
            goto fail;
        }
    }
    Py_DECREF(items);
    return 0;
fail:
    Py_DECREF(items);
    CopyPairs_release(pairs);
    return -1;
}

static void CopyPairs_run(const CopyPairs *pairs) {
    for (Py_ssize_t i = 0; i < pairs->n; i++) {
        memcpy(pairs->targets[i].buf, pairs->sources[i].buf, (size_t)pairs->targets[i].len);
    }
}


/* ------------------------------------------------------------------------------------------ */
/* Copies: a device's readings into the task's inputs.                                          */

typedef struct {
    PyObject_HEAD
    CopyPairs copies;
} Copies;

static void Copies_dealloc(Copies *self) {
    CopyPairs_release(&self->copies);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int Copies_init(Copies *self, PyObject *args, PyObject *kwargs) {
    PyObject *copies;
    if (!PyArg_ParseTuple(args, "O", &copies)) {
        return -1;
    }
    CopyPairs_release(&self->copies);
    return CopyPairs_get(&self->copies, copies);
}

/* run() -> -1 when every value copied is finite, else the index of the first that is not,
 * counted over the pairs in order: a NaN reading must not reach a step unnoticed (the caller
 * raises the fault naming it; readings allowed to be non-finite go through another Copies). */
static PyObject *Copies_run(Copies *self, PyObject *Py_UNUSED(ignored)) {
    CopyPairs_run(&self->copies);
    Py_ssize_t at = 0;
    for (Py_ssize_t i = 0; i < self->copies.n; i++) {
        const double *values = self->copies.targets[i].buf;
        Py_ssize_t n = self->copies.targets[i].len / (Py_ssize_t)sizeof(double);
        for (Py_ssize_t j = 0; j < n; j++) {
            if (!isfinite(values[j])) {
                return PyLong_FromSsize_t(at + j);
            }
        }
        at += n;
    }
    return PyLong_FromLong(-1);
}

static PyObject *Copies_release_method(Copies *self, PyObject *Py_UNUSED(ignored)) {
    CopyPairs_release(&self->copies);
    Py_RETURN_NONE;
}

static PyMethodDef Copies_methods[] = {
    {"run", (PyCFunction)Copies_run, METH_NOARGS, "Copy every source into its target: -1, or a non-finite index."},
    {"release", (PyCFunction)Copies_release_method, METH_NOARGS, "Let go of the vectors."},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject CopiesType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "rtloop.io._devio.Copies",
    .tp_basicsize = sizeof(Copies),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Copies_init,
    .tp_dealloc = (destructor)Copies_dealloc,
    .tp_methods = Copies_methods,
    .tp_doc = "Copies(pairs): float64 vectors copied source -> target by run().",
};

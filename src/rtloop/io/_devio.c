/* The devices' per-cycle work in C: the command guard, signals packed into and out of frame
 * bytes, and a CAN socket drained into the newest copy of each declared frame.
 *
 * Each is the compiled twin of a Python reference that stays the fallback and is tested
 * against it: Guard <-> io/limits.py CommandGuard.apply (+ the copies of io/host.py),
 * Layout <-> io/bytelayout.py ByteLayout.pack_into/unpack_from, CanReceiver <->
 * io/cansocket.py CanSocket._drain. Same arithmetic in the same order, so the results are
 * bit for bit the Python ones. Every buffer a cycle touches is acquired once, when the
 * object is built; a cycle allocates nothing. Built by pip with the system compiler
 * (optional: without a compiler the Python path runs).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <errno.h>
#include <math.h>
#include <poll.h>
#include <stdint.h>
#include <string.h>
#include <sys/socket.h>

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
/* Guard: copies from the task's outputs into a device's commands, then finite, clamp, rate.  */

typedef struct {
    PyObject_HEAD
    Py_buffer u, low, high, step_max, last, out;
    Py_ssize_t n;
    int rate_limited;
    CopyPairs copies;
    int held; /* how many of the six vectors are held (for a partial failure) */
} Guard;

static void Guard_release(Guard *self) {
    Py_buffer *vectors[6] = {&self->u, &self->low, &self->high, &self->step_max, &self->last, &self->out};
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

/* Guard(u, low, high, step_max, last, out, copies, rate_limited): copies is a sequence of
 * (source, target) float64 vectors of equal length (task y slice -> device u slice). */
static int Guard_init(Guard *self, PyObject *args, PyObject *kwargs) {
    PyObject *objects[6], *copies;
    int rate_limited;
    if (!PyArg_ParseTuple(args, "OOOOOOOp", &objects[0], &objects[1], &objects[2], &objects[3], &objects[4],
                          &objects[5], &copies, &rate_limited)) {
        return -1;
    }
    Guard_release(self);
    Py_buffer *vectors[6] = {&self->u, &self->low, &self->high, &self->step_max, &self->last, &self->out};
    const char *names[6] = {"u", "low", "high", "step_max", "last", "out"};
    for (int i = 0; i < 6; i++) {
        if (get_vector(objects[i], vectors[i], i >= 4, names[i]) < 0) {
            goto fail;
        }
        self->held = i + 1;
    }
    self->n = self->u.len / 8;
    for (int i = 1; i < 6; i++) {
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
    if (self->held != 6) {
        PyErr_SetString(PyExc_ValueError, "the guard is released");
        return NULL;
    }
    CopyPairs_run(&self->copies);
    const double *u = self->u.buf, *low = self->low.buf, *high = self->high.buf, *step = self->step_max.buf;
    double *last = self->last.buf, *out = self->out.buf;
    Py_ssize_t n = self->n;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (!isfinite(u[i])) {
            return PyLong_FromSsize_t(i);
        }
    }
    for (Py_ssize_t i = 0; i < n; i++) { /* np.minimum(u, high), np.maximum(out, low) */
        double value = u[i] < high[i] ? u[i] : high[i];
        out[i] = value > low[i] ? value : low[i];
    }
    if (self->rate_limited) { /* delta = out - last, clipped to ±step, out = last + delta: numpy's order */
        for (Py_ssize_t i = 0; i < n; i++) {
            double delta = out[i] - last[i];
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
    .tp_doc = "Guard(u, low, high, step_max, last, out, copies, rate_limited): a device's commands, guarded.",
};

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

static PyObject *Copies_run(Copies *self, PyObject *Py_UNUSED(ignored)) {
    CopyPairs_run(&self->copies);
    Py_RETURN_NONE;
}

static PyObject *Copies_release_method(Copies *self, PyObject *Py_UNUSED(ignored)) {
    CopyPairs_release(&self->copies);
    Py_RETURN_NONE;
}

static PyMethodDef Copies_methods[] = {
    {"run", (PyCFunction)Copies_run, METH_NOARGS, "Copy every source into its target."},
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

/* ------------------------------------------------------------------------------------------ */
/* Layout: signals at fixed places in a frame, value = raw * scale + offset.                   */

typedef struct {
    char code;           /* struct code: B b H h I i Q q f d */
    int size;            /* bytes */
    int is_signed;
    int big_endian;
    Py_ssize_t start;    /* byte offset from the frame's ``at`` */
    double scale, offset;
} FieldPlan;

typedef struct {
    PyObject_HEAD
    Py_ssize_t n;
    FieldPlan *fields;
} Layout;

static void Layout_dealloc(Layout *self) {
    PyMem_Free(self->fields);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* Layout(fields): each field (code, start_byte, scale, offset, big_endian). */
static int Layout_init(Layout *self, PyObject *args, PyObject *kwargs) {
    PyObject *fields;
    if (!PyArg_ParseTuple(args, "O", &fields)) {
        return -1;
    }
    PyObject *items = PySequence_Fast(fields, "fields: a sequence of (code, start, scale, offset, big_endian)");
    if (items == NULL) {
        return -1;
    }
    Py_ssize_t count = PySequence_Fast_GET_SIZE(items);
    PyMem_Free(self->fields);
    self->fields = PyMem_Calloc(count ? count : 1, sizeof(FieldPlan));
    self->n = 0;
    if (self->fields == NULL) {
        PyErr_NoMemory();
        goto fail;
    }
    for (Py_ssize_t i = 0; i < count; i++) {
        FieldPlan *f = &self->fields[i];
        const char *code;
        int big;
        if (!PyArg_ParseTuple(PySequence_Fast_GET_ITEM(items, i), "snddp", &code, &f->start, &f->scale, &f->offset,
                              &big)) {
            goto fail;
        }
        f->code = code[0];
        f->big_endian = big;
        f->is_signed = (f->code == 'b' || f->code == 'h' || f->code == 'i' || f->code == 'q');
        switch (f->code) {
        case 'B': case 'b': f->size = 1; break;
        case 'H': case 'h': f->size = 2; break;
        case 'I': case 'i': case 'f': f->size = 4; break;
        case 'Q': case 'q': case 'd': f->size = 8; break;
        default:
            PyErr_Format(PyExc_ValueError, "unknown field code %R", PySequence_Fast_GET_ITEM(items, i));
            goto fail;
        }
        if (code[1] != '\0' || f->start < 0) {
            PyErr_SetString(PyExc_ValueError, "a field is (one struct code, start >= 0, scale, offset, big_endian)");
            goto fail;
        }
    }
    self->n = count; /* only a whole plan is used: n stays 0 on failure */
    Py_DECREF(items);
    return 0;
fail:
    Py_DECREF(items);
    return -1;
}

static void put_bits(unsigned char *at, uint64_t bits, int size, int big_endian) {
    for (int b = 0; b < size; b++) {
        at[big_endian ? size - 1 - b : b] = (unsigned char)(bits >> (8 * b));
    }
}

static uint64_t get_bits(const unsigned char *at, int size, int big_endian) {
    uint64_t bits = 0;
    for (int b = 0; b < size; b++) {
        bits |= (uint64_t)at[big_endian ? size - 1 - b : b] << (8 * b);
    }
    return bits;
}

/* pack_into(frame, at, values, first) -> -1, or the index (in this layout) of the field whose
 * value is not finite (or too large for an f32): nothing of that field is written. */
static PyObject *Layout_pack_into(Layout *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "pack_into(frame, at, values, first)");
        return NULL;
    }
    Py_ssize_t at = PyLong_AsSsize_t(args[1]), first = PyLong_AsSsize_t(args[3]);
    if ((at == -1 || first == -1) && PyErr_Occurred()) {
        return NULL;
    }
    Py_buffer frame, values;
    if (PyObject_GetBuffer(args[0], &frame, PyBUF_WRITABLE) < 0) {
        return NULL;
    }
    if (get_vector(args[2], &values, 0, "values") < 0) {
        PyBuffer_Release(&frame);
        return NULL;
    }
    long bad = -1;
    if (first < 0 || first + self->n > values.len / 8) {
        PyErr_SetString(PyExc_IndexError, "values: fewer than the layout's fields");
        goto error;
    }
    const double *value = (const double *)values.buf + first;
    for (Py_ssize_t i = 0; i < self->n; i++) {
        const FieldPlan *f = &self->fields[i];
        if (at < 0 || at + f->start + f->size > frame.len) {
            PyErr_SetString(PyExc_ValueError, "the frame is shorter than the layout");
            goto error;
        }
        unsigned char *place = (unsigned char *)frame.buf + at + f->start;
        double raw = (value[i] - f->offset) / f->scale;
        if (!isfinite(raw)) {
            bad = (long)i;
            break;
        }
        uint64_t bits;
        if (f->code == 'd') {
            memcpy(&bits, &raw, 8);
        } else if (f->code == 'f') {
            float narrow = (float)raw;
            if (isinf(narrow)) { /* as struct.pack('f') refuses it */
                bad = (long)i;
                break;
            }
            uint32_t word;
            memcpy(&word, &narrow, 4);
            bits = word;
        } else {
            raw = nearbyint(raw); /* round half to even, as Python's round() */
            int width = 8 * f->size;
            /* the exact range of the raw type, as doubles: [low, high_exclusive) */
            double low = f->is_signed ? -ldexp(1.0, width - 1) : 0.0;
            double high_exclusive = ldexp(1.0, f->is_signed ? width - 1 : width);
            if (f->is_signed) {
                int64_t integer = raw >= high_exclusive ? (int64_t)(((uint64_t)1 << (width - 1)) - 1)
                                  : raw < low ? -(int64_t)(((uint64_t)1 << (width - 1)) - 1) - 1
                                  : (int64_t)raw;
                bits = (uint64_t)integer;
            } else {
                bits = raw >= high_exclusive ? (width == 64 ? UINT64_MAX : ((uint64_t)1 << width) - 1)
                       : raw < low ? 0
                       : (uint64_t)raw;
            }
            if (width < 64) {
                bits &= ((uint64_t)1 << width) - 1;
            }
        }
        put_bits(place, bits, f->size, f->big_endian);
    }
    PyBuffer_Release(&frame);
    PyBuffer_Release(&values);
    return PyLong_FromLong(bad);
error:
    PyBuffer_Release(&frame);
    PyBuffer_Release(&values);
    return NULL;
}

/* unpack_from(frame, at, out, first): the fields of ``frame`` into out[first:first + n]. */
static PyObject *Layout_unpack_from(Layout *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "unpack_from(frame, at, out, first)");
        return NULL;
    }
    Py_ssize_t at = PyLong_AsSsize_t(args[1]), first = PyLong_AsSsize_t(args[3]);
    if ((at == -1 || first == -1) && PyErr_Occurred()) {
        return NULL;
    }
    Py_buffer frame, out;
    if (PyObject_GetBuffer(args[0], &frame, PyBUF_SIMPLE) < 0) {
        return NULL;
    }
    if (get_vector(args[2], &out, 1, "out") < 0) {
        PyBuffer_Release(&frame);
        return NULL;
    }
    if (first < 0 || first + self->n > out.len / 8) {
        PyErr_SetString(PyExc_IndexError, "out: fewer than the layout's fields");
        goto error;
    }
    double *target = (double *)out.buf + first;
    for (Py_ssize_t i = 0; i < self->n; i++) {
        const FieldPlan *f = &self->fields[i];
        if (at < 0 || at + f->start + f->size > frame.len) {
            PyErr_SetString(PyExc_ValueError, "the frame is shorter than the layout");
            goto error;
        }
        uint64_t bits = get_bits((const unsigned char *)frame.buf + at + f->start, f->size, f->big_endian);
        double raw;
        if (f->code == 'd') {
            memcpy(&raw, &bits, 8);
        } else if (f->code == 'f') {
            uint32_t word = (uint32_t)bits;
            float narrow;
            memcpy(&narrow, &word, 4);
            raw = narrow;
        } else if (f->is_signed) {
            int width = 8 * f->size;
            int64_t integer = width == 64 ? (int64_t)bits
                              : (int64_t)(bits ^ ((uint64_t)1 << (width - 1))) - ((int64_t)1 << (width - 1));
            raw = (double)integer;
        } else {
            raw = (double)bits;
        }
        target[i] = raw * f->scale + f->offset;
    }
    PyBuffer_Release(&frame);
    PyBuffer_Release(&out);
    Py_RETURN_NONE;
error:
    PyBuffer_Release(&frame);
    PyBuffer_Release(&out);
    return NULL;
}

static PyMethodDef Layout_methods[] = {
    {"pack_into", (PyCFunction)(void (*)(void))Layout_pack_into, METH_FASTCALL,
     "pack_into(frame, at, values, first) -> -1, or the index of a field whose value cannot be sent."},
    {"unpack_from", (PyCFunction)(void (*)(void))Layout_unpack_from, METH_FASTCALL,
     "unpack_from(frame, at, out, first)"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject LayoutType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "rtloop.io._devio.Layout",
    .tp_basicsize = sizeof(Layout),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Layout_init,
    .tp_dealloc = (destructor)Layout_dealloc,
    .tp_methods = Layout_methods,
    .tp_doc = "Layout(fields): fields (code, start_byte, scale, offset, big_endian) packed and unpacked.",
};

/* ------------------------------------------------------------------------------------------ */
/* CanReceiver: drain a non-blocking socket, keeping the newest copy of each declared id.       */

typedef struct {
    PyObject_HEAD
    int fd;
    Py_ssize_t n;
    uint32_t *ids;       /* wire ids (with the extended flag), host byte order as on the socket */
    Py_buffer *latest;   /* one bytearray per id, of the frame's size (16 or 72) */
    PyObject *fresh;     /* a list of bools, one per id */
    unsigned long long unexpected;
    unsigned char incoming[72];
} CanReceiver;

static void CanReceiver_release(CanReceiver *self) {
    for (Py_ssize_t i = 0; i < self->n; i++) {
        PyBuffer_Release(&self->latest[i]);
    }
    PyMem_Free(self->latest);
    PyMem_Free(self->ids);
    self->latest = NULL;
    self->ids = NULL;
    self->n = 0;
    Py_CLEAR(self->fresh);
}

static void CanReceiver_dealloc(CanReceiver *self) {
    CanReceiver_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* CanReceiver(fd, ids, latest, fresh) */
static int CanReceiver_init(CanReceiver *self, PyObject *args, PyObject *kwargs) {
    PyObject *ids, *latest, *fresh;
    int fd;
    if (!PyArg_ParseTuple(args, "iOOO!", &fd, &ids, &latest, &PyList_Type, &fresh)) {
        return -1;
    }
    CanReceiver_release(self);
    Py_ssize_t count = PySequence_Size(ids);
    if (count < 0 || PySequence_Size(latest) != count || PyList_GET_SIZE(fresh) != count) {
        if (!PyErr_Occurred()) {
            PyErr_SetString(PyExc_ValueError, "ids, latest and fresh differ in length");
        }
        return -1;
    }
    self->ids = PyMem_Calloc(count ? count : 1, sizeof(uint32_t));
    self->latest = PyMem_Calloc(count ? count : 1, sizeof(Py_buffer));
    if (self->ids == NULL || self->latest == NULL) {
        PyErr_NoMemory();
        goto fail;
    }
    for (Py_ssize_t i = 0; i < count; i++) {
        PyObject *id = PySequence_GetItem(ids, i), *buffer = PySequence_GetItem(latest, i);
        unsigned long value = id ? PyLong_AsUnsignedLong(id) : 0;
        int failed = id == NULL || buffer == NULL || PyErr_Occurred() ||
                     PyObject_GetBuffer(buffer, &self->latest[i], PyBUF_WRITABLE) < 0;
        Py_XDECREF(id);
        Py_XDECREF(buffer);
        if (failed) {
            goto fail;
        }
        self->n = i + 1;
        self->ids[i] = (uint32_t)value;
        if (self->latest[i].len > (Py_ssize_t)sizeof(self->incoming)) {
            PyErr_SetString(PyExc_ValueError, "a frame buffer is larger than a CAN FD frame");
            goto fail;
        }
    }
    self->fd = fd;
    Py_INCREF(fresh);
    self->fresh = fresh;
    return 0;
fail:
    CanReceiver_release(self);
    return -1;
}

/* drain() -> how many declared frames became fresh (a frame is fresh once per cycle). */
static PyObject *CanReceiver_drain(CanReceiver *self, PyObject *Py_UNUSED(ignored)) {
    if (self->fresh == NULL) {
        PyErr_SetString(PyExc_ValueError, "the receiver is released");
        return NULL;
    }
    struct pollfd waiting = {.fd = self->fd, .events = POLLIN};
    long came = 0;
    for (;;) {
        int ready = poll(&waiting, 1, 0);
        if (ready < 0) {
            if (errno == EINTR) {
                if (PyErr_CheckSignals() < 0) {
                    return NULL;
                }
                continue;
            }
            return PyErr_SetFromErrno(PyExc_OSError);
        }
        if (ready == 0) {
            break;
        }
        ssize_t size = recv(self->fd, self->incoming, sizeof(self->incoming), 0);
        if (size < 0) {
            if (errno == EAGAIN || errno == EWOULDBLOCK) {
                break;
            }
            if (errno == EINTR) {
                if (PyErr_CheckSignals() < 0) {
                    return NULL;
                }
                continue;
            }
            return PyErr_SetFromErrno(PyExc_OSError);
        }
        uint32_t id = 0;
        if (size >= 4) {
            memcpy(&id, self->incoming, 4);
        }
        Py_ssize_t index = -1;
        for (Py_ssize_t i = 0; i < self->n; i++) {
            if (self->ids[i] == id) {
                index = i;
                break;
            }
        }
        if (index < 0 || size != self->latest[index].len) { /* not declared, or FD where classic was declared */
            self->unexpected++;
            continue;
        }
        memcpy(self->latest[index].buf, self->incoming, (size_t)size);
        if (PyList_GET_ITEM(self->fresh, index) != Py_True) {
            PyObject *old = PyList_GET_ITEM(self->fresh, index);
            Py_INCREF(Py_True);
            PyList_SET_ITEM(self->fresh, index, Py_True);
            Py_DECREF(old);
            came++;
        }
    }
    return PyLong_FromLong(came);
}

static PyObject *CanReceiver_get_unexpected(CanReceiver *self, void *closure) {
    return PyLong_FromUnsignedLongLong(self->unexpected);
}

static PyObject *CanReceiver_release_method(CanReceiver *self, PyObject *Py_UNUSED(ignored)) {
    CanReceiver_release(self);
    Py_RETURN_NONE;
}

static PyMethodDef CanReceiver_methods[] = {
    {"drain", (PyCFunction)CanReceiver_drain, METH_NOARGS, "Take what is queued; how many declared frames came."},
    {"release", (PyCFunction)CanReceiver_release_method, METH_NOARGS, "Let go of the buffers."},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef CanReceiver_getset[] = {
    {"unexpected", (getter)CanReceiver_get_unexpected, NULL, "Frames of no declared id or size.", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject CanReceiverType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "rtloop.io._devio.CanReceiver",
    .tp_basicsize = sizeof(CanReceiver),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)CanReceiver_init,
    .tp_dealloc = (destructor)CanReceiver_dealloc,
    .tp_methods = CanReceiver_methods,
    .tp_getset = CanReceiver_getset,
    .tp_doc = "CanReceiver(fd, ids, latest, fresh): drain a CAN socket into the newest copy of each id.",
};

/* ------------------------------------------------------------------------------------------ */

static struct PyModuleDef devio_module = {
    PyModuleDef_HEAD_INIT, "rtloop.io._devio", "The devices' per-cycle work in C (see io/compiled.py).", -1, NULL,
};

PyMODINIT_FUNC PyInit__devio(void) {
    PyTypeObject *types[] = {&GuardType, &CopiesType, &LayoutType, &CanReceiverType};
    const char *names[] = {"Guard", "Copies", "Layout", "CanReceiver"};
    PyObject *module = PyModule_Create(&devio_module);
    if (module == NULL) {
        return NULL;
    }
    for (int i = 0; i < 4; i++) {
        if (PyType_Ready(types[i]) < 0) {
            Py_DECREF(module);
            return NULL;
        }
        Py_INCREF(types[i]);
        if (PyModule_AddObject(module, names[i], (PyObject *)types[i]) < 0) {
            Py_DECREF(types[i]);
            Py_DECREF(module);
            return NULL;
        }
    }
    return module;
}

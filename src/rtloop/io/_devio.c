/* The devices' per-cycle work in C: the command guard, signals packed into and out of frame
 * bytes, a CAN socket drained into the newest copy of each declared frame, a GPIO device's
 * lines set and read, and an SPI frame sealed, transferred and checked; a CAN device's whole cycle.
 *
 * Each is the compiled twin of a Python reference that stays the fallback and is tested
 * against it: Guard <-> io/limits.py CommandGuard.apply (+ the copies of io/host.py),
 * Layout <-> io/bytelayout.py ByteLayout.pack_into/unpack_from, CanReceiver <->
 * io/cansocket.py CanSocket._drain, CanCycle <-> io/can.py CanDevice.write/read (with
 * CanSocket.receive_cycle), GpioLines <-> io/gpio.py GpioDevice.write/read, SpiFrame <->
 * io/spi.py SpiDevice with io/spiframe.py. Same arithmetic in the same order, so the results are
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
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <time.h>

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
    Py_ssize_t end; /* the bytes the fields reach from the frame's ``at``: checked once per call */
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
    self->n = self->end = 0;
    Py_ssize_t end = 0;
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
        if (code[1] != '\0' || f->start < 0 || f->start > PY_SSIZE_T_MAX - 8) {
            PyErr_SetString(PyExc_ValueError, "a field is (one struct code, start >= 0, scale, offset, big_endian)");
            goto fail;
        }
        if (f->start + f->size > end) {
            end = f->start + f->size;
        }
    }
    self->n = count; /* only a whole plan is used: n stays 0 on failure */
    self->end = end;
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

/* The layout's fields packed into ``frame`` (at least layout->end bytes) from value[0..n-1]:
 * -1, or the index of the first field whose value is not finite (or too large for an f32);
 * nothing of that field or the ones after it is written (as the Python reference stops there). */
static long layout_pack(const Layout *layout, unsigned char *frame, const double *value) {
    for (Py_ssize_t i = 0; i < layout->n; i++) {
        const FieldPlan *f = &layout->fields[i];
        double raw = (value[i] - f->offset) / f->scale;
        if (!isfinite(raw)) {
            return (long)i;
        }
        uint64_t bits;
        if (f->code == 'd') {
            memcpy(&bits, &raw, 8);
        } else if (f->code == 'f') {
            float narrow = (float)raw;
            if (isinf(narrow)) { /* as struct.pack('f') refuses it */
                return (long)i;
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
        put_bits(frame + f->start, bits, f->size, f->big_endian);
    }
    return -1;
}

/* The layout's fields of ``frame`` (at least layout->end bytes) into target[0..n-1]. */
static void layout_unpack(const Layout *layout, const unsigned char *frame, double *target) {
    for (Py_ssize_t i = 0; i < layout->n; i++) {
        const FieldPlan *f = &layout->fields[i];
        uint64_t bits = get_bits(frame + f->start, f->size, f->big_endian);
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
}

/* The frame and vector of a pack_into/unpack_from call, sizes checked: 0, or -1 with an error set
 * (nothing held then). */
static int layout_buffers(const Layout *self, PyObject *const *args, Py_ssize_t nargs, int packing,
                          Py_buffer *frame, Py_buffer *vector, Py_ssize_t *at, Py_ssize_t *first) {
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, packing ? "pack_into(frame, at, values, first)"
                                                 : "unpack_from(frame, at, out, first)");
        return -1;
    }
    *at = PyLong_AsSsize_t(args[1]);
    *first = PyLong_AsSsize_t(args[3]);
    if ((*at == -1 || *first == -1) && PyErr_Occurred()) {
        return -1;
    }
    if (PyObject_GetBuffer(args[0], frame, packing ? PyBUF_WRITABLE : PyBUF_SIMPLE) < 0) {
        return -1;
    }
    if (get_vector(args[2], vector, !packing, packing ? "values" : "out") < 0) {
        PyBuffer_Release(frame);
        return -1;
    }
    if (*first < 0 || *first > vector->len / 8 - self->n) {
        PyErr_SetString(PyExc_IndexError, packing ? "values: fewer than the layout's fields"
                                                  : "out: fewer than the layout's fields");
        goto fail;
    }
    if (*at < 0 || *at > frame->len - self->end) {
        PyErr_SetString(PyExc_ValueError, "the frame is shorter than the layout");
        goto fail;
    }
    return 0;
fail:
    PyBuffer_Release(frame);
    PyBuffer_Release(vector);
    return -1;
}

/* pack_into(frame, at, values, first) -> -1, or the index (in this layout) of the field whose
 * value is not finite (or too large for an f32): nothing of that field is written. */
static PyObject *Layout_pack_into(Layout *self, PyObject *const *args, Py_ssize_t nargs) {
    Py_buffer frame, values;
    Py_ssize_t at, first;
    if (layout_buffers(self, args, nargs, 1, &frame, &values, &at, &first) < 0) {
        return NULL;
    }
    long bad = layout_pack(self, (unsigned char *)frame.buf + at, (const double *)values.buf + first);
    PyBuffer_Release(&frame);
    PyBuffer_Release(&values);
    return PyLong_FromLong(bad);
}

/* unpack_from(frame, at, out, first): the fields of ``frame`` into out[first:first + n]. */
static PyObject *Layout_unpack_from(Layout *self, PyObject *const *args, Py_ssize_t nargs) {
    Py_buffer frame, out;
    Py_ssize_t at, first;
    if (layout_buffers(self, args, nargs, 0, &frame, &out, &at, &first) < 0) {
        return NULL;
    }
    layout_unpack(self, (const unsigned char *)frame.buf + at, (double *)out.buf + first);
    PyBuffer_Release(&frame);
    PyBuffer_Release(&out);
    Py_RETURN_NONE;
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

/* Take what is queued, keeping the newest copy of each declared id: how many declared frames
 * became fresh (a frame is fresh once per cycle), or -1 with an error set. */
static long can_drain(CanReceiver *self) {
    if (self->fresh == NULL) {
        PyErr_SetString(PyExc_ValueError, "the receiver is released");
        return -1;
    }
    struct pollfd waiting = {.fd = self->fd, .events = POLLIN};
    long came = 0;
    for (;;) {
        int ready = poll(&waiting, 1, 0);
        if (ready < 0) {
            if (errno == EINTR) {
                if (PyErr_CheckSignals() < 0) {
                    return -1;
                }
                continue;
            }
            PyErr_SetFromErrno(PyExc_OSError);
            return -1;
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
                    return -1;
                }
                continue;
            }
            PyErr_SetFromErrno(PyExc_OSError);
            return -1;
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
    return came;
}

/* drain() -> how many declared frames became fresh. */
static PyObject *CanReceiver_drain(CanReceiver *self, PyObject *Py_UNUSED(ignored)) {
    long came = can_drain(self);
    return came < 0 ? NULL : PyLong_FromLong(came);
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
/* CanCycle: a CAN device's whole cycle, one call per write and one per read                    */
/* (io/can.py CanDevice.write/read with io/cansocket.py CanSocket.receive_cycle).               */
/*                                                                                              */
/* Only the common outcomes are decided here: every frame sent, every frame fresh. What has     */
/* words (a value that cannot be sent, a failed send, a frame missing) comes back as a code or  */
/* an OSError and io/can.py says it with the reference's own lines, so both paths raise the     */
/* same exceptions with the same text.                                                          */

#define CAN_DATA_AT 8 /* the data bytes of struct can_frame / canfd_frame follow id, len and 3 bytes */

typedef struct {
    PyObject_HEAD
    CanReceiver *receiver;          /* owned: its socket, drain, fresh list and newest copies */
    int fd;                         /* the receiver's socket: frames are sent on it too */
    Py_ssize_t n_send, n_receive;
    Py_ssize_t held;                /* send buffers held (for a partial failure) */
    Py_buffer *sent;                /* each send frame's wire buffer, header built once by Python */
    Layout **send_layouts, **receive_layouts; /* owned */
    Py_ssize_t *send_first, *receive_first;   /* where each frame's signals start in u / y */
    Py_ssize_t n_inputs, n_outputs;
    long long *timeout_ns;          /* per receive frame, counted from the start of the read */
    char *faults;                   /* a missing frame faults (on_missing = "fault"), else it is stale */
    Py_buffer heartbeat;            /* the heartbeat's wire frame, when has_heartbeat */
    int has_heartbeat;
    int count;                      /* the heartbeat's next byte, 0..255 (canframes.HeartbeatCounter) */
} CanCycle;

static void CanCycle_release(CanCycle *self) {
    for (Py_ssize_t i = 0; i < self->held; i++) {
        PyBuffer_Release(&self->sent[i]);
    }
    self->held = 0;
    if (self->has_heartbeat) {
        PyBuffer_Release(&self->heartbeat);
        self->has_heartbeat = 0;
    }
    for (Py_ssize_t i = 0; self->send_layouts != NULL && i < self->n_send; i++) {
        Py_XDECREF(self->send_layouts[i]);
    }
    for (Py_ssize_t i = 0; self->receive_layouts != NULL && i < self->n_receive; i++) {
        Py_XDECREF(self->receive_layouts[i]);
    }
    PyMem_Free(self->sent);
    PyMem_Free(self->send_layouts);
    PyMem_Free(self->receive_layouts);
    PyMem_Free(self->send_first);
    PyMem_Free(self->receive_first);
    PyMem_Free(self->timeout_ns);
    PyMem_Free(self->faults);
    self->sent = NULL;
    self->send_layouts = self->receive_layouts = NULL;
    self->send_first = self->receive_first = NULL;
    self->timeout_ns = NULL;
    self->faults = NULL;
    self->n_send = self->n_receive = 0;
    Py_CLEAR(self->receiver);
    self->fd = -1;
}

static void CanCycle_dealloc(CanCycle *self) {
    CanCycle_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* One Layout of a sequence, owned; where its signals start (the ones before it counted in *at). */
static int can_layout(PyObject *items, Py_ssize_t i, Layout **layout, Py_ssize_t *first, Py_ssize_t *at) {
    PyObject *item = PySequence_Fast_GET_ITEM(items, i);
    if (!PyObject_TypeCheck(item, &LayoutType)) {
        PyErr_SetString(PyExc_TypeError, "layouts: compiled Layouts are needed");
        return -1;
    }
    Py_INCREF(item);
    *layout = (Layout *)item;
    *first = *at;
    *at += (*layout)->n;
    return 0;
}

/* CanCycle(receiver, sent, send_layouts, heartbeat, receive_layouts, timeouts_ns, faults):
 * ``sent`` the send frames' wire buffers (one per send layout), ``heartbeat`` its wire buffer or
 * None; the receive frames are the receiver's, in its order, with their layouts, timeouts and
 * whether a missing one faults. */
static int CanCycle_init(CanCycle *self, PyObject *args, PyObject *kwargs) {
    PyObject *receiver, *sent, *send_layouts, *heartbeat, *receive_layouts, *timeouts, *faults;
    if (!PyArg_ParseTuple(args, "O!OOOOOO", &CanReceiverType, &receiver, &sent, &send_layouts, &heartbeat,
                          &receive_layouts, &timeouts, &faults)) {
        return -1;
    }
    CanCycle_release(self);
    PyObject *lists[5] = {NULL, NULL, NULL, NULL, NULL};
    PyObject *given[5] = {sent, send_layouts, receive_layouts, timeouts, faults};
    for (int i = 0; i < 5; i++) {
        lists[i] = PySequence_Fast(given[i], "CanCycle: a sequence is needed");
        if (lists[i] == NULL) {
            goto fail;
        }
    }
    CanReceiver *r = (CanReceiver *)receiver;
    Py_ssize_t n_send = PySequence_Fast_GET_SIZE(lists[1]), n_receive = PySequence_Fast_GET_SIZE(lists[2]);
    if (PySequence_Fast_GET_SIZE(lists[0]) != n_send || PySequence_Fast_GET_SIZE(lists[3]) != n_receive ||
        PySequence_Fast_GET_SIZE(lists[4]) != n_receive || r->fresh == NULL || r->n != n_receive) {
        PyErr_SetString(PyExc_ValueError, "CanCycle: the frames, layouts and receiver differ in length");
        goto fail;
    }
    self->sent = PyMem_Calloc(n_send ? n_send : 1, sizeof(Py_buffer));
    self->send_layouts = PyMem_Calloc(n_send ? n_send : 1, sizeof(Layout *));
    self->send_first = PyMem_Calloc(n_send ? n_send : 1, sizeof(Py_ssize_t));
    self->receive_layouts = PyMem_Calloc(n_receive ? n_receive : 1, sizeof(Layout *));
    self->receive_first = PyMem_Calloc(n_receive ? n_receive : 1, sizeof(Py_ssize_t));
    self->timeout_ns = PyMem_Calloc(n_receive ? n_receive : 1, sizeof(long long));
    self->faults = PyMem_Calloc(n_receive ? n_receive : 1, 1);
    self->n_send = n_send; /* the layout arrays are zeroed: released up to n whatever was filled */
    self->n_receive = n_receive;
    if (self->sent == NULL || self->send_layouts == NULL || self->send_first == NULL || self->receive_layouts == NULL ||
        self->receive_first == NULL || self->timeout_ns == NULL || self->faults == NULL) {
        PyErr_NoMemory();
        goto fail;
    }
    self->n_inputs = self->n_outputs = 0;
    for (Py_ssize_t i = 0; i < n_send; i++) {
        if (can_layout(lists[1], i, &self->send_layouts[i], &self->send_first[i], &self->n_inputs) < 0 ||
            PyObject_GetBuffer(PySequence_Fast_GET_ITEM(lists[0], i), &self->sent[i], PyBUF_WRITABLE) < 0) {
            goto fail;
        }
        self->held = i + 1;
        if (self->sent[i].len < CAN_DATA_AT + self->send_layouts[i]->end || self->sent[i].len > 72) {
            PyErr_SetString(PyExc_ValueError, "CanCycle: a send frame is not a CAN frame holding its signals");
            goto fail;
        }
    }
    for (Py_ssize_t i = 0; i < n_receive; i++) {
        if (can_layout(lists[2], i, &self->receive_layouts[i], &self->receive_first[i], &self->n_outputs) < 0) {
            goto fail;
        }
        if (r->latest[i].len < CAN_DATA_AT + self->receive_layouts[i]->end) {
            PyErr_SetString(PyExc_ValueError, "CanCycle: a received frame is shorter than its signals");
            goto fail;
        }
        self->timeout_ns[i] = PyLong_AsLongLong(PySequence_Fast_GET_ITEM(lists[3], i));
        int fault = PyObject_IsTrue(PySequence_Fast_GET_ITEM(lists[4], i));
        if ((self->timeout_ns[i] == -1 && PyErr_Occurred()) || fault < 0) {
            goto fail;
        }
        self->faults[i] = (char)fault;
    }
    if (heartbeat != Py_None) {
        if (PyObject_GetBuffer(heartbeat, &self->heartbeat, PyBUF_WRITABLE) < 0) {
            goto fail;
        }
        self->has_heartbeat = 1;
        if (self->heartbeat.len <= CAN_DATA_AT || self->heartbeat.len > 72) {
            PyErr_SetString(PyExc_ValueError, "CanCycle: the heartbeat is not a CAN frame");
            goto fail;
        }
    }
    Py_INCREF(receiver);
    self->receiver = r;
    self->fd = r->fd;
    self->count = 0;
    for (int i = 0; i < 5; i++) {
        Py_DECREF(lists[i]);
    }
    return 0;
fail:
    for (int i = 0; i < 5; i++) {
        Py_XDECREF(lists[i]);
    }
    CanCycle_release(self);
    return -1;
}

static int can_held(CanCycle *self) {
    if (self->receiver == NULL || self->receiver->fresh == NULL ||
        PyList_GET_SIZE(self->receiver->fresh) != self->n_receive) {
        PyErr_SetString(PyExc_ValueError, "the CAN cycle is released");
        return 0;
    }
    return 1;
}

/* A float64 vector of at least ``n`` values, or a TypeError: the caller then runs the Python
 * reference instead (a list, a short or strided vector behave there exactly as they always did). */
static int can_vector(PyObject *obj, Py_buffer *view, int writable, Py_ssize_t n) {
    if (get_vector(obj, view, writable, writable ? "y" : "u") < 0) {
        PyErr_Clear();
        PyErr_SetString(PyExc_TypeError, "not a contiguous float64 vector: the reference path decides");
        return -1;
    }
    if (view->len / 8 < n) {
        PyBuffer_Release(view);
        PyErr_SetString(PyExc_TypeError, "fewer values than the frames' signals: the reference path decides");
        return -1;
    }
    return 0;
}

/* One send of a wire frame (socket.send: retried after a signal, any other error an OSError). */
static int can_send(int fd, const Py_buffer *frame) {
    for (;;) {
        if (send(fd, frame->buf, (size_t)frame->len, 0) >= 0) {
            return 0;
        }
        if (errno != EINTR) {
            PyErr_SetFromErrno(PyExc_OSError);
            return -1;
        }
        if (PyErr_CheckSignals() < 0) {
            return -1;
        }
    }
}

/* write(u) -> -1 once every frame and the heartbeat went out; or the index of the send frame
 * holding a value that cannot be sent (the frames before it went out, it and the rest did not:
 * the caller packs it the Python way to raise the reference's ValueError). A failed send is the
 * OSError of socket.send (the caller words it as CanDevice.link_failed). */
static PyObject *CanCycle_write(CanCycle *self, PyObject *u_object) {
    if (!can_held(self)) {
        return NULL;
    }
    Py_buffer view;
    if (can_vector(u_object, &view, 0, self->n_inputs) < 0) {
        return NULL;
    }
    const double *u = view.buf;
    for (Py_ssize_t k = 0; k < self->n_send; k++) {
        unsigned char *frame = self->sent[k].buf;
        if (layout_pack(self->send_layouts[k], frame + CAN_DATA_AT, u + self->send_first[k]) >= 0) {
            PyBuffer_Release(&view);
            return PyLong_FromSsize_t(k);
        }
        if (can_send(self->fd, &self->sent[k]) < 0) {
            goto fail;
        }
    }
    if (self->has_heartbeat) {
        /* the counter moves before the send, as HeartbeatCounter.next() does before socket.send */
        ((unsigned char *)self->heartbeat.buf)[CAN_DATA_AT] = (unsigned char)self->count;
        self->count = (self->count + 1) & 0xFF;
        if (can_send(self->fd, &self->heartbeat) < 0) {
            goto fail;
        }
    }
    PyBuffer_Release(&view);
    return PyLong_FromLong(-1);
fail:
    PyBuffer_Release(&view);
    return NULL;
}

static long long monotonic_ns(void) {
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now); /* time.monotonic_ns()'s clock */
    return (long long)now.tv_sec * 1000000000LL + now.tv_nsec;
}

/* The receive half of the cycle, CanSocket.receive_cycle: every frame missing until it comes;
 * drain; then wait while a frame is still missing and its timeout (from ``start_ns``) has not
 * passed. 0, or -1 with an error set. */
static int can_receive(CanCycle *self, long long start_ns) {
    CanReceiver *r = self->receiver;
    PyObject *fresh = r->fresh;
    for (Py_ssize_t i = 0; i < self->n_receive; i++) {
        PyObject *old = PyList_GET_ITEM(fresh, i);
        if (old != Py_False) {
            Py_INCREF(Py_False);
            PyList_SET_ITEM(fresh, i, Py_False);
            Py_DECREF(old);
        }
    }
    long came = can_drain(r);
    if (came < 0) {
        return -1;
    }
    long missing = (long)self->n_receive - came;
    struct pollfd waiting = {.fd = self->fd, .events = POLLIN};
    while (missing > 0) {
        long long now_ns = monotonic_ns(), wait_ns = 0;
        for (Py_ssize_t i = 0; i < self->n_receive; i++) {
            long long left_ns = start_ns + self->timeout_ns[i] - now_ns;
            if (PyList_GET_ITEM(fresh, i) != Py_True && left_ns > wait_ns) {
                wait_ns = left_ns;
            }
        }
        if (wait_ns <= 0) {
            return 0; /* what is still missing stays so: the device counts it or faults */
        }
        int ready;
        /* ppoll, to the nanosecond: poll's whole milliseconds would wait 1 ms for a 0.2 ms timeout */
        struct timespec wait = {.tv_sec = (time_t)(wait_ns / 1000000000LL), .tv_nsec = (long)(wait_ns % 1000000000LL)};
        /* the GIL goes while waiting, as ctypes gives it away around ppoll in the reference */
        Py_BEGIN_ALLOW_THREADS
        ready = ppoll(&waiting, 1, &wait, NULL);
        Py_END_ALLOW_THREADS
        if (ready < 0) {
            if (errno != EINTR) {
                PyErr_SetFromErrno(PyExc_OSError);
                return -1;
            }
            if (PyErr_CheckSignals() < 0) {
                return -1;
            }
            continue; /* the wait is worked out again from the clock, as the reference does after a signal */
        }
        if (ready == 0) {
            return 0;
        }
        came = can_drain(r);
        if (came < 0) {
            return -1;
        }
        missing -= came;
    }
    return 0;
}

/* read(y) -> True when every declared frame came this cycle (all unpacked into y). False when one
 * is missing: the frames that came before the first missing frame that faults are unpacked (as
 * the reference does before it raises) and the caller counts the stale ones and raises the fault. */
static PyObject *CanCycle_read(CanCycle *self, PyObject *y_object) {
    if (!can_held(self)) {
        return NULL;
    }
    Py_buffer view;
    if (can_vector(y_object, &view, 1, self->n_outputs) < 0) {
        return NULL;
    }
    long long start_ns = monotonic_ns(); /* timeouts count from the start of the read */
    if (can_receive(self, start_ns) < 0) {
        PyBuffer_Release(&view);
        return NULL;
    }
    double *y = view.buf;
    int all_fresh = 1;
    for (Py_ssize_t i = 0; i < self->n_receive; i++) {
        if (PyList_GET_ITEM(self->receiver->fresh, i) == Py_True) {
            layout_unpack(self->receive_layouts[i], (const unsigned char *)self->receiver->latest[i].buf + CAN_DATA_AT,
                          y + self->receive_first[i]);
        } else {
            all_fresh = 0; /* a stale frame keeps y's values of the last frame that came */
            if (self->faults[i]) {
                break;
            }
        }
    }
    PyBuffer_Release(&view);
    return PyBool_FromLong(all_fresh);
}

static PyObject *CanCycle_release_method(CanCycle *self, PyObject *Py_UNUSED(ignored)) {
    CanCycle_release(self);
    Py_RETURN_NONE;
}

static PyObject *CanCycle_get_count(CanCycle *self, void *closure) {
    return PyLong_FromLong(self->count);
}

static int CanCycle_set_count(CanCycle *self, PyObject *value, void *closure) {
    long count = value ? PyLong_AsLong(value) : -1;
    if (count == -1 && PyErr_Occurred()) {
        return -1;
    }
    if (count < 0 || count > 255) {
        PyErr_SetString(PyExc_ValueError, "the heartbeat's count is 0..255");
        return -1;
    }
    self->count = (int)count;
    return 0;
}

static PyMethodDef CanCycle_methods[] = {
    {"write", (PyCFunction)CanCycle_write, METH_O, "write(u) -> -1 when every frame went out, or the index of a "
     "frame holding a value that cannot be sent."},
    {"read", (PyCFunction)CanCycle_read, METH_O, "read(y) -> whether every frame came (all in y)."},
    {"release", (PyCFunction)CanCycle_release_method, METH_NOARGS, "Let go of the buffers, layouts and receiver."},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef CanCycle_getset[] = {
    {"count", (getter)CanCycle_get_count, (setter)CanCycle_set_count, "The heartbeat's next byte.", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject CanCycleType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "rtloop.io._devio.CanCycle",
    .tp_basicsize = sizeof(CanCycle),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)CanCycle_init,
    .tp_dealloc = (destructor)CanCycle_dealloc,
    .tp_methods = CanCycle_methods,
    .tp_getset = CanCycle_getset,
    .tp_doc = "CanCycle(receiver, sent, send_layouts, heartbeat, receive_layouts, timeouts_ns, faults): "
              "a CAN device's cycle.",
};

/* ------------------------------------------------------------------------------------------ */
/* GpioLines: a GPIO device's outputs and inputs, one ioctl each per cycle (GPIO character      */
/* device v2), and the E-stop's pending edge.                                                   */
/*                                                                                              */
/* The GIL is kept across the ioctls, as the task's hot path keeps it for the scope pin: they    */
/* do not wait for anything (the kernel sets or reads the lines and returns), and giving the GIL */
/* away would let another thread of the process delay the loop when it is taken back.            */

#define GPIO_LINES_MAX 64 /* GPIO_V2_LINES_MAX: a request holds at most 64 lines, one bit each */

/* struct gpio_v2_line_values of <linux/gpio.h>: the bits of the request's lines, and which count */
struct gpio_values {
    uint64_t bits, mask;
};

typedef struct {
    PyObject_HEAD
    int out_fd, in_fd, estop_fd;         /* line request fds; -1: none */
    unsigned long set_request, get_request;
    Py_ssize_t n_out, n_in;
    unsigned char out_bits[GPIO_LINES_MAX]; /* output i's bit in its request's bitmap */
    unsigned char in_bits[GPIO_LINES_MAX];
    uint64_t out_mask, in_mask;          /* the scope pin (same request as the outputs) is not in out_mask */
} GpioLines;

/* Bits of a sequence of line positions (0..63) into ``bits``; their mask, or -1 with an error set. */
static int gpio_bits(PyObject *positions, unsigned char *bits, Py_ssize_t *n, uint64_t *mask) {
    PyObject *items = PySequence_Fast(positions, "bits: a sequence of line positions");
    if (items == NULL) {
        return -1;
    }
    *n = PySequence_Fast_GET_SIZE(items);
    *mask = 0;
    if (*n > GPIO_LINES_MAX) {
        PyErr_SetString(PyExc_ValueError, "a line request holds at most 64 lines");
        goto fail;
    }
    for (Py_ssize_t i = 0; i < *n; i++) {
        long bit = PyLong_AsLong(PySequence_Fast_GET_ITEM(items, i));
        if (bit == -1 && PyErr_Occurred()) {
            goto fail;
        }
        if (bit < 0 || bit >= GPIO_LINES_MAX) {
            PyErr_SetString(PyExc_ValueError, "a line's bit is 0..63");
            goto fail;
        }
        bits[i] = (unsigned char)bit;
        *mask |= (uint64_t)1 << bit;
    }
    Py_DECREF(items);
    return 0;
fail:
    Py_DECREF(items);
    *n = 0;
    return -1;
}

/* GpioLines(out_fd, set_request, out_bits, in_fd, get_request, in_bits, estop_fd) */
static int GpioLines_init(GpioLines *self, PyObject *args, PyObject *kwargs) {
    PyObject *out_bits, *in_bits;
    if (!PyArg_ParseTuple(args, "ikOikOi", &self->out_fd, &self->set_request, &out_bits, &self->in_fd,
                          &self->get_request, &in_bits, &self->estop_fd)) {
        return -1;
    }
    if (gpio_bits(out_bits, self->out_bits, &self->n_out, &self->out_mask) < 0 ||
        gpio_bits(in_bits, self->in_bits, &self->n_in, &self->in_mask) < 0) {
        self->out_fd = self->in_fd = self->estop_fd = -1; /* a half-built object does nothing */
        return -1;
    }
    return 0;
}

/* write(u): output i active when u[i] >= 0.5 (NaN is not: inactive), all in one SET_VALUES. */
static PyObject *GpioLines_write(GpioLines *self, PyObject *u_object) {
    if (self->out_fd < 0 || self->n_out == 0) { /* as the reference: u is not even looked at */
        Py_RETURN_NONE;
    }
    Py_buffer view;
    if (get_vector(u_object, &view, 0, "u") < 0) {
        return NULL;
    }
    if (view.len / 8 < self->n_out) {
        PyBuffer_Release(&view);
        PyErr_SetString(PyExc_IndexError, "u: fewer values than output lines");
        return NULL;
    }
    const double *u = view.buf;
    struct gpio_values values = {0, self->out_mask};
    for (Py_ssize_t i = 0; i < self->n_out; i++) {
        if (u[i] >= 0.5) {
            values.bits |= (uint64_t)1 << self->out_bits[i];
        }
    }
    PyBuffer_Release(&view);
    if (ioctl(self->out_fd, self->set_request, &values) < 0) {
        return PyErr_SetFromErrno(PyExc_OSError); /* what fcntl.ioctl raises */
    }
    Py_RETURN_NONE;
}

/* read(y) -> True when an E-stop edge is waiting (nothing read then: the caller stops on it),
 * else False with input i in y[i] as 1.0 (active) or 0.0, all from one GET_VALUES. */
static PyObject *GpioLines_read(GpioLines *self, PyObject *y_object) {
    if (self->estop_fd >= 0) {
        struct pollfd edge = {.fd = self->estop_fd, .events = POLLIN};
        int ready;
        while ((ready = poll(&edge, 1, 0)) < 0) {
            if (errno != EINTR) {
                return PyErr_SetFromErrno(PyExc_OSError);
            }
            if (PyErr_CheckSignals() < 0) { /* as select.poll: a handler's exception, else try again */
                return NULL;
            }
        }
        if (ready > 0) {
            Py_RETURN_TRUE;
        }
    }
    if (self->in_fd < 0) {
        Py_RETURN_FALSE;
    }
    Py_buffer view;
    if (get_vector(y_object, &view, 1, "y") < 0) {
        return NULL;
    }
    if (view.len / 8 < self->n_in) {
        PyBuffer_Release(&view);
        PyErr_SetString(PyExc_IndexError, "y: fewer places than input lines");
        return NULL;
    }
    struct gpio_values values = {0, self->in_mask};
    if (ioctl(self->in_fd, self->get_request, &values) < 0) {
        PyBuffer_Release(&view);
        return PyErr_SetFromErrno(PyExc_OSError);
    }
    double *y = view.buf;
    for (Py_ssize_t i = 0; i < self->n_in; i++) {
        y[i] = values.bits >> self->in_bits[i] & 1 ? 1.0 : 0.0;
    }
    PyBuffer_Release(&view);
    Py_RETURN_FALSE;
}

static PyObject *GpioLines_release(GpioLines *self, PyObject *Py_UNUSED(ignored)) {
    self->out_fd = self->in_fd = self->estop_fd = -1; /* the fds are the requests' own: closed by them */
    Py_RETURN_NONE;
}

static PyMethodDef GpioLines_methods[] = {
    {"write", (PyCFunction)GpioLines_write, METH_O, "write(u): the outputs, u[i] >= 0.5 active."},
    {"read", (PyCFunction)GpioLines_read, METH_O, "read(y) -> True when an E-stop edge waits, else the inputs."},
    {"release", (PyCFunction)GpioLines_release, METH_NOARGS, "Forget the fds (before the requests close them)."},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject GpioLinesType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "rtloop.io._devio.GpioLines",
    .tp_basicsize = sizeof(GpioLines),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)GpioLines_init,
    .tp_methods = GpioLines_methods,
    .tp_doc = "GpioLines(out_fd, set_request, out_bits, in_fd, get_request, in_bits, estop_fd): a GPIO "
              "device's cycle.",
};

/* ------------------------------------------------------------------------------------------ */
/* SpiFrame: one full-duplex SPI transfer per cycle of a frame with a sequence counter and a    */
/* CRC (io/spiframe.py): the signals packed, counter and CRC sealed, one SPI_IOC_MESSAGE(1) on  */
/* a transfer built once, the answer's CRC and counter checked, its signals unpacked. The        */
/* compiled twin of io/spi.py SpiDevice._exchange/write/read with io/spiframe.py FrameCheck.     */
/* The GIL is kept across the ioctl, as for GPIO above: the transfer of a frame of a few bytes   */
/* takes microseconds, and taking the GIL back could wait behind another thread.                 */

/* CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, not reflected, no final xor), what
 * binascii.crc_hqx(data, 0xFFFF) computes: a byte at a time through a table built at import. */
static uint16_t crc16_table[256];

static void crc16_table_build(void) {
    for (int byte = 0; byte < 256; byte++) {
        uint16_t crc = (uint16_t)(byte << 8);
        for (int bit = 0; bit < 8; bit++) {
            crc = crc & 0x8000 ? (uint16_t)(crc << 1 ^ 0x1021) : (uint16_t)(crc << 1);
        }
        crc16_table[byte] = crc;
    }
}

static uint16_t crc16_ccitt(const unsigned char *data, Py_ssize_t n) {
    uint16_t crc = 0xFFFF;
    for (Py_ssize_t i = 0; i < n; i++) {
        crc = (uint16_t)(crc << 8 ^ crc16_table[(crc >> 8 ^ data[i]) & 0xFF]);
    }
    return crc;
}

enum { SPI_NO_ERROR, SPI_BAD_CRC, SPI_BAD_COUNTER };

typedef struct {
    PyObject_HEAD
    int fd;
    unsigned long request;        /* SPI_IOC_MESSAGE(1), from io/kernel.py */
    Py_buffer transfer, tx, rx;   /* held for the object's life: the addresses in ``transfer`` stay valid */
    int held;                     /* how many of the three are held (for a partial failure) */
    Layout *send, *receive;       /* owned */
    int echo;                     /* the answer carries this transfer's counter (a MOSI-MISO loop), else the one before */
    int counter;                  /* of the next frame sent, 0..255 */
    int expected;                 /* the counter the answer must carry; -1: none (the first answer of "previous") */
    int answered, fresh;          /* the last answer was good; a transfer came since the last read */
    unsigned long long bad_crc, bad_counter;
    int last_error, last_seen, last_expected; /* the last refusal, made into words only when asked */
} SpiFrame;

static void SpiFrame_release(SpiFrame *self) {
    Py_buffer *buffers[3] = {&self->transfer, &self->tx, &self->rx};
    for (int i = 0; i < self->held; i++) {
        PyBuffer_Release(buffers[i]);
    }
    self->held = 0;
    Py_CLEAR(self->send);
    Py_CLEAR(self->receive);
    self->fd = -1;
}

static void SpiFrame_dealloc(SpiFrame *self) {
    SpiFrame_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* SpiFrame(fd, request, transfer, tx, rx, send, receive, echo): ``transfer`` a struct
 * spi_ioc_transfer whose tx_buf, rx_buf and len are tx's and rx's (checked here), ``send`` and
 * ``receive`` the compiled Layouts of the signals. */
static int SpiFrame_init(SpiFrame *self, PyObject *args, PyObject *kwargs) {
    PyObject *objects[3];
    PyObject *send, *receive;
    int fd, echo;
    unsigned long request;
    if (!PyArg_ParseTuple(args, "ikOOOO!O!p", &fd, &request, &objects[0], &objects[1], &objects[2], &LayoutType,
                          &send, &LayoutType, &receive, &echo)) {
        return -1;
    }
    SpiFrame_release(self);
    Py_buffer *buffers[3] = {&self->transfer, &self->tx, &self->rx};
    for (int i = 0; i < 3; i++) {
        if (PyObject_GetBuffer(objects[i], buffers[i], PyBUF_WRITABLE) < 0) {
            goto fail;
        }
        self->held = i + 1;
    }
    Py_ssize_t n = self->tx.len;
    uint64_t tx_address, rx_address;
    uint32_t length;
    if (self->transfer.len < 20) {
        PyErr_SetString(PyExc_ValueError, "transfer: not a struct spi_ioc_transfer");
        goto fail;
    }
    memcpy(&tx_address, self->transfer.buf, 8); /* tx_buf, rx_buf, len: the first fields */
    memcpy(&rx_address, (char *)self->transfer.buf + 8, 8);
    memcpy(&length, (char *)self->transfer.buf + 16, 4);
    if (tx_address != (uint64_t)(uintptr_t)self->tx.buf || rx_address != (uint64_t)(uintptr_t)self->rx.buf ||
        length != (uint32_t)n || self->rx.len != n) {
        PyErr_SetString(PyExc_ValueError, "transfer: not pointing at tx and rx of its length");
        goto fail;
    }
    Py_INCREF(send);
    self->send = (Layout *)send;
    Py_INCREF(receive);
    self->receive = (Layout *)receive;
    if (n < 3 || self->send->end > n - 2 || self->receive->end > n - 2) {
        PyErr_SetString(PyExc_ValueError, "the signals leave no room for the counter and the CRC");
        goto fail;
    }
    self->fd = fd;
    self->request = request;
    self->echo = echo;
    self->counter = 0;
    self->expected = -1;
    self->answered = self->fresh = 0;
    self->bad_crc = self->bad_counter = 0;
    self->last_error = SPI_NO_ERROR;
    return 0;
fail:
    SpiFrame_release(self);
    return -1;
}

/* The counter into byte 0 and the CRC of bytes 0..n-3 into the last two (big-endian); what the
 * answer to this frame must carry (spiframe.seal, FrameCheck.sent). */
static void spi_seal(SpiFrame *self) {
    unsigned char *tx = self->tx.buf;
    Py_ssize_t n = self->tx.len;
    tx[0] = (unsigned char)self->counter;
    uint16_t crc = crc16_ccitt(tx, n - 2);
    tx[n - 2] = (unsigned char)(crc >> 8);
    tx[n - 1] = (unsigned char)(crc & 0xFF);
    if (self->echo) {
        self->expected = self->counter;
    }
}

/* The answer in rx checked (FrameCheck.accept, then .after), the counter moved on. */
static void spi_check(SpiFrame *self) {
    const unsigned char *rx = self->rx.buf;
    Py_ssize_t n = self->rx.len;
    if (crc16_ccitt(rx, n - 2) != (rx[n - 2] << 8 | rx[n - 1])) {
        self->bad_crc++;
        self->last_error = SPI_BAD_CRC;
        self->answered = 0;
    } else if (self->expected >= 0 && rx[0] != self->expected) {
        self->bad_counter++;
        self->last_error = SPI_BAD_COUNTER;
        self->last_seen = rx[0];
        self->last_expected = self->expected;
        self->answered = 0;
    } else {
        self->answered = 1;
    }
    if (!self->echo) {
        self->expected = self->counter;
    }
    self->counter = (self->counter + 1) & 0xFF;
    self->fresh = 1;
}

/* One transfer (SpiDevice._exchange): seal, SPI_IOC_MESSAGE(1), check. -1 with OSError set when
 * the kernel refuses it (then, as in the reference, the counter stays and nothing is fresh). */
static int spi_exchange(SpiFrame *self) {
    spi_seal(self);
    if (ioctl(self->fd, self->request, self->transfer.buf) < 0) {
        PyErr_SetFromErrno(PyExc_OSError); /* what fcntl.ioctl raises */
        return -1;
    }
    spi_check(self);
    return 0;
}

static int spi_held(SpiFrame *self) {
    if (self->held != 3) {
        PyErr_SetString(PyExc_ValueError, "the SPI frame is released");
        return 0;
    }
    return 1;
}

/* write(u) -> -1 once the signals went out and the answer came back (checked), or the index of
 * the first signal that cannot be sent (not finite): then nothing was transferred. */
static PyObject *SpiFrame_write(SpiFrame *self, PyObject *u_object) {
    if (!spi_held(self)) {
        return NULL;
    }
    Py_buffer view;
    if (get_vector(u_object, &view, 0, "u") < 0) {
        return NULL;
    }
    if (view.len / 8 < self->send->n) {
        PyBuffer_Release(&view);
        PyErr_SetString(PyExc_IndexError, "values: fewer than the layout's fields");
        return NULL;
    }
    long bad = layout_pack(self->send, self->tx.buf, view.buf);
    PyBuffer_Release(&view);
    if (bad >= 0) {
        return PyLong_FromLong(bad);
    }
    if (spi_exchange(self) < 0) {
        return NULL;
    }
    return PyLong_FromLong(-1);
}

/* read(y) -> True with the answer's signals in y, or False when the answer is not valid (y
 * untouched; the caller counts it stale or faults). A transfer is made first when none came
 * since the last read. y may be None: the check only (the caller unpacks). */
static PyObject *SpiFrame_read(SpiFrame *self, PyObject *y_object) {
    if (!spi_held(self)) {
        return NULL;
    }
    Py_buffer view;
    int unpack = y_object != Py_None;
    if (unpack) {
        if (get_vector(y_object, &view, 1, "y") < 0) {
            return NULL;
        }
        if (view.len / 8 < self->receive->n) {
            PyBuffer_Release(&view);
            PyErr_SetString(PyExc_IndexError, "out: fewer than the layout's fields");
            return NULL;
        }
    }
    if (!self->fresh && spi_exchange(self) < 0) {
        goto fail;
    }
    self->fresh = 0;
    if (unpack) {
        if (self->answered) {
            layout_unpack(self->receive, self->rx.buf, view.buf);
        }
        PyBuffer_Release(&view);
    }
    return PyBool_FromLong(self->answered);
fail:
    if (unpack) {
        PyBuffer_Release(&view);
    }
    return NULL;
}

/* exchange(): one transfer of what tx holds (after the Python layout packed it). */
static PyObject *SpiFrame_exchange(SpiFrame *self, PyObject *Py_UNUSED(ignored)) {
    if (!spi_held(self) || spi_exchange(self) < 0) {
        return NULL;
    }
    Py_RETURN_NONE;
}

/* seal() and check(): the transfer's two halves without the ioctl, so the tests compare them with
 * the reference on buffers on a machine with no SPI controller. */
static PyObject *SpiFrame_seal(SpiFrame *self, PyObject *Py_UNUSED(ignored)) {
    if (!spi_held(self)) {
        return NULL;
    }
    spi_seal(self);
    Py_RETURN_NONE;
}

static PyObject *SpiFrame_check(SpiFrame *self, PyObject *Py_UNUSED(ignored)) {
    if (!spi_held(self)) {
        return NULL;
    }
    spi_check(self);
    return PyBool_FromLong(self->answered);
}

static PyObject *SpiFrame_release_method(SpiFrame *self, PyObject *Py_UNUSED(ignored)) {
    SpiFrame_release(self);
    Py_RETURN_NONE;
}

static PyObject *SpiFrame_get_bad_crc(SpiFrame *self, void *closure) {
    return PyLong_FromUnsignedLongLong(self->bad_crc);
}

static PyObject *SpiFrame_get_bad_counter(SpiFrame *self, void *closure) {
    return PyLong_FromUnsignedLongLong(self->bad_counter);
}

static PyObject *SpiFrame_get_counter(SpiFrame *self, void *closure) {
    return PyLong_FromLong(self->counter);
}

static PyObject *SpiFrame_get_expected(SpiFrame *self, void *closure) {
    return PyLong_FromLong(self->expected);
}

/* The words of FrameCheck.last_error, made when asked (a refusal in the loop builds no string). */
static PyObject *SpiFrame_get_last_error(SpiFrame *self, void *closure) {
    switch (self->last_error) {
    case SPI_BAD_CRC:
        return PyUnicode_FromString("bad CRC");
    case SPI_BAD_COUNTER:
        return PyUnicode_FromFormat("counter %d where %d was expected", self->last_seen, self->last_expected);
    default:
        return PyUnicode_FromString("");
    }
}

static PyMethodDef SpiFrame_methods[] = {
    {"write", (PyCFunction)SpiFrame_write, METH_O, "write(u) -> -1 when transferred, or a non-finite signal's index."},
    {"read", (PyCFunction)SpiFrame_read, METH_O, "read(y or None) -> whether the answer was valid (then in y)."},
    {"exchange", (PyCFunction)SpiFrame_exchange, METH_NOARGS, "One transfer of what tx holds, checked."},
    {"seal", (PyCFunction)SpiFrame_seal, METH_NOARGS, "Counter and CRC into tx (a transfer's first half)."},
    {"check", (PyCFunction)SpiFrame_check, METH_NOARGS, "Check rx, move the counter on (its second half)."},
    {"release", (PyCFunction)SpiFrame_release_method, METH_NOARGS, "Let go of the buffers and layouts."},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef SpiFrame_getset[] = {
    {"bad_crc", (getter)SpiFrame_get_bad_crc, NULL, "Answers refused for their CRC.", NULL},
    {"bad_counter", (getter)SpiFrame_get_bad_counter, NULL, "Answers refused for their counter.", NULL},
    {"counter", (getter)SpiFrame_get_counter, NULL, "The counter of the next frame sent.", NULL},
    {"expected", (getter)SpiFrame_get_expected, NULL, "The counter the next answer must carry (-1: any).", NULL},
    {"last_error", (getter)SpiFrame_get_last_error, NULL, "Why the last refused answer was refused.", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject SpiFrameType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "rtloop.io._devio.SpiFrame",
    .tp_basicsize = sizeof(SpiFrame),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)SpiFrame_init,
    .tp_dealloc = (destructor)SpiFrame_dealloc,
    .tp_methods = SpiFrame_methods,
    .tp_getset = SpiFrame_getset,
    .tp_doc = "SpiFrame(fd, request, transfer, tx, rx, send, receive, echo): an SPI device's cycle.",
};

/* crc16_ccitt(data) -> the frame's CRC (for the tests: the same as binascii.crc_hqx(data, 0xFFFF)). */
static PyObject *devio_crc16_ccitt(PyObject *module, PyObject *data) {
    Py_buffer view;
    if (PyObject_GetBuffer(data, &view, PyBUF_SIMPLE) < 0) {
        return NULL;
    }
    uint16_t crc = crc16_ccitt(view.buf, view.len);
    PyBuffer_Release(&view);
    return PyLong_FromLong(crc);
}

static PyMethodDef devio_functions[] = {
    {"crc16_ccitt", (PyCFunction)devio_crc16_ccitt, METH_O, "CRC-16/CCITT-FALSE of a buffer."},
    {NULL, NULL, 0, NULL},
};

/* ------------------------------------------------------------------------------------------ */

static struct PyModuleDef devio_module = {
    PyModuleDef_HEAD_INIT, "rtloop.io._devio", "The devices' per-cycle work in C (see io/compiled.py).", -1, devio_functions,
};

PyMODINIT_FUNC PyInit__devio(void) {
    PyTypeObject *types[] = {&GuardType,     &CopiesType,    &LayoutType,  &CanReceiverType,
                             &CanCycleType,  &GpioLinesType, &SpiFrameType};
    const char *names[] = {"Guard", "Copies", "Layout", "CanReceiver", "CanCycle", "GpioLines", "SpiFrame"};
    crc16_table_build();
    PyObject *module = PyModule_Create(&devio_module);
    if (module == NULL) {
        return NULL;
    }
    for (int i = 0; i < 7; i++) {
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

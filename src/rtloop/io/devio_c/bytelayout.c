/* The compiled twin of io/bytelayout.py: ByteLayout.pack_into / unpack_from.
 *
 * Included by ../_devio.c, which builds every part as one translation unit (so each function stays
 * static and inlinable); same arithmetic in the same order as the reference, bit for bit. */

/* ------------------------------------------------------------------------------------------ */
/* Layout: signals at fixed places in a frame, value = raw * scale + offset.                   */

typedef struct {
    char code;           /* struct code: B b H h I i Q q f d */
    int size;            /* bytes */
    int is_signed;
    int big_endian;
    Py_ssize_t start;    /* byte offset from the frame's ``at`` */
    double scale, offset;
    int wrap;            /* an encoder: packed wrapped round, unpacked unwrapped */
    double sent_low, sent_high; /* a duty: the raw values it may be sent as (its range), else +-inf */
    int started;         /* an encoder: read at least once */
    uint64_t last_bits;  /* an encoder: the last reading's bits */
    int64_t count;       /* an encoder: the unwrapped count */
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

/* Layout(fields): each field (code, start_byte, scale, offset, big_endian[, encoder, sent_low, sent_high]). */
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
        int big, wrap = 0;
        f->sent_low = -INFINITY;
        f->sent_high = INFINITY;
        if (!PyArg_ParseTuple(PySequence_Fast_GET_ITEM(items, i), "snddp|pdd", &code, &f->start, &f->scale,
                              &f->offset, &big, &wrap, &f->sent_low, &f->sent_high)) {
            goto fail;
        }
        f->wrap = wrap;
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
        if (f->wrap && (f->code == 'f' || f->code == 'd')) {
            PyErr_SetString(PyExc_ValueError, "an encoder is an integer field");
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
        if ((f->code == 'd' || f->code == 'f') && (raw < f->sent_low || raw > f->sent_high)) {
            raw = raw < f->sent_low ? f->sent_low : f->sent_high; /* a float duty: its range */
        }
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
            if (raw > f->sent_high) { /* a duty: the counts within its range */
                raw = f->sent_high;
            } else if (raw < f->sent_low) {
                raw = f->sent_low;
            }
            int width = 8 * f->size;
            /* the exact range of the raw type, as doubles: [low, high_exclusive) */
            double low = f->is_signed ? -ldexp(1.0, width - 1) : 0.0;
            double high_exclusive = ldexp(1.0, f->is_signed ? width - 1 : width);
            if (f->wrap) { /* an encoder's count wraps round its field, as the counter shows it */
                double modulus = ldexp(1.0, width);
                double wrapped = fmod(raw, modulus); /* exact; the sign of raw */
                if (wrapped < 0) {
                    wrapped += modulus; /* exact: both are multiples of a power of two within 2^64 */
                }
                bits = wrapped >= modulus ? 0 : (uint64_t)wrapped;
            } else if (f->is_signed) {
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

/* The layout's fields of ``frame`` (at least layout->end bytes) into target[0..n-1]; each encoder
 * unwrapped by the shortest signed step from its last reading (the first taken as it is). */
static void layout_unpack(Layout *layout, const unsigned char *frame, double *target) {
    for (Py_ssize_t i = 0; i < layout->n; i++) {
        FieldPlan *f = &layout->fields[i];
        uint64_t bits = get_bits(frame + f->start, f->size, f->big_endian);
        double raw;
        if (f->code == 'd') {
            memcpy(&raw, &bits, 8);
        } else if (f->code == 'f') {
            uint32_t word = (uint32_t)bits;
            float narrow;
            memcpy(&narrow, &word, 4);
            raw = narrow;
        } else if (f->wrap) {
            int width = 8 * f->size;
            uint64_t mask = width == 64 ? UINT64_MAX : ((uint64_t)1 << width) - 1;
            if (!f->started) {
                f->count = !f->is_signed ? (int64_t)bits
                           : width == 64 ? (int64_t)bits
                           : (int64_t)(bits ^ ((uint64_t)1 << (width - 1))) - ((int64_t)1 << (width - 1));
                f->started = 1;
            } else {
                uint64_t step = (bits - f->last_bits) & mask;
                /* step - 2^width when step >= 2^(width-1): the two's complement of step in width bits */
                f->count += step >= ((uint64_t)1 << (width - 1)) ? -(int64_t)((~step + 1) & mask) : (int64_t)step;
            }
            f->last_bits = bits;
            raw = (double)f->count;
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

/* The compiled twin of io/drives/esc.py's process-data path: Segment.process for a frame of logical
 * datagrams (LRD, LWR, LRW: the master's cycle) and the FRMW of the DC reference clock's system
 * time (0x0910, 8 bytes) that follows the LRW with distributed clocks, EmulatedSlave.logical through each slave's FMMUs,
 * EmulatedSlave.application (the drive, esc_drive.c, takes the outputs and computes its inputs) and
 * the SM watchdog's check of EmulatedSlave.tick. A frame with any other datagram (the
 * configuration: registers, the SII, the AL state machine) is left to the Python reference, which
 * does it all; so is a frame whose working counter would overflow or whose datagrams run past its
 * end (the reference raises there). Each slave's ESC memory and its counters (esc.py
 * EmulatedSlave's dropped, outputs_written, ...) are the same bytes on both sides, so either path
 * may serve the next frame. What the log should say (a drive's events, the first exchange in OP)
 * is left for Python (process() returns 2). Of the FRMW, the other slaves' writes of the reference's
time (esc_dc.py DcUnit.written: the difference at 0x092C, the system time) are done here; the
reference's own read (DcUnit.refresh: its SYNC0 state, logged) is its Python read().
 *
 * Included by ../_devio.c (one translation unit). */

enum { LRD_ = 10, LWR_ = 11, LRW_ = 12, FRMW_ = 14 };
enum { C_DROPPED, C_OUTPUTS_WRITTEN, C_LAST_OUTPUTS_NS, C_EXCHANGES_IN_OP, C_EXCHANGES_ENABLED, C_FIRST_CW, C_HAS_DC,
       C_LOCAL_START_NS, C_COUNT };
#define ESC_DC_SYSTEM_TIME 0x0910
#define ESC_DC_OFFSET 0x0920
#define ESC_DC_DELAY 0x0928
#define ESC_DC_DIFFERENCE 0x092C
enum { X_STATUSWORD, X_MODE, X_POSITION, X_VELOCITY, X_TORQUE, X_FOLLOWING, X_ERROR };
#define ESC_MEMORY 0x10000
#define ESC_OUTPUTS_AT 0x1000
#define ESC_INPUTS_AT 0x1200
#define ESC_MAX_TX 16

typedef struct {
    uint8_t *memory;
    long long *counters;
    EmulatedDrive *drive;
    PyObject *clock, *read; /* the slave's clock (its DC unit's), its read(address, data, mode) */
    int rx_size, rx[5]; /* byte offsets of controlword, mode, target position, velocity, torque; -1: not mapped */
    int n_tx, tx_kind[ESC_MAX_TX], tx_at[ESC_MAX_TX];
} EscSlave;

typedef struct {
    PyObject_HEAD
    Py_ssize_t n;
    EscSlave *slaves;
    Py_buffer *views; /* 2 per slave: memory, counters */
    Py_ssize_t held;
    PyObject *drives, *clock, *clocks, *reads;
} EscFrames;

static inline unsigned esc_u16(const uint8_t *p) { return (unsigned)p[0] | (unsigned)p[1] << 8; }
static inline long long esc_u32(const uint8_t *p) {
    return (long long)((uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24);
}
static inline void esc_put16(uint8_t *p, long long v) { p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); }
static inline void esc_put32(uint8_t *p, long long v) {
    p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); p[2] = (uint8_t)(v >> 16); p[3] = (uint8_t)(v >> 24);
}
static inline uint64_t esc_u64(const uint8_t *p) { return (uint64_t)esc_u32(p) | (uint64_t)esc_u32(p + 4) << 32; }
static inline void esc_put64(uint8_t *p, uint64_t v) { esc_put32(p, (long long)(v & 0xFFFFFFFF)); esc_put32(p + 4, (long long)(v >> 32)); }
static inline int esc_in_op(const EscSlave *s) { return (esc_u16(s->memory + 0x0130) & 0x0F) == 8; }

static void EscFrames_release(EscFrames *self) {
    for (Py_ssize_t i = 0; i < self->held; i++) {
        PyBuffer_Release(&self->views[i]);
    }
    self->held = 0;
    PyMem_Free(self->views);
    PyMem_Free(self->slaves);
    self->views = NULL;
    self->slaves = NULL;
}

static void EscFrames_dealloc(EscFrames *self) {
    EscFrames_release(self);
    Py_XDECREF(self->drives);
    Py_XDECREF(self->clock);
    Py_XDECREF(self->clocks);
    Py_XDECREF(self->reads);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* EscFrames(memories, counters, drives, layouts, clocks, reads, clock): per slave its 64 KiB ESC
 * memory, its counters (array('q') of C_COUNT), its EmulatedDrive, its layout (rx size, the five rx
 * offsets, then kind and offset of each tx entry in order), its clock and its read method;
 * clock() -> ns, as Segment.clock. */
static int EscFrames_init(EscFrames *self, PyObject *args, PyObject *kwargs) {
    PyObject *memories, *counters, *drives, *layouts, *clocks, *reads, *clock;
    if (!PyArg_ParseTuple(args, "O!O!O!O!O!O!O", &PyList_Type, &memories, &PyList_Type, &counters, &PyList_Type,
                          &drives, &PyList_Type, &layouts, &PyList_Type, &clocks, &PyList_Type, &reads, &clock)) {
        return -1;
    }
    EscFrames_release(self);
    Py_ssize_t n = PyList_GET_SIZE(memories);
    if (PyList_GET_SIZE(counters) != n || PyList_GET_SIZE(drives) != n || PyList_GET_SIZE(layouts) != n ||
        PyList_GET_SIZE(clocks) != n || PyList_GET_SIZE(reads) != n) {
        PyErr_SetString(PyExc_ValueError, "EscFrames: one memory, counters, drive, layout, clock and read per slave");
        return -1;
    }
    self->slaves = PyMem_Calloc((size_t)n + 1, sizeof(EscSlave));
    self->views = PyMem_Calloc(2 * (size_t)n + 1, sizeof(Py_buffer));
    if (self->slaves == NULL || self->views == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        EscSlave *s = &self->slaves[i];
        Py_buffer *memory = &self->views[self->held];
        if (PyObject_GetBuffer(PyList_GET_ITEM(memories, i), memory, PyBUF_SIMPLE | PyBUF_WRITABLE) < 0) {
            return -1;
        }
        self->held++;
        Py_buffer *count = &self->views[self->held];
        if (PyObject_GetBuffer(PyList_GET_ITEM(counters, i), count, PyBUF_SIMPLE | PyBUF_WRITABLE) < 0) {
            return -1;
        }
        self->held++;
        PyObject *drive = PyList_GET_ITEM(drives, i);
        if (memory->len != ESC_MEMORY || count->len != C_COUNT * (Py_ssize_t)sizeof(long long) ||
            !PyObject_TypeCheck(drive, &EmulatedDriveType)) {
            PyErr_SetString(PyExc_ValueError, "EscFrames: a 64 KiB memory, 8 counters and an EmulatedDrive per slave");
            return -1;
        }
        s->memory = memory->buf;
        s->counters = count->buf;
        s->drive = (EmulatedDrive *)drive;
        s->clock = PyList_GET_ITEM(clocks, i); /* held by self->clocks */
        s->read = PyList_GET_ITEM(reads, i);
        PyObject *layout = PySequence_Fast(PyList_GET_ITEM(layouts, i), "EscFrames: a layout is a sequence of ints");
        if (layout == NULL) {
            return -1;
        }
        Py_ssize_t size = PySequence_Fast_GET_SIZE(layout);
        int bad = size < 6 || (size - 6) % 2 || (size - 6) / 2 > ESC_MAX_TX;
        int values[6 + 2 * ESC_MAX_TX];
        for (Py_ssize_t k = 0; !bad && k < size; k++) {
            values[k] = (int)PyLong_AsLong(PySequence_Fast_GET_ITEM(layout, k));
            bad = (values[k] == -1 && PyErr_Occurred()) || values[k] < -1 || values[k] > 0x200 ||
                  (k >= 6 && k % 2 == 0 && values[k] > X_ERROR);
        }
        Py_DECREF(layout);
        if (bad) {
            if (!PyErr_Occurred()) {
                PyErr_SetString(PyExc_ValueError, "EscFrames: a layout is rx size, 5 rx offsets, (kind, offset) pairs");
            }
            return -1;
        }
        s->rx_size = values[0];
        for (int k = 0; k < 5; k++) {
            s->rx[k] = values[1 + k];
        }
        s->n_tx = (int)(size - 6) / 2;
        for (int k = 0; k < s->n_tx; k++) {
            s->tx_kind[k] = values[6 + 2 * k];
            s->tx_at[k] = values[7 + 2 * k];
        }
    }
    self->n = n;
    Py_XSETREF(self->drives, Py_NewRef(drives));
    Py_XSETREF(self->clock, Py_NewRef(clock));
    Py_XSETREF(self->clocks, Py_NewRef(clocks));
    Py_XSETREF(self->reads, Py_NewRef(reads));
    return 0;
}

/* DcUnit.system_ns: (clock() + local start + offset) mod 2**64; -1 with an exception. */
static int esc_system_ns(EscSlave *s, uint64_t *out) {
    PyObject *now = PyObject_CallNoArgs(s->clock);
    unsigned long long ns = now ? PyLong_AsUnsignedLongLongMask(now) : 0;
    Py_XDECREF(now);
    if (now == NULL || PyErr_Occurred()) {
        return -1;
    }
    *out = ns + (uint64_t)s->counters[C_LOCAL_START_NS] + esc_u64(s->memory + ESC_DC_OFFSET);
    return 0;
}

/* Segment._register_datagram for an FRMW of the system time: the reference (the addressed slave)
 * reads its time into the frame, each other slave with DC writes it (DcUnit.written). 0, -1. */
static int esc_frmw_system_time(EscSlave *s, unsigned adp, uint8_t *data, long long *wkc) {
    if (!s->counters[C_HAS_DC]) {
        return 0; /* no system time: neither read nor written */
    }
    if (adp != esc_u16(s->memory + 0x0010)) {
        uint64_t now, later;
        memcpy(s->memory + ESC_DC_SYSTEM_TIME, data, 8);
        if (esc_system_ns(s, &now) < 0) {
            return -1;
        }
        uint64_t difference = esc_u64(s->memory + ESC_DC_SYSTEM_TIME) + esc_u32(s->memory + ESC_DC_DELAY) - now;
        int negative = difference >= (uint64_t)1 << 63;
        uint64_t magnitude = negative ? (uint64_t)0 - difference : difference;
        magnitude = magnitude < 0x7FFFFFFF ? magnitude : 0x7FFFFFFF;
        esc_put32(s->memory + ESC_DC_DIFFERENCE, (long long)(magnitude | (negative ? 0x80000000u : 0)));
        if (esc_system_ns(s, &later) < 0) {
            return -1;
        }
        esc_put64(s->memory + ESC_DC_SYSTEM_TIME, later);
        *wkc += 1;
        return 0;
    }
    PyObject *view = PyMemoryView_FromMemory((char *)data, 8, PyBUF_WRITE);
    PyObject *done = view ? PyObject_CallFunction(s->read, "iOs", ESC_DC_SYSTEM_TIME, view, "copy") : NULL;
    Py_XDECREF(view);
    if (done == NULL) {
        return -1;
    }
    Py_DECREF(done);
    *wkc += 1;
    return 0;
}

/* EmulatedSlave.logical: the working counter's share. */
static int esc_logical(EscSlave *s, int command, long long address, uint8_t *data, long long length) {
    int read = 0, wrote = 0;
    for (int number = 0; number < 8; number++) {
        const uint8_t *fmmu = s->memory + 0x0600 + 16 * number;
        long long start = esc_u32(fmmu), size = esc_u16(fmmu + 4), physical = esc_u16(fmmu + 8);
        int kind = fmmu[11], active = fmmu[12];
        if (!(active & 1) || !size) {
            continue;
        }
        long long low = start > address ? start : address;
        long long high = start + size < address + length ? start + size : address + length;
        if (low >= high) {
            continue;
        }
        long long frame_at = low - address, memory_at = physical + (low - start), count = high - low;
        if (memory_at + count > ESC_MEMORY) {
            count = ESC_MEMORY - memory_at; /* the reference clamps at the memory's end too */
        }
        if ((kind & 1) && (command == LRD_ || command == LRW_)) {
            memcpy(data + frame_at, s->memory + memory_at, (size_t)count);
            read = 1;
        }
        if ((kind & 2) && (command == LWR_ || command == LRW_)) {
            memcpy(s->memory + memory_at, data + frame_at, (size_t)count);
            if (memory_at < ESC_OUTPUTS_AT + s->rx_size && memory_at + count > ESC_OUTPUTS_AT) {
                s->counters[C_OUTPUTS_WRITTEN] = 1;
            }
            wrote = esc_in_op(s);
        }
    }
    if (command == LRW_) {
        return read + 2 * wrote;
    }
    return read || wrote;
}

/* EmulatedSlave.application: 1 when the log has something to say, 0, -1 with an exception. */
static int esc_application(EscSlave *s, long long now_ns) {
    EmulatedDrive *d = s->drive;
    const uint8_t *out = s->memory + ESC_OUTPUTS_AT;
    long long *c = s->counters;
    c[C_OUTPUTS_WRITTEN] = 0;
    int in_op = esc_in_op(s);
    if (in_op) {
        c[C_LAST_OUTPUTS_NS] = now_ns;
        c[C_EXCHANGES_IN_OP] += 1;
        if (d->state == S_ENABLED) {
            c[C_EXCHANGES_ENABLED] += 1;
        }
    }
    long long controlword = s->rx[0] >= 0 ? esc_u16(out + s->rx[0]) : 0;
    long long mode = s->rx[1] >= 0 ? (int8_t)out[s->rx[1]] : d->mode;
    long long position = s->rx[2] >= 0 ? (int32_t)(uint32_t)esc_u32(out + s->rx[2]) : 0;
    long long velocity = s->rx[3] >= 0 ? (int32_t)(uint32_t)esc_u32(out + s->rx[3]) : 0;
    long long torque = s->rx[4] >= 0 ? (int16_t)esc_u16(out + s->rx[4]) : 0;
    if (in_op && c[C_EXCHANGES_IN_OP] == 1) {
        c[C_FIRST_CW] = controlword; /* "first process data in OP (controlword ...)": Python logs it */
    }
    if (drive_exchange(d, controlword, mode, position, velocity, torque, in_op) < 0) {
        return -1;
    }
    uint8_t *in = s->memory + ESC_INPUTS_AT;
    for (int k = 0; k < s->n_tx; k++) {
        uint8_t *at = in + s->tx_at[k];
        switch (s->tx_kind[k]) {
        case X_STATUSWORD: esc_put16(at, d->statusword); break;
        case X_MODE: at[0] = (uint8_t)d->mode_display; break;
        case X_POSITION: esc_put32(at, d->position); break;
        case X_VELOCITY: esc_put32(at, d->velocity); break;
        case X_TORQUE: esc_put16(at, d->torque); break;
        case X_FOLLOWING: esc_put32(at, d->following_error); break;
        default: esc_put16(at, d->error_code); break;
        }
    }
    return c[C_FIRST_CW] >= 0 || PyList_GET_SIZE(d->events) > 0;
}

/* process(frame, offset) -> 0 not EtherCAT (the reference's False), 1 done, 2 done and the log has
 * something to say (Python takes the drives' events), -1 the Python reference must do this frame
 * (nothing was touched). */
static PyObject *EscFrames_process(EscFrames *self, PyObject *args) {
    Py_buffer view;
    Py_ssize_t offset;
    if (!PyArg_ParseTuple(args, "w*n", &view, &offset)) {
        return NULL;
    }
    uint8_t *frame = view.buf;
    long long size = view.len;
    long result = -1;
    if (offset < 0 || offset + 2 > size) {
        goto done;
    }
    unsigned header = esc_u16(frame + offset);
    if (header >> 12 != 1) {
        result = 0;
        goto done;
    }
    long long start = offset + 2, end = start + (header & 0x07FF);
    for (long long at = start; at + 12 <= end;) { /* may it be done here? */
        int command = frame[at];
        unsigned length_field = esc_u16(frame + at + 6), length = length_field & 0x07FF;
        int system_time = command == FRMW_ && esc_u16(frame + at + 4) == ESC_DC_SYSTEM_TIME && length == 8;
        if ((!system_time && (command < LRD_ || command > LRW_)) || at + 12 + length > size ||
            esc_u16(frame + at + 10 + length) + 3 * self->n > 0xFFFF) {
            goto done;
        }
        at += 12 + length;
        if (!(length_field & 0x8000)) {
            break;
        }
    }
    int outputs = 0;
    for (long long at = start; at + 12 <= end;) {
        int command = frame[at];
        unsigned length_field = esc_u16(frame + at + 6), length = length_field & 0x07FF;
        long long address = esc_u32(frame + at + 2), wkc = esc_u16(frame + at + 10 + length);
        for (Py_ssize_t i = 0; i < self->n; i++) {
            if (self->slaves[i].counters[C_DROPPED]) {
                continue;
            }
            if (command != FRMW_) {
                wkc += esc_logical(&self->slaves[i], command, address, frame + at + 10, length);
            } else if (esc_frmw_system_time(&self->slaves[i], esc_u16(frame + at + 2), frame + at + 10, &wkc) < 0) {
                PyBuffer_Release(&view);
                return NULL;
            }
        }
        outputs |= command == LWR_ || command == LRW_;
        esc_put16(frame + at + 10 + length, wkc);
        at += 12 + length;
        if (!(length_field & 0x8000)) {
            break;
        }
    }
    result = 1;
    PyObject *now = PyObject_CallNoArgs(self->clock);
    long long now_ns = now ? PyLong_AsLongLong(now) : -1;
    Py_XDECREF(now);
    if (now_ns == -1 && PyErr_Occurred()) {
        PyBuffer_Release(&view);
        return NULL;
    }
    for (Py_ssize_t i = 0; outputs && i < self->n; i++) {
        EscSlave *s = &self->slaves[i];
        if (s->counters[C_OUTPUTS_WRITTEN] && !s->counters[C_DROPPED]) {
            int said = esc_application(s, now_ns);
            if (said < 0) {
                PyBuffer_Release(&view);
                return NULL;
            }
            result = said ? 2 : result;
        }
    }
done:
    PyBuffer_Release(&view);
    return PyLong_FromLong(result);
}

/* expired(now_ns) -> True when a slave's SM watchdog has run out (EmulatedSlave.tick then acts). */
static PyObject *EscFrames_expired(EscFrames *self, PyObject *arg) {
    long long now_ns = PyLong_AsLongLong(arg);
    if (now_ns == -1 && PyErr_Occurred()) {
        return NULL;
    }
    for (Py_ssize_t i = 0; i < self->n; i++) {
        EscSlave *s = &self->slaves[i];
        if (esc_in_op(s) && !s->counters[C_DROPPED]) {
            long long limit = ((long long)esc_u16(s->memory + 0x0400) + 2) * 40 * esc_u16(s->memory + 0x0420);
            if (limit && now_ns - s->counters[C_LAST_OUTPUTS_NS] > limit) {
                Py_RETURN_TRUE;
            }
        }
    }
    Py_RETURN_FALSE;
}

static PyMethodDef EscFrames_methods[] = {
    {"process", (PyCFunction)EscFrames_process, METH_VARARGS,
     "process(frame, offset): 0 not EtherCAT, 1 done, 2 done with events to log, -1 for the Python reference."},
    {"expired", (PyCFunction)EscFrames_expired, METH_O, "expired(now_ns): has a slave's SM watchdog run out?"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject EscFramesType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "rtloop.io._devio.EscFrames",
    .tp_basicsize = sizeof(EscFrames),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "The emulated slaves' process-data path (io/drives/esc.py Segment.process), compiled.",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)EscFrames_init,
    .tp_dealloc = (destructor)EscFrames_dealloc,
    .tp_methods = EscFrames_methods,
};

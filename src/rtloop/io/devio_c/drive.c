/* The compiled twin of io/drives/cycle.py: DriveCycle.prepare_outputs and take_inputs while every
 * drive is in Operation enabled (the running cycle). Whatever is not that (the enabling, a mode
 * change, a drive that left Operation enabled and must be named) returns to the Python reference,
 * which does it and says it. Same arithmetic in the same order, bit for bit.
 *
 * Included by ../_devio.c (one translation unit). */

enum {
    D_OUT_CW, D_OUT_MODE, D_OUT_POS, D_OUT_VEL, D_OUT_TQ,
    D_IN_STATUS, D_IN_MODE, D_IN_POS, D_IN_VEL, D_IN_TQ, D_IN_ERR,
    D_U_POS, D_U_VEL, D_U_TQ, D_U_MODE, D_Y_AT, D_PLAN
};
/* plan[joint * D_PLAN + k]: byte offsets in the output and input buffers (-1: not mapped), places
 * in u (-1: none), where the joint's readings start in y. scale[2 * joint]: rad per count, then
 * N·m per permille. modes[joint]: the mode the joint is in (kept by both sides). state[2 * joint]:
 * the statusword and the position actual the last take saw (the Python side reads them back). */

#define DRIVE_ENABLED 4 /* Cia402State.OPERATION_ENABLED */
#define DRIVE_QUICK_STOP 5

typedef struct {
    PyObject_HEAD
    Py_buffer out, in, u, y, plan, scale, modes, state, table;
    Py_ssize_t joints;
    int held;
    /* The EtherCAT link (link()): the frame sent, the buffer its answer comes into, on a blocking
     * raw socket whose receive timeout (SO_RCVTIMEO) is one kernel tick: one send and one recv a
     * cycle, no poll, the frame's own timeout checked on the clock (SOEM's way). */
    Py_buffer frame, reply;
    int linked, fd;
    Py_ssize_t wkc_at;
    long expected_wkc;
    /* Distributed clocks: the working counter of the FRMW datagram after the LRW, which carries the
     * reference clock's system time to the other slaves (0: no DC datagram), and the one expected. */
    Py_ssize_t dc_wkc_at;
    long expected_dc_wkc;
    long long timeout_ns, sent_ns;
    /* The wait to the timeout to the nanosecond (ppoll, then a recv that does not block): lost frames
     * are tolerated (lost_frames_max), so a lost one must end its cycle at the timeout, not at the
     * kernel's next tick (up to 4 ms at HZ=250). 0: the blocking recv alone, one syscall. */
    int precise;
} DriveRun;

static void DriveRun_release(DriveRun *self) {
    Py_buffer *views[9] = {&self->out, &self->in, &self->u, &self->y, &self->plan, &self->scale, &self->modes,
                           &self->state, &self->table};
    for (int i = 0; i < self->held; i++) {
        PyBuffer_Release(views[i]);
    }
    self->held = 0;
}

static void DriveRun_unlink(DriveRun *self) {
    if (self->linked) {
        PyBuffer_Release(&self->frame);
        PyBuffer_Release(&self->reply);
        self->linked = 0;
    }
}

static void DriveRun_dealloc(DriveRun *self) {
    DriveRun_release(self);
    DriveRun_unlink(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static inline uint32_t le_u32(const uint8_t *p) {
    return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}

static inline void put_le(uint8_t *p, uint32_t value, int bytes) {
    for (int i = 0; i < bytes; i++) {
        p[i] = (uint8_t)(value >> (8 * i));
    }
}

/* cia402.to_raw: the value in raw units, saturated at a signed bits-wide range, ties to even. */
static inline int64_t drive_to_raw(double value, double per_unit, int bits) {
    double raw = value / per_unit;
    double high = (double)((INT64_C(1) << (bits - 1)) - 1);
    if (raw >= high) {
        return (int64_t)high;
    }
    if (raw <= -high - 1) {
        return (int64_t)(-high - 1);
    }
    return (int64_t)nearbyint(raw);
}

/* DriveRun(out, in, u, y, plan, scale, modes, state, table): out and in the frame's bytes (writable),
 * u and y float64, plan/modes/state int64, scale float64, table the 0x70 states of a statusword & 0x6F. */
static int DriveRun_init(DriveRun *self, PyObject *args, PyObject *kwargs) {
    PyObject *objects[9];
    if (!PyArg_ParseTuple(args, "OOOOOOOOO", &objects[0], &objects[1], &objects[2], &objects[3], &objects[4],
                          &objects[5], &objects[6], &objects[7], &objects[8])) {
        return -1;
    }
    DriveRun_release(self);
    Py_buffer *views[9] = {&self->out, &self->in, &self->u, &self->y, &self->plan, &self->scale, &self->modes,
                           &self->state, &self->table};
    for (int i = 0; i < 9; i++) {
        int failed;
        if (i < 2) {
            failed = PyObject_GetBuffer(objects[i], views[i], PyBUF_SIMPLE | PyBUF_WRITABLE);
        } else if (i == 2 || i == 3 || i == 5) {
            failed = get_vector(objects[i], views[i], i == 3, "DriveRun");
        } else {
            failed = get_counters(objects[i], views[i], "DriveRun");
        }
        if (failed < 0) {
            DriveRun_release(self);
            return -1;
        }
        self->held = i + 1;
    }
    self->joints = self->modes.len / 8;
    if (self->plan.len / 8 != self->joints * D_PLAN || self->scale.len / 8 != 2 * self->joints ||
        self->state.len / 8 != 2 * self->joints || self->table.len / 8 != 0x70) {
        DriveRun_release(self);
        PyErr_SetString(PyExc_TypeError, "DriveRun: plan, scale, state or table of the wrong size");
        return -1;
    }
    static const int sizes[D_IN_ERR + 1] = {2, 1, 4, 4, 2, 2, 1, 4, 4, 2, 2}; /* bytes of each object */
    const int64_t *plan = self->plan.buf;
    for (Py_ssize_t j = 0; j < self->joints; j++) { /* every offset inside its buffer, every place inside its vector */
        const int64_t *p = plan + j * D_PLAN;
        for (int k = D_OUT_CW; k <= D_IN_ERR; k++) {
            Py_ssize_t room = k <= D_OUT_TQ ? self->out.len : self->in.len;
            int required = k == D_OUT_CW || k == D_OUT_MODE || k == D_IN_STATUS || k == D_IN_POS;
            if ((required && p[k] < 0) || p[k] + sizes[k] > room) {
                DriveRun_release(self);
                PyErr_SetString(PyExc_ValueError, "DriveRun: an object missing or past its buffer");
                return -1;
            }
        }
        for (int k = D_U_POS; k <= D_U_MODE; k++) {
            if (p[k] >= self->u.len / 8) {
                DriveRun_release(self);
                PyErr_SetString(PyExc_ValueError, "DriveRun: a command past u");
                return -1;
            }
        }
        Py_ssize_t readings = 7 + (p[D_IN_VEL] >= 0) + (p[D_IN_TQ] >= 0) + (p[D_IN_ERR] >= 0) + (p[D_IN_MODE] >= 0);
        if (p[D_Y_AT] < 0 || p[D_Y_AT] + readings > self->y.len / 8) {
            DriveRun_release(self);
            PyErr_SetString(PyExc_ValueError, "DriveRun: readings past y");
            return -1;
        }
    }
    return 0;
}

/* prepare() -> -1 when every joint's outputs are written; else the joint the Python side must do
 * (its mode command asks for another mode). */
static Py_ssize_t drive_prepare(DriveRun *self) {
    const int64_t *plan = self->plan.buf;
    const double *u = self->u.buf, *scale = self->scale.buf;
    const int64_t *modes = self->modes.buf, *state = self->state.buf;
    uint8_t *out = self->out.buf;
    for (Py_ssize_t j = 0; j < self->joints; j++) {
        const int64_t *p = plan + j * D_PLAN;
        int64_t mode = modes[j];
        if (p[D_U_MODE] >= 0 && (int64_t)nearbyint(u[p[D_U_MODE]]) != mode) {
            return j;
        }
        double per_count = scale[2 * j], per_permille = scale[2 * j + 1];
        put_le(out + p[D_OUT_CW], 0x0F, 2);
        put_le(out + p[D_OUT_MODE], (uint32_t)mode, 1);
        if (p[D_OUT_POS] >= 0) {
            int64_t value = mode == 8 ? drive_to_raw(u[p[D_U_POS]], per_count, 32) : state[2 * j + 1];
            put_le(out + p[D_OUT_POS], (uint32_t)value, 4);
        }
        if (p[D_OUT_VEL] >= 0) {
            int64_t value = mode == 9 ? drive_to_raw(u[p[D_U_VEL]], per_count, 32) : 0;
            put_le(out + p[D_OUT_VEL], (uint32_t)value, 4);
        }
        if (p[D_OUT_TQ] >= 0) {
            int64_t value = mode == 10 ? drive_to_raw(u[p[D_U_TQ]], per_permille, 16) : 0;
            put_le(out + p[D_OUT_TQ], (uint32_t)value, 2);
        }
    }
    return -1;
}

static PyObject *DriveRun_prepare(DriveRun *self, PyObject *unused) {
    return PyLong_FromSsize_t(drive_prepare(self));
}

/* take() -> -1 when every joint's inputs are in y and every drive is in Operation enabled in its
 * mode; else the first joint that is not (the Python side names it, or waits for its mode). */
static Py_ssize_t drive_take(DriveRun *self) {
    const int64_t *plan = self->plan.buf, *modes = self->modes.buf, *table = self->table.buf;
    const double *scale = self->scale.buf;
    int64_t *state = self->state.buf;
    const uint8_t *in = self->in.buf;
    double *y = self->y.buf;
    for (Py_ssize_t j = 0; j < self->joints; j++) {
        const int64_t *p = plan + j * D_PLAN;
        uint32_t statusword = (uint32_t)in[p[D_IN_STATUS]] | (uint32_t)in[p[D_IN_STATUS] + 1] << 8;
        int32_t position = (int32_t)le_u32(in + p[D_IN_POS]);
        state[2 * j] = statusword;
        state[2 * j + 1] = position;
        if (table[statusword & 0x6F] != DRIVE_ENABLED) {
            return j;
        }
        if (p[D_IN_MODE] >= 0 && (int8_t)in[p[D_IN_MODE]] != modes[j]) {
            return j;
        }
        double per_count = scale[2 * j], per_permille = scale[2 * j + 1];
        Py_ssize_t at = p[D_Y_AT];
        y[at++] = (double)position * per_count;
        if (p[D_IN_VEL] >= 0) {
            y[at++] = (double)(int32_t)le_u32(in + p[D_IN_VEL]) * per_count;
        }
        if (p[D_IN_TQ] >= 0) {
            int16_t torque = (int16_t)((uint16_t)in[p[D_IN_TQ]] | (uint16_t)in[p[D_IN_TQ] + 1] << 8);
            y[at++] = (double)torque * per_permille;
        }
        y[at] = 1.0; /* enabled: checked above */
        y[at + 1] = statusword & 0x0008 ? 1.0 : 0.0;
        y[at + 2] = statusword & 0x0080 ? 1.0 : 0.0;
        y[at + 3] = statusword & 0x0400 ? 1.0 : 0.0;
        y[at + 4] = (statusword & 0x2000) && modes[j] == 8 ? 1.0 : 0.0;
        y[at + 5] = 0.0; /* quick stop active: not while enabled */
        at += 6;
        if (p[D_IN_ERR] >= 0) {
            y[at++] = (double)((uint32_t)in[p[D_IN_ERR]] | (uint32_t)in[p[D_IN_ERR] + 1] << 8);
        }
        if (p[D_IN_MODE] >= 0) {
            y[at] = (double)(int8_t)in[p[D_IN_MODE]];
        }
    }
    return -1;
}

static PyObject *DriveRun_take(DriveRun *self, PyObject *unused) {
    return PyLong_FromSsize_t(drive_take(self));
}

/* ------------------------------------------------------------------------------------------ */
/* The EtherCAT link: the twin of io/drives/ethercat.py EthercatDevice._send and _receive.       */

#define ECAT_COMMAND_AT 16 /* the first datagram's command, then its index (Ethernet 14 + EtherCAT 2) */
#define ECAT_INDEX_AT 17
#define ECAT_LRW 12

/* link(fd, frame, reply, wkc_at, expected_wkc, timeout_ns, dc_wkc_at=0, expected_dc_wkc=0, precise=0): send()
 * and receive() exchange ``frame`` on the raw socket ``fd`` (blocking, its SO_RCVTIMEO one tick),
 * the answer into ``reply``, whose working counter is at ``wkc_at``, due within ``timeout_ns`` of
 * the send; the DC datagram's working counter at ``dc_wkc_at`` (0: none); ``precise``: the wait
 * ends at the timeout to the nanosecond (ppoll). The run's out and in buffers are places in them. */
static PyObject *DriveRun_link(DriveRun *self, PyObject *args) {
    int fd;
    PyObject *frame, *reply;
    Py_ssize_t wkc_at;
    long expected_wkc;
    long long timeout_ns;
    Py_ssize_t dc_wkc_at = 0;
    long expected_dc_wkc = 0;
    int precise = 0;
    if (!PyArg_ParseTuple(args, "iOOnlL|nlp", &fd, &frame, &reply, &wkc_at, &expected_wkc, &timeout_ns, &dc_wkc_at,
                          &expected_dc_wkc, &precise)) {
        return NULL;
    }
    DriveRun_unlink(self);
    if (PyObject_GetBuffer(frame, &self->frame, PyBUF_SIMPLE | PyBUF_WRITABLE) < 0) {
        return NULL;
    }
    if (PyObject_GetBuffer(reply, &self->reply, PyBUF_SIMPLE | PyBUF_WRITABLE) < 0) {
        PyBuffer_Release(&self->frame);
        return NULL;
    }
    self->linked = 1;
    if (self->frame.len <= ECAT_INDEX_AT || wkc_at <= ECAT_INDEX_AT || wkc_at + 2 > self->reply.len ||
        dc_wkc_at < 0 || (dc_wkc_at && (dc_wkc_at <= wkc_at || dc_wkc_at + 2 > self->frame.len))) {
        DriveRun_unlink(self);
        PyErr_SetString(PyExc_ValueError, "DriveRun.link: a frame without its datagram, or the working counter past the reply");
        return NULL;
    }
    self->fd = fd;
    self->wkc_at = wkc_at;
    self->expected_wkc = expected_wkc;
    self->dc_wkc_at = dc_wkc_at;
    self->expected_dc_wkc = expected_dc_wkc;
    self->timeout_ns = timeout_ns;
    self->sent_ns = 0;
    self->precise = precise;
    Py_RETURN_NONE;
}

/* send() -> -1 once the outputs are packed and the frame went out with the next index; else the
 * joint the Python side must prepare (nothing was sent). A failed send is socket.send's OSError. */
static PyObject *DriveRun_send(DriveRun *self, PyObject *unused) {
    if (!self->linked) {
        PyErr_SetString(PyExc_ValueError, "DriveRun.send: no link");
        return NULL;
    }
    Py_ssize_t joint = drive_prepare(self);
    if (joint >= 0) {
        return PyLong_FromSsize_t(joint);
    }
    uint8_t *frame = self->frame.buf;
    frame[ECAT_INDEX_AT] = (uint8_t)(frame[ECAT_INDEX_AT] + 1);
    while (send(self->fd, frame, (size_t)self->frame.len, 0) < 0) {
        if (errno != EINTR) {
            return PyErr_SetFromErrno(PyExc_OSError);
        }
        if (PyErr_CheckSignals() < 0) {
            return NULL;
        }
    }
    self->sent_ns = monotonic_ns();
    return PyLong_FromLong(-1);
}

/* receive() -> -1 once the answer to the frame just sent came in time, with the working counter
 * expected, and its inputs are in y with every drive in Operation enabled in its mode; -2 when it
 * did not come within the timeout (a late answer is seen as it comes, a lost one at the first
 * kernel tick after the timeout); else the answer's working counter, the inputs not taken (the
 * Python side checks it and takes them, naming what is wrong); -4 when every slave exchanged but
 * the DC datagram's working counter is not the one expected (the reference clock's time did not
 * come back to the others; the inputs not taken). Late answers to earlier frames (another datagram
 * index) are passed over, as many as come before the timeout: after lost frames (lost_frames_max)
 * their late answers may queue, and each is drained, never taken for this frame's. EthercatDevice.
 * _receive and _take_answer are the reference. */
static PyObject *DriveRun_receive(DriveRun *self, PyObject *unused) {
    if (!self->linked) {
        PyErr_SetString(PyExc_ValueError, "DriveRun.receive: no link");
        return NULL;
    }
    const uint8_t *frame = self->frame.buf;
    uint8_t *reply = self->reply.buf;
    long long deadline_ns = self->sent_ns + self->timeout_ns;
    for (;;) {
        ssize_t size;
        int flags = 0;
        if (self->precise) { /* wait for the answer until the timeout, to the nanosecond */
            long long left_ns = deadline_ns - monotonic_ns();
            if (left_ns <= 0) {
                return PyLong_FromLong(-2);
            }
            struct pollfd waiting = {.fd = self->fd, .events = POLLIN, .revents = 0};
            struct timespec wait = {.tv_sec = left_ns / 1000000000LL, .tv_nsec = left_ns % 1000000000LL};
            int ready;
            Py_BEGIN_ALLOW_THREADS
            ready = ppoll(&waiting, 1, &wait, NULL);
            Py_END_ALLOW_THREADS
            if (ready == 0) {
                return PyLong_FromLong(-2); /* nothing came in time */
            }
            if (ready < 0) {
                if (errno != EINTR) {
                    return PyErr_SetFromErrno(PyExc_OSError);
                }
                if (PyErr_CheckSignals() < 0) {
                    return NULL;
                }
                continue;
            }
            flags = MSG_DONTWAIT;
        }
        if (flags == MSG_DONTWAIT) { /* after ppoll: it does not wait, so the GIL is kept (giving it away
                                      * again would let another thread's slice delay the answer twice a cycle) */
            size = recv(self->fd, reply, (size_t)self->reply.len, flags);
        } else {
            Py_BEGIN_ALLOW_THREADS /* as socket.recv_into gives the GIL away while it waits */
            size = recv(self->fd, reply, (size_t)self->reply.len, flags);
            Py_END_ALLOW_THREADS
        }
        int saved = errno;
        if (monotonic_ns() > deadline_ns) {
            return PyLong_FromLong(-2); /* nothing, or an answer come too late */
        }
        if (size < 0) {
            if (saved == EAGAIN || saved == EWOULDBLOCK) {
                continue; /* a kernel tick before the timeout: wait on */
            }
            if (saved != EINTR) {
                errno = saved;
                return PyErr_SetFromErrno(PyExc_OSError);
            }
            if (PyErr_CheckSignals() < 0) {
                return NULL;
            }
            continue;
        }
        if (size < self->wkc_at + 2 || reply[ECAT_INDEX_AT] != frame[ECAT_INDEX_AT] ||
            reply[ECAT_COMMAND_AT] != ECAT_LRW) {
            continue; /* an earlier frame's late answer (or not a cycle frame): drained */
        }
        long wkc = (long)reply[self->wkc_at] | (long)reply[self->wkc_at + 1] << 8;
        if (wkc != self->expected_wkc) {
            return PyLong_FromLong(wkc);
        }
        if (self->dc_wkc_at && (size < self->dc_wkc_at + 2 ||
                                ((long)reply[self->dc_wkc_at] | (long)reply[self->dc_wkc_at + 1] << 8) !=
                                    self->expected_dc_wkc)) {
            return PyLong_FromLong(-4);
        }
        if (drive_take(self) >= 0) {
            return PyLong_FromLong(wkc);
        }
        return PyLong_FromLong(-1);
    }
}

static PyMethodDef DriveRun_methods[] = {
    {"prepare", (PyCFunction)DriveRun_prepare, METH_NOARGS, "Outputs of the running cycle; -1, or the joint for Python."},
    {"take", (PyCFunction)DriveRun_take, METH_NOARGS, "Inputs into y; -1, or the joint for Python."},
    {"link", (PyCFunction)DriveRun_link, METH_VARARGS, "link(fd, frame, reply, wkc_at, expected_wkc): the EtherCAT link."},
    {"send", (PyCFunction)DriveRun_send, METH_NOARGS, "Outputs packed, frame sent; -1, or the joint for Python."},
    {"receive", (PyCFunction)DriveRun_receive, METH_NOARGS,
     "The answer taken: -1; -2 none in time; else its working counter (not taken)."},
    {NULL, NULL, 0, NULL},
};

static PyMemberDef DriveRun_members[] = {
    {"sent_ns", T_LONGLONG, offsetof(DriveRun, sent_ns), READONLY,
     "When send() last sent the frame (CLOCK_MONOTONIC, ns; 0: never)."},
    {NULL, 0, 0, 0, NULL},
};

static PyTypeObject DriveRunType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "rtloop.io._devio.DriveRun",
    .tp_basicsize = sizeof(DriveRun),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "A drive device's running cycle (io/drives/cycle.py DriveCycle).",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)DriveRun_init,
    .tp_dealloc = (destructor)DriveRun_dealloc,
    .tp_methods = DriveRun_methods,
    .tp_members = DriveRun_members,
};

/* The compiled twin of io/can.py: CanDevice.write / read (with CanSocket.receive_cycle).
 *
 * Included by ../_devio.c, which builds every part as one translation unit (so each function stays
 * static and inlinable); same arithmetic in the same order as the reference, bit for bit. */

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

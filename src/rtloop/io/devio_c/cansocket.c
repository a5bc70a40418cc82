/* The compiled twin of io/cansocket.py: CanSocket._drain.
 *
 * Included by ../_devio.c, which builds every part as one translation unit (so each function stays
 * static and inlinable); same arithmetic in the same order as the reference, bit for bit. */

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

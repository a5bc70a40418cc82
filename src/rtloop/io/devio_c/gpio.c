/* The compiled twin of io/gpio.py: GpioDevice.write / read.
 *
 * Included by ../_devio.c, which builds every part as one translation unit (so each function stays
 * static and inlinable); same arithmetic in the same order as the reference, bit for bit. */

/* ------------------------------------------------------------------------------------------ */
/* GpioLines: a GPIO device's outputs and inputs, one ioctl each per cycle (GPIO character      */
/* device v2), and the E-stop's pending edge.                                                   */
/*                                                                                              */
/* The GIL is kept across the ioctls, as the task's hot path keeps it for the scope pin: they    */
/* do not wait for anything (the kernel sets or reads the lines and returns), and giving the GIL */
/* away would let another thread of the process delay the loop when it is taken back.            */

#define GPIO_LINES_MAX 64 /* GPIO_V2_LINES_MAX: a request holds at most 64 lines, one bit each */

/* struct gpio_v2_line_values (<linux/gpio.h>, included by _devio.c): the bits of the request's lines, and which count */

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
    struct gpio_v2_line_values values = {0, self->out_mask};
    for (Py_ssize_t i = 0; i < self->n_out; i++) {
        if (u[i] >= 0.5) {
            values.bits |= (uint64_t)1 << self->out_bits[i];
        }
    }
    PyBuffer_Release(&view);
    if (ioctl(self->out_fd, self->set_request, &values) < 0) {
        set_ioctl_error("GPIO_V2_LINE_SET_VALUES_IOCTL", self->out_fd);
        return NULL;
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
    struct gpio_v2_line_values values = {0, self->in_mask};
    if (ioctl(self->in_fd, self->get_request, &values) < 0) {
        set_ioctl_error("GPIO_V2_LINE_GET_VALUES_IOCTL", self->in_fd);
        PyBuffer_Release(&view);
        return NULL;
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

/* The compiled twin of io/spi.py: SpiDevice, with the frame of io/spiframe.py (sequence counter, CRC).
 *
 * Included by ../_devio.c, which builds every part as one translation unit (so each function stays
 * static and inlinable); same arithmetic in the same order as the reference, bit for bit. */

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

/* One transfer (SpiDevice._exchange): seal, SPI_IOC_MESSAGE(1), check. -1 with LibcError set when
 * the kernel refuses it (then, as in the reference, the counter stays and nothing is fresh). */
static int spi_exchange(SpiFrame *self) {
    spi_seal(self);
    if (ioctl(self->fd, self->request, self->transfer.buf) < 0) {
        set_ioctl_error("SPI_IOC_MESSAGE(1)", self->fd);
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

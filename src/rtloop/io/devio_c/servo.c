/* The compiled twin of the smart servos' per-packet checks in io/servos/protocol.py: Dynamixel 2.0's
 * CRC-16 (crc16, crc_matches, seal_crc) and Feetech's checksum (sum_matches, seal_sum).
 *
 * Included by ../_devio.c (one translation unit). The per-cycle packets (SyncWrite.seal, SyncRead's
 * scan of each answer) call these through a Protocol built with the compiled checks
 * (protocol.py Checks); the servo model and the set-up keep the Python references, so every run
 * against the model checks one against the other too. Same arithmetic as the references, bit for
 * bit (tests/test_servo_checks.py). Nothing is allocated: the checks answer True/False or None, and
 * write into the caller's buffer. */

/* CRC-16/UMTS (poly 0x8005, init as given, not reflected, no final xor): Dynamixel 2.0's CRC. */
static uint16_t dxl_crc_table[256];

static void dxl_crc_table_build(void) {
    for (int byte = 0; byte < 256; byte++) {
        uint16_t crc = (uint16_t)(byte << 8);
        for (int bit = 0; bit < 8; bit++) {
            crc = crc & 0x8000 ? (uint16_t)(crc << 1 ^ 0x8005) : (uint16_t)(crc << 1);
        }
        dxl_crc_table[byte] = crc;
    }
}

static uint16_t dxl_crc(const unsigned char *data, Py_ssize_t start, Py_ssize_t end, uint16_t crc) {
    for (Py_ssize_t i = start; i < end; i++) {
        crc = (uint16_t)(crc << 8 ^ dxl_crc_table[(crc >> 8 ^ data[i]) & 0xFF]);
    }
    return crc;
}

/* Feetech: the complement of the byte sum, its low byte. */
static unsigned char byte_sum(const unsigned char *data, Py_ssize_t start, Py_ssize_t end, unsigned long long total) {
    for (Py_ssize_t i = start; i < end; i++) {
        total += data[i];
    }
    return (unsigned char)(~total & 0xFF);
}

/* The arguments (buffer, start, end[, value]) of every check: the buffer held (released by the
 * caller), start..end within it with ``room`` bytes after end (the CRC's 2, the checksum's 1). */
static int servo_arguments(PyObject *const *args, Py_ssize_t nargs, Py_ssize_t wanted, const char *name,
                           int writable, Py_ssize_t room, Py_buffer *view, Py_ssize_t *start, Py_ssize_t *end) {
    if (nargs != wanted) {
        PyErr_Format(PyExc_TypeError, "%s takes %zd arguments (%zd given)", name, wanted, nargs);
        return -1;
    }
    *start = PyLong_AsSsize_t(args[1]);
    if (*start == -1 && PyErr_Occurred()) {
        return -1;
    }
    *end = PyLong_AsSsize_t(args[2]);
    if (*end == -1 && PyErr_Occurred()) {
        return -1;
    }
    if (PyObject_GetBuffer(args[0], view, writable ? PyBUF_WRITABLE : PyBUF_SIMPLE) < 0) {
        return -1;
    }
    if (*start < 0 || *end < *start || *end + room > view->len) {
        PyErr_Format(PyExc_IndexError, "%s: bytes %zd..%zd (and %zd after) outside a buffer of %zd", name, *start,
                     *end, room, view->len);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

static int servo_crc_argument(PyObject *value, uint16_t *crc) {
    long given = PyLong_AsLong(value);
    if (given == -1 && PyErr_Occurred()) {
        return -1;
    }
    if (given < 0 || given > 0xFFFF) {
        PyErr_Format(PyExc_ValueError, "a CRC-16 to start from is 0..0xFFFF, not %ld", given);
        return -1;
    }
    *crc = (uint16_t)given;
    return 0;
}

/* servo_crc16(data, start, end, crc) -> the CRC-16 of data[start:end] from crc (protocol.py crc16). */
static PyObject *devio_servo_crc16(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    Py_buffer view;
    Py_ssize_t start, end;
    uint16_t crc = 0;
    if (nargs == 4 && servo_crc_argument(args[3], &crc) < 0) {
        return NULL;
    }
    if (servo_arguments(args, nargs, 4, "servo_crc16", 0, 0, &view, &start, &end) < 0) {
        return NULL;
    }
    crc = dxl_crc(view.buf, start, end, crc);
    PyBuffer_Release(&view);
    return PyLong_FromLong(crc);
}

/* servo_crc_matches(data, start, end) -> the CRC-16 of data[start:end] is the little-endian u16 at end
 * (protocol.py crc_matches). */
static PyObject *devio_servo_crc_matches(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    Py_buffer view;
    Py_ssize_t start, end;
    if (servo_arguments(args, nargs, 3, "servo_crc_matches", 0, 2, &view, &start, &end) < 0) {
        return NULL;
    }
    const unsigned char *data = view.buf;
    int matches = dxl_crc(data, start, end, 0) == (data[end] | data[end + 1] << 8);
    PyBuffer_Release(&view);
    return PyBool_FromLong(matches);
}

/* servo_seal_crc(data, start, end, crc): the CRC-16 of data[start:end] from crc written at end, little
 * endian (protocol.py seal_crc). */
static PyObject *devio_servo_seal_crc(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    Py_buffer view;
    Py_ssize_t start, end;
    uint16_t crc = 0;
    if (nargs == 4 && servo_crc_argument(args[3], &crc) < 0) {
        return NULL;
    }
    if (servo_arguments(args, nargs, 4, "servo_seal_crc", 1, 2, &view, &start, &end) < 0) {
        return NULL;
    }
    unsigned char *data = view.buf;
    crc = dxl_crc(data, start, end, crc);
    data[end] = (unsigned char)(crc & 0xFF);
    data[end + 1] = (unsigned char)(crc >> 8);
    PyBuffer_Release(&view);
    Py_RETURN_NONE;
}

/* servo_sum_matches(data, start, end) -> Feetech's checksum of data[start:end] is the byte at end
 * (protocol.py sum_matches). */
static PyObject *devio_servo_sum_matches(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    Py_buffer view;
    Py_ssize_t start, end;
    if (servo_arguments(args, nargs, 3, "servo_sum_matches", 0, 1, &view, &start, &end) < 0) {
        return NULL;
    }
    const unsigned char *data = view.buf;
    int matches = byte_sum(data, start, end, 0) == data[end];
    PyBuffer_Release(&view);
    return PyBool_FromLong(matches);
}

/* servo_seal_sum(data, start, end, total): Feetech's checksum of data[start:end], the bytes before start
 * summing to total, written at end (protocol.py seal_sum). Only total's low byte counts, as in Python's
 * ``~total & 0xFF``: it is taken modulo 2**64. */
static PyObject *devio_servo_seal_sum(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    Py_buffer view;
    Py_ssize_t start, end;
    unsigned long long total = 0;
    if (nargs == 4) {
        total = PyLong_AsUnsignedLongLongMask(args[3]);
        if (total == (unsigned long long)-1 && PyErr_Occurred()) {
            return NULL;
        }
    }
    if (servo_arguments(args, nargs, 4, "servo_seal_sum", 1, 1, &view, &start, &end) < 0) {
        return NULL;
    }
    unsigned char *data = view.buf;
    data[end] = byte_sum(data, start, end, total);
    PyBuffer_Release(&view);
    Py_RETURN_NONE;
}

#define SERVO_FUNCTIONS                                                                                          \
    {"servo_crc16", (PyCFunction)(void (*)(void))devio_servo_crc16, METH_FASTCALL,                               \
     "servo_crc16(data, start, end, crc): Dynamixel 2.0's CRC-16 of data[start:end] from crc."},                 \
        {"servo_crc_matches", (PyCFunction)(void (*)(void))devio_servo_crc_matches, METH_FASTCALL,               \
         "servo_crc_matches(data, start, end): the CRC-16 of data[start:end] is the u16 (LE) at end."},          \
        {"servo_seal_crc", (PyCFunction)(void (*)(void))devio_servo_seal_crc, METH_FASTCALL,                     \
         "servo_seal_crc(data, start, end, crc): the CRC-16 of data[start:end] from crc written at end (LE)."},  \
        {"servo_sum_matches", (PyCFunction)(void (*)(void))devio_servo_sum_matches, METH_FASTCALL,               \
         "servo_sum_matches(data, start, end): Feetech's checksum of data[start:end] is the byte at end."},      \
        {"servo_seal_sum", (PyCFunction)(void (*)(void))devio_servo_seal_sum, METH_FASTCALL,                     \
         "servo_seal_sum(data, start, end, total): Feetech's checksum of data[start:end] (after bytes summing "  \
         "to total) written at end."},

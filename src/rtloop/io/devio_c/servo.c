/* The compiled twin of the smart servos' per-packet checks in io/servos/protocol.py: Dynamixel 2.0's
 * CRC-16 (crc16, crc_matches, seal_crc) and Feetech's checksum (sum_matches, seal_sum); and of the
 * scanning loop of SyncRead.collect (servo_take_answers, below).
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

/* ------------------------------------------------------------------------------------------ */
/* The sync read's answers taken as they come: the compiled twin of the scanning loop of        */
/* io/servos/protocol.py SyncRead.collect (Protocol.scan of a status, then copy_params).        */

/* One status packet at b[start:got]: its size, 0 (more bytes are needed: *needed from start) or -1 (not a
 * good status packet: no header, too short, CRC or checksum wrong, not a status). */
static Py_ssize_t servo_status_at(int dynamixel, const unsigned char *b, Py_ssize_t start, Py_ssize_t got,
                                  Py_ssize_t *needed, Py_ssize_t *first, Py_ssize_t *end, int *servo_id) {
    Py_ssize_t have = got - start, total;
    if (dynamixel) {
        if (have < 7) {
            *needed = 7;
            return 0;
        }
        if (b[start] != 0xFF || b[start + 1] != 0xFF || b[start + 2] != 0xFD || b[start + 3] != 0) {
            return -1;
        }
        total = 7 + (b[start + 5] | b[start + 6] << 8);
        if (total < 11) {
            return -1;
        }
        if (have < total) {
            *needed = total;
            return 0;
        }
        Py_ssize_t crc_at = start + total - 2;
        if (dxl_crc(b, start, crc_at, 0) != (b[crc_at] | b[crc_at + 1] << 8) || b[start + 7] != 0x55) {
            return -1;
        }
        *servo_id = b[start + 4];
        *first = start + 8;
        *end = crc_at;
        return total;
    }
    if (have < 4) {
        *needed = 4;
        return 0;
    }
    if (b[start] != 0xFF || b[start + 1] != 0xFF) {
        return -1;
    }
    total = 4 + b[start + 3];
    if (total < 6) {
        return -1;
    }
    if (have < total) {
        *needed = total;
        return 0;
    }
    if (byte_sum(b, start + 2, start + total - 1, 0) != b[start + total - 1]) {
        return -1;
    }
    *servo_id = b[start + 2];
    *first = start + 4;
    *end = start + total - 1;
    return total;
}

/* b[first:end] into target[0:size], Dynamixel's FF FF FD FD back to FF FF FD (left to right, as
 * bytes.replace): 0 when its size, unstuffed, is not ``size`` (nothing written). */
static int servo_copy(int dynamixel, const unsigned char *b, Py_ssize_t first, Py_ssize_t end, unsigned char *target,
                      Py_ssize_t size) {
    Py_ssize_t stuffed = 0;
    if (dynamixel) {
        for (Py_ssize_t i = first; i + 4 <= end;) {
            if (b[i] == 0xFF && b[i + 1] == 0xFF && b[i + 2] == 0xFD && b[i + 3] == 0xFD) {
                stuffed++;
                i += 4;
            } else {
                i++;
            }
        }
    }
    if (end - first - stuffed != size) {
        return 0;
    }
    if (!stuffed) {
        memcpy(target, b + first, (size_t)size);
        return 1;
    }
    Py_ssize_t out = 0;
    for (Py_ssize_t i = first; i < end;) {
        if (i + 4 <= end && b[i] == 0xFF && b[i + 1] == 0xFF && b[i + 2] == 0xFD && b[i + 3] == 0xFD) {
            target[out++] = 0xFF;
            target[out++] = 0xFF;
            target[out++] = 0xFD;
            i += 4;
        } else {
            target[out++] = b[i++];
        }
    }
    return 1;
}

enum { SERVO_STATE_START, SERVO_STATE_COUNT, SERVO_STATE_NEEDED, SERVO_STATE_BAD, SERVO_STATE_SIZE };
enum { SERVO_ALL_IN, SERVO_NEED_MORE, SERVO_TOO_LONG };

/* servo_take_answers(dynamixel, raw, got, wanted, clean, slot, index_of, received, state) -> 0 (``wanted``
 * servos answered), 1 (more bytes are needed) or 2 (they would not fit in raw). ``state`` (int64: start,
 * count, needed, bad) carries the scan from call to call; ``index_of`` (int16 × 256) maps an ID to its
 * servo (-1: none); ``received`` (bool per servo) marks the answers taken, each copied into its slot. */
static PyObject *devio_servo_take_answers(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 9) {
        PyErr_Format(PyExc_TypeError, "servo_take_answers takes 9 arguments (%zd given)", nargs);
        return NULL;
    }
    int dynamixel = PyObject_IsTrue(args[0]);
    Py_ssize_t got = PyLong_AsSsize_t(args[2]), wanted = PyLong_AsSsize_t(args[3]);
    Py_ssize_t slot = PyLong_AsSsize_t(args[5]);
    if (dynamixel < 0 || PyErr_Occurred()) {
        return NULL;
    }
    Py_buffer raw, clean, index_of, received, state;
    Py_buffer *views[5] = {&raw, &clean, &index_of, &received, &state};
    PyObject *objects[5] = {args[1], args[4], args[6], args[7], args[8]};
    int flags[5] = {PyBUF_SIMPLE, PyBUF_WRITABLE, PyBUF_SIMPLE, PyBUF_WRITABLE, PyBUF_WRITABLE};
    int held = 0;
    PyObject *result = NULL;
    for (; held < 5; held++) {
        if (PyObject_GetBuffer(objects[held], views[held], flags[held]) < 0) {
            goto done;
        }
    }
    Py_ssize_t servos = received.len;
    if (index_of.len != 256 * (Py_ssize_t)sizeof(int16_t) || state.len != SERVO_STATE_SIZE * (Py_ssize_t)sizeof(int64_t)
        || clean.len < servos * slot || got < 0 || got > raw.len || wanted > servos) {
        PyErr_SetString(PyExc_ValueError, "servo_take_answers: buffers of the wrong sizes");
        goto done;
    }
    const unsigned char *b = raw.buf;
    const int16_t *index_by_id = index_of.buf;
    unsigned char *taken = received.buf;
    int64_t *s = state.buf;
    Py_ssize_t start = (Py_ssize_t)s[SERVO_STATE_START], count = (Py_ssize_t)s[SERVO_STATE_COUNT];
    long verdict = SERVO_ALL_IN;
    while (count < wanted) {
        Py_ssize_t needed = 0, first = 0, end = 0;
        int servo_id = 0;
        Py_ssize_t size = servo_status_at(dynamixel, b, start, got, &needed, &first, &end, &servo_id);
        if (size == 0) {
            s[SERVO_STATE_NEEDED] = needed;
            verdict = start + needed > raw.len ? SERVO_TOO_LONG : SERVO_NEED_MORE;
            break;
        }
        if (size < 0) {  /* the tail of a late answer, or noise: look for the next header */
            s[SERVO_STATE_BAD] = 1;
            start += 1;
            continue;
        }
        int index = index_by_id[servo_id];
        if (index >= 0 && index < servos && !taken[index]
            && servo_copy(dynamixel, b, first, end, (unsigned char *)clean.buf + index * slot, slot)) {
            taken[index] = 1;
            count++;
        }
        start += size;
    }
    s[SERVO_STATE_START] = start;
    s[SERVO_STATE_COUNT] = count;
    result = PyLong_FromLong(verdict);  /* 0..2: the interpreter's own small ints, nothing allocated */
done:
    for (int i = 0; i < held; i++) {
        PyBuffer_Release(views[i]);
    }
    return result;
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
         "to total) written at end."},\
        {"servo_take_answers", (PyCFunction)(void (*)(void))devio_servo_take_answers, METH_FASTCALL,             \
         "servo_take_answers(dynamixel, raw, got, wanted, clean, slot, index_of, received, state): a sync "    \
         "read's answers scanned, checked and copied (io/servos/protocol.py SyncRead.collect)."},

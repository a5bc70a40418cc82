/* The devices' per-cycle work in C: the command guard, signals packed into and out of frame
 * bytes, a CAN socket drained into the newest copy of each declared frame, a GPIO device's
 * lines set and read, and an SPI frame sealed, transferred and checked; a CAN device's whole cycle.
 *
 * Each is the compiled twin of a Python reference that stays the fallback and is tested
 * against it, one C file per reference in devio_c/: Copies (host.c) <-> the copies of io/host.py,
 * Guard (limits.c) <-> io/limits.py CommandGuard.apply, Layout (bytelayout.c) <->
 * io/bytelayout.py ByteLayout.pack_into/unpack_from, CanReceiver (cansocket.c) <->
 * io/cansocket.py CanSocket._drain, CanCycle (can.c) <-> io/can.py CanDevice.write/read (with
 * CanSocket.receive_cycle), GpioLines (gpio.c) <-> io/gpio.py GpioDevice.write/read, SpiFrame
 * (spi.c) <-> io/spi.py SpiDevice with io/spiframe.py, DriveRun (drive.c) <-> io/drives/cycle.py
 * DriveCycle's running cycle (with EthercatDevice._send/_receive for its link), FrameKeeper
 * (ecat_keeper.c: the EtherCAT process data before T0, no reference: without it OP waits for T0),
 * the servo_* functions (servo.c) <-> io/servos/protocol.py's CRC-16 and
 * checksum (crc16, crc_matches, seal_crc, sum_matches, seal_sum) and SyncRead.collect's scanning loop,
 * EmulatedDrive (esc_drive.c) <-> io/drives/drive_model.py DriveModel and EscFrames (esc_frame.c) <->
 * io/drives/esc.py's process-data path (the emulated EtherCAT drives). This file includes them all (one
 * translation unit) and makes the module. Same arithmetic in the same order, so the results are
 * bit for bit the Python ones. Every buffer a cycle touches is acquired once, when the
 * object is built; a cycle allocates nothing. Built by pip with the system compiler
 * (optional: without a compiler the Python path runs).
 *
 * SOURCES_DIGEST is the digest of the sources it was built from (setup.py passes it): io/compiled.py
 * compares it with the sources beside it and does not use a build older than them (it says so once).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <structmember.h>

#include <errno.h>
#include <linux/gpio.h>
#include <math.h>
#include <poll.h>
#include <stdint.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <time.h>

#include "devio_c/host.c"
#include "devio_c/limits.c"
#include "devio_c/bytelayout.c"
#include "devio_c/cansocket.c"
#include "devio_c/can.c"
#include "devio_c/gpio.c"
#include "devio_c/spi.c"
#include "devio_c/drive.c"
#include "devio_c/ecat_keeper.c"
#include "devio_c/servo.c"
#include "devio_c/esc_drive.c"
#include "devio_c/esc_frame.c"

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
    SERVO_FUNCTIONS
    {NULL, NULL, 0, NULL},
};

/* ------------------------------------------------------------------------------------------ */

static struct PyModuleDef devio_module = {
    PyModuleDef_HEAD_INIT, "rtloop.io._devio", "The devices' per-cycle work in C (see io/compiled.py).", -1, devio_functions,
};

PyMODINIT_FUNC PyInit__devio(void) {
    PyTypeObject *types[] = {&GuardType,     &CopiesType,    &LayoutType,  &CanReceiverType,
                             &CanCycleType,  &GpioLinesType, &SpiFrameType, &DriveRunType,
                             &FrameKeeperType, &EmulatedDriveType, &EscFramesType};
    const char *names[] = {"Guard", "Copies", "Layout", "CanReceiver", "CanCycle", "GpioLines", "SpiFrame",
                           "DriveRun", "FrameKeeper", "EmulatedDrive", "EscFrames"};
    crc16_table_build();
    dxl_crc_table_build();
    PyObject *errors = PyImport_ImportModule("rtloop.errors");
    if (errors == NULL) {
        return NULL;
    }
    libc_error_type = PyObject_GetAttrString(errors, "LibcError");
    Py_DECREF(errors);
    if (libc_error_type == NULL) {
        return NULL;
    }
    PyObject *module = PyModule_Create(&devio_module);
    if (module == NULL) {
        return NULL;
    }
#ifndef RTLOOP_DEVIO_SOURCES_DIGEST
#define RTLOOP_DEVIO_SOURCES_DIGEST "" /* built without setup.py: compiled.py cannot tell, and says so */
#endif
    if (PyModule_AddStringConstant(module, "SOURCES_DIGEST", RTLOOP_DEVIO_SOURCES_DIGEST) < 0) {
        Py_DECREF(module);
        return NULL;
    }
    for (int i = 0; i < (int)(sizeof(types) / sizeof(types[0])); i++) {
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

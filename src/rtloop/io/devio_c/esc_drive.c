/* The compiled twin of io/drives/drive_model.py DriveModel: an emulated CiA 402 drive (its state
 * machine, its loops, a motor with a load), stepped once per process-data exchange. The emulated
 * EtherCAT slaves' process-data path (esc_frame.c) steps it without Python; the configuration path
 * (esc.py) calls its methods as it calls DriveModel's. Same arithmetic in the same order as the
 * reference (Python floats are C doubles; built with -ffp-contract=off, so no fused multiply-add),
 * so the twin (rtloop simulate, which runs the Python DriveModel) equals a run against it bit for
 * bit; tests/test_drive_esc_compiled.py checks that. An event (a state change, a fault) is a str
 * appended to ``events``, as the reference's: rare, and the emulator is not the task's loop.
 *
 * Included by ../_devio.c (one translation unit). */

enum { S_NOT_READY, S_DISABLED, S_READY, S_SWITCHED_ON, S_ENABLED, S_QUICK_STOP, S_FAULT_REACTION, S_FAULT };
static const long long drive_sw_by_state[8] = {0x0000, 0x0040, 0x0021, 0x0023, 0x0027, 0x0007, 0x000F, 0x0008};
#define DRIVE_MAX_MODES 16

typedef struct {
    PyObject_HEAD
    /* DriveParameters, as floats where the reference's arithmetic makes them floats */
    double cycle_s, inertia, damping, torque_max, rated_torque, kp, tau_d, beta, tau_i, kv, quick_stop_torque;
    double rad_per_count;
    long long window;
    long long modes[DRIVE_MAX_MODES];
    int n_modes;
    PyObject *p, *events, *mode_names, *states;
    /* the drive's state: DriveModel's attributes of the same names */
    int state, quick_stop_done;
    long long mode, last_controlword, error_code, pending_fault, target_position;
    double theta, omega, torque_Nm, rate_theta, rate_omega, pd_state, pi_state, rate_pd, rate_pi;
    /* what the master reads (the objects of the last step) */
    long long statusword, mode_display, position, velocity, torque, following_error;
} EmulatedDrive;

static PyTypeObject EmulatedDriveType;

/* Python's round(x) (half to even) then _wrap32; -1 with OverflowError/ValueError where round() raises. */
static int drive_round_wrap32(double x, long long *out) {
    if (isnan(x)) {
        PyErr_SetString(PyExc_ValueError, "cannot convert float NaN to integer");
        return -1;
    }
    if (isinf(x)) {
        PyErr_SetString(PyExc_OverflowError, "cannot convert float infinity to integer");
        return -1;
    }
    double r = fmod(nearbyint(x), 4294967296.0); /* exact: the integer modulo 2**32, sign of x */
    long long v = (long long)r;
    v = ((v + 2147483648LL) % 4294967296LL + 4294967296LL) % 4294967296LL - 2147483648LL;
    *out = v;
    return 0;
}

static long long drive_wrap32(long long v) {
    return ((v + 2147483648LL) % 4294967296LL + 4294967296LL) % 4294967296LL - 2147483648LL;
}

/* _saturate(value, bits) */
static int drive_saturate(double x, int bits, long long *out) {
    long long high = (1LL << (bits - 1)) - 1;
    if (x >= (double)high) {
        *out = high;
    } else if (x <= (double)(-high - 1)) {
        *out = -high - 1;
    } else if (isnan(x)) {
        PyErr_SetString(PyExc_ValueError, "cannot convert float NaN to integer");
        return -1;
    } else {
        *out = (long long)nearbyint(x);
    }
    return 0;
}

/* Python's min(a, b) and max(a, b): the first unless the second is smaller (greater). */
static inline double py_min(double a, double b) { return b < a ? b : a; }
static inline double py_max(double a, double b) { return b > a ? b : a; }

static int drive_event(EmulatedDrive *d, const char *text) {
    PyObject *line = PyUnicode_FromString(text);
    if (line == NULL) {
        return -1;
    }
    int failed = PyList_Append(d->events, line);
    Py_DECREF(line);
    return failed;
}

/* MODE_NAMES.get(mode, mode) as text */
static void drive_mode_name(EmulatedDrive *d, long long mode, char *out, size_t size) {
    PyObject *key = PyLong_FromLongLong(mode);
    PyObject *name = key ? PyDict_GetItemWithError(d->mode_names, key) : NULL;
    Py_XDECREF(key);
    const char *text = name && PyUnicode_Check(name) ? PyUnicode_AsUTF8(name) : NULL;
    PyErr_Clear();
    if (text) {
        snprintf(out, size, "%s", text);
    } else {
        snprintf(out, size, "%lld", mode);
    }
}

static int drive_enter(EmulatedDrive *d, int state, const char *why) {
    if (state != d->state) {
        d->state = state;
        d->quick_stop_done = 0;
        return drive_event(d, why);
    }
    return 0;
}

static int drive_fault(EmulatedDrive *d, long long code, const char *why) {
    if (d->state != S_FAULT && d->state != S_FAULT_REACTION) {
        char text[160];
        d->error_code = code;
        snprintf(text, sizeof text, "fault 0x%04llX: %s", code, why);
        return drive_enter(d, S_FAULT_REACTION, text);
    }
    return 0;
}

static int drive_outputs_lost(EmulatedDrive *d) {
    if (d->state == S_ENABLED) {
        return drive_enter(d, S_QUICK_STOP, "quick stop (outputs no longer valid: the slave left OP)");
    }
    return 0;
}

static int drive_state_machine(EmulatedDrive *d, long long controlword) {
    int state = d->state;
    int rising_reset = (controlword & 0x80) && !(d->last_controlword & 0x80);
    d->last_controlword = controlword;
    long long command = controlword & 0x8F;
    int voltage = (controlword & 0x02) != 0;
    int quick = voltage && !(controlword & 0x04);
    if (state == S_FAULT) {
        if (rising_reset) {
            d->error_code = 0;
            return drive_enter(d, S_DISABLED, "fault reset");
        }
        return 0;
    }
    if (state == S_FAULT_REACTION) {
        return 0;
    }
    if (!voltage) {
        return drive_enter(d, S_DISABLED, "switch on disabled (disable voltage)");
    } else if (state == S_ENABLED && quick) {
        return drive_enter(d, S_QUICK_STOP, "quick stop (controlword)");
    } else if (quick) {
        return state != S_QUICK_STOP ? drive_enter(d, S_DISABLED, "switch on disabled (quick stop)") : 0;
    } else if (state == S_DISABLED && (command & 0x87) == 0x06) {
        return drive_enter(d, S_READY, "ready to switch on");
    } else if (state == S_READY && (command & 0x87) == 0x07) {
        return drive_enter(d, S_SWITCHED_ON, "switched on");
    } else if (state == S_SWITCHED_ON && command == 0x0F) {
        char name[64], text[96];
        d->pd_state = d->pi_state = 0.0;
        drive_mode_name(d, d->mode, name, sizeof name);
        snprintf(text, sizeof text, "operation enabled (%s)", name);
        return drive_enter(d, S_ENABLED, text);
    } else if (state == S_SWITCHED_ON && (command & 0x87) == 0x06) {
        return drive_enter(d, S_READY, "ready to switch on (shutdown)");
    } else if (state == S_ENABLED && (command & 0x8F) == 0x07) {
        return drive_enter(d, S_SWITCHED_ON, "switched on (disable operation)");
    } else if (state == S_ENABLED && (command & 0x87) == 0x06) {
        return drive_enter(d, S_READY, "ready to switch on (shutdown)");
    }
    return 0;
}

static int drive_publish(EmulatedDrive *d, long long following, int saturated, int at_rest) {
    int state = d->state;
    long long word = drive_sw_by_state[state];
    if (state != S_DISABLED && state != S_NOT_READY) {
        word |= 0x0010; /* voltage enabled */
    }
    word |= 0x0200; /* remote */
    if (saturated) {
        word |= 1 << 7; /* warning */
    }
    if (state == S_ENABLED) {
        word |= 0x1000;
        long long half = d->window >= 0 ? d->window / 2 : -((-d->window + 1) / 2); /* Python's // 2 */
        long long magnitude = following < 0 ? -following : following;
        if (d->mode == 8 && magnitude > half) {
            word |= 1 << 13; /* following error */
        }
        if (d->mode == 8 && magnitude <= 16 && at_rest) {
            word |= 1 << 10; /* target reached */
        }
    } else if (state == S_QUICK_STOP && at_rest) {
        word |= 1 << 10;
    }
    d->statusword = word;
    d->mode_display = d->mode;
    if (drive_round_wrap32(d->theta / d->rad_per_count, &d->position) < 0 ||
        drive_saturate(d->omega / d->rad_per_count, 32, &d->velocity) < 0 ||
        drive_saturate(d->torque_Nm / d->rated_torque * 1000.0, 16, &d->torque) < 0) {
        return -1;
    }
    d->following_error = drive_wrap32(following);
    return 0;
}

static int drive_step(EmulatedDrive *d, long long target_position, long long target_velocity, long long target_torque) {
    double h = d->cycle_s;
    d->theta += h * d->rate_theta;
    d->omega += h * d->rate_omega;
    d->pd_state += h * d->rate_pd;
    d->pi_state += h * d->rate_pi;
    d->rate_pd = d->rate_pi = 0.0;
    int state = d->state;
    double torque = 0.0;
    long long following = 0;
    if (state == S_ENABLED) {
        if (d->mode == 8) {
            long long actual;
            if (drive_round_wrap32(d->theta / d->rad_per_count, &actual) < 0) {
                return -1;
            }
            following = target_position - actual;
            double error = (double)following * d->rad_per_count;
            double pd_out = d->pd_state + d->kp * error / d->beta;
            d->rate_pd = (d->kp * error - pd_out) / (d->beta * d->tau_d);
            d->rate_pi = pd_out / d->tau_i;
            torque = d->pi_state + pd_out;
            if ((following < 0 ? -following : following) > d->window) {
                char why[96];
                snprintf(why, sizeof why, "following error %lld counts (window %lld)", following, d->window);
                if (drive_fault(d, 0x8611, why) < 0) {
                    return -1;
                }
            }
        } else if (d->mode == 9) {
            torque = d->kv * ((double)target_velocity * d->rad_per_count - d->omega);
        } else if (d->mode == 10) {
            torque = (double)target_torque * d->rated_torque / 1000.0;
        }
    } else if (state == S_QUICK_STOP || state == S_FAULT_REACTION) {
        double stop = d->inertia * d->omega / d->cycle_s;
        torque = -py_max(-d->quick_stop_torque, py_min(d->quick_stop_torque, stop));
    }
    int saturated = fabs(torque) > d->torque_max;
    torque = py_max(-d->torque_max, py_min(d->torque_max, torque));
    d->torque_Nm = torque;
    d->rate_theta = d->omega;
    d->rate_omega = (torque - d->damping * d->omega) / d->inertia;
    int at_rest = fabs(d->omega) * h < d->rad_per_count && fabs(d->rate_omega) * h * h < d->rad_per_count;
    if (state == S_FAULT_REACTION && at_rest) {
        char text[96];
        snprintf(text, sizeof text, "fault (error code 0x%04llX), drive at rest", d->error_code);
        if (drive_enter(d, S_FAULT, text) < 0) {
            return -1;
        }
    } else if (state == S_QUICK_STOP && at_rest && !d->quick_stop_done) {
        d->quick_stop_done = 1;
        if (drive_event(d, "quick stop done: at rest") < 0) {
            return -1;
        }
    }
    d->target_position = target_position;
    return drive_publish(d, following, saturated, at_rest);
}

/* DriveModel.exchange; 0, or -1 with an exception set (where the reference raises). */
static int drive_exchange(EmulatedDrive *d, long long controlword, long long mode, long long target_position,
                          long long target_velocity, long long target_torque, int outputs_valid) {
    if (outputs_valid) {
        if (drive_state_machine(d, controlword) < 0) {
            return -1;
        }
        int supported = 0;
        for (int i = 0; i < d->n_modes; i++) {
            supported |= d->modes[i] == mode;
        }
        if (mode != d->mode && d->state != S_FAULT && supported) {
            char old[64], new[64], text[160];
            drive_mode_name(d, d->mode, old, sizeof old);
            drive_mode_name(d, mode, new, sizeof new);
            snprintf(text, sizeof text, "mode %s -> %s", old, new);
            if (drive_event(d, text) < 0) {
                return -1;
            }
            d->mode = mode;
            d->pd_state = d->pi_state = 0.0;
        }
    } else if (drive_outputs_lost(d) < 0) {
        return -1;
    }
    if (d->pending_fault) {
        if (drive_fault(d, d->pending_fault, "drive fault injected") < 0) {
            return -1;
        }
        d->pending_fault = 0;
    }
    return drive_step(d, target_position, target_velocity, target_torque);
}

/* --- the Python side: DriveModel's interface ------------------------------------------------- */

static int drive_double(PyObject *p, const char *name, double *out) {
    PyObject *value = PyObject_GetAttrString(p, name);
    if (value == NULL) {
        return -1;
    }
    *out = PyFloat_AsDouble(value); /* an int as Python's int * float makes it: correctly rounded */
    Py_DECREF(value);
    return *out == -1.0 && PyErr_Occurred() ? -1 : 0;
}

static int drive_integer(PyObject *p, const char *name, long long *out) {
    PyObject *value = PyObject_GetAttrString(p, name);
    if (value == NULL) {
        return -1;
    }
    *out = PyLong_AsLongLong(value);
    Py_DECREF(value);
    return *out == -1 && PyErr_Occurred() ? -1 : 0;
}

/* EmulatedDrive(parameters, mode_names, states): parameters a DriveParameters, mode_names
 * cia402.MODE_NAMES, states tuple(Cia402State) (what ``state`` reads as). */
static int EmulatedDrive_init(EmulatedDrive *d, PyObject *args, PyObject *kwargs) {
    PyObject *p, *names, *states;
    if (!PyArg_ParseTuple(args, "OO!O!", &p, &PyDict_Type, &names, &PyTuple_Type, &states)) {
        return -1;
    }
    if (PyTuple_GET_SIZE(states) != 8) {
        PyErr_SetString(PyExc_ValueError, "EmulatedDrive: states must be the 8 Cia402State members");
        return -1;
    }
    long long counts_per_rev;
    if (drive_double(p, "cycle_s", &d->cycle_s) < 0 || drive_double(p, "inertia_kgm2", &d->inertia) < 0 ||
        drive_double(p, "damping_Nms", &d->damping) < 0 || drive_double(p, "torque_max_Nm", &d->torque_max) < 0 ||
        drive_double(p, "rated_torque_Nm", &d->rated_torque) < 0 ||
        drive_double(p, "kp_Nm_per_rad", &d->kp) < 0 || drive_double(p, "tau_d_s", &d->tau_d) < 0 ||
        drive_double(p, "beta", &d->beta) < 0 || drive_double(p, "tau_i_s", &d->tau_i) < 0 ||
        drive_double(p, "kv_Nms", &d->kv) < 0 || drive_double(p, "quick_stop_torque_Nm", &d->quick_stop_torque) < 0 ||
        drive_integer(p, "counts_per_rev", &counts_per_rev) < 0 ||
        drive_integer(p, "following_error_window", &d->window) < 0) {
        return -1;
    }
    PyObject *modes = PyObject_GetAttrString(p, "modes");
    PyObject *sequence = modes ? PySequence_Fast(modes, "EmulatedDrive: modes must be a sequence") : NULL;
    Py_XDECREF(modes);
    if (sequence == NULL) {
        return -1;
    }
    d->n_modes = 0;
    for (Py_ssize_t i = 0; i < PySequence_Fast_GET_SIZE(sequence) && d->n_modes < DRIVE_MAX_MODES; i++) {
        long long mode = PyLong_AsLongLong(PySequence_Fast_GET_ITEM(sequence, i));
        if (mode == -1 && PyErr_Occurred()) {
            Py_DECREF(sequence);
            return -1;
        }
        d->modes[d->n_modes++] = mode;
    }
    int too_many = PySequence_Fast_GET_SIZE(sequence) > DRIVE_MAX_MODES;
    Py_DECREF(sequence);
    if (too_many || counts_per_rev <= 0) {
        PyErr_SetString(PyExc_ValueError, "EmulatedDrive: counts_per_rev must be > 0, at most 16 modes");
        return -1;
    }
    d->rad_per_count = 2.0 * M_PI / (double)counts_per_rev;
    Py_XSETREF(d->p, Py_NewRef(p));
    Py_XSETREF(d->mode_names, Py_NewRef(names));
    Py_XSETREF(d->states, Py_NewRef(states));
    Py_XSETREF(d->events, PyList_New(0));
    if (d->events == NULL) {
        return -1;
    }
    d->state = S_DISABLED;
    d->mode = 8;
    d->theta = d->omega = d->torque_Nm = d->rate_theta = d->rate_omega = 0.0;
    d->pd_state = d->pi_state = d->rate_pd = d->rate_pi = 0.0;
    d->last_controlword = d->error_code = d->pending_fault = d->target_position = 0;
    d->quick_stop_done = 0;
    return drive_publish(d, 0, 0, 1);
}

static void EmulatedDrive_dealloc(EmulatedDrive *d) {
    Py_XDECREF(d->p);
    Py_XDECREF(d->events);
    Py_XDECREF(d->mode_names);
    Py_XDECREF(d->states);
    Py_TYPE(d)->tp_free((PyObject *)d);
}

static PyObject *EmulatedDrive_exchange(EmulatedDrive *d, PyObject *args, PyObject *kwargs) {
    static char *keywords[] = {"controlword", "mode", "target_position", "target_velocity", "target_torque",
                               "outputs_valid", NULL};
    long long controlword, mode, position, velocity, torque;
    int valid = 1;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "LLLLL|p", keywords, &controlword, &mode, &position, &velocity,
                                     &torque, &valid)) {
        return NULL;
    }
    if (drive_exchange(d, controlword, mode, position, velocity, torque, valid) < 0) {
        return NULL;
    }
    Py_RETURN_NONE;
}

static PyObject *EmulatedDrive_inject_fault(EmulatedDrive *d, PyObject *args) {
    long long code = 0x5530; /* drive_model.INJECTED_FAULT_CODE */
    if (!PyArg_ParseTuple(args, "|L", &code)) {
        return NULL;
    }
    d->pending_fault = code;
    Py_RETURN_NONE;
}

static PyObject *EmulatedDrive_outputs_lost(EmulatedDrive *d, PyObject *unused) {
    if (drive_outputs_lost(d) < 0) {
        return NULL;
    }
    Py_RETURN_NONE;
}

static PyObject *EmulatedDrive_get_state(EmulatedDrive *d, void *closure) {
    return Py_NewRef(PyTuple_GET_ITEM(d->states, d->state));
}

static PyMethodDef EmulatedDrive_methods[] = {
    {"exchange", (PyCFunction)(void (*)(void))EmulatedDrive_exchange, METH_VARARGS | METH_KEYWORDS,
     "exchange(controlword, mode, target_position, target_velocity, target_torque, outputs_valid=True)"},
    {"inject_fault", (PyCFunction)EmulatedDrive_inject_fault, METH_VARARGS, "A drive fault at the next step."},
    {"outputs_lost", (PyCFunction)EmulatedDrive_outputs_lost, METH_NOARGS, "The slave left OP: quick stop."},
    {NULL, NULL, 0, NULL},
};

#define DRIVE_MEMBER(name, type, flags) {#name, type, offsetof(EmulatedDrive, name), flags, NULL}
static PyMemberDef EmulatedDrive_members[] = {
    DRIVE_MEMBER(p, T_OBJECT_EX, READONLY),
    DRIVE_MEMBER(events, T_OBJECT_EX, READONLY),
    DRIVE_MEMBER(mode, T_LONGLONG, READONLY),
    DRIVE_MEMBER(theta, T_DOUBLE, READONLY),
    DRIVE_MEMBER(omega, T_DOUBLE, READONLY),
    DRIVE_MEMBER(torque_Nm, T_DOUBLE, READONLY),
    DRIVE_MEMBER(rate_theta, T_DOUBLE, READONLY),
    DRIVE_MEMBER(rate_omega, T_DOUBLE, READONLY),
    DRIVE_MEMBER(pd_state, T_DOUBLE, READONLY),
    DRIVE_MEMBER(pi_state, T_DOUBLE, READONLY),
    DRIVE_MEMBER(rate_pd, T_DOUBLE, READONLY),
    DRIVE_MEMBER(rate_pi, T_DOUBLE, READONLY),
    DRIVE_MEMBER(rad_per_count, T_DOUBLE, READONLY),
    DRIVE_MEMBER(last_controlword, T_LONGLONG, READONLY),
    DRIVE_MEMBER(error_code, T_LONGLONG, READONLY),
    DRIVE_MEMBER(pending_fault, T_LONGLONG, READONLY),
    DRIVE_MEMBER(target_position, T_LONGLONG, READONLY),
    DRIVE_MEMBER(quick_stop_done, T_INT, READONLY),
    DRIVE_MEMBER(statusword, T_LONGLONG, READONLY),
    DRIVE_MEMBER(mode_display, T_LONGLONG, READONLY),
    DRIVE_MEMBER(position, T_LONGLONG, READONLY),
    DRIVE_MEMBER(velocity, T_LONGLONG, READONLY),
    DRIVE_MEMBER(torque, T_LONGLONG, READONLY),
    DRIVE_MEMBER(following_error, T_LONGLONG, READONLY),
    {NULL, 0, 0, 0, NULL},
};

static PyGetSetDef EmulatedDrive_getset[] = {
    {"state", (getter)EmulatedDrive_get_state, NULL, "The drive's Cia402State.", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject EmulatedDriveType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "rtloop.io._devio.EmulatedDrive",
    .tp_basicsize = sizeof(EmulatedDrive),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "An emulated CiA 402 drive (io/drives/drive_model.py DriveModel), compiled.",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)EmulatedDrive_init,
    .tp_dealloc = (destructor)EmulatedDrive_dealloc,
    .tp_methods = EmulatedDrive_methods,
    .tp_members = EmulatedDrive_members,
    .tp_getset = EmulatedDrive_getset,
};

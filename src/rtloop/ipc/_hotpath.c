/* The per-cycle framework work of one task, compiled: rtloop's hot path.
 *
 * This is the C twin of rtloop/ipc/hotpath.py (PythonCycle, which is the reference:
 * read it first). Same shared-memory layout, same results; only faster. A Core is
 * built once before the loop: it holds the buffers (PyObject_GetBuffer, released in
 * dealloc) and precomputed pointers, so a cycle allocates no Python objects except
 * the three ints it stores in the TickInfo, which the Python twin stores too.
 *
 * Memory ordering follows Boehm, "Can seqlocks get along with programming language
 * memory models?" (HPL-2012-68, fig. 6): the payload is copied with relaxed atomic
 * loads and an acquire fence orders them before the second sequence load. Acquire and
 * release make it correct on aarch64 by construction; on x86-64 they cost nothing.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <errno.h>
#include <math.h>
#include <stdatomic.h>
#include <stdint.h>
#include <string.h>
#include <time.h>

#if ATOMIC_LLONG_LOCK_FREE != 2
#error "rtloop's shared memory needs lock-free 64-bit atomics"
#endif

typedef _Atomic int64_t aword; /* one 8-byte word of shared memory */

/* Every word and offset of shared memory, generated from schema.py (hotpath.py checks the
   built module agrees with it: _hotpath.SCHEMA). */
#include "_schema.h"
#define SNAPSHOT_DUE 2 /* finish(): the supervisor asked for the task's state before the next release */
#define CYCLE_LATE 3 /* finish(): this cycle missed its deadline (the loop reads the thread's counters) */

#define LOAD(p, order) atomic_load_explicit((p), memory_order_##order)
#define STORE(p, v, order) atomic_store_explicit((p), (v), memory_order_##order)

typedef struct {
    int64_t from, to, count; /* scratch[from:from+count] -> u[to:to+count] */
} Span;

typedef struct { /* every connection from one writer: one seqlock read per cycle */
    aword *words;
    int64_t n_slots, slot_words, period_ns, first, width, n_spans;
    int64_t *scratch;
    Span *spans;
} Input;

typedef struct { /* LatestValue: an input port written by non-RT code */
    aword *words;
    int64_t count, to, last_seq;
    int64_t *scratch;
    double index; /* its place among the task's input ports, for the input log */
    double *dest; /* u + to, or the buffer of a profile's live nudges */
    int fresh;    /* delivered a new value at this release */
} LivePort;

typedef struct { /* a setpoint profile, piecewise constant in time since T0 */
    const int64_t *t_ns;
    const double *rows;
    int64_t n_rows, count, to, index;
    int64_t live_port, mode; /* live nudges: index into live_ports and NUDGE_OFFSET/OVERRIDE, or -1 and 0 */
} Profile;


typedef struct { /* SampleQueue (or the timing Int64Ring, same header) */
    aword *words;
    int64_t *ticks; /* NULL for an Int64Ring: its records hold everything */
    int64_t *rows;
    int64_t width, capacity, written, from;
} Queue;

typedef struct {
    PyObject_HEAD
    PyObject *tick;
    Py_buffer *views;
    Py_ssize_t n_views;
    double *u, *y;
    int64_t n_u, n_y;
    aword *control, *status;
    Queue timing;
    aword *output; /* LetChannel words, or NULL */
    int64_t output_slots, output_slot_words, published;
    Input *inputs;
    LivePort *live_ports;
    Profile *profiles;
    Queue *out_ports;
    Queue record;
    int has_record;
    int64_t *record_row;
    const double *sent; /* what the task's devices were sent (their guards write it), recorded after u */
    int64_t n_sent;
    /* set_input_guards(): guarded connections (min, max, rate_per_s), applied right after the read */
    Py_ssize_t n_guarded;
    const int64_t *guard_index; /* the element of u each guarded value is */
    const double *guard_low, *guard_high, *guard_step;
    double *guard_last;
    int64_t *guard_clamped, *guard_rate_limited;
    Queue input_log; /* [port index, values...] each time a live port delivers a new value */
    int has_input_log;
    double *input_log_row;
    Queue read_log; /* [release, writer index, stamp got, stamp due] (ns since T0) for each stale read */
    int has_read_log;
    Py_ssize_t n_inputs, n_live_ports, n_profiles, n_out_ports;
    int64_t period_ns, catch_up, t0_ns, end_ns;
    int64_t max_misses, misses_in_a_row; /* max_misses 0: no limit */
    int64_t cycle, release_ns, start_ns, stale_reads;
    int64_t last_end_ns; /* when the last cycle ended (or start()): is the next sleep a long one? */
    int64_t snapshot_taken_ns; /* the last SNAPSHOT_NS answered */
    int closed; /* after close(): no shared memory held, every call refused */
    /* measure_busy(): time from each wake-up to the next sleep (everything but the sleep call) */
    int measure_busy;
    int64_t busy_ns, busy_cycles, busy_max_ns, busy_wake_ns;
    /* set_finite_check(): outputs that cross a connection; a non-finite one is a fault unless allowed */
    Py_ssize_t n_checks;
    int64_t *check_index, *check_fault;
    PyObject *check_labels; /* tuple of str, one per checked output, for the fault's message */
    PyObject *check_error;  /* the exception type raised on a fault */
} Core;


static PyObject *str_cycle, *str_release_ns, *str_start_ns;

static int64_t now_ns(void) {
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    return (int64_t)now.tv_sec * 1000000000 + now.tv_nsec;
}

/* ---- setup (once, before the loop): buffers and checked sizes ---------------------- */

static void *hold_buffer(Core *self, PyObject *obj, int writable, Py_ssize_t min_bytes, Py_ssize_t *len) {
    Py_buffer *views = PyMem_Realloc(self->views, (self->n_views + 1) * sizeof(Py_buffer));
    if (views == NULL) {
        PyErr_NoMemory();
        return NULL;
    }
    self->views = views;
    Py_buffer *view = &views[self->n_views];
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | (writable ? PyBUF_WRITABLE : 0)) < 0)
        return NULL;
    self->n_views++;
    if ((view->len > 0 && ((uintptr_t)view->buf & 7) != 0) || view->len < min_bytes) {
        PyErr_Format(PyExc_ValueError, "hot path: buffer of %zd bytes at %p is misaligned or smaller than %zd bytes",
                     view->len, view->buf, min_bytes);
        return NULL;
    }
    if (len != NULL)
        *len = view->len;
    return view->buf;
}

/* The Python twin's words for the sleep (linux/rt.py AbsoluteSleeper), so both raise the same error. */
#define CLOCK_NANOSLEEP_CALL "clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)"

/* Raise rtloop.errors.LibcError(call, errno_value), as the Python twin's libc checker does: the
   error names the call (a bare OSError would not). Only on the way out of a failed call. */
static void set_libc_error(const char *call, int errno_value) {
    PyObject *errors = PyImport_ImportModule("rtloop.errors");
    PyObject *libc_error = errors != NULL ? PyObject_GetAttrString(errors, "LibcError") : NULL;
    PyObject *error = libc_error != NULL ? PyObject_CallFunction(libc_error, "si", call, errno_value) : NULL;
    if (error != NULL)
        PyErr_SetObject(libc_error, error);
    else if (!PyErr_Occurred()) {
        errno = errno_value;
        PyErr_SetFromErrno(PyExc_OSError);
    }
    Py_XDECREF(error);
    Py_XDECREF(libc_error);
    Py_XDECREF(errors);
}

static int64_t *zeros(int64_t count) {
    int64_t *memory = PyMem_Calloc(count > 0 ? count : 1, sizeof(int64_t));
    if (memory == NULL)
        PyErr_NoMemory();
    return memory;
}

static int attach_queue(Core *self, PyObject *buffer, Queue *queue, int with_ticks) {
    Py_ssize_t len;
    aword *words = hold_buffer(self, buffer, 1, HEADER_WORDS * 8, &len);
    if (words == NULL)
        return -1;
    queue->words = words;
    queue->width = LOAD(&words[QUEUE_WIDTH], relaxed);
    queue->capacity = LOAD(&words[QUEUE_CAPACITY], relaxed);
    queue->written = LOAD(&words[QUEUE_WRITTEN], relaxed);
    int64_t needed = HEADER_WORDS + queue->capacity * (queue->width + (with_ticks ? 1 : 0));
    if (queue->capacity <= 0 || queue->width < 0 || needed * 8 > len) {
        PyErr_SetString(PyExc_ValueError, "hot path: queue header does not match its buffer");
        return -1;
    }
    int64_t *data = (int64_t *)(words + HEADER_WORDS);
    queue->ticks = with_ticks ? data : NULL;
    queue->rows = with_ticks ? data + queue->capacity : data;
    return 0;
}

static int Core_init(Core *self, PyObject *args, PyObject *kwargs) {
    static char *keywords[] = {"tick", "u", "y", "control", "status", "timing", "period_ns", "catch_up", "max_misses",
                               NULL};
    PyObject *tick, *u, *y, *control, *status, *timing;
    long long period_ns;
    int catch_up;
    long long max_misses = 0;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "OOOOOOLp|L", keywords, &tick, &u, &y, &control, &status, &timing,
                                     &period_ns, &catch_up, &max_misses))
        return -1;
    if (self->tick != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "hot path: a Core is built once");
        return -1;
    }
    Py_ssize_t len_u, len_y;
    Py_INCREF(tick);
    self->tick = tick;
    if ((self->u = hold_buffer(self, u, 1, 0, &len_u)) == NULL || (self->y = hold_buffer(self, y, 1, 0, &len_y)) == NULL ||
        (self->control = hold_buffer(self, control, 1, CONTROL_WORDS * 8, NULL)) == NULL ||
        (self->status = hold_buffer(self, status, 1, STATUS_WORDS * 8, NULL)) == NULL ||
        attach_queue(self, timing, &self->timing, 0) < 0)
        return -1;
    if (self->timing.width != TIMING_RECORD_WORDS) {
        PyErr_SetString(PyExc_ValueError, "hot path: the timing ring must hold 4-word records");
        return -1;
    }
    self->n_u = len_u / 8;
    self->n_y = len_y / 8;
    self->period_ns = period_ns;
    self->catch_up = catch_up;
    self->max_misses = max_misses;
    return 0;
}

static int check_span(int64_t start, int64_t count, int64_t size, const char *what) {
    if (start < 0 || count < 0 || start + count > size) {
        PyErr_Format(PyExc_ValueError, "hot path: %s [%lld:%lld] outside 0..%lld", what, (long long)start,
                     (long long)(start + count), (long long)size);
        return -1;
    }
    return 0;
}

/* add_input(channel_words, writer_period_ns, first, width, spans): spans = ((from, to, count), ...) */
static PyObject *Core_add_input(Core *self, PyObject *args) {
    PyObject *buffer, *spans;
    long long period_ns, first, width;
    if (!PyArg_ParseTuple(args, "OLLLO!", &buffer, &period_ns, &first, &width, &PyTuple_Type, &spans))
        return NULL;
    Py_ssize_t len;
    aword *words = hold_buffer(self, buffer, 1, HEADER_WORDS * 8, &len);
    if (words == NULL)
        return NULL;
    Input *inputs = PyMem_Realloc(self->inputs, (self->n_inputs + 1) * sizeof(Input));
    if (inputs == NULL)
        return PyErr_NoMemory();
    self->inputs = inputs;
    Input *input = &inputs[self->n_inputs];
    memset(input, 0, sizeof *input);
    int64_t n_values = LOAD(&words[CHANNEL_N_VALUES], relaxed);
    input->words = words;
    input->n_slots = LOAD(&words[CHANNEL_N_SLOTS], relaxed);
    input->slot_words = SLOT_VALUES + n_values;
    input->period_ns = period_ns;
    input->first = first;
    input->width = width;
    if (input->n_slots <= 0 || period_ns <= 0 || (HEADER_WORDS + input->n_slots * input->slot_words) * 8 > len ||
        check_span(first, width, n_values, "writer outputs") < 0) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_ValueError, "hot path: channel header does not match its buffer");
        return NULL;
    }
    input->n_spans = PyTuple_GET_SIZE(spans);
    input->scratch = zeros(width);
    input->spans = PyMem_Calloc(input->n_spans ? input->n_spans : 1, sizeof(Span));
    if (input->scratch == NULL || input->spans == NULL) { /* not counted yet: dealloc would not free them */
        PyMem_Free(input->scratch);
        PyMem_Free(input->spans);
        input->scratch = NULL;
        input->spans = NULL;
        return PyErr_NoMemory();
    }
    self->n_inputs++; /* from here on dealloc frees it */
    for (Py_ssize_t i = 0; i < input->n_spans; i++) {
        Span *span = &input->spans[i];
        long long from, to, count;
        if (!PyArg_ParseTuple(PyTuple_GET_ITEM(spans, i), "LLL", &from, &to, &count))
            return NULL;
        *span = (Span){from, to, count};
        if (check_span(from, count, width, "connection source") < 0 || check_span(to, count, self->n_u, "u") < 0)
            return NULL;
    }
    Py_RETURN_NONE;
}

/* add_live_port(latest_value_words, to, count, last_seq_seen, index[, nudge float64 buffer instead of u]) */
static PyObject *Core_add_live_port(Core *self, PyObject *args) {
    PyObject *buffer, *nudge = Py_None;
    long long to, count, last_seq;
    double index;
    if (!PyArg_ParseTuple(args, "OLLLd|O", &buffer, &to, &count, &last_seq, &index, &nudge))
        return NULL;
    aword *words = hold_buffer(self, buffer, 1, (HEADER_WORDS + count) * 8, NULL);
    if (words == NULL || check_span(to, count, self->n_u, "u") < 0)
        return NULL;
    double *dest = self->u + to;
    if (nudge != Py_None && (dest = hold_buffer(self, nudge, 1, count * 8, NULL)) == NULL)
        return NULL;
    if (LOAD(&words[PORT_N_VALUES], relaxed) != count) {
        PyErr_SetString(PyExc_ValueError, "hot path: port size does not match its header");
        return NULL;
    }
    LivePort *ports = PyMem_Realloc(self->live_ports, (self->n_live_ports + 1) * sizeof(LivePort));
    if (ports == NULL)
        return PyErr_NoMemory();
    self->live_ports = ports;
    int64_t *scratch = zeros(count);
    if (scratch == NULL)
        return NULL;
    ports[self->n_live_ports++] = (LivePort){words, count, to, last_seq, scratch, index, dest, 0};
    Py_RETURN_NONE;
}

/* add_profile(t_ns int64 array, rows float64 array, to, count, index of the row in force[, live port, mode]) */
static PyObject *Core_add_profile(Core *self, PyObject *args) {
    PyObject *t_ns, *rows;
    long long to, count, index, live_port = -1, mode = 0;
    if (!PyArg_ParseTuple(args, "OOLLL|LL", &t_ns, &rows, &to, &count, &index, &live_port, &mode))
        return NULL;
    if (mode != 0 && (live_port < 0 || live_port >= self->n_live_ports || self->live_ports[live_port].count != count)) {
        PyErr_SetString(PyExc_ValueError, "hot path: a profile's nudges need a live port of its size");
        return NULL;
    }
    Py_ssize_t len_t, len_rows;
    const int64_t *times = hold_buffer(self, t_ns, 0, 0, &len_t);
    const double *values = times ? hold_buffer(self, rows, 0, 0, &len_rows) : NULL;
    if (values == NULL || check_span(to, count, self->n_u, "u") < 0)
        return NULL;
    if (len_rows != len_t * count) {
        PyErr_SetString(PyExc_ValueError, "hot path: profile rows do not match its times");
        return NULL;
    }
    Profile *profiles = PyMem_Realloc(self->profiles, (self->n_profiles + 1) * sizeof(Profile));
    if (profiles == NULL)
        return PyErr_NoMemory();
    self->profiles = profiles;
    profiles[self->n_profiles++] = (Profile){times, values, len_t / 8, count, to, index, live_port, mode};
    Py_RETURN_NONE;
}

/* set_output(let_channel_words) */
static PyObject *Core_set_output(Core *self, PyObject *buffer) {
    Py_ssize_t len;
    aword *words = hold_buffer(self, buffer, 1, HEADER_WORDS * 8, &len);
    if (words == NULL)
        return NULL;
    int64_t n_values = LOAD(&words[CHANNEL_N_VALUES], relaxed);
    self->output_slots = LOAD(&words[CHANNEL_N_SLOTS], relaxed);
    self->output_slot_words = SLOT_VALUES + n_values;
    if (n_values != self->n_y || self->output_slots <= 0 ||
        (HEADER_WORDS + self->output_slots * self->output_slot_words) * 8 > len) {
        PyErr_SetString(PyExc_ValueError, "hot path: output channel does not match y");
        return NULL;
    }
    self->published = LOAD(&words[CHANNEL_PUBLISHED], relaxed);
    self->output = words;
    Py_RETURN_NONE;
}

/* add_output_port(sample_queue_words, from) */
static PyObject *Core_add_output_port(Core *self, PyObject *args) {
    PyObject *buffer;
    long long from;
    if (!PyArg_ParseTuple(args, "OL", &buffer, &from))
        return NULL;
    Queue *queues = PyMem_Realloc(self->out_ports, (self->n_out_ports + 1) * sizeof(Queue));
    if (queues == NULL)
        return PyErr_NoMemory();
    self->out_ports = queues;
    Queue *queue = &queues[self->n_out_ports];
    if (attach_queue(self, buffer, queue, 1) < 0 || check_span(from, queue->width, self->n_y, "y") < 0)
        return NULL;
    queue->from = from;
    self->n_out_ports++;
    Py_RETURN_NONE;
}

/* set_record(sample_queue_words, sent): every tick's [y..., u..., sent...] for the recorder; sent is
   the float64 vector of what the task's devices were sent (TaskWiring.sent, maybe empty) */
static PyObject *Core_set_record(Core *self, PyObject *args) {
    PyObject *buffer, *sent;
    Py_ssize_t sent_len;
    if (!PyArg_ParseTuple(args, "OO", &buffer, &sent))
        return NULL;
    self->sent = hold_buffer(self, sent, 0, 0, &sent_len);
    if (self->sent == NULL && PyErr_Occurred())
        return NULL;
    self->n_sent = sent_len / 8;
    if (attach_queue(self, buffer, &self->record, 1) < 0)
        return NULL;
    if (self->record.width != self->n_y + self->n_u + self->n_sent) {
        PyErr_SetString(PyExc_ValueError, "hot path: record queue width is not len(y) + len(u) + len(sent)");
        return NULL;
    }
    self->record_row = zeros(self->record.width);
    if (self->record_row == NULL)
        return NULL;
    self->has_record = 1;
    Py_RETURN_NONE;
}

/* set_input_guards(indices, low, high, step_max, last, clamped, rate_limited): the guarded
   connections' elements of u (int64 indices) and their bounds, state and counters (float64 and
   int64 vectors of one length, held: wiring.InputGuards owns them and reads the counts) */
static PyObject *Core_set_input_guards(Core *self, PyObject *args) {
    PyObject *objects[7];
    if (!PyArg_ParseTuple(args, "OOOOOOO", &objects[0], &objects[1], &objects[2], &objects[3], &objects[4],
                          &objects[5], &objects[6]))
        return NULL;
    void *buffers[7];
    Py_ssize_t lengths[7];
    for (int i = 0; i < 7; i++) {
        if ((buffers[i] = hold_buffer(self, objects[i], i >= 4, 0, &lengths[i])) == NULL)
            return NULL;
        if (lengths[i] != lengths[0]) {
            PyErr_SetString(PyExc_ValueError, "hot path: the input guards' vectors differ in length");
            return NULL;
        }
    }
    const int64_t *index = buffers[0];
    for (Py_ssize_t k = 0; k < lengths[0] / 8; k++)
        if (index[k] < 0 || index[k] >= self->n_u) {
            PyErr_SetString(PyExc_ValueError, "hot path: an input guard's index is outside u");
            return NULL;
        }
    self->guard_index = index;
    self->guard_low = buffers[1];
    self->guard_high = buffers[2];
    self->guard_step = buffers[3];
    self->guard_last = buffers[4];
    self->guard_clamped = buffers[5];
    self->guard_rate_limited = buffers[6];
    self->n_guarded = lengths[0] / 8;
    Py_RETURN_NONE;
}

/* The guards of guarded connections (wiring.InputGuards.apply, element by element): clamp to
   [low, high], then a step of at most step_max from the last value, each counted. A value the
   rate limit does not hold back stays as clamped, exactly as the Python twin leaves it. */
static void guard_inputs(Core *self) {
    for (Py_ssize_t k = 0; k < self->n_guarded; k++) {
        double value = self->u[self->guard_index[k]];
        double out = value < self->guard_high[k] ? value : self->guard_high[k];
        out = out > self->guard_low[k] ? out : self->guard_low[k];
        self->guard_clamped[k] += out != value;
        double delta = out - self->guard_last[k], step = self->guard_step[k];
        if (delta > step || delta < -step) {
            self->guard_rate_limited[k]++;
            delta = delta < step ? delta : step;
            delta = delta > -step ? delta : -step;
            out = self->guard_last[k] + delta;
        }
        self->guard_last[k] = out;
        self->u[self->guard_index[k]] = out;
    }
}

/* set_input_log(sample_queue_words): what entered through live ports, for replay */
static PyObject *Core_set_input_log(Core *self, PyObject *buffer) {
    if (attach_queue(self, buffer, &self->input_log, 1) < 0)
        return NULL;
    if (self->input_log.width < 1) {
        PyErr_SetString(PyExc_ValueError, "hot path: input log rows need room for the port index");
        return NULL;
    }
    self->input_log_row = (double *)zeros(self->input_log.width);
    if (self->input_log_row == NULL)
        return NULL;
    self->has_input_log = 1;
    Py_RETURN_NONE;
}

/* set_read_log(record_ring_memory): reads that got another sample than LET promised, for replay */
static PyObject *Core_set_read_log(Core *self, PyObject *buffer) {
    if (attach_queue(self, buffer, &self->read_log, 0) < 0)
        return NULL;
    if (self->read_log.width != READ_LOG_RECORD_WORDS) {
        PyErr_SetString(PyExc_ValueError, "hot path: the read log must hold 4-word records");
        return NULL;
    }
    self->has_read_log = 1;
    Py_RETURN_NONE;
}

/* set_finite_check(indices, faults, labels, error_type): y[indices[i]] crosses a connection; a NaN
   or inf there is counted, and raises error_type(labels[i] ...) when faults[i] is true */
static PyObject *Core_set_finite_check(Core *self, PyObject *args) {
    PyObject *indices, *faults, *labels, *error_type;
    if (!PyArg_ParseTuple(args, "O!O!O!O", &PyTuple_Type, &indices, &PyTuple_Type, &faults, &PyTuple_Type, &labels,
                          &error_type))
        return NULL;
    Py_ssize_t n = PyTuple_GET_SIZE(indices);
    if (PyTuple_GET_SIZE(faults) != n || PyTuple_GET_SIZE(labels) != n || !PyExceptionClass_Check(error_type) ||
        self->check_index != NULL) {
        PyErr_SetString(PyExc_ValueError, "set_finite_check(indices, faults, labels, error_type): once, same lengths");
        return NULL;
    }
    self->check_index = zeros(n);
    self->check_fault = zeros(n);
    if (self->check_index == NULL || self->check_fault == NULL)
        return NULL;
    for (Py_ssize_t i = 0; i < n; i++) {
        long long index = PyLong_AsLongLong(PyTuple_GET_ITEM(indices, i));
        int fault = PyObject_IsTrue(PyTuple_GET_ITEM(faults, i));
        if (PyErr_Occurred() || fault < 0 || check_span(index, 1, self->n_y, "checked output") < 0 ||
            !PyUnicode_Check(PyTuple_GET_ITEM(labels, i))) {
            if (!PyErr_Occurred())
                PyErr_SetString(PyExc_TypeError, "set_finite_check: labels are str");
            return NULL;
        }
        self->check_index[i] = index;
        self->check_fault[i] = fault;
    }
    Py_INCREF(labels);
    Py_INCREF(error_type);
    self->check_labels = labels;
    self->check_error = error_type;
    self->n_checks = n;
    Py_RETURN_NONE;
}

/* start(t0_ns, end_ns, stale_reads): the timeline and the counts carried over */
static PyObject *Core_start(Core *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "start(t0_ns, end_ns, stale_reads)");
        return NULL;
    }
    self->t0_ns = PyLong_AsLongLong(args[0]);
    self->end_ns = PyLong_AsLongLong(args[1]);
    self->stale_reads = PyLong_AsLongLong(args[2]);
    if (PyErr_Occurred())
        return NULL;
    self->cycle = 0;
    self->release_ns = self->t0_ns;
    self->last_end_ns = now_ns();
    Py_RETURN_NONE;
}

/* ---- the cycle: no allocation, no Python objects but the tick's three ints -------------- */

static int64_t read_channel(Input *input, int64_t time_ns) {
    aword *words = input->words;
    int64_t published = LOAD(&words[CHANNEL_PUBLISHED], acquire);
    int64_t back = 1, tries = 0;
    while (back <= published && back <= input->n_slots && tries < READ_RETRIES * input->n_slots) {
        tries++;
        aword *slot = words + HEADER_WORDS + ((published - back) % input->n_slots) * input->slot_words;
        int64_t seq = LOAD(&slot[SLOT_SEQ], acquire);
        if (seq & 1)
            continue; /* being written: look again */
        int64_t stamp = LOAD(&slot[SLOT_STAMP_NS], relaxed);
        if (stamp <= time_ns) {
            aword *values = slot + SLOT_VALUES + input->first;
            for (int64_t i = 0; i < input->width; i++)
                input->scratch[i] = LOAD(&values[i], relaxed);
        }
        atomic_thread_fence(memory_order_acquire);
        if (LOAD(&slot[SLOT_SEQ], relaxed) != seq)
            continue; /* changed under us (the writer may have lapped it): look again */
        if (stamp <= time_ns)
            return stamp;
        back++; /* too new for this reader: the slot before */
    }
    return NO_STAMP;
}

/* 1 when the port delivered a value not seen before (it is then in u), else 0 */
static int read_live_port(LivePort *port) {
    aword *words = port->words;
    for (int tries = 0; tries < READ_RETRIES; tries++) {
        int64_t seq = LOAD(&words[PORT_SEQ], acquire);
        if (seq & 1)
            continue;
        for (int64_t i = 0; i < port->count; i++)
            port->scratch[i] = LOAD(&words[HEADER_WORDS + i], relaxed);
        atomic_thread_fence(memory_order_acquire);
        if (LOAD(&words[PORT_SEQ], relaxed) != seq)
            continue;
        memcpy(port->dest, port->scratch, port->count * 8);
        if (seq != port->last_seq) {
            port->last_seq = seq;
            STORE(&words[PORT_READS], LOAD(&words[PORT_READS], relaxed) + 1, relaxed); /* this reader's word */
            return 1;
        }
        return 0;
    }
    return 0;
}

static void push(Queue *queue, int64_t tick, const void *values);

static void log_input(Core *self, LivePort *port, int64_t since_t0_ns) {
    double *row = self->input_log_row;
    int64_t width = self->input_log.width, count = port->count < width - 1 ? port->count : width - 1;
    row[0] = port->index;
    memcpy(row + 1, port->dest, count * 8);
    for (int64_t i = 1 + count; i < width; i++)
        row[i] = 0.0;
    push(&self->input_log, since_t0_ns, row);
}

static void copy_spans(Core *self, const Input *input, const int64_t *values) {
    for (int64_t s = 0; s < input->n_spans; s++) {
        const Span *span = &input->spans[s];
        memcpy(self->u + span->to, values + span->from, span->count * 8);
    }
}

/* A replay's stale read that found no sample at all (the inputs keep what they held) */
static const int64_t NOTHING_READ[1];

/* instead: NULL in the loop; a replay's stale reads: per input, NULL (read the channel) or what the
   run read instead (the input's scratch layout, or NOTHING_READ). The guards act on either. */
static void read_inputs(Core *self, int64_t release_ns, const int64_t *const *instead) {
    int64_t since_t0_ns = release_ns - self->t0_ns;
    for (Py_ssize_t i = 0; i < self->n_inputs; i++) {
        Input *input = &self->inputs[i];
        if (instead != NULL && instead[i] != NULL) {
            if (instead[i] != NOTHING_READ)
                copy_spans(self, input, instead[i]);
            continue;
        }
        int64_t stamp = read_channel(input, release_ns);
        if (stamp == INITIAL_STAMP) /* the writer's initial outputs, published before T0: valid from T0 */
            stamp = self->t0_ns;
        if (stamp != NO_STAMP)
            copy_spans(self, input, input->scratch);
        int64_t entitled = self->t0_ns + since_t0_ns / input->period_ns * input->period_ns;
        if (stamp < entitled) { /* the writer has not published what we are entitled to */
            self->stale_reads++;
            STORE(&self->status[STATUS_STALE_READS], self->stale_reads, relaxed);
            if (self->has_read_log) { /* what the task got instead, for replay */
                int64_t record[READ_LOG_RECORD_WORDS];
                record[READ_LOG_RELEASE_NS] = since_t0_ns;
                record[READ_LOG_WRITER] = (int64_t)i;
                record[READ_LOG_STAMP_GOT_NS] = stamp == NO_STAMP ? NO_STAMP : stamp - self->t0_ns;
                record[READ_LOG_STAMP_DUE_NS] = entitled - self->t0_ns;
                push(&self->read_log, 0, record);
            }
        }
    }
    if (self->n_guarded)
        guard_inputs(self);
    for (Py_ssize_t i = 0; i < self->n_live_ports; i++)
        if ((self->live_ports[i].fresh = read_live_port(&self->live_ports[i])) && self->has_input_log)
            log_input(self, &self->live_ports[i], since_t0_ns);
    for (Py_ssize_t i = 0; i < self->n_profiles; i++) {
        Profile *profile = &self->profiles[i];
        int64_t index = profile->index;
        while (index + 1 < profile->n_rows && profile->t_ns[index + 1] <= since_t0_ns)
            index++;
        int changed = index != profile->index && index >= 0;
        if (changed)
            profile->index = index;
        double *u = self->u + profile->to;
        const double *row = profile->index >= 0 ? profile->rows + profile->index * profile->count : NULL;
        LivePort *nudge = profile->mode ? &self->live_ports[profile->live_port] : NULL;
        if (profile->mode == NUDGE_OFFSET) {
            if (profile->index >= 0)
                for (int64_t k = 0; k < profile->count; k++)
                    u[k] = row[k] + nudge->dest[k];
        } else if (nudge != NULL && nudge->fresh) {
            memcpy(u, nudge->dest, profile->count * 8);
        } else if (changed) {
            memcpy(u, row, profile->count * 8);
        }
    }
}

/* A single-producer queue: a full one drops and counts, it never waits. */
static void push(Queue *queue, int64_t tick, const void *values) {
    aword *words = queue->words;
    int64_t written = queue->written;
    if (written - LOAD(&words[QUEUE_READ], acquire) >= queue->capacity) {
        STORE(&words[QUEUE_DROPPED], LOAD(&words[QUEUE_DROPPED], relaxed) + 1, relaxed);
        return;
    }
    int64_t index = written % queue->capacity;
    if (queue->ticks != NULL)
        queue->ticks[index] = tick;
    memcpy(queue->rows + index * queue->width, values, queue->width * 8);
    queue->written = written + 1;
    STORE(&words[QUEUE_WRITTEN], written + 1, release); /* the row is visible before the count announcing it */
}

/* NaN or inf in an output headed across a connection: counted (and the first one named) in the
   status block; -1 with the exception set when a connection does not allow it (nothing published). */
static int check_finite(Core *self, int64_t cycle) {
    for (Py_ssize_t i = 0; i < self->n_checks; i++) {
        double value = self->y[self->check_index[i]];
        if (isfinite(value))
            continue;
        aword *status = self->status;
        int64_t count = LOAD(&status[STATUS_NONFINITE_VALUES], relaxed);
        if (count == 0) {
            STORE(&status[STATUS_NONFINITE_FIRST_CYCLE], cycle, relaxed);
            STORE(&status[STATUS_NONFINITE_FIRST_OUTPUT], self->check_index[i], relaxed);
        }
        STORE(&status[STATUS_NONFINITE_VALUES], count + 1, relaxed);
        if (self->check_fault[i]) {
            PyObject *shown = PyFloat_FromDouble(value);
            if (shown != NULL) {
                PyErr_Format(self->check_error, "%U is %R at cycle %lld: a non-finite value crossing a connection "
                             "is a fault (allow_nonfinite = true on the connection lets it through)",
                             PyTuple_GET_ITEM(self->check_labels, i), shown, (long long)cycle);
                Py_DECREF(shown);
            }
            return -1;
        }
    }
    return 0;
}

static int publish_outputs(Core *self, int64_t cycle, int64_t publish_ns) {
    if (self->n_checks && check_finite(self, cycle) < 0)
        return -1;
    if (self->output != NULL) {
        aword *slot = self->output + HEADER_WORDS + (self->published % self->output_slots) * self->output_slot_words;
        int64_t seq = LOAD(&slot[SLOT_SEQ], relaxed) + 1;
        STORE(&slot[SLOT_SEQ], seq, relaxed); /* odd: slot being written */
        atomic_thread_fence(memory_order_release);
        for (int64_t i = 0; i < self->n_y; i++) {
            int64_t bits; /* the double's bits, copied: read through an int64_t lvalue it would break strict aliasing */
            memcpy(&bits, &self->y[i], sizeof bits);
            STORE(&slot[SLOT_VALUES + i], bits, relaxed);
        }
        STORE(&slot[SLOT_STAMP_NS], publish_ns, relaxed);
        STORE(&slot[SLOT_SEQ], seq + 1, release); /* even: slot complete */
        self->published++;
        STORE(&self->output[CHANNEL_PUBLISHED], self->published, release);
    }
    for (Py_ssize_t i = 0; i < self->n_out_ports; i++)
        push(&self->out_ports[i], cycle, self->y + self->out_ports[i].from);
    if (self->has_record) {
        memcpy(self->record_row, self->y, self->n_y * 8);
        memcpy(self->record_row + self->n_y, self->u, self->n_u * 8);
        if (self->n_sent)
            memcpy(self->record_row + self->n_y + self->n_u, self->sent, self->n_sent * 8);
        push(&self->record, cycle, self->record_row);
    }
    return 0;
}

static int set_tick(Core *self, PyObject *name, int64_t value) {
    PyObject *number = PyLong_FromLongLong(value);
    if (number == NULL)
        return -1;
    int result = PyObject_SetAttr(self->tick, name, number);
    Py_DECREF(number);
    return result;
}

/* Sleep to the release: 1 when reached, 0 when a stop was requested meanwhile, -1 on an error.
   A long sleep wakes every STOP_POLL_NS before the release to look at the stop flag, and a
   signal (its handler may set the flag: SIGTERM does) makes it look at once. */
static int sleep_until_release(Core *self, int64_t release_ns) {
    for (;;) {
        int64_t wake_ns = release_ns;
        if (release_ns - self->last_end_ns > STOP_POLL_NS) { /* a long sleep: cut it into slices */
            int64_t left_ns = release_ns - now_ns();
            if (left_ns > STOP_POLL_NS)
                wake_ns = release_ns - (left_ns - 1) / STOP_POLL_NS * STOP_POLL_NS;
        }
        struct timespec deadline = {wake_ns / 1000000000, wake_ns % 1000000000};
        int result;
        Py_BEGIN_ALLOW_THREADS
        result = clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &deadline, NULL);
        Py_END_ALLOW_THREADS
        if (result == EINTR) {
            if (PyErr_CheckSignals() < 0)
                return -1;
        } else if (result != 0) {
            set_libc_error(CLOCK_NANOSLEEP_CALL, result);
            return -1;
        } else if (wake_ns == release_ns) {
            return 1;
        }
        if (LOAD(&self->control[CONTROL_STOP], relaxed))
            return 0;
    }
}

static int refuse_closed(Core *self) {
    if (self->closed)
        PyErr_SetString(PyExc_ValueError, "hot path: this Core is closed");
    return self->closed;
}

/* The cycle starts at start_ns: stamp it, tell the tick, read the inputs valid at the release. */
static PyObject *start_cycle(Core *self, int64_t start_ns) {
    int64_t release_ns = self->release_ns;
    self->start_ns = start_ns;
    if (self->measure_busy)
        self->busy_wake_ns = start_ns;
    if (set_tick(self, str_cycle, self->cycle) < 0 || set_tick(self, str_release_ns, release_ns) < 0 ||
        set_tick(self, str_start_ns, start_ns) < 0)
        return NULL;
    read_inputs(self, release_ns, NULL);
    Py_RETURN_TRUE;
}

static int time_to_stop(Core *self) {
    return self->release_ns >= self->end_ns || LOAD(&self->control[CONTROL_STOP], relaxed);
}

/* begin(): sleep to the release, stamp the start, read the inputs. False: stop. */
static PyObject *Core_begin(Core *self, PyObject *unused) {
    if (refuse_closed(self))
        return NULL;
    if (time_to_stop(self))
        Py_RETURN_FALSE;
    if (self->measure_busy && self->busy_wake_ns) { /* the whole iteration since the last wake-up */
        int64_t busy_ns = now_ns() - self->busy_wake_ns;
        self->busy_ns += busy_ns;
        self->busy_cycles++;
        if (busy_ns > self->busy_max_ns)
            self->busy_max_ns = busy_ns;
    }
    int reached = sleep_until_release(self, self->release_ns);
    if (reached < 0)
        return NULL;
    if (!reached)
        Py_RETURN_FALSE;
    return start_cycle(self, now_ns());
}

/* begin_at(start_ns): begin() on a given clock, without sleeping (the seam the twins' tests drive). */
static PyObject *Core_begin_at(Core *self, PyObject *arg) {
    int64_t start_ns = PyLong_AsLongLong(arg);
    if ((start_ns == -1 && PyErr_Occurred()) || refuse_closed(self))
        return NULL;
    if (time_to_stop(self))
        Py_RETURN_FALSE;
    return start_cycle(self, start_ns);
}

/* The cycle ended at end_ns: record it, count a miss, move to the next release as the policy says. */
static PyObject *end_cycle(Core *self, int64_t end_ns) {
    int64_t cycle = self->cycle, release_ns = self->release_ns, start_ns = self->start_ns;
    int64_t period_ns = self->period_ns;
    self->last_end_ns = end_ns;
    int64_t record[TIMING_RECORD_WORDS];
    record[TIMING_CYCLE] = cycle;
    record[TIMING_RELEASE_NS] = release_ns;
    record[TIMING_START_NS] = start_ns;
    record[TIMING_END_NS] = end_ns;
    push(&self->timing, 0, record);
    aword *status = self->status;
    STORE(&status[STATUS_CYCLE], cycle, relaxed);
    STORE(&status[STATUS_LATENCY_LAST_NS], start_ns - release_ns, relaxed);
    STORE(&status[STATUS_EXEC_LAST_NS], end_ns - start_ns, relaxed);
    cycle++;
    release_ns += period_ns;
    int go_on = 1;
    if (end_ns > release_ns) { /* overran into the next period */
        STORE(&status[STATUS_DEADLINE_MISSES], LOAD(&status[STATUS_DEADLINE_MISSES], relaxed) + 1, relaxed);
        self->misses_in_a_row++;
        if (self->misses_in_a_row > LOAD(&status[STATUS_MISSES_IN_A_ROW_MAX], relaxed))
            STORE(&status[STATUS_MISSES_IN_A_ROW_MAX], self->misses_in_a_row, relaxed);
        go_on = self->max_misses == 0 || self->misses_in_a_row < self->max_misses;
        int64_t skipped = 1, first_missed_ns = release_ns;
        if (!self->catch_up) {
            int64_t next_cycle = (end_ns - self->t0_ns) / period_ns + 1;
            skipped = next_cycle - cycle;
            cycle = next_cycle;
            release_ns = self->t0_ns + next_cycle * period_ns;
        }
        /* releases at or after the run's end were never the run's: they are no overruns */
        int64_t left_ns = self->end_ns - first_missed_ns;
        if (left_ns < skipped * period_ns)
            skipped = left_ns <= 0 ? 0 : (left_ns + period_ns - 1) / period_ns;
        STORE(&status[STATUS_OVERRUNS], LOAD(&status[STATUS_OVERRUNS], relaxed) + skipped, relaxed);
    } else {
        self->misses_in_a_row = 0;
    }
    int late = end_ns > self->release_ns + period_ns;
    self->cycle = cycle;
    self->release_ns = release_ns;
    int64_t wanted_ns = LOAD(&self->control[CONTROL_SNAPSHOT_NS], relaxed);
    if (go_on && wanted_ns > self->snapshot_taken_ns && release_ns >= wanted_ns) {
        self->snapshot_taken_ns = wanted_ns;
        return PyLong_FromLong(SNAPSHOT_DUE);
    }
    if (go_on && late)
        return PyLong_FromLong(CYCLE_LATE);
    return PyBool_FromLong(go_on); /* False: max_misses deadline misses in a row */
}

/* finish(): publish the outputs valid from release + P, record the cycle, go to the next release. */
static PyObject *Core_finish(Core *self, PyObject *unused) {
    if (refuse_closed(self))
        return NULL;
    if (publish_outputs(self, self->cycle, self->release_ns + self->period_ns) < 0)
        return NULL;
    return end_cycle(self, now_ns());
}

/* finish_at(end_ns): finish() on a given clock (the seam the twins' tests drive). */
static PyObject *Core_finish_at(Core *self, PyObject *arg) {
    int64_t end_ns = PyLong_AsLongLong(arg);
    if ((end_ns == -1 && PyErr_Occurred()) || refuse_closed(self))
        return NULL;
    if (publish_outputs(self, self->cycle, self->release_ns + self->period_ns) < 0)
        return NULL;
    return end_cycle(self, end_ns);
}

/* read_inputs(release_ns[, instead]) and publish_outputs(cycle, publish_ns): the simulator's steps.
   instead (a replay's stale reads): {input index: what the run read in place of the channel's sample,
   a float64 array of the input's width, or None for nothing read}; the guards then act on it. */
static PyObject *Core_read_inputs(Core *self, PyObject *const *args, Py_ssize_t nargs) {
    if (self->closed) {
        PyErr_SetString(PyExc_ValueError, "hot path: this Core is closed");
        return NULL;
    }
    if (nargs < 1 || nargs > 2) {
        PyErr_SetString(PyExc_TypeError, "read_inputs(release_ns[, instead])");
        return NULL;
    }
    int64_t release_ns = PyLong_AsLongLong(args[0]);
    if (release_ns == -1 && PyErr_Occurred())
        return NULL;
    PyObject *instead = nargs == 2 && args[1] != Py_None ? args[1] : NULL;
    if (instead == NULL) {
        read_inputs(self, release_ns, NULL);
        Py_RETURN_NONE;
    }
    if (!PyDict_Check(instead)) {
        PyErr_SetString(PyExc_TypeError, "hot path: read_inputs' instead must be a dict");
        return NULL;
    }
    Py_ssize_t n = self->n_inputs > 0 ? self->n_inputs : 1;
    const int64_t **rows = PyMem_Calloc(n, sizeof *rows);
    Py_buffer *views = PyMem_Calloc(n, sizeof *views);
    int failed = rows == NULL || views == NULL;
    if (failed)
        PyErr_NoMemory();
    PyObject *key, *value;
    Py_ssize_t position = 0;
    while (!failed && PyDict_Next(instead, &position, &key, &value)) {
        Py_ssize_t i = PyLong_AsSsize_t(key);
        if (i == -1 && PyErr_Occurred()) {
            failed = 1;
        } else if (i < 0 || i >= self->n_inputs) {
            PyErr_Format(PyExc_ValueError, "hot path: read_inputs' instead names input %zd of %zd", i,
                         self->n_inputs);
            failed = 1;
        } else if (value == Py_None) {
            rows[i] = NOTHING_READ;
        } else if (PyObject_GetBuffer(value, &views[i], PyBUF_C_CONTIGUOUS) < 0) {
            failed = 1;
        } else if (views[i].len != self->inputs[i].width * 8) {
            PyErr_Format(PyExc_ValueError, "hot path: read_inputs' instead for input %zd holds %zd bytes, "
                         "not %lld", i, views[i].len, (long long)(self->inputs[i].width * 8));
            failed = 1;
        } else {
            rows[i] = views[i].buf;
        }
    }
    if (!failed)
        read_inputs(self, release_ns, rows);
    for (Py_ssize_t i = 0; views != NULL && i < self->n_inputs; i++)
        if (views[i].obj != NULL)
            PyBuffer_Release(&views[i]);
    PyMem_Free(views);
    PyMem_Free(rows);
    if (failed)
        return NULL;
    Py_RETURN_NONE;
}

static PyObject *Core_publish_outputs(Core *self, PyObject *const *args, Py_ssize_t nargs) {
    if (self->closed) {
        PyErr_SetString(PyExc_ValueError, "hot path: this Core is closed");
        return NULL;
    }
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "publish_outputs(cycle, publish_ns)");
        return NULL;
    }
    int64_t cycle = PyLong_AsLongLong(args[0]), publish_ns = PyLong_AsLongLong(args[1]);
    if (PyErr_Occurred())
        return NULL;
    if (publish_outputs(self, cycle, publish_ns) < 0)
        return NULL;
    Py_RETURN_NONE;
}

static PyObject *Core_get_stale_reads(Core *self, void *closure) { return PyLong_FromLongLong(self->stale_reads); }
static PyObject *Core_get_cycle(Core *self, void *closure) { return PyLong_FromLongLong(self->cycle); }
static PyObject *Core_get_release_ns(Core *self, void *closure) { return PyLong_FromLongLong(self->release_ns); }

/* measure_busy(): from now on, sum the time from each wake-up to the next sleep (a benchmark's probe) */
static PyObject *Core_measure_busy(Core *self, PyObject *unused) {
    self->measure_busy = 1;
    self->busy_ns = self->busy_cycles = self->busy_max_ns = self->busy_wake_ns = 0;
    Py_RETURN_NONE;
}

static PyObject *Core_get_busy(Core *self, void *closure) {
    return Py_BuildValue("(LLL)", (long long)self->busy_ns, (long long)self->busy_cycles,
                         (long long)self->busy_max_ns);
}

static int Core_traverse(Core *self, visitproc visit, void *arg) {
    Py_VISIT(self->tick);
    Py_VISIT(self->check_labels);
    Py_VISIT(self->check_error);
    /* The buffers' exporters (memoryviews, arrays, mappings of shared memory) are not visited: none
       refers back to a Core, and a memoryview the collector cleared before us (its tp_clear drops
       its managed buffer while we still hold an export) crashes in our release of it. Unvisited,
       they stay alive until Core_clear releases them. */
    return 0;
}

/* Let go of the shared memory and the tick: after this the Core does nothing (close(), or the
   garbage collector breaking a cycle — a mapping must never outlive the views we hold of it). */
static int Core_clear(Core *self) {
    for (Py_ssize_t i = 0; i < self->n_views; i++)
        PyBuffer_Release(&self->views[i]);
    self->n_views = 0;
    self->closed = 1;
    self->u = self->y = NULL;
    self->control = self->status = self->output = NULL;
    Py_CLEAR(self->tick);
    Py_CLEAR(self->check_labels);
    Py_CLEAR(self->check_error);
    self->n_checks = 0;
    return 0;
}

static PyObject *Core_close(Core *self, PyObject *unused) {
    Core_clear(self);
    Py_RETURN_NONE;
}

static void Core_dealloc(Core *self) {
    PyObject_GC_UnTrack(self);
    Core_clear(self);
    PyMem_Free(self->views);
    for (Py_ssize_t i = 0; i < self->n_inputs; i++) {
        PyMem_Free(self->inputs[i].scratch);
        PyMem_Free(self->inputs[i].spans);
    }
    for (Py_ssize_t i = 0; i < self->n_live_ports; i++)
        PyMem_Free(self->live_ports[i].scratch);
    PyMem_Free(self->inputs);
    PyMem_Free(self->live_ports);
    PyMem_Free(self->profiles);
    PyMem_Free(self->out_ports);
    PyMem_Free(self->record_row);
    PyMem_Free(self->input_log_row);
    PyMem_Free(self->check_index);
    PyMem_Free(self->check_fault);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyMethodDef Core_methods[] = {
    {"add_input", (PyCFunction)Core_add_input, METH_VARARGS, "Attach every connection from one writer."},
    {"add_live_port", (PyCFunction)Core_add_live_port, METH_VARARGS, "Attach an input port (LatestValue)."},
    {"set_input_log", (PyCFunction)Core_set_input_log, METH_O, "Attach the input log (SampleQueue) for replay."},
    {"set_read_log", (PyCFunction)Core_set_read_log, METH_O, "Attach the read log (Int64Ring) for replay."},
    {"close", (PyCFunction)Core_close, METH_NOARGS, "Release the shared memory and the tick (idempotent)."},
    {"add_profile", (PyCFunction)Core_add_profile, METH_VARARGS, "Attach a setpoint profile."},
    {"set_output", (PyCFunction)Core_set_output, METH_O, "Attach this task's output channel."},
    {"add_output_port", (PyCFunction)Core_add_output_port, METH_VARARGS, "Attach an output port (SampleQueue)."},
    {"set_record", (PyCFunction)Core_set_record, METH_VARARGS,
     "set_record(words, sent): attach the recorder's queue and what the devices were sent."},
    {"set_input_guards", (PyCFunction)Core_set_input_guards, METH_VARARGS,
     "set_input_guards(indices, low, high, step_max, last, clamped, rate_limited): guarded connections."},
    {"start", (PyCFunction)(void (*)(void))Core_start, METH_FASTCALL, "start(t0_ns, end_ns, stale_reads)"},
    {"begin", (PyCFunction)Core_begin, METH_NOARGS, "Sleep to the release, read inputs; False: stop."},
    {"finish", (PyCFunction)Core_finish, METH_NOARGS, "Publish, record timing and status, advance."},
    {"set_finite_check", (PyCFunction)Core_set_finite_check, METH_VARARGS,
     "set_finite_check(indices, faults, labels, error_type): NaN/inf crossing a connection."},
    {"begin_at", (PyCFunction)Core_begin_at, METH_O, "begin() on a given clock: begin_at(start_ns), no sleep."},
    {"finish_at", (PyCFunction)Core_finish_at, METH_O, "finish() on a given clock: finish_at(end_ns)."},
    {"read_inputs", (PyCFunction)(void (*)(void))Core_read_inputs, METH_FASTCALL,
     "read_inputs(release_ns[, instead])"},
    {"measure_busy", (PyCFunction)Core_measure_busy, METH_NOARGS, "Sum wake-up → next sleep from now on."},
    {"publish_outputs", (PyCFunction)(void (*)(void))Core_publish_outputs, METH_FASTCALL,
     "publish_outputs(cycle, publish_ns)"},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef Core_getset[] = {
    {"stale_reads", (getter)Core_get_stale_reads, NULL, "Reads that found older data than due.", NULL},
    {"cycle", (getter)Core_get_cycle, NULL, "The cycle begin() runs next (or runs now).", NULL},
    {"release_ns", (getter)Core_get_release_ns, NULL, "Its release time.", NULL},
    {"busy", (getter)Core_get_busy, NULL, "(total ns, iterations, max ns) wake-up → next sleep.", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject CoreType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "rtloop.ipc._hotpath.Core",
    .tp_doc = "The per-cycle framework work of one task (C twin of hotpath.PythonCycle).",
    .tp_basicsize = sizeof(Core),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Core_init,
    .tp_dealloc = (destructor)Core_dealloc,
    .tp_traverse = (traverseproc)Core_traverse,
    .tp_clear = (inquiry)Core_clear,
    .tp_methods = Core_methods,
    .tp_getset = Core_getset,
};

/* sleep_until(deadline_ns): an absolute clock_nanosleep, for measuring its cost alone */
static PyObject *hotpath_sleep_until(PyObject *module, PyObject *arg) {
    int64_t deadline_ns = PyLong_AsLongLong(arg);
    if (deadline_ns == -1 && PyErr_Occurred())
        return NULL;
    struct timespec deadline = {deadline_ns / 1000000000, deadline_ns % 1000000000};
    int result;
    Py_BEGIN_ALLOW_THREADS
    result = clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &deadline, NULL);
    Py_END_ALLOW_THREADS
    if (result != 0 && result != EINTR) {
        set_libc_error(CLOCK_NANOSLEEP_CALL, result);
        return NULL;
    }
    Py_RETURN_NONE;
}

static PyMethodDef module_methods[] = {
    {"sleep_until", hotpath_sleep_until, METH_O, "Absolute clock_nanosleep(CLOCK_MONOTONIC) to deadline_ns."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef hotpath_module = {
    PyModuleDef_HEAD_INIT, "_hotpath", "rtloop's compiled per-cycle path (see hotpath.py).", -1, module_methods,
};

/* _hotpath.SCHEMA: every constant this module was built with (hotpath.py compares it with schema.py) */
static int export_schema(PyObject *schema) {
#define EXPORT(name)                                                                                             \
    do {                                                                                                         \
        PyObject *value = PyLong_FromLongLong(name);                                                             \
        if (value == NULL || PyDict_SetItemString(schema, #name, value) < 0) {                                   \
            Py_XDECREF(value);                                                                                   \
            return -1;                                                                                           \
        }                                                                                                        \
        Py_DECREF(value);                                                                                        \
    } while (0);
    RTLOOP_SCHEMA(EXPORT)
#undef EXPORT
    return 0;
}

PyMODINIT_FUNC PyInit__hotpath(void) {
    if (PyType_Ready(&CoreType) < 0)
        return NULL;
    str_cycle = PyUnicode_InternFromString("cycle");
    str_release_ns = PyUnicode_InternFromString("release_ns");
    str_start_ns = PyUnicode_InternFromString("start_ns");
    if (str_cycle == NULL || str_release_ns == NULL || str_start_ns == NULL)
        return NULL;
    PyObject *module = PyModule_Create(&hotpath_module);
    if (module == NULL)
        return NULL;
    Py_INCREF(&CoreType);
    PyObject *schema = PyDict_New();
#ifndef RTLOOP_HOTPATH_SOURCES_DIGEST
#define RTLOOP_HOTPATH_SOURCES_DIGEST "" /* built without setup.py: hotpath.py says it cannot tell */
#endif
    if (schema == NULL || PyModule_AddObject(module, "Core", (PyObject *)&CoreType) < 0 ||
        PyModule_AddObject(module, "SCHEMA", schema) < 0 || export_schema(schema) < 0 ||
        PyModule_AddStringConstant(module, "SOURCES_DIGEST", RTLOOP_HOTPATH_SOURCES_DIGEST) < 0) {
        Py_DECREF(module);
        return NULL;
    }
    return module;
}

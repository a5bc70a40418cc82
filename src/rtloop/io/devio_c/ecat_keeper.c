/* FrameKeeper: an EtherCAT device's process data kept flowing between configure and T0, so the
 * slaves can be taken to OP before T0 (a slave in OP leaves it when no process data comes within
 * its SM watchdog time). A thread of its own in C: it never takes the GIL, so the task process's
 * start-up work (imports, collections, the other tasks' preparation) does not starve it, as it
 * starved a Python thread. It sends the frame as it is (the outputs' safe values: the drives
 * disabled) every interval and takes each answer into a buffer of its own, keeping the last
 * working counter; stop() ends it (at T0) before the task's loop exchanges the same frame.
 *
 * Included by ../_devio.c (one translation unit). No Python reference: without the C build the
 * device asks for OP at T0 instead (io/drives/ethercat.py says so). */

#include <pthread.h>
#include <sched.h>
#include <signal.h>

#define KEEPER_REPLY_BYTES 1600

typedef struct {
    PyObject_HEAD
    Py_buffer frame;
    int held, fd, started, stopping;
    Py_ssize_t wkc_at;
    long long interval_ns, timeout_ns, exchanges;
    long last_wkc; /* -1: none yet; -2: the last frame did not come back in time */
    pthread_t thread;
    pthread_mutex_t lock;
    pthread_cond_t wake;
    int sync_made;
    uint8_t reply[KEEPER_REPLY_BYTES];
} FrameKeeper;

/* One exchange of the frame: its working counter, or -2 when no answer came within the timeout. */
static long keeper_exchange(FrameKeeper *self) {
    uint8_t *frame = self->frame.buf;
    frame[ECAT_INDEX_AT] = (uint8_t)(frame[ECAT_INDEX_AT] + 1);
    if (send(self->fd, frame, (size_t)self->frame.len, 0) < 0) {
        return -2;
    }
    long long sent_ns = monotonic_ns();
    for (int passed = 0; passed < 16;) {
        ssize_t size = recv(self->fd, self->reply, sizeof(self->reply), 0);
        int saved = errno;
        if (monotonic_ns() - sent_ns > self->timeout_ns) {
            return -2;
        }
        if (size < 0) {
            if (saved == EAGAIN || saved == EWOULDBLOCK || saved == EINTR) {
                continue; /* a tick of the socket's receive timeout: wait on until the frame's */
            }
            return -2;
        }
        if (size >= self->wkc_at + 2 && self->reply[ECAT_INDEX_AT] == frame[ECAT_INDEX_AT] &&
            self->reply[ECAT_COMMAND_AT] == ECAT_LRW) {
            return (long)self->reply[self->wkc_at] | (long)self->reply[self->wkc_at + 1] << 8;
        }
        passed++; /* another frame's answer (a state request of the main thread's) */
    }
    return -2;
}

static void *keeper_run(void *argument) {
    FrameKeeper *self = argument;
    struct timespec next;
    clock_gettime(CLOCK_MONOTONIC, &next);
    pthread_mutex_lock(&self->lock);
    while (!self->stopping) {
        pthread_mutex_unlock(&self->lock);
        long wkc = keeper_exchange(self);
        pthread_mutex_lock(&self->lock);
        self->last_wkc = wkc;
        self->exchanges++;
        long long at_ns = (long long)next.tv_sec * 1000000000LL + next.tv_nsec + self->interval_ns;
        if (at_ns < monotonic_ns()) {
            at_ns = monotonic_ns(); /* late (a long answer): from now on, not a burst to catch up */
        }
        next.tv_sec = (time_t)(at_ns / 1000000000LL);
        next.tv_nsec = (long)(at_ns % 1000000000LL);
        while (!self->stopping && pthread_cond_timedwait(&self->wake, &self->lock, &next) != ETIMEDOUT) {
        }
    }
    pthread_mutex_unlock(&self->lock);
    return NULL;
}

static void keeper_stop(FrameKeeper *self) {
    if (!self->started) {
        return;
    }
    pthread_mutex_lock(&self->lock);
    self->stopping = 1;
    pthread_cond_signal(&self->wake);
    pthread_mutex_unlock(&self->lock);
    Py_BEGIN_ALLOW_THREADS /* its last exchange ends within the frame's timeout */
    pthread_join(self->thread, NULL);
    Py_END_ALLOW_THREADS
    self->started = 0;
}

static void FrameKeeper_dealloc(FrameKeeper *self) {
    keeper_stop(self);
    if (self->held) {
        PyBuffer_Release(&self->frame);
    }
    if (self->sync_made) {
        pthread_cond_destroy(&self->wake);
        pthread_mutex_destroy(&self->lock);
    }
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* FrameKeeper(fd, frame, wkc_at, interval_ns, timeout_ns) */
static int FrameKeeper_init(FrameKeeper *self, PyObject *args, PyObject *kwargs) {
    int fd;
    PyObject *frame;
    Py_ssize_t wkc_at;
    long long interval_ns, timeout_ns;
    if (!PyArg_ParseTuple(args, "iOnLL", &fd, &frame, &wkc_at, &interval_ns, &timeout_ns)) {
        return -1;
    }
    if (self->held || self->started) {
        PyErr_SetString(PyExc_ValueError, "FrameKeeper: made once");
        return -1;
    }
    if (PyObject_GetBuffer(frame, &self->frame, PyBUF_SIMPLE | PyBUF_WRITABLE) < 0) {
        return -1;
    }
    self->held = 1;
    if (self->frame.len <= ECAT_INDEX_AT || wkc_at + 2 > KEEPER_REPLY_BYTES || interval_ns <= 0 || timeout_ns <= 0) {
        PyErr_SetString(PyExc_ValueError, "FrameKeeper: a frame without its datagram, or a bad interval or timeout");
        return -1;
    }
    pthread_condattr_t attributes;
    pthread_condattr_init(&attributes);
    pthread_condattr_setclock(&attributes, CLOCK_MONOTONIC);
    pthread_mutex_init(&self->lock, NULL);
    pthread_cond_init(&self->wake, &attributes);
    pthread_condattr_destroy(&attributes);
    self->sync_made = 1;
    self->fd = fd;
    self->wkc_at = wkc_at;
    self->interval_ns = interval_ns;
    self->timeout_ns = timeout_ns;
    self->last_wkc = -1;
    return 0;
}

/* start(): the thread begins exchanging (signals stay the main thread's: all blocked in it). Where
 * the calling thread is real-time (SCHED_FIFO/RR, priority p), the keeper runs at SCHED_FIFO p + 1:
 * the task's start-up work at p (locking its memory, a collection) would otherwise hold the CPU
 * longer than the SM watchdog, and a thread of the same FIFO priority cannot preempt it. Its
 * exchanges are short and it stops at T0. */
static PyObject *FrameKeeper_start(FrameKeeper *self, PyObject *unused) {
    if (!self->sync_made || self->started) {
        PyErr_SetString(PyExc_ValueError, "FrameKeeper: not made, or started already");
        return NULL;
    }
    pthread_attr_t attributes;
    pthread_attr_init(&attributes);
    int policy;
    struct sched_param own;
    if (pthread_getschedparam(pthread_self(), &policy, &own) == 0 && (policy == SCHED_FIFO || policy == SCHED_RR)) {
        struct sched_param above = {.sched_priority = own.sched_priority < sched_get_priority_max(SCHED_FIFO)
                                                          ? own.sched_priority + 1
                                                          : own.sched_priority};
        pthread_attr_setinheritsched(&attributes, PTHREAD_EXPLICIT_SCHED);
        pthread_attr_setschedpolicy(&attributes, SCHED_FIFO);
        pthread_attr_setschedparam(&attributes, &above);
    }
    sigset_t all, previous;
    sigfillset(&all);
    pthread_sigmask(SIG_SETMASK, &all, &previous);
    self->stopping = 0;
    int failed = pthread_create(&self->thread, &attributes, keeper_run, self);
    pthread_sigmask(SIG_SETMASK, &previous, NULL);
    pthread_attr_destroy(&attributes);
    if (failed) {
        errno = failed;
        return PyErr_SetFromErrno(PyExc_OSError);
    }
    self->started = 1;
    Py_RETURN_NONE;
}

static PyObject *FrameKeeper_stop(FrameKeeper *self, PyObject *unused) {
    keeper_stop(self);
    Py_RETURN_NONE;
}

/* state() -> (exchanges, last working counter: -1 none yet, -2 the last frame not back in time) */
static PyObject *FrameKeeper_state(FrameKeeper *self, PyObject *unused) {
    long long exchanges;
    long wkc;
    pthread_mutex_lock(&self->lock);
    exchanges = self->exchanges;
    wkc = self->last_wkc;
    pthread_mutex_unlock(&self->lock);
    return Py_BuildValue("(Ll)", exchanges, wkc);
}

static PyMethodDef FrameKeeper_methods[] = {
    {"start", (PyCFunction)FrameKeeper_start, METH_NOARGS, "Begin exchanging the frame every interval."},
    {"stop", (PyCFunction)FrameKeeper_stop, METH_NOARGS, "End the thread (its last exchange done)."},
    {"state", (PyCFunction)FrameKeeper_state, METH_NOARGS, "(exchanges, last working counter)."},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject FrameKeeperType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "rtloop.io._devio.FrameKeeper",
    .tp_basicsize = sizeof(FrameKeeper),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "FrameKeeper(fd, frame, wkc_at, interval_ns, timeout_ns): the process data kept flowing before T0.",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)FrameKeeper_init,
    .tp_dealloc = (destructor)FrameKeeper_dealloc,
    .tp_methods = FrameKeeper_methods,
};

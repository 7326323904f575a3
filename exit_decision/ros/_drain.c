/* Draining a subscription's queue in C: the messages a node would refuse unread are taken and
 * dropped here, and only the rest reach Python (``take.SerializedTake.drain``, ``executor.take_waiting``).
 *
 * Why C: under a flood a node takes thousands of junk messages a second, and in Python each one
 * cost its take, a copy, an info dict and the callbacks that refuse it (about 15 us of the node's
 * main thread). Here each costs rcl's take and a few comparisons.
 *
 * rcl's take comes in as a function pointer (``rcl_take_serialized_message`` as rclpy loaded it,
 * found by ctypes) and the buffers as addresses (the ctypes structures of take.py, which mirror
 * rmw/types.h and rcutils/types/uint8_array.h of Jazzy): this file needs Python.h only, no ROS
 * headers or libraries at build time.
 *
 * A message is dropped here when it is over ``size_limit`` bytes, or when a ``window`` is given
 * (episode >= 0) and its header's (episode, step) is readable and outside it: another episode,
 * or a step outside [first_step, last_step]. Each dropped message leaves a record (its publisher's
 * gid and sequence number, why, and its length or its episode and step) for Python's counters.
 * Every other message (within the limit; in the window, or with no window, or with a header too
 * short to read, which Python counts as undecodable) stays in the buffer for Python.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

typedef struct { void *allocate, *deallocate, *reallocate, *zero_allocate, *state; } allocator_t;
typedef struct { uint8_t *buffer; size_t buffer_length; size_t buffer_capacity; allocator_t allocator; } serialized_t;
typedef struct { const char *implementation_identifier; uint8_t data[16]; } publisher_gid_t;
typedef struct {
    int64_t source_timestamp, received_timestamp;
    uint64_t publication_sequence_number, reception_sequence_number;
    publisher_gid_t publisher_gid;
    _Bool from_intra_process;
} message_info_t;
typedef int32_t (*take_t)(const void *subscription, serialized_t *message, message_info_t *info, void *allocation);

enum { QUEUE_EMPTY = 0, MESSAGE_WAITING = 1, MORE_MAY_WAIT = 2 };
enum { TOO_LARGE = 1, OUT_OF_WINDOW = 2 };
/* one record, little endian, no padding: gid (16), sequence number (8), cause (1), two uint32:
 * the length (too large) or the episode and the step (out of the window) */
#define RECORD_BYTES 33

static uint32_t read_uint32(const uint8_t *at, int little) {
    return little ? (uint32_t)at[0] | (uint32_t)at[1] << 8 | (uint32_t)at[2] << 16 | (uint32_t)at[3] << 24
                  : (uint32_t)at[3] | (uint32_t)at[2] << 8 | (uint32_t)at[1] << 16 | (uint32_t)at[0] << 24;
}

/* (episode, step) after a std_msgs/Header (step_gaps.episode_and_step); 0 if the bytes are too short */
static int episode_and_step(const uint8_t *cdr, size_t length, uint32_t *episode, uint32_t *step) {
    if (length < 16)
        return 0;
    int little = cdr[1] & 1;
    uint64_t frame_id = read_uint32(cdr + 12, little);
    uint64_t offset = 4 + (8 + 4 + frame_id + 3) / 4 * 4;
    if (offset + 8 > length)
        return 0;
    *episode = read_uint32(cdr + offset, little);
    *step = read_uint32(cdr + offset + 4, little);
    return 1;
}

static void put_uint32(uint8_t *at, uint32_t value) {
    for (int i = 0; i < 4; i++)
        at[i] = (uint8_t)(value >> 8 * i);
}

static void put_record(uint8_t *at, const message_info_t *info, uint8_t cause, uint32_t first, uint32_t second) {
    memcpy(at, info->publisher_gid.data, 16);
    for (int i = 0; i < 8; i++)
        at[16 + i] = (uint8_t)(info->publication_sequence_number >> 8 * i);
    at[24] = cause;
    put_uint32(at + 25, first);
    put_uint32(at + 29, second);
}

PyDoc_STRVAR(drain_doc,
"drain(take, subscription, message, info, size_limit, episode, first_step, last_step, records, most)\n"
"Take messages of ``subscription`` (addresses: rcl's take, the rcl subscription, the serialized\n"
"message and the message info it fills) until one is for Python, the queue is empty, ``records``\n"
"(a writable buffer) is full or ``most`` (0: no limit) were taken; drop those over ``size_limit``\n"
"and, with ``episode`` >= 0, those whose (episode, step) is outside (episode, first..last step).\n"
"Returns (status, records written): 0 the queue is empty, 1 a message waits in the buffer,\n"
"2 ``records`` is full or ``most`` were taken (more may wait).");

static PyObject *drain(PyObject *module, PyObject *args) {
    unsigned long long take_address, subscription, message_address, info_address;
    unsigned long long size_limit;
    long long episode, first_step, last_step;
    Py_ssize_t most;
    Py_buffer records;
    if (!PyArg_ParseTuple(args, "KKKKKLLLw*n", &take_address, &subscription, &message_address, &info_address,
                          &size_limit, &episode, &first_step, &last_step, &records, &most))
        return NULL;
    take_t take = (take_t)(uintptr_t)take_address;
    serialized_t *message = (serialized_t *)(uintptr_t)message_address;
    message_info_t *info = (message_info_t *)(uintptr_t)info_address;
    Py_ssize_t capacity = records.len / RECORD_BYTES, written = 0, taken = 0;
    if (capacity == 0) {
        PyBuffer_Release(&records);
        PyErr_SetString(PyExc_ValueError, "records: room for no record");
        return NULL;
    }
    int status = MORE_MAY_WAIT;
    Py_BEGIN_ALLOW_THREADS   /* rcl's take and plain bytes from here on: other threads may run */
    while (written < capacity && (most == 0 || taken < most)) {
        if (take((const void *)(uintptr_t)subscription, message, info, NULL) != 0) {
            status = QUEUE_EMPTY;
            break;
        }
        taken++;
        uint8_t *record = (uint8_t *)records.buf + written * RECORD_BYTES;
        size_t length = message->buffer_length;
        if (length > size_limit) {
            put_record(record, info, TOO_LARGE, length > UINT32_MAX ? UINT32_MAX : (uint32_t)length, 0);
            written++;
            continue;
        }
        uint32_t its_episode, step;
        if (episode >= 0 && episode_and_step(message->buffer, length, &its_episode, &step)
                && (its_episode != episode || step < first_step || step > last_step)) {
            put_record(record, info, OUT_OF_WINDOW, its_episode, step);
            written++;
            continue;
        }
        status = MESSAGE_WAITING;
        break;
    }
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&records);
    return Py_BuildValue("in", status, written);
}

static PyMethodDef methods[] = {
    {"drain", drain, METH_VARARGS, drain_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_drain", "Draining a subscription's queue in C (take.py).", -1, methods,
};

/* the statuses, causes and record size, for take.py: defined here only */
PyMODINIT_FUNC PyInit__drain(void) {
    PyObject *made = PyModule_Create(&module);
    if (made == NULL)
        return NULL;
    if (PyModule_AddIntConstant(made, "QUEUE_EMPTY", QUEUE_EMPTY) < 0
            || PyModule_AddIntConstant(made, "MESSAGE_WAITING", MESSAGE_WAITING) < 0
            || PyModule_AddIntConstant(made, "MORE_MAY_WAIT", MORE_MAY_WAIT) < 0
            || PyModule_AddIntConstant(made, "TOO_LARGE", TOO_LARGE) < 0
            || PyModule_AddIntConstant(made, "OUT_OF_WINDOW", OUT_OF_WINDOW) < 0
            || PyModule_AddIntConstant(made, "RECORD_BYTES", RECORD_BYTES) < 0) {
        Py_DECREF(made);
        return NULL;
    }
    return made;
}

/*
 * native_decoder.c - a chunk's JSON messages decoded into float64 columns in C (module
 * orchestrator.trace._decode), the read side's twin of native_encoder.c.
 *
 * orchestrator/trace/columns.py drives it. Reading a trace with Python's json module cost about 25 us a
 * message and the mcap stream reader's per-record Python about 20 us more: a trace took 5-11x the run that
 * wrote it. Here a chunk's decompressed records are walked once, with the GIL released:
 *
 * - a Message record whose channel has a slot and whose log time is in [t_lo, t_hi] is decoded;
 * - a JSON slot has a *skeleton*: the channel's first message with every number token replaced by one
 *   NUL byte (made by skeleton() below from that message, which Python has checked is an object of
 *   numbers). A message matches when it is that skeleton with a valid JSON number at each NUL: then the
 *   numbers are its values, in text order, which is the order of the keys Python read from the first
 *   message. Each number goes straight into its column (out[k * capacity + row]). A message that does not
 *   match (other keys, other spacing, NaN literals ...) is handed back for Python's json to decode, so
 *   any valid trace reads as Python's json reads it;
 * - a raw slot (the protobuf log) hands its messages back as bytes.
 *
 * Numbers are read as Python's float() reads them (correctly rounded): Clinger's exact fast path where
 * the digits fit 2^53 and the power of ten is exact; else, with x87 extended precision, one correctly
 * rounded operation on a 64-bit significand (below, ``extended_value``); else strtod in the C locale
 * (correctly rounded in glibc and the BSD libcs). An integer token that is zero ("-0") is +0.0, as
 * Python's int gives it.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <float.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#if defined(__GLIBC__) || defined(__APPLE__)
#include <locale.h>
#if defined(__APPLE__)
#include <xlocale.h>
#endif
#define HAVE_STRTOD_L 1
static locale_t c_locale;
#endif

/* --- numbers --------------------------------------------------------------------------------- */

static const double exact_pow10[23] = {
    1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11,
    1e12, 1e13, 1e14, 1e15, 1e16, 1e17, 1e18, 1e19, 1e20, 1e21, 1e22,
};

static inline int is_digit(unsigned char c) { return c >= '0' && c <= '9'; }

#if LDBL_MANT_DIG == 64 && (defined(__x86_64__) || defined(__i386__))
/* The shortest digits of a double are up to 17, beyond Clinger's 2^53: a trace's doubles went to strtod
 * four times in ten, ~1200 instructions each (a third of `platoon report`'s decoding). Their digits
 * (< 10^19 < 2^64) and 10^k for k <= 27 (5^27 < 2^63) are exact in the x87's 64-bit significand, so
 * r = digits * 10^e (or / 10^-e) is the true value x correctly rounded to 64 bits. Rounding is monotonic
 * and every point halfway between two adjacent doubles is exact in 64 bits, so x and r lie on the same
 * side of each such point unless r is one: then (double)r is x correctly rounded to a double, as strtod
 * gives it. When r is a halfway point (or the FPU does not round to 64 bits: extended_ok, checked at
 * import; valgrind, for one, computes in doubles), strtod decides. The range keeps every result normal. */
#define HAVE_EXTENDED 1
static int extended_ok;
static const long double exact_pow10_extended[28] = {
    1e0L, 1e1L, 1e2L, 1e3L, 1e4L, 1e5L, 1e6L, 1e7L, 1e8L, 1e9L, 1e10L, 1e11L, 1e12L, 1e13L,
    1e14L, 1e15L, 1e16L, 1e17L, 1e18L, 1e19L, 1e20L, 1e21L, 1e22L, 1e23L, 1e24L, 1e25L, 1e26L, 1e27L,
};

/* digits * 10^exponent10 correctly rounded to a double, in *value; 0 on success, -1 to ask strtod. */
static int extended_value(uint64_t digits, int exponent10, double *value)
{
    if (!extended_ok || exponent10 < -27 || exponent10 > 27) return -1;
    long double r = (long double)digits;
    r = exponent10 < 0 ? r / exact_pow10_extended[-exponent10] : r * exact_pow10_extended[exponent10];
    double d = (double)r;
    if ((long double)d != r) {
        double other = nextafter(d, r > (long double)d ? INFINITY : -INFINITY);
        if (r == ((long double)d + (long double)other) / 2.0L) return -1;  /* a tie: strtod */
    }
    *value = d;
    return 0;
}

static int check_extended(void)
{
    volatile long double one = 1.0L, tiny = 0x1p-63L;  /* 1 + 2^-63 exists only with 64-bit rounding */
    return one + tiny != one;
}
#endif

/* The end of the JSON number token at text[0..], or 0 if none starts there (RFC 8259's grammar). */
static size_t number_end(const unsigned char *text, size_t n, int *is_integer)
{
    size_t i = 0;
    *is_integer = 1;
    if (i < n && text[i] == '-') i++;
    if (i >= n || !is_digit(text[i])) return 0;
    if (text[i] == '0') i++;
    else while (i < n && is_digit(text[i])) i++;
    if (i < n && text[i] == '.') {
        i++;
        if (i >= n || !is_digit(text[i])) return 0;
        while (i < n && is_digit(text[i])) i++;
        *is_integer = 0;
    }
    if (i < n && (text[i] == 'e' || text[i] == 'E')) {
        i++;
        if (i < n && (text[i] == '+' || text[i] == '-')) i++;
        if (i >= n || !is_digit(text[i])) return 0;
        while (i < n && is_digit(text[i])) i++;
        *is_integer = 0;
    }
    return i;
}

/* The double of a number token already checked by number_end; 0 on success. */
static int number_value(const unsigned char *text, size_t n, int is_integer, double *value)
{
    size_t i = 0;
    int negative = text[0] == '-';
    if (negative) i++;
    uint64_t digits = 0;
    int significant = 0, exponent10 = 0;
    for (; i < n && is_digit(text[i]); i++) {
        if (significant < 19) {
            digits = digits * 10 + (uint64_t)(text[i] - '0');
            if (digits) significant++;
        } else {
            significant = 99;  /* too many digits for the fast path */
        }
    }
    if (i < n && text[i] == '.') {
        for (i++; i < n && is_digit(text[i]); i++) {
            if (significant < 19) {
                digits = digits * 10 + (uint64_t)(text[i] - '0');
                if (digits) significant++;
                exponent10--;
            } else {
                significant = 99;
            }
        }
    }
    if (digits == 0 && significant == 0) {  /* every digit is zero */
        *value = (negative && !is_integer) ? -0.0 : 0.0;
        return 0;
    }
    int explicit_exponent = 0, exponent_negative = 0, exponent_digits = 0;
    if (i < n && (text[i] == 'e' || text[i] == 'E')) {
        i++;
        if (text[i] == '+' || text[i] == '-') exponent_negative = text[i++] == '-';
        for (; i < n; i++) {
            if (explicit_exponent < 100000) explicit_exponent = explicit_exponent * 10 + (text[i] - '0');
            exponent_digits++;
        }
        exponent10 += exponent_negative ? -explicit_exponent : explicit_exponent;
    }
    if (significant <= 19 && digits <= (UINT64_C(1) << 53) && exponent10 >= -22 && exponent10 <= 22) {
        double v = (double)digits;  /* exact: digits <= 2^53 */
        v = exponent10 < 0 ? v / exact_pow10[-exponent10] : v * exact_pow10[exponent10];
        *value = negative ? -v : v;
        return 0;
    }
#ifdef HAVE_EXTENDED
    if (significant <= 19 && extended_value(digits, exponent10, value) == 0) {
        if (negative) *value = -*value;
        return 0;
    }
#endif
    char copy[64];
    if (n >= sizeof copy) return -1;  /* an absurdly long number: Python's json reads it */
    memcpy(copy, text, n);
    copy[n] = '\0';
#ifdef HAVE_STRTOD_L
    *value = strtod_l(copy, NULL, c_locale);
#else
    *value = strtod(copy, NULL);
#endif
    return 0;
}

/* --- skeletons --------------------------------------------------------------------------------- */

/* The end of the JSON string starting at text[0] == '"', or 0 if it does not end. */
static size_t string_end(const unsigned char *text, size_t n)
{
    for (size_t i = 1; i < n; i++) {
        if (text[i] == '\\') i++;
        else if (text[i] == '"') return i + 1;
    }
    return 0;
}

/*
 * Match `text` against `skeleton`; write its numbers to out[k * stride], k = 0 .. count-1. 1 when it
 * matches (every number written), 0 when not (some may be written: the caller redoes the row).
 */
static int match(const unsigned char *text, size_t n, const unsigned char *skeleton, size_t skeleton_length,
                 Py_ssize_t count, double *out, Py_ssize_t stride)
{
    size_t i = 0, j = 0;
    Py_ssize_t k = 0;
    if (count < 0) return 0;  /* a channel Python decodes whole */
    while (i < n) {
        unsigned char c = text[i];
        if (c == '"') {
            size_t end = string_end(text + i, n - i);
            if (end == 0 || j + end > skeleton_length || memcmp(text + i, skeleton + j, end) != 0) return 0;
            i += end;
            j += end;
        } else if (c == '-' || is_digit(c)) {
            int is_integer;
            size_t end = number_end(text + i, n - i, &is_integer);
            if (end == 0 || j >= skeleton_length || skeleton[j] != 0 || k >= count) return 0;
            if (number_value(text + i, end, is_integer, out + k * stride) != 0) return 0;
            k++;
            i += end;
            j++;
        } else {
            if (c == 0 || j >= skeleton_length || skeleton[j] != c) return 0;
            i++;
            j++;
        }
    }
    return j == skeleton_length && k == count;
}

static PyObject *py_skeleton(PyObject *self, PyObject *args)
{
    Py_buffer text;
    if (!PyArg_ParseTuple(args, "y*", &text)) return NULL;
    const unsigned char *t = text.buf;
    size_t n = (size_t)text.len, i = 0;
    unsigned char *out = PyMem_Malloc(n ? n : 1);
    if (out == NULL) {
        PyBuffer_Release(&text);
        return PyErr_NoMemory();
    }
    size_t length = 0;
    Py_ssize_t numbers = 0;
    int valid = 1;
    while (i < n && valid) {
        unsigned char c = t[i];
        if (c == '"') {
            size_t end = string_end(t + i, n - i);
            if (end == 0) valid = 0;
            else {
                memcpy(out + length, t + i, end);
                length += end;
                i += end;
            }
        } else if (c == '-' || is_digit(c)) {
            int is_integer;
            size_t end = number_end(t + i, n - i, &is_integer);
            if (end == 0) valid = 0;
            else {
                out[length++] = 0;
                numbers++;
                i += end;
            }
        } else if (c == 0) {
            valid = 0;
        } else {
            out[length++] = c;
            i++;
        }
    }
    PyBuffer_Release(&text);
    PyObject *result = valid ? Py_BuildValue("(y#n)", (const char *)out, (Py_ssize_t)length, numbers)
                             : Py_NewRef(Py_None);
    PyMem_Free(out);
    return result;
}

/* --- a chunk's records ----------------------------------------------------------------------------- */

enum { SLOT_NONE = -1 };
enum { TARGET_JSON = 0, TARGET_RAW = 1, TARGET_UNKNOWN = 2 };

typedef struct {
    int kind;
    Py_buffer skeleton, out, times;
    Py_ssize_t values, capacity, count;
} Target;

typedef struct {
    int slot;
    Py_ssize_t row;  /* JSON: the row to redo; raw: -1 */
    uint64_t log_time;
    size_t start, length;
} Handback;

typedef struct {
    Handback *items;
    size_t len, cap;
} Handbacks;

static int handback(Handbacks *h, Handback item)
{
    if (h->len == h->cap) {
        size_t cap = h->cap ? 2 * h->cap : 64;
        Handback *items = realloc(h->items, cap * sizeof *items);
        if (items == NULL) return -1;
        h->items = items;
        h->cap = cap;
    }
    h->items[h->len++] = item;
    return 0;
}

static inline uint64_t le64(const unsigned char *p)
{
    uint64_t v = 0;
    for (int i = 7; i >= 0; i--) v = (v << 8) | p[i];
    return v;
}

enum { STOP_DONE = 0, STOP_UNKNOWN = 1, STOP_FULL = 2, STOP_DAMAGED = 3, STOP_MEMORY = 4 };

/*
 * Walk records from `offset`; stop at the end, at a message of an UNKNOWN slot (its offset in *at, the
 * caller makes the slot and calls again from there), at a JSON slot that is full, or at a damaged record.
 */
static int walk(const unsigned char *data, size_t n, size_t offset, const int *slots, size_t channels,
                Target *targets, uint64_t t_lo, uint64_t t_hi, Handbacks *handbacks, size_t *at, int *stop_slot)
{
    size_t pos = offset;
    while (pos < n) {
        if (n - pos < 9) {
            *at = pos;
            return STOP_DAMAGED;
        }
        uint64_t length = le64(data + pos + 1);
        size_t body = pos + 9;
        if (length > n - body) {
            *at = pos;
            return STOP_DAMAGED;
        }
        if (data[pos] == 0x05) {
            if (length < 22) {
                *at = pos;
                return STOP_DAMAGED;
            }
            unsigned channel = (unsigned)data[body] | ((unsigned)data[body + 1] << 8);
            int slot = channel < channels ? slots[channel] : SLOT_NONE;
            uint64_t log_time = le64(data + body + 6);
            if (slot != SLOT_NONE && log_time >= t_lo && log_time <= t_hi) {
                Target *target = &targets[slot];
                size_t start = body + 22, size = (size_t)length - 22;
                if (target->kind == TARGET_UNKNOWN) {
                    *at = pos;
                    *stop_slot = slot;
                    return STOP_UNKNOWN;
                }
                if (target->kind == TARGET_RAW) {
                    if (handback(handbacks, (Handback){slot, -1, log_time, start, size}) < 0) return STOP_MEMORY;
                } else {
                    if (target->count >= target->capacity) {
                        *at = pos;
                        *stop_slot = slot;
                        return STOP_FULL;
                    }
                    double *column = (double *)target->out.buf + target->count;
                    if (!match(data + start, size, target->skeleton.buf, (size_t)target->skeleton.len,
                               target->values, column, target->capacity)) {
                        if (handback(handbacks, (Handback){slot, target->count, log_time, start, size}) < 0)
                            return STOP_MEMORY;
                    }
                    ((uint64_t *)target->times.buf)[target->count] = log_time;
                    target->count++;
                }
            }
        }
        pos = body + (size_t)length;
    }
    *at = pos;
    return STOP_DONE;
}

static void release_targets(Target *targets, Py_ssize_t n)
{
    for (Py_ssize_t i = 0; i < n; i++) {
        if (targets[i].kind == TARGET_JSON) {
            PyBuffer_Release(&targets[i].skeleton);
            PyBuffer_Release(&targets[i].out);
            PyBuffer_Release(&targets[i].times);
        }
    }
    PyMem_Free(targets);
}

/* Each target: None (not known yet), "raw", or (skeleton, values, out, times, capacity, count). */
static Target *read_targets(PyObject *list, Py_ssize_t *count)
{
    PyObject *seq = PySequence_Fast(list, "targets must be a sequence");
    if (seq == NULL) return NULL;
    Py_ssize_t n = PySequence_Fast_GET_SIZE(seq);
    Target *targets = PyMem_Calloc(n ? (size_t)n : 1, sizeof *targets);
    if (targets == NULL) {
        Py_DECREF(seq);
        PyErr_NoMemory();
        return NULL;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *item = PySequence_Fast_GET_ITEM(seq, i);
        if (item == Py_None) {
            targets[i].kind = TARGET_UNKNOWN;
        } else if (PyUnicode_Check(item)) {
            targets[i].kind = TARGET_RAW;
        } else {
            Target *t = &targets[i];
            t->kind = TARGET_UNKNOWN;  /* until its buffers are held */
            if (!PyArg_ParseTuple(item, "y*w*w*nnn", &t->skeleton, &t->out, &t->times, &t->values, &t->capacity,
                                  &t->count)) {
                release_targets(targets, i);
                Py_DECREF(seq);
                return NULL;
            }
            t->kind = TARGET_JSON;
            if (t->out.len < (Py_ssize_t)sizeof(double) * t->values * t->capacity ||
                t->times.len < (Py_ssize_t)sizeof(uint64_t) * t->capacity || t->count < 0 || t->count > t->capacity) {
                release_targets(targets, i + 1);
                Py_DECREF(seq);
                PyErr_SetString(PyExc_ValueError, "a target's buffers are smaller than its capacity");
                return NULL;
            }
        }
    }
    Py_DECREF(seq);
    *count = n;
    return targets;
}

static const char decode_doc[] =
    "decode(records, offset, slots, targets, t_lo, t_hi) -> (stop, at, slot, counts, handbacks)\n\n"
    "Decode a chunk's records from `offset`. slots: per channel id, its target's index or -1. targets: per\n"
    "slot None (not known yet), 'raw', or (skeleton, out float64, times int64, values, capacity, count);\n"
    "values -1: every message handed back.\n"
    "stop: 0 done, 1 a message of an unknown slot at `at` (slot `slot`), 2 slot `slot` full at `at`, 3 a\n"
    "damaged record at `at`. counts: each JSON target's new count. handbacks: (slot, row, log_time, start,\n"
    "length) of each message for Python to decode (row -1: a raw slot's message).";

static PyObject *py_decode(PyObject *self, PyObject *args)
{
    Py_buffer records;
    Py_ssize_t offset;
    PyObject *slot_list, *target_list;
    unsigned long long t_lo, t_hi;
    if (!PyArg_ParseTuple(args, "y*nOOKK", &records, &offset, &slot_list, &target_list, &t_lo, &t_hi)) return NULL;
    PyObject *result = NULL;
    int *slots = NULL;
    Target *targets = NULL;
    Py_ssize_t target_count = 0;
    Handbacks handbacks = {0};
    PyObject *seq = PySequence_Fast(slot_list, "slots must be a sequence");
    if (seq == NULL) goto done;
    Py_ssize_t channels = PySequence_Fast_GET_SIZE(seq);
    slots = PyMem_Malloc((channels ? (size_t)channels : 1) * sizeof *slots);
    if (slots == NULL) {
        PyErr_NoMemory();
        Py_DECREF(seq);
        goto done;
    }
    for (Py_ssize_t i = 0; i < channels; i++) {
        long slot = PyLong_AsLong(PySequence_Fast_GET_ITEM(seq, i));
        if (slot == -1 && PyErr_Occurred()) {
            Py_DECREF(seq);
            goto done;
        }
        slots[i] = (int)slot;
    }
    Py_DECREF(seq);
    targets = read_targets(target_list, &target_count);
    if (targets == NULL) goto done;
    for (Py_ssize_t i = 0; i < channels; i++) {
        if (slots[i] >= target_count || slots[i] < SLOT_NONE) {
            PyErr_SetString(PyExc_ValueError, "a slot has no target");
            goto done;
        }
    }
    if (offset < 0 || offset > records.len) {
        PyErr_SetString(PyExc_ValueError, "offset outside the records");
        goto done;
    }
    size_t at = 0;
    int stop_slot = -1, stop;
    Py_BEGIN_ALLOW_THREADS
    stop = walk(records.buf, (size_t)records.len, (size_t)offset, slots, (size_t)channels, targets, t_lo, t_hi,
                &handbacks, &at, &stop_slot);
    Py_END_ALLOW_THREADS
    if (stop == STOP_MEMORY) {
        PyErr_NoMemory();
        goto done;
    }
    PyObject *counts = PyList_New(target_count);
    PyObject *backs = PyList_New((Py_ssize_t)handbacks.len);
    if (counts == NULL || backs == NULL) {
        Py_XDECREF(counts);
        Py_XDECREF(backs);
        goto done;
    }
    for (Py_ssize_t i = 0; i < target_count; i++)
        PyList_SET_ITEM(counts, i, PyLong_FromSsize_t(targets[i].kind == TARGET_JSON ? targets[i].count : 0));
    for (size_t i = 0; i < handbacks.len; i++) {
        Handback *h = &handbacks.items[i];
        PyList_SET_ITEM(backs, (Py_ssize_t)i, Py_BuildValue("(inKnn)", h->slot, h->row, (unsigned long long)h->log_time,
                                                            (Py_ssize_t)h->start, (Py_ssize_t)h->length));
    }
    result = Py_BuildValue("(innNN)", stop, (Py_ssize_t)at, (Py_ssize_t)stop_slot, counts, backs);
done:
    free(handbacks.items);
    if (targets) release_targets(targets, target_count);
    PyMem_Free(slots);
    PyBuffer_Release(&records);
    return result;
}

static PyMethodDef module_methods[] = {
    {"decode", py_decode, METH_VARARGS, decode_doc},
    {"skeleton", py_skeleton, METH_VARARGS,
     "skeleton(text) -> (skeleton, numbers) or None: the JSON text with each number token replaced by a NUL."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef decode_module = {
    PyModuleDef_HEAD_INIT, "_decode", "A trace chunk's JSON messages into float64 columns (native_decoder.c).", -1,
    module_methods,
};

PyMODINIT_FUNC PyInit__decode(void)
{
#ifdef HAVE_EXTENDED
    extended_ok = check_extended();
#endif
#ifdef HAVE_STRTOD_L
    c_locale = newlocale(LC_ALL_MASK, "C", (locale_t)0);
    if (c_locale == (locale_t)0) return PyErr_NoMemory();
#endif
    return PyModule_Create(&decode_module);
}

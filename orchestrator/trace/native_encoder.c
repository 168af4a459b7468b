/*
 * native_encoder.c - the trace's per-row messages encoded in C (module orchestrator.trace._native).
 *
 * orchestrator/trace/native_rows.py drives it; orchestrator/trace/encoding.py and foxglove.py stay the
 * reference, and the messages written here are byte for byte theirs (tests/test_trace_native.py):
 *
 * - each component's JSON row, `{"t":..,"x":..,...}`, from the key pieces ComponentMessages makes;
 * - /platoon/errors (JSON): per vehicle the path's signed distance, gap - d*, speed - V_c;
 * - at the scene's rate /platoon/tf (foxglove.FrameTransforms) and /platoon/scene (foxglove.SceneUpdate),
 *   protobuf as the foxglove SDK (prost) writes it: fields in number order, zero numbers, false and
 *   empty strings left out, every present sub-message written (even empty);
 * - the MCAP Message records framing them, and the message index entries of the chunk.
 *
 * Channels come in chunk groups (orchestrator/trace/format.py: chunk_group): each group's messages go
 * to a records buffer of their own, framed for that group's chunk, so a reader of one group never
 * decompresses the others.
 *
 * Numbers are written as orjson writes them (orchestrator/trace/format.py: number_texts): the
 * shortest text that reads back as the same double, the closest such text when several, fixed
 * notation for decimal exponents -5 ... 15 (".0" for an integer), else d.ddde+E / d.ddde-E. The
 * shortest digits come from exact integer arithmetic (below: shortest_digits) for 1e-22 <= |x| < 2^53,
 * and from CPython's own repr (David Gay's dtoa) outside that range.
 *
 * Rows arrive as one buffer of float64 (the native engine's block, or the bytes the trace worker
 * received): no Python object per value. The caller finalizes chunks (compression, chunk index);
 * encode() stops after the row that takes a group's chunk past its size.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <string.h>

#include "pymath.h" /* py_hypot: math.hypot to the last bit (fmus/native) */

/* --- a growable byte buffer ------------------------------------------------------------------- */

typedef struct {
    char *data;
    size_t len, cap;
} Buf;

static int buf_reserve(Buf *b, size_t extra)
{
    if (b->len + extra <= b->cap) return 0;
    size_t cap = b->cap ? b->cap : 4096;
    while (cap < b->len + extra) cap *= 2;
    char *data = PyMem_Realloc(b->data, cap);
    if (data == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    b->data = data;
    b->cap = cap;
    return 0;
}

static inline int buf_put(Buf *b, const void *data, size_t n)
{
    if (buf_reserve(b, n) < 0) return -1;
    memcpy(b->data + b->len, data, n);
    b->len += n;
    return 0;
}

static inline void put_u16(char *p, uint16_t v) { p[0] = (char)v; p[1] = (char)(v >> 8); }
static inline void put_u32(char *p, uint32_t v) { for (int i = 0; i < 4; i++) p[i] = (char)(v >> (8 * i)); }
static inline void put_u64(char *p, uint64_t v) { for (int i = 0; i < 8; i++) p[i] = (char)(v >> (8 * i)); }

/* --- numbers as orjson writes them ------------------------------------------------------------ */

typedef unsigned __int128 u128;

#define MAX_K 38 /* 10^38 < 2^127 */

static u128 POW10[MAX_K + 1];

static void init_pow10(void)
{
    POW10[0] = 1;
    for (int i = 1; i <= MAX_K; i++) POW10[i] = POW10[i - 1] * 10;
}

/* floor(a b / 2^shift) for 1 <= shift < 192, the quotient known to fit 64 bits (a b has at most 192);
 * *inexact: whether the division leaves a remainder. */
static inline uint64_t mul_shift(uint64_t a, u128 b, int shift, int *inexact)
{
    u128 low = (u128)a * (uint64_t)b, high = (u128)a * (uint64_t)(b >> 64);
    u128 middle = (low >> 64) + (uint64_t)high;
    uint64_t p0 = (uint64_t)low, p1 = (uint64_t)middle, p2 = (uint64_t)(high >> 64) + (uint64_t)(middle >> 64);
    u128 top = (u128)p2 << 64 | p1; /* a b = top 2^64 + p0 */
    if (shift >= 64) {
        int t = shift - 64;
        *inexact = p0 != 0 || (top & (((u128)1 << t) - 1)) != 0;
        return (uint64_t)(top >> t);
    }
    u128 bottom = (u128)p1 << 64 | p0; /* p2 is 0: the quotient fits 64 bits */
    *inexact = (bottom & (((u128)1 << shift) - 1)) != 0;
    return (uint64_t)(bottom >> shift);
}

/* The shortest decimal digits of x > 0 (closest to x among the shortest) by exact integer
 * arithmetic: x = m 2^e is scaled by 10^k to 17 integer digits, and the rounding interval of x
 * (ties to even: an even m keeps its bounds) is searched for the multiple of the largest power of
 * ten it holds. Returns 0 outside 1e-22 <= x < 2^53 (10^k or the shift out of range); else the
 * digits (no trailing zeros) in *digits, x being about *digits 10^*scale. */
static int shortest_digits(double x, uint64_t *digits, int *scale)
{
    uint64_t bits;
    memcpy(&bits, &x, 8);
    int biased = (int)((bits >> 52) & 0x7ff);
    uint64_t fraction = bits & ((1ULL << 52) - 1);
    if (biased == 0) return 0; /* subnormal */
    uint64_t m = fraction | (1ULL << 52);
    int e = biased - 1075; /* x = m 2^e */
    if (e > -1 || x < 1e-22) return 0;
    int estimate = ((biased - 1023) * 78913) >> 18; /* floor(log10(2) (biased - 1023)): log10(x) or one below */
    int s = -e, rest; /* s: 1 ... 126 */
    for (int attempt = 0; attempt < 3; attempt++) {
        int k = 16 - estimate;
        if (k < 0 || k > MAX_K) return 0;
        uint64_t center = mul_shift(m, POW10[k], s, &rest); /* x 10^k, rounded down */
        if (center < (uint64_t)POW10[16]) { estimate--; continue; }
        if (center >= (uint64_t)POW10[17]) { estimate++; continue; }
        /* the interval [x - low gap, x + ulp/2] scaled: numerators over 2^(s + 2); its integer bounds,
         * the scaled x and all candidates below are under 2 10^17 */
        int low_rest, high_rest, twice_rest;
        uint64_t low = mul_shift(fraction == 0 && biased > 1 ? 4 * m - 1 : 4 * m - 2, POW10[k], s + 2, &low_rest);
        uint64_t high = mul_shift(4 * m + 2, POW10[k], s + 2, &high_rest);
        int inclusive = (m & 1) == 0;
        uint64_t lo = low + (inclusive ? low_rest != 0 : 1);
        uint64_t hi = high - (inclusive ? 0 : high_rest == 0);
        uint64_t twice_whole = mul_shift(2 * m, POW10[k], s, &twice_rest); /* 2 x 10^k, rounded down */
        /* the largest power of ten with a multiple in [lo, hi] (one at 10^0: the interval is wider than 1) */
        uint64_t p = 1, lo_j = lo, hi_j = hi;
        int power = 0;
        for (;;) {
            uint64_t lo_next = lo_j / 10 + (lo_j % 10 != 0), hi_next = hi_j / 10;
            if (lo_next > hi_next) break;
            lo_j = lo_next;
            hi_j = hi_next;
            p *= 10;
            power++;
        }
        /* the multiples of p around x: a (below) and a + 1 (above); either has no trailing zero, else a
         * multiple of 10 p would be in the interval */
        uint64_t a = center / p, below = a * p, above = below + p, chosen;
        int has_below = below >= lo, has_above = above <= hi;
        if (has_below && has_above) {
            uint64_t sum = below + above;
            if (twice_whole < sum) chosen = a;
            else if (twice_whole > sum || twice_rest) chosen = a + 1;
            else chosen = a % 2 == 0 ? a : a + 1;
        } else {
            chosen = has_below ? a : a + 1;
        }
        *digits = chosen;
        *scale = power - k;
        return 1;
    }
    return 0;
}

/* The shortest digits from CPython's repr (any finite x > 0): float.__repr__'s text, taken apart. */
static int repr_digits(double x, uint64_t *digits, int *scale_out)
{
    char *text = PyOS_double_to_string(x, 'r', 0, 0, NULL);
    if (text == NULL) return -1;
    char d[40];
    int n = 0, point = -1;
    const char *p = text;
    for (; *p && *p != 'e' && n < 39; p++) {
        if (*p == '.') point = n;
        else d[n++] = *p;
    }
    if (point < 0) point = n;
    int scale = point - n + (*p == 'e' ? atoi(p + 1) : 0); /* x = int(d) 10^scale */
    PyMem_Free(text);
    int start = 0, end = n;
    while (start < n - 1 && d[start] == '0') start++;
    while (end > start + 1 && d[end - 1] == '0') { end--; scale++; }
    uint64_t c = 0;
    for (int i = start; i < end; i++) c = c * 10 + (uint64_t)(d[i] - '0');
    *digits = c;
    *scale_out = scale;
    return 0;
}

/* Writes x (finite) as orjson does; returns the length (at most 32), or -1 with an exception set. */
static int format_double(char *out, double x)
{
    char *p = out;
    if (signbit(x)) { *p++ = '-'; x = -x; }
    if (x == 0.0) { memcpy(p, "0.0", 3); return (int)(p - out) + 3; }
    uint64_t c;
    int scale;
    if (!shortest_digits(x, &c, &scale) && repr_digits(x, &c, &scale) < 0) return -1;
    static const char pairs[] = "00010203040506070809101112131415161718192021222324252627282930313233343536373839"
                                "40414243444546474849505152535455565758596061626364656667686970717273747576777879"
                                "8081828384858687888990919293949596979899";
    char text[24];
    int n = 0;
    /* eight digits at a time from 32-bit halves: their divisions do not wait on each other (one chain
     * of 64-bit divisions by 100 was a fifth of the encoder's time) */
    while (c >= 100000000) {
        uint64_t high = c / 100000000;
        uint32_t low = (uint32_t)(c - high * 100000000), upper = low / 10000, lower = low % 10000;
        c = high;
        memcpy(text + 16 - n, pairs + 2 * (upper / 100), 2);
        memcpy(text + 18 - n, pairs + 2 * (upper % 100), 2);
        memcpy(text + 20 - n, pairs + 2 * (lower / 100), 2);
        memcpy(text + 22 - n, pairs + 2 * (lower % 100), 2);
        n += 8;
    }
    uint32_t rest = (uint32_t)c; /* below 10^8 */
    while (rest >= 100) {
        unsigned pair = rest % 100;
        rest /= 100;
        n += 2;
        memcpy(text + 24 - n, pairs + 2 * pair, 2);
    }
    if (rest >= 10) {
        n += 2;
        memcpy(text + 24 - n, pairs + 2 * rest, 2);
    } else {
        text[24 - ++n] = (char)('0' + rest);
    }
    const char *digits = text + 24 - n;
    int exponent = scale + n - 1; /* of the first digit */
    if (exponent >= -5 && exponent <= 15) {
        if (exponent < 0) {
            *p++ = '0'; *p++ = '.';
            for (int i = -1; i > exponent; i--) *p++ = '0';
            memcpy(p, digits, n); p += n;
        } else if (n <= exponent + 1) {
            memcpy(p, digits, n); p += n;
            for (int i = n; i <= exponent; i++) *p++ = '0';
            *p++ = '.'; *p++ = '0';
        } else {
            memcpy(p, digits, exponent + 1); p += exponent + 1;
            *p++ = '.';
            memcpy(p, digits + exponent + 1, n - exponent - 1); p += n - exponent - 1;
        }
    } else {
        *p++ = digits[0];
        if (n > 1) { *p++ = '.'; memcpy(p, digits + 1, n - 1); p += n - 1; }
        *p++ = 'e';
        *p++ = exponent < 0 ? '-' : '+';
        int a = exponent < 0 ? -exponent : exponent;
        if (a >= 100) *p++ = (char)('0' + a / 100);
        if (a >= 10) *p++ = (char)('0' + a / 10 % 10);
        *p++ = (char)('0' + a % 10);
    }
    return (int)(p - out);
}

static inline int put_number(Buf *b, double x)
{
    if (buf_reserve(b, 40) < 0) return -1;
    int n = format_double(b->data + b->len, x);
    if (n < 0) return -1;
    b->len += (size_t)n;
    return 0;
}

/* format_double for Python: the tests hold it to orjson on millions of doubles */
static PyObject *py_format_double(PyObject *self, PyObject *arg)
{
    double x = PyFloat_AsDouble(arg);
    if (x == -1.0 && PyErr_Occurred()) return NULL;
    if (!isfinite(x)) {
        PyErr_SetString(PyExc_ValueError, "not a finite number");
        return NULL;
    }
    char out[40];
    int n = format_double(out, x);
    return n < 0 ? NULL : PyBytes_FromStringAndSize(out, n);
}

/* The first row of a flat float64 block holding nan or inf, or None: the stepping process checks each
   block before shipping it (orchestrator/trace/worker.py) without importing numpy for it. */
static PyObject *py_first_non_finite(PyObject *self, PyObject *args)
{
    PyObject *data;
    Py_ssize_t width;
    if (!PyArg_ParseTuple(args, "On", &data, &width)) return NULL;
    if (width < 1) {
        PyErr_SetString(PyExc_ValueError, "width must be >= 1");
        return NULL;
    }
    Py_buffer view;
    if (PyObject_GetBuffer(data, &view, PyBUF_C_CONTIGUOUS) < 0) return NULL;
    Py_ssize_t count = view.len / (Py_ssize_t)sizeof(double);
    if (view.len % (Py_ssize_t)sizeof(double) != 0 || count % width != 0) {
        PyBuffer_Release(&view);
        PyErr_Format(PyExc_ValueError, "%zd bytes are not whole rows of %zd doubles", view.len, width);
        return NULL;
    }
    const double *values = (const double *)view.buf;
    Py_ssize_t bad = -1;
    for (Py_ssize_t i = 0; i < count; i++) {
        double x;
        memcpy(&x, values + i, sizeof x); /* raw bytes need not be aligned */
        if (!isfinite(x)) {
            bad = i / width;
            break;
        }
    }
    PyBuffer_Release(&view);
    if (bad < 0) Py_RETURN_NONE;
    return PyLong_FromSsize_t(bad);
}

/* --- protobuf, as prost writes it --------------------------------------------------------------- */

static int pb_varint(Buf *b, uint64_t v)
{
    if (buf_reserve(b, 10) < 0) return -1;
    char *p = b->data + b->len;
    int n = 0;
    do {
        uint8_t byte = v & 0x7f;
        v >>= 7;
        p[n++] = (char)(v ? byte | 0x80 : byte);
    } while (v);
    b->len += (size_t)n;
    return 0;
}

static inline int pb_tag(Buf *b, int field, int wire) { return pb_varint(b, (uint64_t)(field << 3 | wire)); }

static int pb_double(Buf *b, int field, double v)
{
    if (v == 0.0) return 0; /* proto3: a zero (either sign) is not written */
    uint64_t bits;
    memcpy(&bits, &v, 8);
    if (pb_tag(b, field, 1) < 0 || buf_reserve(b, 8) < 0) return -1;
    put_u64(b->data + b->len, bits);
    b->len += 8;
    return 0;
}

static int pb_uint(Buf *b, int field, uint64_t v)
{
    if (v == 0) return 0;
    return pb_tag(b, field, 0) < 0 ? -1 : pb_varint(b, v);
}

static int pb_text(Buf *b, int field, const char *text, size_t n)
{
    if (n == 0) return 0;
    if (pb_tag(b, field, 2) < 0 || pb_varint(b, n) < 0) return -1;
    return buf_put(b, text, n);
}

/* A sub-message: write its fields after pb_begin, then pb_end puts the tag and length before them. */
static inline size_t pb_begin(Buf *b) { return b->len; }

static int pb_end(Buf *b, int field, size_t start)
{
    size_t length = b->len - start;
    char header[16];
    Buf h = {header, 0, sizeof header};
    uint64_t key = (uint64_t)(field << 3 | 2);
    for (int i = 0; i < 2; i++) {
        uint64_t v = i == 0 ? key : length;
        do {
            uint8_t byte = v & 0x7f;
            v >>= 7;
            header[h.len++] = (char)(v ? byte | 0x80 : byte);
        } while (v);
    }
    if (buf_reserve(b, h.len) < 0) return -1;
    memmove(b->data + start + h.len, b->data + start, length);
    memcpy(b->data + start, header, h.len);
    b->len += h.len;
    return 0;
}

static int pb_vector(Buf *b, int field, double x, double y, double z)
{
    size_t start = pb_begin(b);
    if (pb_double(b, 1, x) < 0 || pb_double(b, 2, y) < 0 || pb_double(b, 3, z) < 0) return -1;
    return pb_end(b, field, start);
}

/* foxglove._quaternion(yaw) */
static int pb_yaw(Buf *b, int field, double yaw)
{
    size_t start = pb_begin(b);
    if (pb_double(b, 3, sin(0.5 * yaw)) < 0 || pb_double(b, 4, cos(0.5 * yaw)) < 0) return -1;
    return pb_end(b, field, start);
}

static int pb_color(Buf *b, int field, const double rgba[4])
{
    size_t start = pb_begin(b);
    for (int i = 0; i < 4; i++)
        if (pb_double(b, i + 1, rgba[i]) < 0) return -1;
    return pb_end(b, field, start);
}

static int pb_pose(Buf *b, int field, double x, double y, double z, double yaw)
{
    size_t start = pb_begin(b);
    if (pb_vector(b, 1, x, y, z) < 0 || pb_yaw(b, 2, yaw) < 0) return -1;
    return pb_end(b, field, start);
}

static int pb_timestamp(Buf *b, int field, int64_t stamp)
{
    size_t start = pb_begin(b);
    int64_t sec = stamp / 1000000000, nsec = stamp % 1000000000;
    if (nsec < 0) { nsec += 1000000000; sec -= 1; } /* Python's // and % */
    if (pb_uint(b, 1, (uint64_t)sec) < 0 || pb_uint(b, 2, (uint64_t)nsec) < 0) return -1;
    return pb_end(b, field, start);
}

/* --- the encoder ---------------------------------------------------------------------------------- */

#define ROOT_FRAME "world"
#define PATH_PIXELS 2.0
#define TRAIL_PIXELS 3.0
#define MARKER_PIXELS 9.0

typedef struct {
    uint16_t channel;
    Py_ssize_t start, count; /* the component's outputs: row[start ... start + count) */
    Py_ssize_t *piece_at;    /* count + 3 offsets into pieces: "{\"t\":", ",\"x\":", ..., "}" */
    char *pieces;
} Component;

typedef struct {
    Py_ssize_t ix, iy, ih; /* x, y, heading among the row's values */
    Py_ssize_t ig, iv;     /* gap, speed (vehicles) */
    int vehicle;
    char *name, *label;
    Py_ssize_t name_len, label_len;
    double solid[4], faded[4];
    double *trail; /* ring of (x, y), `history` long */
    Py_ssize_t trail_count, trail_head;
} Body;

typedef struct {
    Buf data;              /* records of one encode() call */
    Buf index;             /* its message index entries: (stamp, offset) */
    Py_ssize_t count;
} ChannelOut;

#define MAX_GROUPS 4 /* chunk groups (format.py: CHUNK_GROUPS) */

typedef struct {
    Buf records;           /* Message records of one encode() call, for this group's chunk */
    uint64_t position;     /* where in the group's chunk they start */
    int64_t first, last;   /* least and greatest log time written */
    Py_ssize_t messages;
} GroupOut;

typedef struct {
    PyObject_HEAD
    Py_ssize_t width;
    Py_ssize_t ncomponents;
    Component *components;
    /* the Foxglove channels (scene == 0: none) */
    int foxglove;
    uint16_t errors_channel, tf_channel, scene_channel;
    Py_ssize_t nbodies;
    Body *bodies;
    Py_ssize_t *errors_at; /* offsets of the errors JSON pieces */
    char *errors_pieces;
    int circle_distance;   /* the path's signed distance: circle (a, b, c = cx, cy, R) or line (ox, oy, heading) */
    double distance[3];
    double d_star, v_c, period, next_scene, size, label_offset;
    int circle_scene;      /* the scene's path: a circle (fixed points) or a line through the platoon */
    double center[2], heading;
    double *path_points;   /* circle: (x, y) pairs */
    Py_ssize_t npath;
    Py_ssize_t history;
    Py_ssize_t scenes;
    double white[4], grey[4];
    /* per encode() call */
    Py_ssize_t nchannels;  /* channel ids are < nchannels */
    ChannelOut *out;
    uint16_t *order;       /* channels in the order of their first message in the call (the Python writer's) */
    Py_ssize_t norder;
    uint8_t *group_of;     /* each channel's chunk group */
    Py_ssize_t ngroups;
    GroupOut groups[MAX_GROUPS];
    Buf *records;          /* the open message's group buffer */
    Buf scratch;
    Buf texts;
    Py_ssize_t *text_at;
} Encoder;

static void free_encoder(Encoder *self)
{
    for (Py_ssize_t i = 0; i < self->ncomponents && self->components; i++) {
        PyMem_Free(self->components[i].piece_at);
        PyMem_Free(self->components[i].pieces);
    }
    PyMem_Free(self->components);
    for (Py_ssize_t i = 0; i < self->nbodies && self->bodies; i++) {
        PyMem_Free(self->bodies[i].name);
        PyMem_Free(self->bodies[i].label);
        PyMem_Free(self->bodies[i].trail);
    }
    PyMem_Free(self->bodies);
    PyMem_Free(self->errors_at);
    PyMem_Free(self->errors_pieces);
    PyMem_Free(self->path_points);
    for (Py_ssize_t i = 0; i < self->nchannels && self->out; i++) PyMem_Free(self->out[i].index.data);
    PyMem_Free(self->out);
    PyMem_Free(self->order);
    PyMem_Free(self->group_of);
    for (int i = 0; i < MAX_GROUPS; i++) PyMem_Free(self->groups[i].records.data);
    PyMem_Free(self->scratch.data);
    PyMem_Free(self->texts.data);
    PyMem_Free(self->text_at);
}

static void Encoder_dealloc(Encoder *self)
{
    free_encoder(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* pieces: a sequence of bytes, concatenated into *joined with offsets *at (len + 1 of them) */
static int take_pieces(PyObject *sequence, char **joined, Py_ssize_t **at, Py_ssize_t expected)
{
    PyObject *fast = PySequence_Fast(sequence, "pieces must be a sequence of bytes");
    if (fast == NULL) return -1;
    Py_ssize_t n = PySequence_Fast_GET_SIZE(fast);
    if (n != expected) {
        PyErr_Format(PyExc_ValueError, "expected %zd pieces, got %zd", expected, n);
        Py_DECREF(fast);
        return -1;
    }
    Py_ssize_t total = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *piece = PySequence_Fast_GET_ITEM(fast, i);
        if (!PyBytes_Check(piece)) {
            PyErr_SetString(PyExc_TypeError, "pieces must be bytes");
            Py_DECREF(fast);
            return -1;
        }
        total += PyBytes_GET_SIZE(piece);
    }
    *joined = PyMem_Malloc((size_t)total + 1);
    *at = PyMem_Malloc(sizeof(Py_ssize_t) * (size_t)(n + 1));
    if (*joined == NULL || *at == NULL) {
        Py_DECREF(fast);
        PyErr_NoMemory();
        return -1;
    }
    Py_ssize_t offset = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *piece = PySequence_Fast_GET_ITEM(fast, i);
        (*at)[i] = offset;
        memcpy(*joined + offset, PyBytes_AS_STRING(piece), (size_t)PyBytes_GET_SIZE(piece));
        offset += PyBytes_GET_SIZE(piece);
    }
    (*at)[n] = offset;
    Py_DECREF(fast);
    return 0;
}

static int copy_text(PyObject *bytes, char **text, Py_ssize_t *length)
{
    char *data;
    if (PyBytes_AsStringAndSize(bytes, &data, length) < 0) return -1;
    *text = PyMem_Malloc((size_t)*length + 1);
    if (*text == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    memcpy(*text, data, (size_t)*length);
    return 0;
}

static int take_doubles(PyObject *sequence, double *out, Py_ssize_t n, const char *what)
{
    PyObject *fast = PySequence_Fast(sequence, what);
    if (fast == NULL) return -1;
    if (PySequence_Fast_GET_SIZE(fast) != n) {
        PyErr_Format(PyExc_ValueError, "%s: expected %zd numbers", what, n);
        Py_DECREF(fast);
        return -1;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        out[i] = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(fast, i));
        if (out[i] == -1.0 && PyErr_Occurred()) {
            Py_DECREF(fast);
            return -1;
        }
    }
    Py_DECREF(fast);
    return 0;
}

static int init_bodies(Encoder *self, PyObject *bodies)
{
    PyObject *fast = PySequence_Fast(bodies, "bodies must be a sequence");
    if (fast == NULL) return -1;
    self->nbodies = PySequence_Fast_GET_SIZE(fast);
    self->bodies = PyMem_Calloc((size_t)self->nbodies + 1, sizeof(Body));
    if (self->bodies == NULL) {
        Py_DECREF(fast);
        PyErr_NoMemory();
        return -1;
    }
    for (Py_ssize_t i = 0; i < self->nbodies; i++) {
        Body *body = &self->bodies[i];
        PyObject *name, *label, *solid, *faded;
        if (!PyArg_ParseTuple(PySequence_Fast_GET_ITEM(fast, i), "nnnnnpSSOO", &body->ix, &body->iy, &body->ih,
                              &body->ig, &body->iv, &body->vehicle, &name, &label, &solid, &faded)
            || copy_text(name, &body->name, &body->name_len) < 0 || copy_text(label, &body->label, &body->label_len) < 0
            || take_doubles(solid, body->solid, 4, "solid colour") < 0
            || take_doubles(faded, body->faded, 4, "faded colour") < 0) {
            Py_DECREF(fast);
            return -1;
        }
        Py_ssize_t top = self->width;
        if (body->ix < 1 || body->ix >= top || body->iy < 1 || body->iy >= top || body->ih < 1 || body->ih >= top
            || (body->vehicle && (body->ig < 1 || body->ig >= top || body->iv < 1 || body->iv >= top))) {
            PyErr_SetString(PyExc_ValueError, "a body's value index is outside the row");
            Py_DECREF(fast);
            return -1;
        }
        if (body->vehicle) {
            body->trail = PyMem_Malloc(sizeof(double) * 2 * (size_t)self->history);
            if (body->trail == NULL) {
                Py_DECREF(fast);
                PyErr_NoMemory();
                return -1;
            }
        }
    }
    Py_DECREF(fast);
    return 0;
}

static int init_foxglove(Encoder *self, PyObject *foxglove)
{
    PyObject *errors_pieces, *bodies, *points;
    int errors, tf, scene;
    if (!PyArg_ParseTuple(foxglove, "(iii)OO(pddd)(dddddd)n(pddd)O", &errors, &tf, &scene, &errors_pieces, &bodies,
                          &self->circle_distance, &self->distance[0], &self->distance[1], &self->distance[2],
                          &self->period, &self->next_scene, &self->size, &self->label_offset, &self->d_star, &self->v_c,
                          &self->history, &self->circle_scene, &self->center[0], &self->center[1], &self->heading,
                          &points))
        return -1;
    if (self->history < 1) {
        PyErr_SetString(PyExc_ValueError, "history must hold a point");
        return -1;
    }
    self->foxglove = 1;
    self->errors_channel = (uint16_t)errors;
    self->tf_channel = (uint16_t)tf;
    self->scene_channel = (uint16_t)scene;
    if (init_bodies(self, bodies) < 0) return -1;
    Py_ssize_t vehicles = 0;
    for (Py_ssize_t i = 0; i < self->nbodies; i++) vehicles += self->bodies[i].vehicle;
    if (take_pieces(errors_pieces, &self->errors_pieces, &self->errors_at, 3 * vehicles + 2) < 0) return -1;
    if (self->circle_scene) {
        Py_ssize_t n = PySequence_Size(points);
        if (n < 0) return -1;
        self->npath = n / 2;
        self->path_points = PyMem_Malloc(sizeof(double) * (size_t)(n + 1));
        if (self->path_points == NULL) {
            PyErr_NoMemory();
            return -1;
        }
        if (take_doubles(points, self->path_points, n, "path points") < 0) return -1;
    }
    for (int i = 0; i < 4; i++) self->white[i] = 1.0;
    self->grey[0] = self->grey[1] = self->grey[2] = 0.6;
    self->grey[3] = 1.0;
    return 0;
}

static int init_components(Encoder *self, PyObject *components)
{
    PyObject *fast = PySequence_Fast(components, "components must be a sequence");
    if (fast == NULL) return -1;
    self->ncomponents = PySequence_Fast_GET_SIZE(fast);
    self->components = PyMem_Calloc((size_t)self->ncomponents + 1, sizeof(Component));
    if (self->components == NULL) {
        Py_DECREF(fast);
        PyErr_NoMemory();
        return -1;
    }
    for (Py_ssize_t i = 0; i < self->ncomponents; i++) {
        Component *c = &self->components[i];
        int channel;
        PyObject *pieces;
        if (!PyArg_ParseTuple(PySequence_Fast_GET_ITEM(fast, i), "innO", &channel, &c->start, &c->count, &pieces)
            || take_pieces(pieces, &c->pieces, &c->piece_at, c->count + 2) < 0) {
            Py_DECREF(fast);
            return -1;
        }
        if (c->start < 1 || c->count < 0 || c->start + c->count > self->width) {
            PyErr_SetString(PyExc_ValueError, "a component's outputs are outside the row");
            Py_DECREF(fast);
            return -1;
        }
        c->channel = (uint16_t)channel;
    }
    Py_DECREF(fast);
    return 0;
}

/* groups: each channel id's chunk group (0 for ids past its end) */
static int init_groups(Encoder *self, PyObject *groups)
{
    PyObject *fast = PySequence_Fast(groups, "groups must be a sequence of chunk groups, one per channel id");
    if (fast == NULL) return -1;
    Py_ssize_t n = PySequence_Fast_GET_SIZE(fast);
    for (Py_ssize_t i = 0; i < n && i < self->nchannels; i++) {
        long group = PyLong_AsLong(PySequence_Fast_GET_ITEM(fast, i));
        if (group == -1 && PyErr_Occurred()) {
            Py_DECREF(fast);
            return -1;
        }
        if (group < 0 || group >= MAX_GROUPS) {
            Py_DECREF(fast);
            PyErr_Format(PyExc_ValueError, "a chunk group must be 0 ... %d", MAX_GROUPS - 1);
            return -1;
        }
        self->group_of[i] = (uint8_t)group;
        if (group + 1 > self->ngroups) self->ngroups = group + 1;
    }
    Py_DECREF(fast);
    return 0;
}

static int Encoder_init(Encoder *self, PyObject *args, PyObject *kwargs)
{
    PyObject *components, *foxglove, *groups = NULL;
    static char *keywords[] = {"width", "components", "foxglove", "groups", NULL};
    if (self->components != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "an Encoder is set up once");
        return -1;
    }
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "nOO|O", keywords, &self->width, &components, &foxglove,
                                     &groups))
        return -1;
    if (self->width < 1) {
        PyErr_SetString(PyExc_ValueError, "width must be at least 1");
        return -1;
    }
    if (init_components(self, components) < 0) return -1;
    if (foxglove != Py_None && init_foxglove(self, foxglove) < 0) return -1;
    int top = 0;
    for (Py_ssize_t i = 0; i < self->ncomponents; i++) top = top > self->components[i].channel ? top : self->components[i].channel;
    if (self->foxglove) {
        int ids[3] = {self->errors_channel, self->tf_channel, self->scene_channel};
        for (int i = 0; i < 3; i++) top = top > ids[i] ? top : ids[i];
    }
    self->nchannels = top + 1;
    self->out = PyMem_Calloc((size_t)self->nchannels, sizeof(ChannelOut));
    self->order = PyMem_Calloc((size_t)self->nchannels, sizeof(uint16_t));
    self->text_at = PyMem_Malloc(sizeof(Py_ssize_t) * (size_t)(self->width + 3 * self->nbodies + 2));
    self->group_of = PyMem_Calloc((size_t)self->nchannels, 1);
    if (self->out == NULL || self->order == NULL || self->text_at == NULL || self->group_of == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    self->ngroups = 1;
    return groups == NULL || groups == Py_None ? 0 : init_groups(self, groups);
}

/* --- one row's messages ------------------------------------------------------------------------- */

#define HEADER 31 /* a Message record's opcode, length, channel, sequence, log time, publish time */

static int begin_message(Encoder *self, uint16_t channel, uint32_t sequence, int64_t stamp, size_t *at)
{
    Buf *b = self->records = &self->groups[self->group_of[channel]].records;
    if (buf_reserve(b, HEADER) < 0) return -1;
    char *p = b->data + b->len;
    p[0] = 0x05;
    put_u16(p + 9, channel);
    put_u32(p + 11, sequence);
    put_u64(p + 15, (uint64_t)stamp);
    put_u64(p + 23, (uint64_t)stamp);
    *at = b->len;
    b->len += HEADER;
    return 0;
}

static int end_message(Encoder *self, uint16_t channel, int64_t stamp, size_t at)
{
    GroupOut *group = &self->groups[self->group_of[channel]];
    put_u64(group->records.data + at + 1, (uint64_t)(group->records.len - at - 9));
    if (group->messages++ == 0 || stamp < group->first) group->first = stamp;
    if (group->messages == 1 || stamp > group->last) group->last = stamp;
    ChannelOut *out = &self->out[channel];
    if (buf_reserve(&out->index, 16) < 0) return -1;
    put_u64(out->index.data + out->index.len, (uint64_t)stamp);
    put_u64(out->index.data + out->index.len + 8, group->position + at);
    out->index.len += 16;
    if (out->count++ == 0) self->order[self->norder++] = channel;
    return 0;
}

/* fmus.model.paths: CirclePath.signed_distance / LinePath.signed_distance */
static double signed_distance(const Encoder *self, double x, double y)
{
    if (self->circle_distance) return py_hypot(x - self->distance[0], y - self->distance[1]) - self->distance[2];
    double dx = x - self->distance[0], dy = y - self->distance[1];
    return dx * sin(self->distance[2]) - dy * cos(self->distance[2]);
}

/* FoxgloveChannels.errors_message; 1 when a value is not finite (the row is not written) */
static int errors_message(Encoder *self, const double *row, uint32_t sequence, int64_t stamp)
{
    Py_ssize_t vehicles = 0;
    double values[3];
    double sum = row[0];
    Buf *texts = &self->scratch;
    texts->len = 0;
    Py_ssize_t *at = self->text_at, n = 0;
    at[n++] = 0;
    if (put_number(texts, row[0]) < 0) return -1;
    for (Py_ssize_t i = 0; i < self->nbodies; i++) {
        const Body *body = &self->bodies[i];
        if (!body->vehicle) continue;
        values[0] = signed_distance(self, row[body->ix], row[body->iy]);
        values[1] = row[body->ig] - self->d_star;
        values[2] = row[body->iv] - self->v_c;
        for (int j = 0; j < 3; j++) {
            sum += values[j];
            at[n++] = (Py_ssize_t)texts->len;
            if (isfinite(values[j]) && put_number(texts, values[j]) < 0) return -1;
        }
        vehicles++;
    }
    at[n] = (Py_ssize_t)texts->len;
    if (!isfinite(sum)) return 1;
    size_t start;
    if (begin_message(self, self->errors_channel, sequence, stamp, &start) < 0) return -1;
    Py_ssize_t count = 3 * vehicles + 1;
    for (Py_ssize_t i = 0; i < count; i++) {
        if (buf_put(self->records, self->errors_pieces + self->errors_at[i],
                    (size_t)(self->errors_at[i + 1] - self->errors_at[i])) < 0
            || buf_put(self->records, texts->data + at[i], (size_t)(at[i + 1] - at[i])) < 0)
            return -1;
    }
    if (buf_put(self->records, self->errors_pieces + self->errors_at[count],
                (size_t)(self->errors_at[count + 1] - self->errors_at[count])) < 0)
        return -1;
    return end_message(self, self->errors_channel, stamp, start);
}

/* FoxgloveChannels.advance: at a scene tick, the vehicles' positions join their trails; 1 then */
static int advance(Encoder *self, double time, const double *row)
{
    if (time < self->next_scene - 1e-9) return 0;
    for (Py_ssize_t i = 0; i < self->nbodies; i++) {
        Body *body = &self->bodies[i];
        if (!body->vehicle) continue;
        Py_ssize_t slot = (body->trail_head + body->trail_count) % self->history;
        if (body->trail_count == self->history) body->trail_head = (body->trail_head + 1) % self->history;
        else body->trail_count++;
        body->trail[2 * slot] = row[body->ix];
        body->trail[2 * slot + 1] = row[body->iy];
    }
    while (self->next_scene <= time + 1e-9) self->next_scene += self->period;
    return 1;
}

static int transforms_message(Encoder *self, const double *row, uint32_t sequence, int64_t stamp)
{
    size_t start;
    if (begin_message(self, self->tf_channel, sequence, stamp, &start) < 0) return -1;
    Buf *b = self->records;
    for (Py_ssize_t i = 0; i < self->nbodies; i++) {
        const Body *body = &self->bodies[i];
        double x = row[body->ix], y = row[body->iy], heading = row[body->ih];
        size_t transform = pb_begin(b);
        if (pb_timestamp(b, 1, stamp) < 0 || pb_text(b, 2, ROOT_FRAME, 5) < 0
            || pb_text(b, 3, body->name, (size_t)body->name_len) < 0 || pb_vector(b, 4, x, y, 0.0) < 0
            || pb_yaw(b, 5, heading) < 0 || pb_end(b, 1, transform) < 0)
            return -1;
    }
    return end_message(self, self->tf_channel, stamp, start);
}

static int line_primitive(Buf *b, int type, double thickness, const double *xy, Py_ssize_t n, Py_ssize_t head,
                          Py_ssize_t ring, const double *z, const double color[4])
{
    size_t line = pb_begin(b);
    if (pb_uint(b, 1, (uint64_t)type) < 0 || pb_double(b, 3, thickness) < 0 || pb_uint(b, 4, 1) < 0) return -1;
    for (Py_ssize_t i = 0; i < n; i++) {
        Py_ssize_t k = ring ? (head + i) % ring : i;
        if (pb_vector(b, 5, xy[2 * k], xy[2 * k + 1], z ? z[k] : 0.0) < 0) return -1;
    }
    if (pb_color(b, 6, color) < 0) return -1;
    return pb_end(b, 11, line);
}

/* the path entity: FoxgloveChannels._scene's first entity (_circle_points or _line_points) */
static int path_entity(Encoder *self, const double *row, int64_t stamp)
{
    Buf *b = self->records;
    size_t entity = pb_begin(b);
    if (pb_timestamp(b, 1, stamp) < 0 || pb_text(b, 2, ROOT_FRAME, 5) < 0 || pb_text(b, 3, "path", 4) < 0) return -1;
    if (self->circle_scene) {
        if (line_primitive(b, 1, PATH_PIXELS, self->path_points, self->npath, 0, 0, NULL, self->grey) < 0) return -1;
    } else {
        double ux = cos(self->heading), uy = sin(self->heading), low = 0.0, high = 0.0;
        for (Py_ssize_t i = 0; i < self->nbodies; i++) {
            const Body *body = &self->bodies[i];
            double along = (row[body->ix] - self->center[0]) * ux + (row[body->iy] - self->center[1]) * uy;
            if (i == 0 || along < low) low = along;
            if (i == 0 || along > high) high = along;
        }
        double margin = 2.0 * self->d_star;
        low = low - margin;
        high = high + margin;
        double points[4] = {self->center[0] + low * ux, self->center[1] + low * uy, self->center[0] + high * ux,
                            self->center[1] + high * uy};
        if (line_primitive(b, 0, PATH_PIXELS, points, 2, 0, 0, NULL, self->grey) < 0) return -1;
    }
    return pb_end(b, 2, entity);
}

static int body_entity(Encoder *self, const Body *body, const double *row, int64_t stamp)
{
    Buf *b = self->records;
    double x = row[body->ix], y = row[body->iy], heading = row[body->ih], size = self->size;
    double nx = -sin(heading), ny = cos(heading); /* FoxgloveChannels._outward */
    if (self->circle_scene) {
        double dx = x - self->center[0], dy = y - self->center[1], r = py_hypot(dx, dy);
        if (r > 0.0) {
            nx = dx / r;
            ny = dy / r;
        }
    }
    double marker[4] = {x - 0.5 * size * cos(heading), y - 0.5 * size * sin(heading), x + 0.5 * size * cos(heading),
                        y + 0.5 * size * sin(heading)};
    double marker_z[2] = {0.01 * size, 0.01 * size};
    const double *color = body->vehicle ? body->solid : self->white;
    size_t entity = pb_begin(b), part;
    if (pb_timestamp(b, 1, stamp) < 0 || pb_text(b, 2, ROOT_FRAME, 5) < 0
        || pb_text(b, 3, body->name, (size_t)body->name_len) < 0)
        return -1;
    /* arrows (7) */
    part = pb_begin(b);
    double shaft = body->vehicle ? 0.9 * size : 0.6 * size, diameter = body->vehicle ? 0.1 * size : 0.08 * size;
    double head = body->vehicle ? 0.4 * size : 0.3 * size, head_diameter = body->vehicle ? 0.25 * size : 0.2 * size;
    if (pb_pose(b, 1, x, y, 0.0, heading) < 0 || pb_double(b, 2, shaft) < 0 || pb_double(b, 3, diameter) < 0
        || pb_double(b, 4, head) < 0 || pb_double(b, 5, head_diameter) < 0 || pb_color(b, 6, color) < 0
        || pb_end(b, 7, part) < 0)
        return -1;
    /* cubes (8) for a vehicle, spheres (9) for the target */
    part = pb_begin(b);
    int ok = pb_pose(b, 1, x, y, 0.0, heading) < 0 ? -1
             : body->vehicle ? pb_vector(b, 2, size, 0.45 * size, 0.35 * size)
                             : pb_vector(b, 2, 0.5 * size, 0.5 * size, 0.5 * size);
    if (ok < 0) return -1;
    if (pb_color(b, 3, color) < 0 || pb_end(b, body->vehicle ? 8 : 9, part) < 0) return -1;
    /* lines (11): a vehicle's trail, then the dash along the heading */
    if (body->vehicle && line_primitive(b, 0, TRAIL_PIXELS, body->trail, body->trail_count, body->trail_head,
                                        self->history, NULL, body->faded) < 0)
        return -1;
    if (line_primitive(b, 2, body->vehicle ? MARKER_PIXELS : 0.7 * MARKER_PIXELS, marker, 2, 0, 0, marker_z, color) < 0)
        return -1;
    /* texts (13): the label, off the path */
    part = pb_begin(b);
    size_t pose = pb_begin(b);
    if (pb_vector(b, 1, x + self->label_offset * nx, y + self->label_offset * ny, 0.8 * size) < 0
        || pb_yaw(b, 2, 0.0) < 0 || pb_end(b, 1, pose) < 0 || pb_uint(b, 2, 1) < 0 || pb_double(b, 3, 12.0) < 0
        || pb_uint(b, 4, 1) < 0 || pb_color(b, 5, self->white) < 0
        || pb_text(b, 6, body->label, (size_t)body->label_len) < 0 || pb_end(b, 13, part) < 0)
        return -1;
    return pb_end(b, 2, entity);
}

static int scene_message(Encoder *self, const double *row, uint32_t sequence, int64_t stamp)
{
    size_t start;
    if (begin_message(self, self->scene_channel, sequence, stamp, &start) < 0 || path_entity(self, row, stamp) < 0)
        return -1;
    for (Py_ssize_t i = 0; i < self->nbodies; i++)
        if (body_entity(self, &self->bodies[i], row, stamp) < 0) return -1;
    self->scenes++;
    return end_message(self, self->scene_channel, stamp, start);
}

enum { REFUSED_ROW = 1, REFUSED_ERRORS = 2 };

/* One row's messages; REFUSED_ROW (a value is not finite: TraceWriter.flush's test, the sum of the
 * row) or REFUSED_ERRORS (an errors value is not finite) when the row cannot be written: nothing is
 * added then. */
static int encode_row(Encoder *self, const double *row, uint32_t sequence)
{
    double time = row[0], sum = 0.0;
    for (Py_ssize_t i = 0; i < self->width; i++) sum += row[i];
    if (!isfinite(sum)) return REFUSED_ROW;
    int64_t stamp = (int64_t)nearbyint(time * 1e9); /* int(round(time * 1e9)): ties to even */
    Buf *texts = &self->texts;
    texts->len = 0;
    Py_ssize_t *at = self->text_at;
    for (Py_ssize_t i = 0; i < self->width; i++) {
        at[i] = (Py_ssize_t)texts->len;
        if (put_number(texts, row[i]) < 0) return -1;
    }
    at[self->width] = (Py_ssize_t)texts->len;
    GroupOut saved[MAX_GROUPS]; /* the groups as the row found them, to take its messages back out */
    memcpy(saved, self->groups, sizeof saved);
    for (Py_ssize_t i = 0; i < self->ncomponents; i++) {
        const Component *c = &self->components[i];
        size_t start;
        if (begin_message(self, c->channel, sequence, stamp, &start) < 0) return -1;
        Buf *b = self->records;
        if (buf_put(b, c->pieces, (size_t)c->piece_at[1]) < 0 || buf_put(b, texts->data, (size_t)at[1]) < 0) return -1;
        for (Py_ssize_t j = 0; j < c->count; j++) {
            Py_ssize_t k = c->start + j;
            if (buf_put(b, c->pieces + c->piece_at[j + 1], (size_t)(c->piece_at[j + 2] - c->piece_at[j + 1])) < 0
                || buf_put(b, texts->data + at[k], (size_t)(at[k + 1] - at[k])) < 0)
                return -1;
        }
        if (buf_put(b, c->pieces + c->piece_at[c->count + 1], (size_t)(c->piece_at[c->count + 2] - c->piece_at[c->count + 1])) < 0
            || end_message(self, c->channel, stamp, start) < 0)
            return -1;
    }
    if (!self->foxglove) return 0;
    int refused = errors_message(self, row, sequence, stamp);
    if (refused != 0) {
        if (refused > 0) {
            refused = REFUSED_ERRORS; /* take the row's component messages back out */
            for (Py_ssize_t g = 0; g < self->ngroups; g++) { /* the buffers may have moved: keep them */
                self->groups[g].records.len = saved[g].records.len;
                self->groups[g].first = saved[g].first;
                self->groups[g].last = saved[g].last;
                self->groups[g].messages = saved[g].messages;
            }
            for (Py_ssize_t i = 0; i < self->ncomponents; i++) {
                ChannelOut *out = &self->out[self->components[i].channel];
                out->index.len -= 16;
                if (--out->count == 0) self->norder--; /* it was among the last to start */
            }
        }
        return refused;
    }
    if (advance(self, time, row)
        && (transforms_message(self, row, sequence, stamp) < 0 || scene_message(self, row, sequence, stamp) < 0))
        return -1;
    return 0;
}

/* --- Encoder.encode ------------------------------------------------------------------------------ */

static PyObject *take_indexes(Encoder *self)
{
    PyObject *indexes = PyList_New(0);
    if (indexes == NULL) return NULL;
    for (Py_ssize_t i = 0; i < self->norder; i++) {
        Py_ssize_t channel = self->order[i];
        ChannelOut *out = &self->out[channel];
        PyObject *entry = Py_BuildValue("(ny#n)", channel, out->index.data, (Py_ssize_t)out->index.len, out->count);
        if (entry == NULL || PyList_Append(indexes, entry) < 0) {
            Py_XDECREF(entry);
            Py_DECREF(indexes);
            return NULL;
        }
        Py_DECREF(entry);
    }
    return indexes;
}

PyDoc_STRVAR(encode_doc,
"encode(rows, first, positions, limit, sequence) -> (next, groups, last_time, written, indexes, refused)\n\n"
"Encode the rows of ``rows`` (float64 values, ``width`` per row: a C-contiguous array or raw bytes) from\n"
"row ``first`` on, each row's messages numbered ``sequence``, ``sequence + 1``, ...; ``positions``: where\n"
"in each chunk group's open chunk the records start. Stops after the row that takes a group's chunk past\n"
"``limit`` bytes, or at a row that cannot be written (``refused``: 1 a value is not finite, 2 an errors\n"
"value is not; ``next`` is that row). ``groups``: per chunk group (records, first_stamp, last_stamp,\n"
"messages): the Message records of the ``written`` rows' messages of that group, their least and greatest\n"
"log time and their number; ``indexes``: (channel, packed little-endian (log time, offset) pairs, count) of\n"
"each channel written, offsets in its group's chunk; ``last_time``: the time of the last row.");

static PyObject *take_groups(Encoder *self)
{
    PyObject *groups = PyTuple_New(self->ngroups);
    if (groups == NULL) return NULL;
    for (Py_ssize_t g = 0; g < self->ngroups; g++) {
        GroupOut *group = &self->groups[g];
        PyObject *entry = Py_BuildValue("(y#LLn)", group->records.data, (Py_ssize_t)group->records.len,
                                        (long long)group->first, (long long)group->last, group->messages);
        if (entry == NULL) {
            Py_DECREF(groups);
            return NULL;
        }
        PyTuple_SET_ITEM(groups, g, entry);
    }
    return groups;
}

/* positions: one chunk position per group; 0 when taken */
static int take_positions(Encoder *self, PyObject *positions)
{
    PyObject *fast = PySequence_Fast(positions, "positions must be a sequence, one per chunk group");
    if (fast == NULL) return -1;
    if (PySequence_Fast_GET_SIZE(fast) < self->ngroups) {
        Py_DECREF(fast);
        PyErr_Format(PyExc_ValueError, "positions must hold one position per chunk group (%zd)", self->ngroups);
        return -1;
    }
    for (Py_ssize_t g = 0; g < self->ngroups; g++) {
        GroupOut *group = &self->groups[g];
        group->position = PyLong_AsUnsignedLongLong(PySequence_Fast_GET_ITEM(fast, g));
        if (PyErr_Occurred()) {
            Py_DECREF(fast);
            return -1;
        }
        group->records.len = 0;
        group->messages = 0;
        group->first = group->last = 0;
    }
    Py_DECREF(fast);
    return 0;
}

static int any_group_full(const Encoder *self, unsigned long long limit)
{
    for (Py_ssize_t g = 0; g < self->ngroups; g++)
        if (self->groups[g].position + self->groups[g].records.len > limit) return 1;
    return 0;
}

static PyObject *Encoder_encode(Encoder *self, PyObject *args)
{
    PyObject *rows, *positions;
    Py_ssize_t first;
    unsigned long long limit, sequence;
    if (self->components == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "the Encoder is not set up");
        return NULL;
    }
    if (!PyArg_ParseTuple(args, "OnOKK", &rows, &first, &positions, &limit, &sequence)) return NULL;
    if (take_positions(self, positions) < 0) return NULL;
    Py_buffer view;
    if (PyObject_GetBuffer(rows, &view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) return NULL;
    int raw = view.itemsize == 1, doubles = view.itemsize == 8 && view.format != NULL
                                            && (strcmp(view.format, "d") == 0 || strcmp(view.format, "<d") == 0
                                                || strcmp(view.format, "=d") == 0);
    Py_ssize_t row_bytes = 8 * self->width;
    if ((!raw && !doubles) || view.len % row_bytes != 0) {
        PyBuffer_Release(&view);
        PyErr_SetString(PyExc_ValueError, "rows must be float64 values, a whole number of rows");
        return NULL;
    }
    Py_ssize_t count = view.len / row_bytes, row = first < 0 ? 0 : first;
    for (Py_ssize_t i = 0; i < self->nchannels; i++) {
        self->out[i].index.len = 0;
        self->out[i].count = 0;
    }
    self->norder = 0;
    int refused = 0, failed = 0;
    double last_time = 0.0;
    Py_ssize_t written = 0;
    while (row < count) {
        const double *values = (const double *)((const char *)view.buf + row * row_bytes);
        int result = encode_row(self, values, (uint32_t)(sequence + (unsigned long long)written));
        if (result < 0) { failed = 1; break; }
        if (result > 0) { refused = result; break; }
        last_time = values[0];
        written++;
        row++;
        if (any_group_full(self, limit)) break;
    }
    PyBuffer_Release(&view);
    if (failed) return NULL;
    PyObject *indexes = take_indexes(self);
    if (indexes == NULL) return NULL;
    PyObject *groups = take_groups(self);
    if (groups == NULL) {
        Py_DECREF(indexes);
        return NULL;
    }
    return Py_BuildValue("(nNdnNi)", row, groups, last_time, written, indexes, refused);
}

static PyObject *Encoder_get_scenes(Encoder *self, void *closure)
{
    (void)closure;
    return PyLong_FromSsize_t(self->scenes);
}

static PyObject *Encoder_get_next_scene(Encoder *self, void *closure)
{
    (void)closure;
    return PyFloat_FromDouble(self->next_scene);
}

static PyMethodDef Encoder_methods[] = {
    {"encode", (PyCFunction)Encoder_encode, METH_VARARGS, encode_doc},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef Encoder_getset[] = {
    {"scenes", (getter)Encoder_get_scenes, NULL, "scenes written so far", NULL},
    {"next_scene", (getter)Encoder_get_next_scene, NULL, "simulated time of the next scene tick", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

PyDoc_STRVAR(Encoder_doc,
"Encoder(width, components, foxglove): a run's per-row trace messages (orchestrator/trace/native_rows.py\n"
"builds the arguments from ComponentMessages and FoxgloveChannels).");

static PyTypeObject EncoderType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "orchestrator.trace._native.Encoder",
    .tp_basicsize = sizeof(Encoder),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = Encoder_doc,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Encoder_init,
    .tp_dealloc = (destructor)Encoder_dealloc,
    .tp_methods = Encoder_methods,
    .tp_getset = Encoder_getset,
};

static PyMethodDef module_methods[] = {
    {"format_double", py_format_double, METH_O, "The JSON text of a finite double, as orjson writes it."},
    {"first_non_finite", py_first_non_finite, METH_VARARGS,
     "first_non_finite(data, width): the first row of flat float64 data holding nan or inf, or None."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef native_module = {
    PyModuleDef_HEAD_INIT, "_native", "The trace's per-row messages in C (orchestrator/trace/native_encoder.c).", -1,
    module_methods,
};

PyMODINIT_FUNC PyInit__native(void)
{
    init_pow10();
    if (PyType_Ready(&EncoderType) < 0) return NULL;
    PyObject *module = PyModule_Create(&native_module);
    if (module == NULL) return NULL;
    Py_INCREF(&EncoderType);
    if (PyModule_AddObject(module, "Encoder", (PyObject *)&EncoderType) < 0) {
        Py_DECREF(&EncoderType);
        Py_DECREF(module);
        return NULL;
    }
    return module;
}

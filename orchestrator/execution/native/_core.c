/*
 * orchestrator.execution.native._core: the native stepping core.
 *
 * One `Core` object holds a whole co-simulation: the FMU instances (each FMU binary dlopen()ed once
 * per process and never unloaded), their input and output value references, the connection list as
 * index arrays, the scheduled disturbance pulses, and one contiguous array with every output of
 * every component. `initialize` does what orchestrator.execution.python_master.Master.initialize does (instantiate,
 * set up, set parameters, enter initialization mode, settle sweeps, exit initialization mode);
 * `run` steps a range of communication points entirely in C (transfer, fmi2SetReal, fmi2DoStep,
 * fmi2GetReal, Jacobi or Gauss-Seidel exactly as Master.step) and copies the output rows it is asked
 * to record into a caller-owned float64 buffer, so Python sees the run once per block of steps.
 *
 * The GIL is held throughout: pythonfmu FMUs run their model in this very interpreter and take the
 * GIL themselves with PyGILState_Ensure, which nests on the thread that already holds it.
 *
 * Arithmetic that decides results is written exactly as the Python master writes it (t_k = t0 + k h,
 * h_k = t_(k+1) - t_k, the pulse window test of ScheduledInput.value_at, inputs zeroed then summed);
 * the module is compiled with -ffp-contract=off so no fused multiply-add changes a rounding.
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <dlfcn.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* --- FMI 2.0 co-simulation types (the subset used here, as in fmi2FunctionTypes.h) ------------- */

typedef void *fmi2Component;
typedef void *fmi2ComponentEnvironment;
typedef unsigned int fmi2ValueReference;
typedef double fmi2Real;
typedef int fmi2Integer;
typedef int fmi2Boolean;
typedef const char *fmi2String;
typedef int fmi2Status; /* fmi2OK 0, fmi2Warning 1, fmi2Discard 2, fmi2Error 3, fmi2Fatal 4, fmi2Pending 5 */

#define fmi2True 1
#define fmi2False 0
#define fmi2Warning 1
#define fmi2CoSimulation 1

typedef void (*fmi2CallbackLogger)(fmi2ComponentEnvironment, fmi2String, fmi2Status, fmi2String, fmi2String, ...);
typedef void *(*fmi2CallbackAllocateMemory)(size_t, size_t);
typedef void (*fmi2CallbackFreeMemory)(void *);
typedef void (*fmi2StepFinished)(fmi2ComponentEnvironment, fmi2Status);

typedef struct {
    fmi2CallbackLogger logger;
    fmi2CallbackAllocateMemory allocateMemory;
    fmi2CallbackFreeMemory freeMemory;
    fmi2StepFinished stepFinished;
    fmi2ComponentEnvironment componentEnvironment;
} fmi2CallbackFunctions;

typedef fmi2Component (*fmi2InstantiateTYPE)(fmi2String, int, fmi2String, fmi2String, const fmi2CallbackFunctions *,
                                              fmi2Boolean, fmi2Boolean);
typedef void (*fmi2FreeInstanceTYPE)(fmi2Component);
typedef fmi2Status (*fmi2SetupExperimentTYPE)(fmi2Component, fmi2Boolean, fmi2Real, fmi2Real, fmi2Boolean, fmi2Real);
typedef fmi2Status (*fmi2ModeTYPE)(fmi2Component); /* Enter/ExitInitializationMode, Terminate */
typedef fmi2Status (*fmi2GetRealTYPE)(fmi2Component, const fmi2ValueReference[], size_t, fmi2Real[]);
typedef fmi2Status (*fmi2SetRealTYPE)(fmi2Component, const fmi2ValueReference[], size_t, const fmi2Real[]);
typedef fmi2Status (*fmi2SetIntegerTYPE)(fmi2Component, const fmi2ValueReference[], size_t, const fmi2Integer[]);
typedef fmi2Status (*fmi2SetBooleanTYPE)(fmi2Component, const fmi2ValueReference[], size_t, const fmi2Boolean[]);
typedef fmi2Status (*fmi2SetStringTYPE)(fmi2Component, const fmi2ValueReference[], size_t, const fmi2String[]);
typedef fmi2Status (*fmi2DoStepTYPE)(fmi2Component, fmi2Real, fmi2Real, fmi2Boolean);

/* --- FMU binaries: loaded once per path, never unloaded --------------------------------------- */

typedef struct Library {
    char *path;
    void *handle;
    fmi2InstantiateTYPE instantiate;
    fmi2FreeInstanceTYPE freeInstance;
    fmi2SetupExperimentTYPE setupExperiment;
    fmi2ModeTYPE enterInitializationMode;
    fmi2ModeTYPE exitInitializationMode;
    fmi2ModeTYPE terminate;
    fmi2GetRealTYPE getReal;
    fmi2SetRealTYPE setReal;
    fmi2SetIntegerTYPE setInteger;
    fmi2SetBooleanTYPE setBoolean;
    fmi2SetStringTYPE setString;
    fmi2DoStepTYPE doStep;
    struct Library *next;
} Library;

/* Every library this process loaded. dlclose() is never called: a pythonfmu binary leaves objects in
 * the host's interpreter, and unloading it corrupts the heap at interpreter exit (see
 * orchestrator/components/fmu.py, FmuComponent.close). */
static Library *libraries = NULL;

static void *resolve(Library *lib, const char *name) {
    void *symbol = dlsym(lib->handle, name);
    if (symbol == NULL)
        PyErr_Format(PyExc_OSError, "%s does not export %s", lib->path, name);
    return symbol;
}

static Library *load_library(const char *path) {
    for (Library *lib = libraries; lib != NULL; lib = lib->next)
        if (strcmp(lib->path, path) == 0)
            return lib;
    /* The flags ctypes (FMPy) uses: a pythonfmu binary resolves the Python C API from the process. */
    void *handle = dlopen(path, RTLD_NOW | RTLD_LOCAL);
    if (handle == NULL) {
        const char *why = dlerror();
        PyErr_Format(PyExc_OSError, "cannot load FMU binary %s: %s", path, why ? why : "unknown error");
        return NULL;
    }
    Library *lib = calloc(1, sizeof(Library));
    if (lib == NULL)
        return (Library *)PyErr_NoMemory();
    lib->path = strdup(path);
    lib->handle = handle;
    if (lib->path == NULL
        || !(lib->instantiate = (fmi2InstantiateTYPE)resolve(lib, "fmi2Instantiate"))
        || !(lib->freeInstance = (fmi2FreeInstanceTYPE)resolve(lib, "fmi2FreeInstance"))
        || !(lib->setupExperiment = (fmi2SetupExperimentTYPE)resolve(lib, "fmi2SetupExperiment"))
        || !(lib->enterInitializationMode = (fmi2ModeTYPE)resolve(lib, "fmi2EnterInitializationMode"))
        || !(lib->exitInitializationMode = (fmi2ModeTYPE)resolve(lib, "fmi2ExitInitializationMode"))
        || !(lib->terminate = (fmi2ModeTYPE)resolve(lib, "fmi2Terminate"))
        || !(lib->getReal = (fmi2GetRealTYPE)resolve(lib, "fmi2GetReal"))
        || !(lib->setReal = (fmi2SetRealTYPE)resolve(lib, "fmi2SetReal"))
        || !(lib->setInteger = (fmi2SetIntegerTYPE)resolve(lib, "fmi2SetInteger"))
        || !(lib->setBoolean = (fmi2SetBooleanTYPE)resolve(lib, "fmi2SetBoolean"))
        || !(lib->setString = (fmi2SetStringTYPE)resolve(lib, "fmi2SetString"))
        || !(lib->doStep = (fmi2DoStepTYPE)resolve(lib, "fmi2DoStep"))) {
        if (!PyErr_Occurred())
            PyErr_NoMemory();
        /* keep the handle loaded (never dlclose); the half-filled entry is simply not registered */
        free(lib->path);
        free(lib);
        return NULL;
    }
    lib->next = libraries;
    libraries = lib;
    return lib;
}

/* --- instances -------------------------------------------------------------------------------- */

#define MESSAGES_KEPT 50     /* like FmuComponent.messages, a deque(maxlen=50) */
#define MAX_MESSAGE_LENGTH 2048 /* like FMPy's logger proxy */

enum { P_REAL, P_INTEGER, P_BOOLEAN, P_STRING };

typedef struct {
    int kind;
    size_t count;
    fmi2ValueReference *refs;
    double *reals;
    int *ints;      /* Integer and Boolean */
    char **strings;
} ParameterGroup;

typedef struct {
    char *name;
    char *guid;
    char *resource_uri;
    Library *lib;
    fmi2Component component;
    fmi2CallbackFunctions callbacks;
    int instantiated;

    size_t n_in, n_out, out_offset;
    fmi2ValueReference *in_refs, *out_refs;
    double *inputs; /* persistent input vector, starts at the inputs' start values (Master.inputs) */

    size_t n_connected; /* inputs fed by outputs: input index <- global output index */
    size_t *connected_input, *connected_source;
    size_t n_scheduled; /* pulses: value on [start - tol, start + duration - tol) */
    size_t *scheduled_input;
    double *scheduled_start, *scheduled_duration, *scheduled_value, *scheduled_tolerance;
    double *scheduled_frequency; /* > 0: value * sin(frequency (t - start)) on the window */

    size_t n_groups;
    ParameterGroup *groups;

    char *messages[MESSAGES_KEPT]; /* ring of the latest log lines */
    size_t message_count;          /* lines received so far */
} Instance;

/* The instance whose FMU is being called; used by the logger when an FMU does not hand back its
 * componentEnvironment. */
static Instance *calling = NULL;

static void remember(Instance *inst, const char *text) {
    char *copy = strdup(text);
    if (copy == NULL)
        return;
    size_t slot = inst->message_count % MESSAGES_KEPT;
    free(inst->messages[slot]);
    inst->messages[slot] = copy;
    inst->message_count++;
}

static void logger(fmi2ComponentEnvironment environment, fmi2String instance_name, fmi2Status status,
                   fmi2String category, fmi2String message, ...) {
    (void)instance_name;
    (void)status;
    (void)category;
    Instance *inst = environment != NULL ? (Instance *)environment : calling;
    if (inst == NULL)
        return;
    char buffer[MAX_MESSAGE_LENGTH];
    buffer[0] = '\0';
    if (message != NULL) {
        va_list args;
        va_start(args, message);
        vsnprintf(buffer, sizeof buffer, message, args);
        va_end(args);
    }
    remember(inst, buffer);
}

static const char *last_message(const Instance *inst) {
    if (inst->message_count == 0)
        return NULL;
    return inst->messages[(inst->message_count - 1) % MESSAGES_KEPT];
}

static const char *status_label(fmi2Status status) {
    static const char *labels[] = {"ok", "warning", "discard", "error", "fatal", "pending"};
    return status >= 0 && status <= 5 ? labels[status] : "illegal return code";
}

static void free_instance_memory(Instance *inst) {
    free(inst->name);
    free(inst->guid);
    free(inst->resource_uri);
    free(inst->in_refs);
    free(inst->out_refs);
    free(inst->inputs);
    free(inst->connected_input);
    free(inst->connected_source);
    free(inst->scheduled_input);
    free(inst->scheduled_start);
    free(inst->scheduled_duration);
    free(inst->scheduled_value);
    free(inst->scheduled_tolerance);
    free(inst->scheduled_frequency);
    for (size_t g = 0; g < inst->n_groups; g++) {
        ParameterGroup *group = &inst->groups[g];
        free(group->refs);
        free(group->reals);
        free(group->ints);
        if (group->strings != NULL)
            for (size_t i = 0; i < group->count; i++)
                free(group->strings[i]);
        free(group->strings);
    }
    free(inst->groups);
    for (size_t i = 0; i < MESSAGES_KEPT; i++)
        free(inst->messages[i]);
}

/* --- the Core object -------------------------------------------------------------------------- */

typedef struct {
    PyObject_HEAD
    size_t n;
    Instance *instances;
    size_t total_out;
    size_t max_out;
    double *outputs; /* every output of every component, component after component */
    double *fresh;   /* scratch for the settle sweeps */
    int gauss_seidel;
    int initialized;
    int closed;
    PyObject *error_class; /* orchestrator.components.fmu.ComponentError */
    Py_ssize_t steps_done; /* of the last run() call, also when it raised */
    Py_ssize_t rows_done;
} Core;

/* Raise error_class(component name, time, reason); reason is the FMU's last log line if any. */
static void fail(Core *self, const Instance *inst, double time, const char *fallback) {
    const char *reason = last_message(inst);
    if (reason == NULL)
        reason = fallback;
    PyObject *text = PyUnicode_DecodeUTF8(reason, (Py_ssize_t)strlen(reason), "replace");
    if (text == NULL)
        return;
    PyObject *error = PyObject_CallFunction(self->error_class, "sdO", inst->name, time, text);
    Py_DECREF(text);
    if (error == NULL)
        return;
    PyErr_SetObject((PyObject *)Py_TYPE(error), error);
    Py_DECREF(error);
}

static void fail_status(Core *self, const Instance *inst, double time, const char *function, fmi2Status status) {
    char fallback[160];
    /* FMPy's FMICallException text, which FmuComponent reports when the FMU logged nothing */
    snprintf(fallback, sizeof fallback, "%s failed with status %d (%s).", function, status, status_label(status));
    fail(self, inst, time, fallback);
}

/* Sequence helpers ------------------------------------------------------------------------------ */

static int get_refs(PyObject *sequence, fmi2ValueReference **out, size_t *count) {
    PyObject *fast = PySequence_Fast(sequence, "expected a sequence of value references");
    if (fast == NULL)
        return -1;
    Py_ssize_t n = PySequence_Fast_GET_SIZE(fast);
    *count = (size_t)n;
    *out = calloc(n > 0 ? (size_t)n : 1, sizeof(fmi2ValueReference));
    if (*out == NULL) {
        Py_DECREF(fast);
        PyErr_NoMemory();
        return -1;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        unsigned long value = PyLong_AsUnsignedLong(PySequence_Fast_GET_ITEM(fast, i));
        if (value == (unsigned long)-1 && PyErr_Occurred()) {
            Py_DECREF(fast);
            return -1;
        }
        (*out)[i] = (fmi2ValueReference)value;
    }
    Py_DECREF(fast);
    return 0;
}

static char *copy_string(PyObject *text) {
    const char *utf8 = PyUnicode_AsUTF8(text);
    if (utf8 == NULL)
        return NULL;
    char *copy = strdup(utf8);
    if (copy == NULL)
        PyErr_NoMemory();
    return copy;
}

/* One component description, a tuple:
 * (name, library path, guid, resource URI, input refs, output refs, input start values,
 *  parameter groups [(kind, refs, values)], connected [(input, global output index)],
 *  scheduled [(input, start, duration, value, tolerance, frequency)]) */
static int parse_instance(Instance *inst, PyObject *item) {
    PyObject *name, *library, *guid, *uri, *in_refs, *out_refs, *defaults, *groups, *connected, *scheduled;
    if (!PyArg_ParseTuple(item, "UUUUOOOOOO", &name, &library, &guid, &uri, &in_refs, &out_refs, &defaults,
                          &groups, &connected, &scheduled))
        return -1;
    if (!(inst->name = copy_string(name)) || !(inst->guid = copy_string(guid)) || !(inst->resource_uri = copy_string(uri)))
        return -1;
    const char *path = PyUnicode_AsUTF8(library);
    if (path == NULL || !(inst->lib = load_library(path)))
        return -1;
    if (get_refs(in_refs, &inst->in_refs, &inst->n_in) < 0 || get_refs(out_refs, &inst->out_refs, &inst->n_out) < 0)
        return -1;

    PyObject *fast = PySequence_Fast(defaults, "input start values must be a sequence");
    if (fast == NULL)
        return -1;
    if ((size_t)PySequence_Fast_GET_SIZE(fast) != inst->n_in) {
        Py_DECREF(fast);
        PyErr_SetString(PyExc_ValueError, "one start value per input expected");
        return -1;
    }
    inst->inputs = calloc(inst->n_in > 0 ? inst->n_in : 1, sizeof(double));
    if (inst->inputs == NULL) {
        Py_DECREF(fast);
        PyErr_NoMemory();
        return -1;
    }
    for (size_t i = 0; i < inst->n_in; i++) {
        inst->inputs[i] = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(fast, (Py_ssize_t)i));
        if (inst->inputs[i] == -1.0 && PyErr_Occurred()) {
            Py_DECREF(fast);
            return -1;
        }
    }
    Py_DECREF(fast);

    /* parameter groups, applied in this order (FmuComponent._set_parameters) */
    fast = PySequence_Fast(groups, "parameter groups must be a sequence");
    if (fast == NULL)
        return -1;
    inst->n_groups = (size_t)PySequence_Fast_GET_SIZE(fast);
    inst->groups = calloc(inst->n_groups > 0 ? inst->n_groups : 1, sizeof(ParameterGroup));
    if (inst->groups == NULL) {
        Py_DECREF(fast);
        PyErr_NoMemory();
        return -1;
    }
    for (size_t g = 0; g < inst->n_groups; g++) {
        ParameterGroup *group = &inst->groups[g];
        PyObject *refs, *values;
        const char *kind;
        if (!PyArg_ParseTuple(PySequence_Fast_GET_ITEM(fast, (Py_ssize_t)g), "sOO", &kind, &refs, &values))
            goto group_error;
        if (strcmp(kind, "Real") == 0) group->kind = P_REAL;
        else if (strcmp(kind, "Integer") == 0) group->kind = P_INTEGER;
        else if (strcmp(kind, "Boolean") == 0) group->kind = P_BOOLEAN;
        else if (strcmp(kind, "String") == 0) group->kind = P_STRING;
        else {
            PyErr_Format(PyExc_ValueError, "unknown variable type %s", kind);
            goto group_error;
        }
        if (get_refs(refs, &group->refs, &group->count) < 0)
            goto group_error;
        PyObject *items = PySequence_Fast(values, "parameter values must be a sequence");
        if (items == NULL)
            goto group_error;
        if ((size_t)PySequence_Fast_GET_SIZE(items) != group->count) {
            Py_DECREF(items);
            PyErr_SetString(PyExc_ValueError, "one value per parameter reference expected");
            goto group_error;
        }
        size_t n = group->count > 0 ? group->count : 1;
        if (group->kind == P_REAL) group->reals = calloc(n, sizeof(double));
        else if (group->kind == P_STRING) group->strings = calloc(n, sizeof(char *));
        else group->ints = calloc(n, sizeof(int));
        if (!group->reals && !group->strings && !group->ints) {
            Py_DECREF(items);
            PyErr_NoMemory();
            goto group_error;
        }
        for (size_t i = 0; i < group->count; i++) {
            PyObject *value = PySequence_Fast_GET_ITEM(items, (Py_ssize_t)i);
            int bad = 0;
            if (group->kind == P_REAL) {
                group->reals[i] = PyFloat_AsDouble(value);
                bad = group->reals[i] == -1.0 && PyErr_Occurred();
            } else if (group->kind == P_INTEGER) {
                long v = PyLong_AsLong(value);
                bad = v == -1 && PyErr_Occurred();
                group->ints[i] = (int)v;
            } else if (group->kind == P_BOOLEAN) {
                int v = PyObject_IsTrue(value);
                bad = v < 0;
                group->ints[i] = v ? fmi2True : fmi2False;
            } else {
                bad = (group->strings[i] = copy_string(value)) == NULL;
            }
            if (bad) {
                Py_DECREF(items);
                goto group_error;
            }
        }
        Py_DECREF(items);
    }
    Py_DECREF(fast);

    fast = PySequence_Fast(connected, "connections must be a sequence");
    if (fast == NULL)
        return -1;
    inst->n_connected = (size_t)PySequence_Fast_GET_SIZE(fast);
    inst->connected_input = calloc(inst->n_connected + 1, sizeof(size_t));
    inst->connected_source = calloc(inst->n_connected + 1, sizeof(size_t));
    if (!inst->connected_input || !inst->connected_source) {
        Py_DECREF(fast);
        PyErr_NoMemory();
        return -1;
    }
    for (size_t i = 0; i < inst->n_connected; i++) {
        Py_ssize_t input, source;
        if (!PyArg_ParseTuple(PySequence_Fast_GET_ITEM(fast, (Py_ssize_t)i), "nn", &input, &source)) {
            Py_DECREF(fast);
            return -1;
        }
        if (input < 0 || (size_t)input >= inst->n_in || source < 0) {
            Py_DECREF(fast);
            PyErr_SetString(PyExc_ValueError, "connection index out of range");
            return -1;
        }
        inst->connected_input[i] = (size_t)input;
        inst->connected_source[i] = (size_t)source; /* checked against total_out by the caller */
    }
    Py_DECREF(fast);

    fast = PySequence_Fast(scheduled, "schedules must be a sequence");
    if (fast == NULL)
        return -1;
    size_t m = (size_t)PySequence_Fast_GET_SIZE(fast);
    inst->n_scheduled = m;
    inst->scheduled_input = calloc(m + 1, sizeof(size_t));
    inst->scheduled_start = calloc(m + 1, sizeof(double));
    inst->scheduled_duration = calloc(m + 1, sizeof(double));
    inst->scheduled_value = calloc(m + 1, sizeof(double));
    inst->scheduled_tolerance = calloc(m + 1, sizeof(double));
    inst->scheduled_frequency = calloc(m + 1, sizeof(double));
    if (!inst->scheduled_input || !inst->scheduled_start || !inst->scheduled_duration || !inst->scheduled_value
        || !inst->scheduled_tolerance || !inst->scheduled_frequency) {
        Py_DECREF(fast);
        PyErr_NoMemory();
        return -1;
    }
    for (size_t i = 0; i < m; i++) {
        Py_ssize_t input;
        if (!PyArg_ParseTuple(PySequence_Fast_GET_ITEM(fast, (Py_ssize_t)i), "nddddd", &input, &inst->scheduled_start[i],
                              &inst->scheduled_duration[i], &inst->scheduled_value[i], &inst->scheduled_tolerance[i],
                              &inst->scheduled_frequency[i])) {
            Py_DECREF(fast);
            return -1;
        }
        if (input < 0 || (size_t)input >= inst->n_in) {
            Py_DECREF(fast);
            PyErr_SetString(PyExc_ValueError, "scheduled input index out of range");
            return -1;
        }
        inst->scheduled_input[i] = (size_t)input;
    }
    Py_DECREF(fast);

    inst->callbacks.logger = logger;
    inst->callbacks.allocateMemory = calloc;
    inst->callbacks.freeMemory = free;
    inst->callbacks.stepFinished = NULL;
    inst->callbacks.componentEnvironment = inst;
    return 0;

group_error:
    Py_DECREF(fast);
    return -1;
}

static void Core_dealloc(Core *self) {
    Py_CLEAR(self->error_class);
    if (self->instances != NULL) {
        int live = 0;
        for (size_t c = 0; c < self->n; c++)
            live |= self->instances[c].instantiated;
        /* An FMU instance still alive holds pointers into its Instance (callbacks, environment):
         * without close() the memory is deliberately kept. */
        if (!live) {
            for (size_t c = 0; c < self->n; c++)
                free_instance_memory(&self->instances[c]);
            free(self->instances);
        }
    }
    free(self->outputs);
    free(self->fresh);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int Core_init(Core *self, PyObject *args, PyObject *kwargs) {
    static char *keywords[] = {"components", "algorithm", "error_class", NULL};
    PyObject *components, *error_class;
    const char *algorithm;
    if (self->instances != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "Core is already initialized");
        return -1;
    }
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "OsO", keywords, &components, &algorithm, &error_class))
        return -1;
    if (strcmp(algorithm, "jacobi") == 0) self->gauss_seidel = 0;
    else if (strcmp(algorithm, "gauss-seidel") == 0) self->gauss_seidel = 1;
    else {
        PyErr_Format(PyExc_ValueError, "unknown master %s", algorithm);
        return -1;
    }
    Py_INCREF(error_class);
    self->error_class = error_class;
    PyObject *fast = PySequence_Fast(components, "components must be a sequence");
    if (fast == NULL)
        return -1;
    self->n = (size_t)PySequence_Fast_GET_SIZE(fast);
    self->instances = calloc(self->n > 0 ? self->n : 1, sizeof(Instance));
    if (self->instances == NULL) {
        Py_DECREF(fast);
        PyErr_NoMemory();
        return -1;
    }
    self->total_out = 0;
    self->max_out = 1;
    for (size_t c = 0; c < self->n; c++) {
        Instance *inst = &self->instances[c];
        if (parse_instance(inst, PySequence_Fast_GET_ITEM(fast, (Py_ssize_t)c)) < 0) {
            Py_DECREF(fast);
            return -1;
        }
        inst->out_offset = self->total_out;
        self->total_out += inst->n_out;
        if (inst->n_out > self->max_out)
            self->max_out = inst->n_out;
    }
    Py_DECREF(fast);
    for (size_t c = 0; c < self->n; c++)
        for (size_t i = 0; i < self->instances[c].n_connected; i++)
            if (self->instances[c].connected_source[i] >= self->total_out) {
                PyErr_SetString(PyExc_ValueError, "connection source out of range");
                return -1;
            }
    self->outputs = calloc(self->total_out > 0 ? self->total_out : 1, sizeof(double));
    self->fresh = calloc(self->max_out, sizeof(double));
    if (!self->outputs || !self->fresh) {
        PyErr_NoMemory();
        return -1;
    }
    return 0;
}

/* --- the stepping primitives ------------------------------------------------------------------ */

/* Master._transfer: connected inputs from the current outputs, then pulses (zeroed, then summed in
 * schedule order, sampled at t), then one fmi2SetReal of the whole input vector. */
static inline fmi2Status transfer(const Core *self, Instance *inst, double t) {
    double *vector = inst->inputs;
    const double *outputs = self->outputs;
    for (size_t i = 0; i < inst->n_connected; i++)
        vector[inst->connected_input[i]] = outputs[inst->connected_source[i]];
    if (inst->n_scheduled) {
        for (size_t i = 0; i < inst->n_scheduled; i++)
            vector[inst->scheduled_input[i]] = 0.0;
        for (size_t i = 0; i < inst->n_scheduled; i++) {
            /* ScheduledInput.value_at: start - tol <= t < start + duration - tol */
            double start = inst->scheduled_start[i], tolerance = inst->scheduled_tolerance[i];
            double value = (start - tolerance <= t && t < start + inst->scheduled_duration[i] - tolerance)
                               ? inst->scheduled_value[i] : 0.0;
            if (value != 0.0 && inst->scheduled_frequency[i] > 0.0)
                value *= sin(inst->scheduled_frequency[i] * (t - start));
            vector[inst->scheduled_input[i]] += value;
        }
    }
    calling = inst;
    return inst->lib->setReal(inst->component, inst->in_refs, inst->n_in, vector);
}

static inline fmi2Status read_outputs(const Core *self, Instance *inst, double *into) {
    (void)self;
    calling = inst;
    return inst->lib->getReal(inst->component, inst->out_refs, inst->n_out, into);
}

/* Every instance's outputs into the shared output array (Master: outputs = [c.get_outputs() ...]).
 * Returns 0, or -1 with the exception set. */
static int read_all_outputs(Core *self, double t) {
    for (size_t c = 0; c < self->n; c++) {
        Instance *inst = &self->instances[c];
        fmi2Status status = read_outputs(self, inst, self->outputs + inst->out_offset);
        if (status > fmi2Warning) {
            fail_status(self, inst, t, "fmi2GetReal", status);
            return -1;
        }
    }
    return 0;
}

static inline fmi2Status do_step(Instance *inst, double t, double h) {
    calling = inst;
    return inst->lib->doStep(inst->component, t, h, fmi2True);
}

/* One communication step from t to t + h (Master.step). Returns 0, or -1 with the exception set. */
static int step_once(Core *self, double t, double h) {
    fmi2Status status;
    const size_t n = self->n;
    Instance *instances = self->instances;
    if (!self->gauss_seidel) {
        for (size_t c = 0; c < n; c++)
            if ((status = transfer(self, &instances[c], t)) > fmi2Warning) {
                fail_status(self, &instances[c], t, "fmi2SetReal", status);
                return -1;
            }
        for (size_t c = 0; c < n; c++)
            if ((status = do_step(&instances[c], t, h)) > fmi2Warning) {
                fail_status(self, &instances[c], t, "fmi2DoStep", status);
                return -1;
            }
        return read_all_outputs(self, t);
    } else {
        for (size_t c = 0; c < n; c++) {
            Instance *inst = &instances[c];
            if ((status = transfer(self, inst, t)) > fmi2Warning) {
                fail_status(self, inst, t, "fmi2SetReal", status);
                return -1;
            }
            if ((status = do_step(inst, t, h)) > fmi2Warning) {
                fail_status(self, inst, t, "fmi2DoStep", status);
                return -1;
            }
            if ((status = read_outputs(self, inst, self->outputs + inst->out_offset)) > fmi2Warning) {
                fail_status(self, inst, t, "fmi2GetReal", status);
                return -1;
            }
        }
    }
    return 0;
}

static int require_state(Core *self, int initialized) {
    if (self->instances == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "Core is not constructed");
        return -1;
    }
    if (self->closed) {
        PyErr_SetString(PyExc_RuntimeError, "Core is closed");
        return -1;
    }
    if (initialized && !self->initialized) {
        PyErr_SetString(PyExc_RuntimeError, "Core is not initialized");
        return -1;
    }
    return 0;
}

static int set_parameters(Core *self, Instance *inst, double start_time) {
    static const char *functions[] = {"fmi2SetReal", "fmi2SetInteger", "fmi2SetBoolean", "fmi2SetString"};
    for (size_t g = 0; g < inst->n_groups; g++) {
        ParameterGroup *group = &inst->groups[g];
        fmi2Status status;
        calling = inst;
        switch (group->kind) {
        case P_REAL: status = inst->lib->setReal(inst->component, group->refs, group->count, group->reals); break;
        case P_INTEGER: status = inst->lib->setInteger(inst->component, group->refs, group->count, group->ints); break;
        case P_BOOLEAN: status = inst->lib->setBoolean(inst->component, group->refs, group->count, group->ints); break;
        default: status = inst->lib->setString(inst->component, group->refs, group->count, (const fmi2String *)group->strings); break;
        }
        if (status > fmi2Warning) {
            fail_status(self, inst, start_time, functions[group->kind], status);
            return -1;
        }
    }
    return 0;
}

/* Master.initialize, for every component in order. */
static PyObject *Core_initialize(Core *self, PyObject *arg) {
    double start = PyFloat_AsDouble(arg);
    if (start == -1.0 && PyErr_Occurred())
        return NULL;
    if (require_state(self, 0) < 0)
        return NULL;
    if (self->initialized) {
        PyErr_SetString(PyExc_RuntimeError, "Core is already initialized");
        return NULL;
    }
    self->initialized = 1; /* even when it fails half way: close() frees what was instantiated */
    fmi2Status status;
    for (size_t c = 0; c < self->n; c++) {
        Instance *inst = &self->instances[c];
        calling = inst;
        inst->component = inst->lib->instantiate(inst->name, fmi2CoSimulation, inst->guid, inst->resource_uri,
                                                 &inst->callbacks, fmi2False, fmi2True);
        if (inst->component == NULL) {
            fail(self, inst, start, "Failed to instantiate model");
            return NULL;
        }
        inst->instantiated = 1;
        calling = inst;
        if ((status = inst->lib->setupExperiment(inst->component, fmi2False, 0.0, start, fmi2False, 0.0)) > fmi2Warning) {
            fail_status(self, inst, start, "fmi2SetupExperiment", status);
            return NULL;
        }
        if (set_parameters(self, inst, start) < 0)
            return NULL;
        calling = inst;
        if ((status = inst->lib->enterInitializationMode(inst->component)) > fmi2Warning) {
            fail_status(self, inst, start, "fmi2EnterInitializationMode", status);
            return NULL;
        }
    }
    if (read_all_outputs(self, start) < 0)
        return NULL;
    /* settle sweeps: propagate initial outputs until nothing changes (at most n + 2 sweeps) */
    for (size_t sweep = 0; sweep < self->n + 2; sweep++) {
        int changed = 0;
        for (size_t c = 0; c < self->n; c++) {
            Instance *inst = &self->instances[c];
            if ((status = transfer(self, inst, start)) > fmi2Warning) {
                fail_status(self, inst, start, "fmi2SetReal", status);
                return NULL;
            }
            if ((status = read_outputs(self, inst, self->fresh)) > fmi2Warning) {
                fail_status(self, inst, start, "fmi2GetReal", status);
                return NULL;
            }
            double *current = self->outputs + inst->out_offset;
            for (size_t i = 0; i < inst->n_out; i++) {
                changed |= self->fresh[i] != current[i]; /* NaN counts as changed, as in Python */
                current[i] = self->fresh[i];
            }
        }
        if (!changed)
            break;
    }
    for (size_t c = 0; c < self->n; c++) {
        Instance *inst = &self->instances[c];
        calling = inst;
        if ((status = inst->lib->exitInitializationMode(inst->component)) > fmi2Warning) {
            fail_status(self, inst, start, "fmi2ExitInitializationMode", status);
            return NULL;
        }
    }
    if (read_all_outputs(self, start) < 0)
        return NULL;
    Py_RETURN_NONE;
}

/* step(t, h): one Master.step at communication point t. */
static PyObject *Core_step(Core *self, PyObject *args) {
    double t, h;
    if (!PyArg_ParseTuple(args, "dd", &t, &h))
        return NULL;
    if (require_state(self, 1) < 0)
        return NULL;
    if (step_once(self, t, h) < 0)
        return NULL;
    Py_RETURN_NONE;
}

/* run(t0, h, k_start, k_stop, buffer=None, every=1, row=0, check=None) -> rows written.
 *
 * Steps k = k_start .. k_stop-1 from t_k = t0 + k h to t_(k+1) = t0 + (k+1) h (Master.run). After
 * step k, when (k + 1) % every == 0, the row [t_(k+1), outputs...] is written to the C-contiguous
 * float64 buffer at row index row, row+1, ... The buffer must hold every row asked for. On a failure
 * (or a Python signal handler raising between two steps, or check() raising: it is called after every
 * step, so a handler that only sets a flag can stop the run at a step boundary, never inside an FMU's
 * Python code) the exception is raised and steps_done/rows_done say how far the call got; the rows
 * written until then are valid. */
static PyObject *Core_run(Core *self, PyObject *args, PyObject *kwargs) {
    static char *keywords[] = {"t0", "h", "k_start", "k_stop", "buffer", "every", "row", "check", NULL};
    double t0, h;
    Py_ssize_t k_start, k_stop, every = 1, row = 0;
    PyObject *buffer_object = Py_None, *check = Py_None;
    self->steps_done = 0;
    self->rows_done = 0;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "ddnn|OnnO", keywords, &t0, &h, &k_start, &k_stop,
                                     &buffer_object, &every, &row, &check))
        return NULL;
    if (require_state(self, 1) < 0)
        return NULL;
    if (every < 1 || k_start < 0 || k_stop < k_start || row < 0) {
        PyErr_SetString(PyExc_ValueError, "need every >= 1, 0 <= k_start <= k_stop and row >= 0");
        return NULL;
    }
    Py_buffer view;
    double *rows = NULL;
    const size_t width = 1 + self->total_out;
    int have_buffer = buffer_object != Py_None;
    if (have_buffer) {
        if (PyObject_GetBuffer(buffer_object, &view, PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
            return NULL;
        if (view.itemsize != sizeof(double) || view.format == NULL || strcmp(view.format, "d") != 0) {
            PyBuffer_Release(&view);
            PyErr_SetString(PyExc_TypeError, "the trace buffer must hold float64 values");
            return NULL;
        }
        /* rows recorded: (k+1) % every == 0 for k in [k_start, k_stop) */
        Py_ssize_t wanted = k_stop / every - k_start / every;
        Py_ssize_t capacity = (Py_ssize_t)(view.len / (Py_ssize_t)(sizeof(double) * width));
        if (row + wanted > capacity) {
            PyBuffer_Release(&view);
            PyErr_Format(PyExc_ValueError, "the trace buffer holds %zd rows of %zu values; %zd needed",
                         capacity, width, row + wanted);
            return NULL;
        }
        rows = (double *)view.buf + (size_t)row * width;
    }
    const size_t total_out = self->total_out;
    const double *outputs = self->outputs;
    int failed = 0;
    Py_ssize_t countdown = every - (k_start % every); /* steps until the next recorded row */
    for (Py_ssize_t k = k_start; k < k_stop; k++) {
        /* t_k = t0 + k h exactly and each step spans t_(k+1) - t_k, as Master.run */
        double t = t0 + (double)k * h;
        double following = t0 + (double)(k + 1) * h;
        if (step_once(self, t, following - t) < 0) {
            failed = 1;
            break;
        }
        self->steps_done++;
        if (have_buffer && --countdown == 0) {
            countdown = every;
            rows[0] = following;
            memcpy(rows + 1, outputs, total_out * sizeof(double));
            rows += width;
            self->rows_done++;
        }
        if (PyErr_CheckSignals() < 0) { /* a handler that raises stops the run between two steps */
            failed = 1;
            break;
        }
        if (check != Py_None) {
            PyObject *result = PyObject_CallNoArgs(check);
            if (result == NULL) {
                failed = 1;
                break;
            }
            Py_DECREF(result);
        }
    }
    if (have_buffer)
        PyBuffer_Release(&view);
    if (failed)
        return NULL;
    return PyLong_FromSsize_t(self->rows_done);
}

/* outputs() -> list of lists, one per component (Master.outputs). */
static PyObject *Core_outputs(Core *self, PyObject *unused) {
    (void)unused;
    if (self->instances == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "Core is not constructed");
        return NULL;
    }
    PyObject *result = PyList_New((Py_ssize_t)self->n);
    if (result == NULL)
        return NULL;
    for (size_t c = 0; c < self->n; c++) {
        Instance *inst = &self->instances[c];
        PyObject *values = PyList_New((Py_ssize_t)inst->n_out);
        if (values == NULL) {
            Py_DECREF(result);
            return NULL;
        }
        for (size_t i = 0; i < inst->n_out; i++) {
            PyObject *value = PyFloat_FromDouble(self->outputs[inst->out_offset + i]);
            if (value == NULL) {
                Py_DECREF(values);
                Py_DECREF(result);
                return NULL;
            }
            PyList_SET_ITEM(values, (Py_ssize_t)i, value);
        }
        PyList_SET_ITEM(result, (Py_ssize_t)c, values);
    }
    return result;
}

/* messages(c) -> the latest log lines of component c, oldest first. */
static PyObject *Core_messages(Core *self, PyObject *arg) {
    Py_ssize_t c = PyLong_AsSsize_t(arg);
    if (c == -1 && PyErr_Occurred())
        return NULL;
    if (self->instances == NULL || c < 0 || (size_t)c >= self->n) {
        PyErr_SetString(PyExc_IndexError, "no such component");
        return NULL;
    }
    Instance *inst = &self->instances[c];
    size_t kept = inst->message_count < MESSAGES_KEPT ? inst->message_count : MESSAGES_KEPT;
    PyObject *result = PyList_New((Py_ssize_t)kept);
    if (result == NULL)
        return NULL;
    for (size_t i = 0; i < kept; i++) {
        const char *text = inst->messages[(inst->message_count - kept + i) % MESSAGES_KEPT];
        PyObject *line = PyUnicode_DecodeUTF8(text, (Py_ssize_t)strlen(text), "replace");
        if (line == NULL) {
            Py_DECREF(result);
            return NULL;
        }
        PyList_SET_ITEM(result, (Py_ssize_t)i, line);
    }
    return result;
}

/* close(): fmi2Terminate (status ignored) and fmi2FreeInstance for every instantiated component; the
 * libraries stay loaded. */
static PyObject *Core_close(Core *self, PyObject *unused) {
    (void)unused;
    if (self->instances == NULL || self->closed)
        Py_RETURN_NONE;
    for (size_t c = 0; c < self->n; c++) {
        Instance *inst = &self->instances[c];
        if (inst->instantiated) {
            calling = inst;
            inst->lib->terminate(inst->component);
            inst->lib->freeInstance(inst->component);
            inst->instantiated = 0;
            inst->component = NULL;
        }
    }
    calling = NULL;
    self->closed = 1;
    Py_RETURN_NONE;
}

static PyObject *Core_get_steps_done(Core *self, void *closure) {
    (void)closure;
    return PyLong_FromSsize_t(self->steps_done);
}

static PyObject *Core_get_rows_done(Core *self, void *closure) {
    (void)closure;
    return PyLong_FromSsize_t(self->rows_done);
}

static PyObject *Core_get_width(Core *self, void *closure) {
    (void)closure;
    return PyLong_FromSize_t(1 + self->total_out);
}

static PyMethodDef Core_methods[] = {
    {"initialize", (PyCFunction)Core_initialize, METH_O, "initialize(start_time): Master.initialize in C"},
    {"step", (PyCFunction)Core_step, METH_VARARGS, "step(t, h): one Master.step at communication point t"},
    {"run", (PyCFunction)(void (*)(void))Core_run, METH_VARARGS | METH_KEYWORDS,
     "run(t0, h, k_start, k_stop, buffer=None, every=1, row=0, check=None) -> rows written"},
    {"outputs", (PyCFunction)Core_outputs, METH_NOARGS, "outputs() -> every component's outputs, as lists"},
    {"messages", (PyCFunction)Core_messages, METH_O, "messages(c) -> latest log lines of component c"},
    {"close", (PyCFunction)Core_close, METH_NOARGS, "close(): terminate and free every instance"},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef Core_getset[] = {
    {"steps_done", (getter)Core_get_steps_done, NULL, "steps completed by the last run() call", NULL},
    {"rows_done", (getter)Core_get_rows_done, NULL, "rows written by the last run() call", NULL},
    {"width", (getter)Core_get_width, NULL, "values per trace row: 1 + every output", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject CoreType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "orchestrator.execution.native._core.Core",
    .tp_basicsize = sizeof(Core),
    .tp_dealloc = (destructor)Core_dealloc,
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Core(components, algorithm, error_class): FMU instances and the stepping loop in C",
    .tp_methods = Core_methods,
    .tp_getset = Core_getset,
    .tp_init = (initproc)Core_init,
    .tp_new = PyType_GenericNew,
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "orchestrator.execution.native._core",
    .m_doc = "The native stepping core: FMI 2.0 co-simulation FMUs stepped from C.",
    .m_size = -1,
};

PyMODINIT_FUNC PyInit__core(void) {
    if (PyType_Ready(&CoreType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    Py_INCREF(&CoreType);
    if (PyModule_AddObject(m, "Core", (PyObject *)&CoreType) < 0) {
        Py_DECREF(&CoreType);
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddIntConstant(m, "MESSAGES_KEPT", MESSAGES_KEPT) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}

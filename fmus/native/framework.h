/*
 * framework.h - what a native platoon FMU is made of, independent of the FMI version.
 *
 * A native FMU is one model file (vehicle.c or target.c: the science of fmus/model, equation by
 * equation), this small framework (variables, lazy outputs, step checks, FMU state) and one FMI
 * layer (fmi2.c; an FMI 3.0 layer calls the same functions). The variable table (names, value
 * references, types, start values) is generated at build time from the Python declarations
 * (fmus/slaves/Vehicle.py, VirtualTarget.py) into "variables.h" by fmus/native_build.py, so the
 * native and the pythonfmu FMUs share one list.
 *
 * The framework's calls mirror fmus/slaves/base.py (PlatoonSlave): every refusal names its reason
 * through the instance's log function, and an instance that failed (invalid parameters at the end
 * of initialization) refuses every later call but terminate, reset and free, cleanly.
 *
 * No FMI types appear here: statuses are FwStatus (same order as fmi2Status and fmi3Status), and
 * the FMI layer passes a log function that forwards messages to its host's logger.
 */
#ifndef PLATOON_FRAMEWORK_H
#define PLATOON_FRAMEWORK_H

#include <stddef.h>

typedef enum { FW_OK, FW_WARNING, FW_DISCARD, FW_ERROR, FW_FATAL } FwStatus;

typedef enum { VAR_REAL, VAR_INTEGER, VAR_BOOLEAN, VAR_STRING } VarType;
typedef enum { CAUSALITY_PARAMETER, CAUSALITY_INPUT, CAUSALITY_OUTPUT } Causality;

/* One FMU variable; its value reference is its index in the model's table. */
typedef struct {
    const char *name;
    VarType type;
    Causality causality;
    double start_real;       /* Real */
    int start_integer;       /* Integer, Boolean (0/1) */
    const char *start_string; /* String */
} VariableDef;

/* Life cycle, as in FMI 2.0 co-simulation (FMI 3.0 maps onto the same). */
typedef enum {
    MODE_INSTANTIATED,   /* parameters may be set, outputs are provisional */
    MODE_INITIALIZATION, /* same, between enter and exit initialization mode */
    MODE_STEP,           /* the model runs: doStep, inputs may be set */
    MODE_TERMINATED,
    MODE_FAILED          /* initialization failed: every later call is refused */
} Mode;

#define FW_MAX_STATE 16       /* the longest state vector of any model (m3pi in the sampled loop: 16, vehicle.c) */
#define FW_MAX_SUBSTEPS 100000 /* fmus.slaves.base.PlatoonSlave.MAX_SUBSTEPS_PER_STEP */
#define FW_TEXT_SIZE 4096

/* A bounded text buffer for reasons and log messages (never overflows, truncates). */
typedef struct {
    char text[FW_TEXT_SIZE];
    size_t length;
} FwText;

void fw_text_clear(FwText *out);
void fw_text_append(FwText *out, const char *format, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 2, 3)))
#endif
    ;
/* Python's repr(float): the shortest text that reads back as the same double ("0.0", "1e-05",
 * "inf", "nan"), so reasons read exactly like the pythonfmu FMUs' (fmus.model.factory). */
void fw_text_float(FwText *out, double value);

/* Python's repr(str) for the plain texts parameters hold ('sine'; "it's"). */
void fw_text_string_repr(FwText *out, const char *value);

typedef struct Instance Instance;

/* What a model's step leaves for the outputs computed right after it (fw_do_step), laid out as the
 * model likes: the vehicle keeps the target pose it extrapolated for the step's end, which its
 * outputs need again. The framework only carries it from the one call to the other. */
typedef struct {
    int known;
    double values[7];
} FwStepMemo;

/* What a model file provides to the framework; one constant per model (MODEL in vehicle.c /
 * target.c). The model's own cached configuration lives in Instance.config (config_size bytes). */
typedef struct {
    const char *identifier; /* modelIdentifier, e.g. "Vehicle" */
    const char *guid;       /* of this build (generated) */
    int variable_count;
    const VariableDef *variables;
    size_t config_size;
    /* Appends "; "-separated reasons why the current parameter values cannot run (the sentences of
     * fmus.model.factory.*_parameter_errors); returns how many there are. */
    int (*parameter_errors)(const Instance *instance, FwText *reasons);
    /* Caches the parameters (valid ones) in instance->config, as fmus.model.factory builds a
     * stepper, and sets instance->state to the initial state. */
    void (*configure)(Instance *instance);
    /* The longest RK4 substep (the max_substep parameter). */
    double (*max_substep)(const Instance *instance);
    /* Every output at instance->time from the state and the inputs, into values[vr]. memo is what
     * the step just taken left there (same inputs, same instance), or NULL when the outputs are
     * asked for at any other moment: a pure speed-up, the outputs must be the same numbers. */
    void (*outputs)(const Instance *instance, const FwStepMemo *memo, double *values);
    /* Advance the state from t by h; 0 when done, else nonzero with the reason in why (the state
     * may then be anything: the framework restores it). It may leave in memo what its outputs can
     * reuse. */
    int (*step)(Instance *instance, double t, double h, FwStepMemo *memo, FwText *why);
    /* Doubles of evolving memory beyond the state vector (the Link's messages in flight; 0 for the
     * others): zeroed at instantiation and reset, carried by the FMU state, serialized after the
     * state vector. A step does not back it up: a model with memory keeps what its state vector does
     * not point to as it was, so restoring the state vector undoes a step (link.c's ring). */
    int memory_count;
} ModelDef;

/* The FMI layer's log function: forwards one finished message to the host. */
typedef void (*FwLogFunction)(Instance *instance, FwStatus status, const char *category, const char *message);

struct Instance {
    unsigned int magic; /* FW_INSTANCE_MAGIC while alive: fw_is_instance */
    const ModelDef *model;
    char *name;
    Mode mode;
    FwLogFunction log;
    void *host;       /* the FMI layer's own data (callbacks, environment) */
    int logging_on;   /* debug logging; refusals are always logged */
    double start_time;
    double time;      /* the time the state describes */
    double state[FW_MAX_STATE];
    double *reals;    /* by value reference; outputs hold the latest computed values */
    int *integers;    /* Integer and Boolean, by value reference */
    char **strings;   /* String, by value reference (owned copies) */
    int outputs_valid;
    int *output_refs; /* the value references of the outputs, in order: the loops of every step */
    int output_count;
    double *scratch;  /* variable_count doubles: outputs computed before they are accepted */
    char *failure;    /* why the instance failed (MODE_FAILED), owned */
    void *config;     /* the model's cached parameters */
    double *memory;   /* model->memory_count doubles (NULL when 0) */
};

/* --- life cycle ------------------------------------------------------------------------------- */

/* A new instance with every variable at its start value, or NULL (out of memory). */
Instance *fw_instantiate(const ModelDef *model, const char *name, FwLogFunction log, void *host, int logging_on);
void fw_free(Instance *instance);
/* Nonzero if pointer is a live instance of this binary: the FMI layers refuse anything else
 * (NULL, an instance freed already, a state handed over as an instance) instead of using it.
 * Best effort: a pointer into memory that was never ours cannot be told apart safely. */
int fw_is_instance(const void *pointer);
FwStatus fw_setup_experiment(Instance *instance, double start_time);
FwStatus fw_enter_initialization(Instance *instance);
FwStatus fw_exit_initialization(Instance *instance);
FwStatus fw_terminate(Instance *instance);
FwStatus fw_reset(Instance *instance);

/* --- variables (refs may name any variable; a wrong reference or type is refused) ------------- */

FwStatus fw_get_real(Instance *instance, const unsigned int *refs, size_t count, double *values);
FwStatus fw_set_real(Instance *instance, const unsigned int *refs, size_t count, const double *values);
FwStatus fw_get_integer(Instance *instance, const unsigned int *refs, size_t count, int *values);
FwStatus fw_set_integer(Instance *instance, const unsigned int *refs, size_t count, const int *values);
/* Booleans as 0/1 ints (each FMI layer converts its own boolean type). */
FwStatus fw_get_boolean(Instance *instance, const unsigned int *refs, size_t count, int *values);
FwStatus fw_set_boolean(Instance *instance, const unsigned int *refs, size_t count, const int *values);
FwStatus fw_get_string(Instance *instance, const unsigned int *refs, size_t count, const char **values);
FwStatus fw_set_string(Instance *instance, const unsigned int *refs, size_t count, const char *const *values);

/* --- stepping ------------------------------------------------------------------------------------ */

/* One communication step: fmi2DoStep / fmi3DoStep. FW_ERROR for a call that cannot be a step
 * (failed or uninitialized instance, non-finite t or h, h <= 0, more than FW_MAX_SUBSTEPS
 * substeps); FW_DISCARD when the motion breaks down or its outputs would not be finite. In both
 * cases the instance is left exactly as it was. */
FwStatus fw_do_step(Instance *instance, double t, double h);

/* --- FMU state ----------------------------------------------------------------------------------- */

typedef struct FwState FwState;
FwStatus fw_get_state(Instance *instance, FwState **state); /* *state reused if not NULL */
FwStatus fw_set_state(Instance *instance, const FwState *state);
FwStatus fw_free_state(Instance *instance, FwState **state);
FwStatus fw_serialized_size(Instance *instance, const FwState *state, size_t *size);
FwStatus fw_serialize(Instance *instance, const FwState *state, unsigned char *bytes, size_t size);
FwStatus fw_deserialize(Instance *instance, const unsigned char *bytes, size_t size, FwState **state);

/* --- parameter checks (fmus.model.factory) --------------------------------------------------------- */

/* The index of String variable vr's value among allowed, or -1 (the parameters are checked already). */
int fw_chosen(const Instance *instance, int vr, const char *const *allowed, int count);
/* fmus.model.factory._choice: the index of String variable vr's value among allowed, or -1 with
 * "name = 'value': expected one of a, b" added to reasons ("; "-separated, counted in *errors). */
int fw_choice(const Instance *instance, int vr, const char *const *allowed, int count, FwText *reasons, int *errors);
/* fmus.model.factory._positive: Real variable vr must be a finite number > 0. */
void fw_positive(const Instance *instance, int vr, FwText *reasons, int *errors);

/* --- for the FMI layers and the models ----------------------------------------------------------- */

/* Logs a refusal (FW_ERROR) prefixed with the instance name and returns FW_ERROR. */
FwStatus fw_refuse(Instance *instance, const char *format, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 2, 3)))
#endif
    ;
void fw_log(Instance *instance, FwStatus status, const char *format, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 3, 4)))
#endif
    ;

#endif

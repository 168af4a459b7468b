/*
 * framework.c - variables, lazy outputs, checked steps and FMU state for a native platoon FMU.
 *
 * The behaviour mirrors fmus/slaves/base.py (PlatoonSlave) call by call; where the pythonfmu FMU
 * can only answer fmi2Fatal (its binary maps every Python exception to it) this answers the
 * status FMI asks for: fmi2Error for a call that is refused, fmi2Discard for a step whose motion
 * breaks down. Every refusal is logged with its reason; nothing a host passes (NULL pointers,
 * unknown value references, NaN, garbage state bytes) is read out of bounds or crashes.
 */
#include "framework.h"

#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* --- text ------------------------------------------------------------------------------------------ */

void fw_text_clear(FwText *out)
{
    out->length = 0;
    out->text[0] = '\0';
}

static void text_append_va(FwText *out, const char *format, va_list args)
{
    if (out->length >= FW_TEXT_SIZE - 1) return;
    int written = vsnprintf(out->text + out->length, FW_TEXT_SIZE - out->length, format, args);
    if (written < 0) return;
    out->length += (size_t)written;
    if (out->length > FW_TEXT_SIZE - 1) out->length = FW_TEXT_SIZE - 1;
}

void fw_text_append(FwText *out, const char *format, ...)
{
    va_list args;
    va_start(args, format);
    text_append_va(out, format, args);
    va_end(args);
}

void fw_text_float(FwText *out, double value)
{
    if (isnan(value)) {
        fw_text_append(out, "nan");
        return;
    }
    if (isinf(value)) {
        fw_text_append(out, value > 0 ? "inf" : "-inf");
        return;
    }
    /* the shortest round-tripping digits, then Python's layout (repr: fixed notation for decimal
     * exponents -4 < e <= 16 with ".0" added to integers, else d.ddde+XX) */
    char digits[40];
    int precision;
    for (precision = 0; precision < 17; ++precision) {
        snprintf(digits, sizeof digits, "%.*e", precision, value);
        if (strtod(digits, NULL) == value) break;
    }
    snprintf(digits, sizeof digits, "%.*e", precision, value);
    const char *p = digits;
    int negative = 0;
    if (*p == '-') {
        negative = 1;
        ++p;
    }
    char mantissa[24];
    size_t count = 0;
    for (; *p && *p != 'e'; ++p) { /* the digits only: the decimal point may be a host locale's ',' */
        if (*p >= '0' && *p <= '9' && count < sizeof mantissa - 1) mantissa[count++] = *p;
    }
    mantissa[count] = '\0';
    int exponent = *p == 'e' ? atoi(p + 1) : 0;
    int point = exponent + 1; /* digits before the decimal point */
    if (negative) fw_text_append(out, "-");
    if (point > -4 && point <= 16) {
        if (point <= 0) {
            fw_text_append(out, "0.");
            for (int i = 0; i < -point; ++i) fw_text_append(out, "0");
            fw_text_append(out, "%s", mantissa);
        } else if ((size_t)point >= count) {
            fw_text_append(out, "%s", mantissa);
            for (size_t i = count; i < (size_t)point; ++i) fw_text_append(out, "0");
            fw_text_append(out, ".0");
        } else {
            fw_text_append(out, "%.*s.%s", point, mantissa, mantissa + point);
        }
    } else {
        fw_text_append(out, "%c", mantissa[0]);
        if (count > 1) fw_text_append(out, ".%s", mantissa + 1);
        fw_text_append(out, "e%c%02d", exponent < 0 ? '-' : '+', abs(exponent));
    }
}

void fw_text_string_repr(FwText *out, const char *value)
{
    char quote = strchr(value, '\'') && !strchr(value, '"') ? '"' : '\'';
    fw_text_append(out, "%c", quote);
    for (const unsigned char *c = (const unsigned char *)value; *c; ++c) {
        if (*c == (unsigned char)quote || *c == '\\') {
            fw_text_append(out, "\\%c", *c);
        } else if (*c < 0x20 || *c == 0x7f) {
            fw_text_append(out, *c == '\n' ? "\\n" : *c == '\t' ? "\\t" : *c == '\r' ? "\\r" : "\\x%02x", *c);
        } else {
            fw_text_append(out, "%c", *c);
        }
    }
    fw_text_append(out, "%c", quote);
}

/* --- parameter checks ------------------------------------------------------------------------------ */

int fw_chosen(const Instance *instance, int vr, const char *const *allowed, int count)
{
    const char *value = instance->strings[vr] ? instance->strings[vr] : "";
    for (int i = 0; i < count; ++i) {
        if (strcmp(value, allowed[i]) == 0) return i;
    }
    return -1;
}

int fw_choice(const Instance *instance, int vr, const char *const *allowed, int count, FwText *reasons, int *errors)
{
    int index = fw_chosen(instance, vr, allowed, count);
    if (index >= 0) return index;
    const char *value = instance->strings[vr] ? instance->strings[vr] : "";
    fw_text_append(reasons, "%s%s = ", (*errors)++ ? "; " : "", instance->model->variables[vr].name);
    fw_text_string_repr(reasons, value);
    fw_text_append(reasons, ": expected one of ");
    for (int i = 0; i < count; ++i) fw_text_append(reasons, "%s%s", i ? ", " : "", allowed[i]);
    return -1;
}

void fw_positive(const Instance *instance, int vr, FwText *reasons, int *errors)
{
    double value = instance->reals[vr];
    if (isfinite(value) && value > 0.0) return;
    fw_text_append(reasons, "%s%s = ", (*errors)++ ? "; " : "", instance->model->variables[vr].name);
    fw_text_float(reasons, value);
    fw_text_append(reasons, ": must be a finite number > 0");
}

/* --- logging ------------------------------------------------------------------------------------- */

static const char *category_of(FwStatus status)
{
    switch (status) {
    case FW_OK: return "logAll";
    case FW_WARNING: return "logStatusWarning";
    case FW_DISCARD: return "logStatusDiscard";
    case FW_ERROR: return "logStatusError";
    default: return "logStatusFatal";
    }
}

static void log_va(Instance *instance, FwStatus status, const char *format, va_list args)
{
    if (!instance->log || (status == FW_OK && !instance->logging_on)) return;
    FwText message;
    fw_text_clear(&message);
    fw_text_append(&message, "%s: ", instance->name);
    text_append_va(&message, format, args);
    instance->log(instance, status, category_of(status), message.text);
}

void fw_log(Instance *instance, FwStatus status, const char *format, ...)
{
    va_list args;
    va_start(args, format);
    log_va(instance, status, format, args);
    va_end(args);
}

FwStatus fw_refuse(Instance *instance, const char *format, ...)
{
    va_list args;
    va_start(args, format);
    log_va(instance, FW_ERROR, format, args);
    va_end(args);
    return FW_ERROR;
}

/* fmus.slaves.base.PlatoonSlave._refuse_if_failed */
static int refused_if_failed(Instance *instance, FwStatus *status)
{
    if (instance->mode != MODE_FAILED) return 0;
    *status = fw_refuse(instance, "refused, the instance failed: %s", instance->failure);
    return 1;
}

#define REFUSE_IF_FAILED(instance)                                                                      \
    do {                                                                                                \
        FwStatus failed_status_;                                                                        \
        if (refused_if_failed((instance), &failed_status_)) return failed_status_;                      \
    } while (0)

/* --- life cycle ------------------------------------------------------------------------------------ */

static char *copy_text(const char *text)
{
    size_t length = strlen(text);
    char *copy = malloc(length + 1);
    if (copy) memcpy(copy, text, length + 1);
    return copy;
}

static int set_start_values(Instance *instance)
{
    const ModelDef *model = instance->model;
    for (int vr = 0; vr < model->variable_count; ++vr) {
        const VariableDef *variable = &model->variables[vr];
        instance->reals[vr] = variable->type == VAR_REAL ? variable->start_real : 0.0;
        instance->integers[vr] = variable->start_integer;
        free(instance->strings[vr]);
        instance->strings[vr] = NULL;
        if (variable->type == VAR_STRING) {
            instance->strings[vr] = copy_text(variable->start_string ? variable->start_string : "");
            if (!instance->strings[vr]) return 0;
        }
    }
    instance->start_time = instance->time = 0.0;
    memset(instance->state, 0, sizeof instance->state);
    if (instance->memory) memset(instance->memory, 0, (size_t)model->memory_count * sizeof *instance->memory);
    instance->outputs_valid = 0;
    return 1;
}

#define FW_INSTANCE_MAGIC 0x504c544eu /* "PLTN" */
#define FW_STATE_MAGIC 0x504c5453u    /* "PLTS" */

int fw_is_instance(const void *pointer)
{
    return pointer && ((const Instance *)pointer)->magic == FW_INSTANCE_MAGIC;
}

Instance *fw_instantiate(const ModelDef *model, const char *name, FwLogFunction log, void *host, int logging_on)
{
    Instance *instance = calloc(1, sizeof *instance);
    if (!instance) return NULL;
    instance->magic = FW_INSTANCE_MAGIC;
    int count = model->variable_count;
    instance->model = model;
    instance->name = copy_text(name ? name : "");
    instance->log = log;
    instance->host = host;
    instance->logging_on = logging_on;
    instance->mode = MODE_INSTANTIATED;
    instance->reals = calloc((size_t)count, sizeof *instance->reals);
    instance->integers = calloc((size_t)count, sizeof *instance->integers);
    instance->strings = calloc((size_t)count, sizeof *instance->strings);
    instance->scratch = calloc((size_t)count, sizeof *instance->scratch);
    instance->config = calloc(1, model->config_size ? model->config_size : 1);
    instance->output_refs = calloc((size_t)count, sizeof *instance->output_refs);
    if (model->memory_count > 0) instance->memory = calloc((size_t)model->memory_count, sizeof *instance->memory);
    if (!instance->name || !instance->reals || !instance->integers || !instance->strings || !instance->scratch ||
        !instance->config || !instance->output_refs || (model->memory_count > 0 && !instance->memory) ||
        !set_start_values(instance)) {
        fw_free(instance);
        return NULL;
    }
    for (int vr = 0; vr < count; ++vr) {
        if (model->variables[vr].causality == CAUSALITY_OUTPUT) instance->output_refs[instance->output_count++] = vr;
    }
    return instance;
}

void fw_free(Instance *instance)
{
    if (!instance) return;
    instance->magic = 0;
    if (instance->strings) {
        for (int vr = 0; vr < instance->model->variable_count; ++vr) free(instance->strings[vr]);
    }
    free(instance->strings);
    free(instance->integers);
    free(instance->reals);
    free(instance->scratch);
    free(instance->output_refs);
    free(instance->config);
    free(instance->memory);
    free(instance->failure);
    free(instance->name);
    free(instance);
}

/* fmus.slaves.base.PlatoonSlave.setup_experiment */
FwStatus fw_setup_experiment(Instance *instance, double start_time)
{
    REFUSE_IF_FAILED(instance);
    if (instance->mode != MODE_INSTANTIATED && instance->mode != MODE_INITIALIZATION) {
        return fw_refuse(instance, "setupExperiment is only allowed before initialization ends");
    }
    if (!isfinite(start_time)) return fw_refuse(instance, "start time %g is not finite", start_time);
    instance->start_time = instance->time = start_time;
    instance->outputs_valid = 0;
    return FW_OK;
}

FwStatus fw_enter_initialization(Instance *instance)
{
    REFUSE_IF_FAILED(instance);
    if (instance->mode != MODE_INSTANTIATED) {
        return fw_refuse(instance, "enterInitializationMode is only allowed once, after instantiation");
    }
    instance->mode = MODE_INITIALIZATION;
    return FW_OK;
}

/* The parameters' errors, or 0; reasons gets them "; "-separated. */
static int parameter_errors(const Instance *instance, FwText *reasons)
{
    fw_text_clear(reasons);
    return instance->model->parameter_errors(instance, reasons);
}

/* fmus.slaves.base.PlatoonSlave.exit_initialization_mode */
FwStatus fw_exit_initialization(Instance *instance)
{
    REFUSE_IF_FAILED(instance);
    if (instance->mode != MODE_INITIALIZATION && instance->mode != MODE_INSTANTIATED) {
        return fw_refuse(instance, "exitInitializationMode is only allowed in initialization mode");
    }
    FwText reasons;
    if (parameter_errors(instance, &reasons)) {
        FwText failure;
        fw_text_clear(&failure);
        fw_text_append(&failure, "invalid parameter(s): %s", reasons.text);
        free(instance->failure);
        instance->failure = copy_text(failure.text);
        if (!instance->failure) instance->failure = copy_text("invalid parameter(s)");
        instance->mode = MODE_FAILED;
        return fw_refuse(instance, "%s", failure.text);
    }
    instance->model->configure(instance);
    instance->time = instance->start_time;
    instance->mode = MODE_STEP;
    instance->outputs_valid = 0;
    return FW_OK;
}

/* fmus.slaves.base.PlatoonSlave.terminate: always allowed, also on a failed instance. */
FwStatus fw_terminate(Instance *instance)
{
    if (instance->mode != MODE_FAILED) instance->mode = MODE_TERMINATED;
    return FW_OK;
}

FwStatus fw_reset(Instance *instance)
{
    free(instance->failure);
    instance->failure = NULL;
    instance->mode = MODE_INSTANTIATED;
    if (!set_start_values(instance)) {
        instance->mode = MODE_FAILED;
        instance->failure = NULL;
        return fw_refuse(instance, "reset: out of memory");
    }
    return FW_OK;
}

/* --- outputs ----------------------------------------------------------------------------------------- */

/* How many outputs in values are not finite (0 if all are); their names and values into names
 * unless it is NULL. */
static int not_finite_outputs(const Instance *instance, const double *values, FwText *names)
{
    int count = 0;
    for (int i = 0; i < instance->output_count; ++i) {
        int vr = instance->output_refs[i];
        const VariableDef *variable = &instance->model->variables[vr];
        if (isfinite(values[vr])) continue;
        if (!names) {
            ++count;
            continue;
        }
        fw_text_append(names, "%s%s = ", count ? ", " : "", variable->name);
        fw_text_float(names, values[vr]);
        ++count;
    }
    return count;
}

static void copy_outputs(Instance *instance, const double *values)
{
    for (int i = 0; i < instance->output_count; ++i) {
        int vr = instance->output_refs[i];
        instance->reals[vr] = values[vr];
    }
    instance->outputs_valid = 1;
}

/* fmus.slaves.base.PlatoonSlave._current_outputs (and _provisional_outputs before the end of
 * initialization: the outputs of a model built from the parameters and inputs set so far). */
static FwStatus current_outputs(Instance *instance)
{
    if (instance->outputs_valid) return FW_OK;
    if (instance->mode == MODE_INSTANTIATED || instance->mode == MODE_INITIALIZATION) {
        FwText reasons;
        if (parameter_errors(instance, &reasons)) {
            return fw_refuse(instance, "no outputs while parameters are invalid: %s", reasons.text);
        }
        instance->model->configure(instance);
        instance->time = instance->start_time;
    }
    double *values = instance->scratch;
    memcpy(values, instance->reals, (size_t)instance->model->variable_count * sizeof *values);
    instance->model->outputs(instance, NULL, values);
    FwText names;
    fw_text_clear(&names);
    if (not_finite_outputs(instance, values, &names)) {
        return fw_refuse(instance, "output(s) %s not finite at t = %.6g s; check the inputs", names.text,
                         instance->time);
    }
    copy_outputs(instance, values);
    return FW_OK;
}

/* --- variables --------------------------------------------------------------------------------------- */

static const char *type_name(VarType type)
{
    switch (type) {
    case VAR_REAL: return "Real";
    case VAR_INTEGER: return "Integer";
    case VAR_BOOLEAN: return "Boolean";
    default: return "String";
    }
}

/* Checks the arguments of a get or set call: the instance may answer, the arrays exist, every
 * reference names a variable of the type. */
static FwStatus check_access(Instance *instance, const unsigned int *refs, size_t count, const void *values,
                             VarType type, const char *call)
{
    REFUSE_IF_FAILED(instance);
    if (count == 0) return FW_OK;
    if (!refs || !values) return fw_refuse(instance, "%s: the value reference or value array is NULL", call);
    for (size_t i = 0; i < count; ++i) {
        if (refs[i] >= (unsigned int)instance->model->variable_count) {
            return fw_refuse(instance, "%s: no variable has value reference %u", call, refs[i]);
        }
        const VariableDef *variable = &instance->model->variables[refs[i]];
        if (variable->type != type) {
            return fw_refuse(instance, "%s: %s (value reference %u) is a %s, not a %s", call, variable->name, refs[i],
                             type_name(variable->type), type_name(type));
        }
    }
    return FW_OK;
}

/* A set call may change this variable now: inputs any time, parameters before the end of
 * initialization (they are fixed), outputs never. */
static FwStatus check_settable(Instance *instance, const unsigned int *refs, size_t count, const char *call)
{
    for (size_t i = 0; i < count; ++i) {
        const VariableDef *variable = &instance->model->variables[refs[i]];
        if (variable->causality == CAUSALITY_OUTPUT) {
            return fw_refuse(instance, "%s: %s is an output; it cannot be set", call, variable->name);
        }
        if (variable->causality == CAUSALITY_PARAMETER && instance->mode != MODE_INSTANTIATED &&
            instance->mode != MODE_INITIALIZATION) {
            return fw_refuse(instance, "%s: refused %s: a parameter is fixed once initialization has ended", call,
                             variable->name);
        }
    }
    return FW_OK;
}

FwStatus fw_get_real(Instance *instance, const unsigned int *refs, size_t count, double *values)
{
    FwStatus status = check_access(instance, refs, count, values, VAR_REAL, "getReal");
    if (status != FW_OK || count == 0) return status;
    for (size_t i = 0; i < count; ++i) {
        if (instance->model->variables[refs[i]].causality == CAUSALITY_OUTPUT) {
            status = current_outputs(instance);
            if (status != FW_OK) return status;
            break;
        }
    }
    for (size_t i = 0; i < count; ++i) values[i] = instance->reals[refs[i]];
    return FW_OK;
}

/* fmus.slaves.base.PlatoonSlave.set_real: a value that is not finite is refused, naming it, before
 * anything is stored. */
FwStatus fw_set_real(Instance *instance, const unsigned int *refs, size_t count, const double *values)
{
    FwStatus status = check_access(instance, refs, count, values, VAR_REAL, "setReal");
    if (status != FW_OK || count == 0) return status;
    status = check_settable(instance, refs, count, "setReal");
    if (status != FW_OK) return status;
    FwText bad;
    fw_text_clear(&bad);
    int bad_count = 0;
    for (size_t i = 0; i < count; ++i) {
        if (isfinite(values[i])) continue;
        fw_text_append(&bad, "%s%s = ", bad_count++ ? ", " : "", instance->model->variables[refs[i]].name);
        fw_text_float(&bad, values[i]);
    }
    if (bad_count) return fw_refuse(instance, "refused %s: values must be finite", bad.text);
    for (size_t i = 0; i < count; ++i) instance->reals[refs[i]] = values[i];
    instance->outputs_valid = 0;
    return FW_OK;
}

FwStatus fw_get_integer(Instance *instance, const unsigned int *refs, size_t count, int *values)
{
    FwStatus status = check_access(instance, refs, count, values, VAR_INTEGER, "getInteger");
    if (status != FW_OK) return status;
    for (size_t i = 0; i < count; ++i) values[i] = instance->integers[refs[i]];
    return FW_OK;
}

FwStatus fw_set_integer(Instance *instance, const unsigned int *refs, size_t count, const int *values)
{
    FwStatus status = check_access(instance, refs, count, values, VAR_INTEGER, "setInteger");
    if (status == FW_OK) status = check_settable(instance, refs, count, "setInteger");
    if (status != FW_OK) return status;
    for (size_t i = 0; i < count; ++i) instance->integers[refs[i]] = values[i];
    if (count) instance->outputs_valid = 0;
    return FW_OK;
}

FwStatus fw_get_boolean(Instance *instance, const unsigned int *refs, size_t count, int *values)
{
    FwStatus status = check_access(instance, refs, count, values, VAR_BOOLEAN, "getBoolean");
    if (status != FW_OK) return status;
    for (size_t i = 0; i < count; ++i) values[i] = instance->integers[refs[i]];
    return FW_OK;
}

FwStatus fw_set_boolean(Instance *instance, const unsigned int *refs, size_t count, const int *values)
{
    FwStatus status = check_access(instance, refs, count, values, VAR_BOOLEAN, "setBoolean");
    if (status == FW_OK) status = check_settable(instance, refs, count, "setBoolean");
    if (status != FW_OK) return status;
    for (size_t i = 0; i < count; ++i) instance->integers[refs[i]] = values[i] != 0;
    if (count) instance->outputs_valid = 0;
    return FW_OK;
}

FwStatus fw_get_string(Instance *instance, const unsigned int *refs, size_t count, const char **values)
{
    FwStatus status = check_access(instance, refs, count, values, VAR_STRING, "getString");
    if (status != FW_OK) return status;
    for (size_t i = 0; i < count; ++i) values[i] = instance->strings[refs[i]];
    return FW_OK;
}

FwStatus fw_set_string(Instance *instance, const unsigned int *refs, size_t count, const char *const *values)
{
    FwStatus status = check_access(instance, refs, count, values, VAR_STRING, "setString");
    if (status == FW_OK) status = check_settable(instance, refs, count, "setString");
    if (status != FW_OK) return status;
    for (size_t i = 0; i < count; ++i) {
        if (!values[i]) {
            return fw_refuse(instance, "setString: the value of %s is NULL", instance->model->variables[refs[i]].name);
        }
    }
    for (size_t i = 0; i < count; ++i) {
        char *copy = copy_text(values[i]);
        if (!copy) return fw_refuse(instance, "setString: out of memory");
        free(instance->strings[refs[i]]);
        instance->strings[refs[i]] = copy;
    }
    if (count) instance->outputs_valid = 0;
    return FW_OK;
}

/* --- stepping ----------------------------------------------------------------------------------------- */

/* fmus.slaves.base.PlatoonSlave.do_step and _step */
FwStatus fw_do_step(Instance *instance, double t, double h)
{
    const char *refused = NULL;
    FwText reason;
    fw_text_clear(&reason);
    if (instance->mode == MODE_FAILED) {
        fw_text_append(&reason, "the instance failed: %s", instance->failure);
        refused = reason.text;
    } else if (instance->mode != MODE_STEP) {
        refused = "the instance is not initialized (call ExitInitializationMode first)";
    } else if (!(isfinite(t) && isfinite(h))) {
        refused = "time and step size must be finite numbers";
    } else if (h <= 0.0) {
        refused = "the step size must be > 0";
    } else {
        double max_substep = instance->model->max_substep(instance);
        double substeps = h / max_substep; /* substep_count without the rounding allowance */
        substeps = ceil(substeps - 1e-9);
        if (!(substeps <= FW_MAX_SUBSTEPS)) {
            fw_text_append(&reason,
                           "it needs %.3g RK4 substeps of at most max_substep = %g s; the limit is %d per step "
                           "(h <= %g s)",
                           substeps, max_substep, FW_MAX_SUBSTEPS, FW_MAX_SUBSTEPS * max_substep);
            refused = reason.text;
        }
    }
    if (refused) {
        fw_log(instance, FW_ERROR, "step from t = %.6g s by h = %.6g s refused: %s", t, h, refused);
        return FW_ERROR;
    }

    /* take the step; on any failure put everything back as it was */
    double state[FW_MAX_STATE];
    memcpy(state, instance->state, sizeof state);
    double time = instance->time;
    fw_text_clear(&reason);
    FwStepMemo memo;
    memo.known = 0;
    if (instance->model->step(instance, t, h, &memo, &reason) != 0) {
        memcpy(instance->state, state, sizeof state);
        instance->time = time;
        fw_log(instance, FW_DISCARD, "step from t = %.6g s by h = %.6g s refused: %s", t, h, reason.text);
        return FW_DISCARD;
    }
    int count = instance->model->variable_count;
    double *values = instance->scratch;
    memcpy(values, instance->reals, (size_t)count * sizeof *values);
    instance->model->outputs(instance, &memo, values);
    if (not_finite_outputs(instance, values, NULL)) {
        FwText names;
        fw_text_clear(&names);
        not_finite_outputs(instance, values, &names);
        memcpy(instance->state, state, sizeof state);
        instance->time = time;
        fw_log(instance, FW_DISCARD, "step from t = %.6g s by h = %.6g s refused: output(s) %s would not be finite; "
               "check the inputs", t, h, names.text);
        return FW_DISCARD;
    }
    copy_outputs(instance, values);
    return FW_OK;
}

/* --- FMU state ----------------------------------------------------------------------------------------
 *
 * A state holds everything that evolves and every variable's value, parameters included: setting
 * it reconfigures the model from the state's own parameters (fmus.slaves.base: a state restored
 * into an instance created with other parameters replays with the state's, not the
 * old trajectory with the new parameters).
 *
 * Serialized: the tag "platoon-cosim native FMU state", a format version, the model identifier,
 * the variable count and a digest of the variable table (names and types), then mode, start time,
 * time, the state vector and every variable's value; integers little-endian, doubles as their
 * IEEE bits. Bytes that are not exactly that are refused with the reason.
 */

#define STATE_TAG "platoon-cosim native FMU state"
#define STATE_FORMAT 1u

struct FwState {
    unsigned int magic; /* FW_STATE_MAGIC while alive */
    const ModelDef *model;
    Mode mode;
    double start_time;
    double time;
    double state[FW_MAX_STATE];
    double *memory; /* model->memory_count doubles (NULL when 0) */
    double *reals;
    int *integers;
    char **strings;
};

static void state_release(FwState *state)
{
    if (!state || state->magic != FW_STATE_MAGIC) return;
    state->magic = 0;
    if (state->strings) {
        for (int vr = 0; vr < state->model->variable_count; ++vr) free(state->strings[vr]);
    }
    free(state->strings);
    free(state->integers);
    free(state->reals);
    free(state->memory);
    free(state);
}

static FwState *state_new(const ModelDef *model)
{
    FwState *state = calloc(1, sizeof *state);
    if (!state) return NULL;
    state->magic = FW_STATE_MAGIC;
    state->model = model;
    state->reals = calloc((size_t)model->variable_count, sizeof *state->reals);
    state->integers = calloc((size_t)model->variable_count, sizeof *state->integers);
    state->strings = calloc((size_t)model->variable_count, sizeof *state->strings);
    if (model->memory_count > 0) state->memory = calloc((size_t)model->memory_count, sizeof *state->memory);
    if (!state->reals || !state->integers || !state->strings || (model->memory_count > 0 && !state->memory)) {
        state_release(state);
        return NULL;
    }
    return state;
}

/* Copies the values of one instance-like holder into another; 0 when out of memory. */
static int copy_values(const ModelDef *model, double *reals, int *integers, char **strings, const double *from_reals,
                       const int *from_integers, char *const *from_strings)
{
    int count = model->variable_count;
    char **copies = calloc((size_t)count, sizeof *copies);
    if (!copies) return 0;
    for (int vr = 0; vr < count; ++vr) {
        if (from_strings[vr] && !(copies[vr] = copy_text(from_strings[vr]))) {
            for (int i = 0; i < vr; ++i) free(copies[i]);
            free(copies);
            return 0;
        }
    }
    memcpy(reals, from_reals, (size_t)count * sizeof *reals);
    memcpy(integers, from_integers, (size_t)count * sizeof *integers);
    for (int vr = 0; vr < count; ++vr) {
        free(strings[vr]);
        strings[vr] = copies[vr];
    }
    free(copies);
    return 1;
}

/* fmus.slaves.base.PlatoonSlave._get_fmu_state */
FwStatus fw_get_state(Instance *instance, FwState **state)
{
    REFUSE_IF_FAILED(instance);
    if (!state) return fw_refuse(instance, "getFMUstate: the state pointer is NULL");
    FwState *target = *state;
    if (target && (target->magic != FW_STATE_MAGIC || target->model != instance->model)) {
        return fw_refuse(instance, "getFMUstate: the state to overwrite is not one of this model's");
    }
    if (!target && !(target = state_new(instance->model))) return fw_refuse(instance, "getFMUstate: out of memory");
    if (!copy_values(instance->model, target->reals, target->integers, target->strings, instance->reals,
                     instance->integers, instance->strings)) {
        if (!*state) state_release(target);
        return fw_refuse(instance, "getFMUstate: out of memory");
    }
    target->mode = instance->mode;
    target->start_time = instance->start_time;
    target->time = instance->time;
    memcpy(target->state, instance->state, sizeof target->state);
    if (instance->model->memory_count > 0) {
        memcpy(target->memory, instance->memory, (size_t)instance->model->memory_count * sizeof *target->memory);
    }
    *state = target;
    return FW_OK;
}

/* fmus.slaves.base.PlatoonSlave._set_fmu_state */
FwStatus fw_set_state(Instance *instance, const FwState *state)
{
    REFUSE_IF_FAILED(instance);
    if (!state) return fw_refuse(instance, "refused the FMU state: it is NULL");
    if (state->magic != FW_STATE_MAGIC) return fw_refuse(instance, "refused the FMU state: it is not a live FMU state");
    if (state->model != instance->model) {
        return fw_refuse(instance, "refused the FMU state: it is a state of another model, not of %s",
                         instance->model->identifier);
    }
    /* the state's parameters must be valid to rebuild its model: check them on a scratch copy */
    Instance scratch = *instance;
    scratch.reals = state->reals;
    scratch.integers = state->integers;
    scratch.strings = state->strings;
    FwText reasons;
    if (state->mode == MODE_STEP && parameter_errors(&scratch, &reasons)) {
        return fw_refuse(instance, "refused the FMU state: its parameters are invalid: %s", reasons.text);
    }
    if (!copy_values(instance->model, instance->reals, instance->integers, instance->strings, state->reals,
                     state->integers, state->strings)) {
        return fw_refuse(instance, "setFMUstate: out of memory");
    }
    instance->mode = state->mode == MODE_FAILED ? MODE_INITIALIZATION : state->mode;
    instance->start_time = state->start_time;
    if (instance->mode == MODE_STEP || instance->mode == MODE_TERMINATED) instance->model->configure(instance);
    instance->time = state->time;
    memcpy(instance->state, state->state, sizeof instance->state);
    if (instance->model->memory_count > 0) {
        memcpy(instance->memory, state->memory, (size_t)instance->model->memory_count * sizeof *instance->memory);
    }
    instance->outputs_valid = 0;
    return FW_OK;
}

FwStatus fw_free_state(Instance *instance, FwState **state)
{
    (void)instance;
    if (state) {
        state_release(*state);
        *state = NULL;
    }
    return FW_OK;
}

/* --- serialization: a little writer and reader over a byte buffer ------------------------------- */

typedef struct {
    unsigned char *bytes; /* NULL: only count */
    size_t size, position;
    int overflow;
} Writer;

static void put_bytes(Writer *w, const void *data, size_t size)
{
    if (w->bytes) {
        if (w->position + size > w->size) {
            w->overflow = 1;
            return;
        }
        memcpy(w->bytes + w->position, data, size);
    }
    w->position += size;
}

static void put_u32(Writer *w, uint32_t value)
{
    unsigned char b[4] = {(unsigned char)value, (unsigned char)(value >> 8), (unsigned char)(value >> 16),
                          (unsigned char)(value >> 24)};
    put_bytes(w, b, 4);
}

static void put_u64(Writer *w, uint64_t value)
{
    put_u32(w, (uint32_t)value);
    put_u32(w, (uint32_t)(value >> 32));
}

static void put_double(Writer *w, double value)
{
    uint64_t bits;
    memcpy(&bits, &value, sizeof bits);
    put_u64(w, bits);
}

static void put_text(Writer *w, const char *text)
{
    size_t length = strlen(text);
    put_u32(w, (uint32_t)length);
    put_bytes(w, text, length);
}

/* FNV-1a of the variable table's names and types: a state fits only the table it was taken from. */
static uint32_t layout_digest(const ModelDef *model)
{
    uint32_t hash = 2166136261u;
    for (int vr = 0; vr < model->variable_count; ++vr) {
        for (const char *c = model->variables[vr].name; *c; ++c) hash = (hash ^ (unsigned char)*c) * 16777619u;
        hash = (hash ^ (unsigned char)('0' + model->variables[vr].type)) * 16777619u;
    }
    return hash;
}

static void write_state(Writer *w, const FwState *state)
{
    const ModelDef *model = state->model;
    put_bytes(w, STATE_TAG, sizeof STATE_TAG - 1);
    put_u32(w, STATE_FORMAT);
    put_text(w, model->identifier);
    put_u32(w, (uint32_t)model->variable_count);
    put_u32(w, layout_digest(model));
    put_u32(w, (uint32_t)state->mode);
    put_double(w, state->start_time);
    put_double(w, state->time);
    put_u32(w, FW_MAX_STATE);
    for (int i = 0; i < FW_MAX_STATE; ++i) put_double(w, state->state[i]);
    for (int i = 0; i < model->memory_count; ++i) put_double(w, state->memory[i]); /* none but the Link's */
    for (int vr = 0; vr < model->variable_count; ++vr) {
        switch (model->variables[vr].type) {
        case VAR_REAL: put_double(w, state->reals[vr]); break;
        case VAR_INTEGER:
        case VAR_BOOLEAN: put_u32(w, (uint32_t)state->integers[vr]); break;
        case VAR_STRING: put_text(w, state->strings[vr] ? state->strings[vr] : ""); break;
        }
    }
}

FwStatus fw_serialized_size(Instance *instance, const FwState *state, size_t *size)
{
    if (!state || !size) return fw_refuse(instance, "serializedFMUstateSize: a NULL argument");
    if (state->magic != FW_STATE_MAGIC) return fw_refuse(instance, "serializedFMUstateSize: not a live FMU state");
    Writer w = {NULL, 0, 0, 0};
    write_state(&w, state);
    *size = w.position;
    return FW_OK;
}

FwStatus fw_serialize(Instance *instance, const FwState *state, unsigned char *bytes, size_t size)
{
    if (!state || !bytes) return fw_refuse(instance, "serializeFMUstate: a NULL argument");
    if (state->magic != FW_STATE_MAGIC) return fw_refuse(instance, "serializeFMUstate: not a live FMU state");
    Writer w = {bytes, size, 0, 0};
    write_state(&w, state);
    if (w.overflow) return fw_refuse(instance, "serializeFMUstate: %zu bytes are too few", size);
    return FW_OK;
}

typedef struct {
    const unsigned char *bytes;
    size_t size, position;
    const char *problem;
} Reader;

static const unsigned char *take(Reader *r, size_t size)
{
    if (r->problem) return NULL;
    if (size > r->size - r->position) {
        r->problem = "it ends too early";
        return NULL;
    }
    const unsigned char *at = r->bytes + r->position;
    r->position += size;
    return at;
}

static uint32_t get_u32(Reader *r)
{
    const unsigned char *b = take(r, 4);
    if (!b) return 0;
    return (uint32_t)b[0] | (uint32_t)b[1] << 8 | (uint32_t)b[2] << 16 | (uint32_t)b[3] << 24;
}

static double get_double(Reader *r)
{
    uint64_t low = get_u32(r);
    uint64_t high = get_u32(r);
    uint64_t bits = low | high << 32;
    double value;
    memcpy(&value, &bits, sizeof value);
    return value;
}

/* A string of the serialized state as a fresh copy, or NULL with r->problem set. */
static char *get_text(Reader *r)
{
    uint32_t length = get_u32(r);
    const unsigned char *at = take(r, length);
    if (!at) return NULL;
    if (memchr(at, '\0', length)) {
        r->problem = "a string holds a NUL byte";
        return NULL;
    }
    char *text = malloc((size_t)length + 1);
    if (!text) {
        r->problem = "out of memory";
        return NULL;
    }
    memcpy(text, at, length);
    text[length] = '\0';
    return text;
}

/* fmus.slaves.base.PlatoonSlave._fmu_state_from_bytes and _state_problem */
FwStatus fw_deserialize(Instance *instance, const unsigned char *bytes, size_t size, FwState **state)
{
    REFUSE_IF_FAILED(instance);
    if (!state || (!bytes && size)) return fw_refuse(instance, "deSerializeFMUstate: a NULL argument");
    const ModelDef *model = instance->model;
    Reader r = {bytes, size, 0, NULL};
    const unsigned char *tag = take(&r, sizeof STATE_TAG - 1);
    if (!tag || memcmp(tag, STATE_TAG, sizeof STATE_TAG - 1) != 0) {
        return fw_refuse(instance, "refused the FMU state: the serialized state cannot be read (it is not a "
                         "serialized state of a native platoon-cosim FMU)");
    }
    uint32_t format = get_u32(&r);
    if (!r.problem && format != STATE_FORMAT) {
        return fw_refuse(instance, "refused the FMU state: the serialized state cannot be read (format %u, this FMU "
                         "reads format %u)", format, STATE_FORMAT);
    }
    char *identifier = get_text(&r);
    uint32_t count = get_u32(&r);
    uint32_t digest = get_u32(&r);
    if (!r.problem && strcmp(identifier, model->identifier) != 0) {
        FwStatus status = fw_refuse(instance, "refused the FMU state: it is a state of '%s', not of %s", identifier,
                                    model->identifier);
        free(identifier);
        return status;
    }
    free(identifier);
    if (!r.problem && (count != (uint32_t)model->variable_count || digest != layout_digest(model))) {
        return fw_refuse(instance, "refused the FMU state: its variables are not this model's");
    }
    FwState *result = state_new(model);
    if (!result) return fw_refuse(instance, "deSerializeFMUstate: out of memory");
    uint32_t mode = get_u32(&r);
    if (!r.problem && mode > MODE_FAILED) r.problem = "its mode is unknown";
    result->mode = (Mode)mode;
    result->start_time = get_double(&r);
    result->time = get_double(&r);
    if (get_u32(&r) != FW_MAX_STATE && !r.problem) r.problem = "its state vector has the wrong length";
    for (int i = 0; i < FW_MAX_STATE; ++i) result->state[i] = get_double(&r);
    for (int i = 0; i < model->memory_count; ++i) result->memory[i] = get_double(&r);
    for (int vr = 0; vr < model->variable_count && !r.problem; ++vr) {
        switch (model->variables[vr].type) {
        case VAR_REAL: result->reals[vr] = get_double(&r); break;
        case VAR_INTEGER: result->integers[vr] = (int)get_u32(&r); break;
        case VAR_BOOLEAN: result->integers[vr] = get_u32(&r) != 0; break;
        case VAR_STRING: result->strings[vr] = get_text(&r); break;
        }
    }
    if (!r.problem && r.position != r.size) r.problem = "it has bytes left over at its end";
    if (r.problem) {
        state_release(result);
        return fw_refuse(instance, "refused the FMU state: the serialized state cannot be read (%s)", r.problem);
    }
    *state = result;
    return FW_OK;
}

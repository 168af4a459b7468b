/*
 * fmi3.c - the FMI 3.0 co-simulation entry points of a native platoon FMU.
 *
 * The FMI 3.0 twin of fmi2.c over the same framework (framework.h) and model file: each function
 * checks its instance pointer and hands over to the framework, which knows no FMI version, so both
 * FMU kinds compute the same numbers and refuse the same calls for the same reasons. What FMI 3.0
 * adds is mapped here:
 *
 * - fmi3EnterInitializationMode carries the start time (FMI 2.0: fmi2SetupExperiment).
 * - The independent variable `time` (PLATOON_TIME_VALUE_REFERENCE, generated into fmi3config.h from
 *   fmus/modeldescription3.py) can be
 *   read with fmi3GetFloat64 (the time the state describes), never set.
 * - fmi3DoStep reports lastSuccessfulTime (the time of the state after the call: t + h after a
 *   step, the unchanged time after a refused one) and never asks to terminate, to handle events or
 *   returns early; a refused step leaves the instance exactly as it was, so a host may retry.
 * - Get/Set check that nValues equals nValueReferences (every variable is a scalar).
 *
 * Functions of Model Exchange, Scheduled Execution, clocks, events and derivatives, and the types
 * the models do not have (Float32, Int8.., Binary, Clock) answer fmi3Error with a logged "not
 * supported", never crash. The standard's headers come from FMPy's copy (fmpy/c-code) at build time
 * (fmus/native_build.py), as for fmi2.c; MODEL.guid of an FMI 3.0 build is its instantiationToken.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi3Functions.h"
#include "fmi3config.h" /* generated: PLATOON_TIME_VALUE_REFERENCE */
#include "framework.h"

extern const ModelDef MODEL;

/* The framework takes value references as unsigned int and integers as int. */
typedef char value_reference_is_unsigned_int[sizeof(fmi3ValueReference) == sizeof(unsigned int) ? 1 : -1];
typedef char int32_is_int[sizeof(fmi3Int32) == sizeof(int) ? 1 : -1];

/* What the host gave fmi3InstantiateCoSimulation, kept for the logger. */
typedef struct {
    fmi3InstanceEnvironment environment;
    fmi3LogMessageCallback log_message;
} Host;

static void log_to_host(Instance *instance, FwStatus status, const char *category, const char *message)
{
    const Host *host = (const Host *)instance->host;
    if (!host || !host->log_message) return;
    host->log_message(host->environment, (fmi3Status)status, category, message); /* FwStatus: fmi3Status order */
}

#define INSTANCE(c) ((Instance *)(c))
/* NULL or anything that is not a live instance (freed already, a state) has nobody to log to: fmi3Error. */
#define CHECK(c)                                                                                        \
    do {                                                                                                \
        if (!fw_is_instance(c)) return fmi3Error;                                                       \
    } while (0)

/* Every variable is a scalar: as many values as value references, and arrays where there are any. */
#define CHECK_ARRAYS(c, function, vr, nvr, values, nValues)                                             \
    do {                                                                                                \
        if ((nValues) != (nvr)) {                                                                       \
            return (fmi3Status)fw_refuse(INSTANCE(c), "%s: %zu values for %zu value references; every "  \
                                         "variable of this FMU is a scalar", function, (size_t)(nValues), \
                                         (size_t)(nvr));                                                \
        }                                                                                               \
        if ((nvr) > 0 && (!(vr) || !(values))) {                                                        \
            return (fmi3Status)fw_refuse(INSTANCE(c), "%s: NULL value references or values", function);  \
        }                                                                                               \
    } while (0)

static const char *const LOG_CATEGORIES[] = {"logStatusWarning", "logStatusDiscard", "logStatusError",
                                             "logStatusFatal", "logAll"};

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance instance, fmi3Boolean loggingOn, size_t nCategories,
                               const fmi3String categories[])
{
    CHECK(instance);
    for (size_t i = 0; i < nCategories; ++i) {
        int known = 0;
        for (size_t k = 0; categories && categories[i] && k < sizeof LOG_CATEGORIES / sizeof *LOG_CATEGORIES; ++k) {
            known |= strcmp(categories[i], LOG_CATEGORIES[k]) == 0;
        }
        if (!known) {
            return (fmi3Status)fw_refuse(INSTANCE(instance), "fmi3SetDebugLogging: unknown log category %s "
                                         "(the model description lists them)",
                                         categories && categories[i] ? categories[i] : "(NULL)");
        }
    }
    /* refusals are logged whatever this says; it switches the other messages */
    INSTANCE(instance)->logging_on = loggingOn;
    return fmi3OK;
}

static void refuse_before_instance(fmi3InstanceEnvironment environment, fmi3LogMessageCallback log_message,
                                   const char *name, const char *what)
{
    if (!log_message) return;
    char message[512];
    snprintf(message, sizeof message, "%s: %s", name, what);
    log_message(environment, fmi3Error, "logStatusError", message);
}

fmi3Instance fmi3InstantiateCoSimulation(fmi3String instanceName, fmi3String instantiationToken,
                                         fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                         fmi3Boolean eventModeUsed, fmi3Boolean earlyReturnAllowed,
                                         const fmi3ValueReference requiredIntermediateVariables[],
                                         size_t nRequiredIntermediateVariables,
                                         fmi3InstanceEnvironment instanceEnvironment,
                                         fmi3LogMessageCallback logMessage,
                                         fmi3IntermediateUpdateCallback intermediateUpdate)
{
    (void)resourcePath; /* the model needs no files */
    (void)visible;
    (void)earlyReturnAllowed; /* it never returns early */
    (void)requiredIntermediateVariables;
    (void)intermediateUpdate; /* providesIntermediateUpdate="false" */
    const char *name = instanceName ? instanceName : "";
    char reason[400];
    if (eventModeUsed) {
        snprintf(reason, sizeof reason, "%s has no event mode (hasEventMode=\"false\"); instantiate it with "
                 "eventModeUsed = false", MODEL.identifier);
        refuse_before_instance(instanceEnvironment, logMessage, name, reason);
        return NULL;
    }
    if (nRequiredIntermediateVariables > 0) {
        snprintf(reason, sizeof reason, "%s provides no intermediate variables (providesIntermediateUpdate=\"false\")",
                 MODEL.identifier);
        refuse_before_instance(instanceEnvironment, logMessage, name, reason);
        return NULL;
    }
    if (!instantiationToken || strcmp(instantiationToken, MODEL.guid) != 0) {
        snprintf(reason, sizeof reason, "instantiationToken %.100s does not match this binary's %s (a model "
                 "description from another build?)", instantiationToken ? instantiationToken : "(NULL)", MODEL.guid);
        refuse_before_instance(instanceEnvironment, logMessage, name, reason);
        return NULL;
    }
    Host *host = malloc(sizeof *host);
    if (!host) return NULL;
    host->environment = instanceEnvironment;
    host->log_message = logMessage;
    Instance *instance = fw_instantiate(&MODEL, name, log_to_host, host, loggingOn);
    if (!instance) {
        refuse_before_instance(instanceEnvironment, logMessage, name, "out of memory");
        free(host);
        return NULL;
    }
    return instance;
}

fmi3Instance fmi3InstantiateModelExchange(fmi3String instanceName, fmi3String instantiationToken,
                                          fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                          fmi3InstanceEnvironment instanceEnvironment,
                                          fmi3LogMessageCallback logMessage)
{
    (void)instantiationToken, (void)resourcePath, (void)visible, (void)loggingOn;
    refuse_before_instance(instanceEnvironment, logMessage, instanceName ? instanceName : "",
                           "this is a co-simulation FMU; Model Exchange is not supported");
    return NULL;
}

fmi3Instance fmi3InstantiateScheduledExecution(fmi3String instanceName, fmi3String instantiationToken,
                                               fmi3String resourcePath, fmi3Boolean visible,
                                               fmi3Boolean loggingOn, fmi3InstanceEnvironment instanceEnvironment,
                                               fmi3LogMessageCallback logMessage, fmi3ClockUpdateCallback clockUpdate,
                                               fmi3LockPreemptionCallback lockPreemption,
                                               fmi3UnlockPreemptionCallback unlockPreemption)
{
    (void)instantiationToken, (void)resourcePath, (void)visible, (void)loggingOn;
    (void)clockUpdate, (void)lockPreemption, (void)unlockPreemption;
    refuse_before_instance(instanceEnvironment, logMessage, instanceName ? instanceName : "",
                           "this is a co-simulation FMU; Scheduled Execution is not supported");
    return NULL;
}

void fmi3FreeInstance(fmi3Instance instance)
{
    if (!fw_is_instance(instance)) return; /* NULL, or freed already */
    free(INSTANCE(instance)->host);
    fw_free(INSTANCE(instance));
}

fmi3Status fmi3EnterInitializationMode(fmi3Instance instance, fmi3Boolean toleranceDefined, fmi3Float64 tolerance,
                                       fmi3Float64 startTime, fmi3Boolean stopTimeDefined, fmi3Float64 stopTime)
{
    (void)toleranceDefined, (void)tolerance; /* fixed RK4 substeps: no tolerance to honour */
    (void)stopTimeDefined, (void)stopTime;
    CHECK(instance);
    Instance *c = INSTANCE(instance);
    if (c->mode == MODE_INSTANTIATED) { /* otherwise fw_enter_initialization says why not */
        FwStatus status = fw_setup_experiment(c, startTime);
        if (status != FW_OK) return (fmi3Status)status;
    }
    return (fmi3Status)fw_enter_initialization(c);
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance instance)
{
    CHECK(instance);
    return (fmi3Status)fw_exit_initialization(INSTANCE(instance));
}

fmi3Status fmi3Terminate(fmi3Instance instance)
{
    CHECK(instance);
    return (fmi3Status)fw_terminate(INSTANCE(instance));
}

fmi3Status fmi3Reset(fmi3Instance instance)
{
    CHECK(instance);
    return (fmi3Status)fw_reset(INSTANCE(instance));
}

/* --- variables --------------------------------------------------------------------------------- */

static int names_time(const fmi3ValueReference vr[], size_t nvr)
{
    for (size_t i = 0; i < nvr; ++i) {
        if (vr[i] == PLATOON_TIME_VALUE_REFERENCE) return 1;
    }
    return 0;
}

fmi3Status fmi3GetFloat64(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, fmi3Float64 values[],
                          size_t nValues)
{
    CHECK(instance);
    CHECK_ARRAYS(instance, "fmi3GetFloat64", vr, nvr, values, nValues);
    Instance *c = INSTANCE(instance);
    if (!names_time(vr, nvr)) return (fmi3Status)fw_get_real(c, vr, nvr, values);
    if (c->mode == MODE_FAILED) return (fmi3Status)fw_refuse(c, "refused, the instance failed: %s", c->failure);
    for (size_t i = 0; i < nvr; ++i) { /* time among the others: one at a time */
        if (vr[i] == PLATOON_TIME_VALUE_REFERENCE) {
            values[i] = c->time;
        } else {
            FwStatus status = fw_get_real(c, &vr[i], 1, &values[i]);
            if (status != FW_OK) return (fmi3Status)status;
        }
    }
    return fmi3OK;
}

fmi3Status fmi3SetFloat64(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                          const fmi3Float64 values[], size_t nValues)
{
    CHECK(instance);
    CHECK_ARRAYS(instance, "fmi3SetFloat64", vr, nvr, values, nValues);
    if (names_time(vr, nvr)) {
        return (fmi3Status)fw_refuse(INSTANCE(instance), "fmi3SetFloat64: time (value reference %u) is the "
                                     "independent variable; it cannot be set", PLATOON_TIME_VALUE_REFERENCE);
    }
    return (fmi3Status)fw_set_real(INSTANCE(instance), vr, nvr, values);
}

fmi3Status fmi3GetInt32(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, fmi3Int32 values[],
                        size_t nValues)
{
    CHECK(instance);
    CHECK_ARRAYS(instance, "fmi3GetInt32", vr, nvr, values, nValues);
    return (fmi3Status)fw_get_integer(INSTANCE(instance), vr, nvr, (int *)values);
}

fmi3Status fmi3SetInt32(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, const fmi3Int32 values[],
                        size_t nValues)
{
    CHECK(instance);
    CHECK_ARRAYS(instance, "fmi3SetInt32", vr, nvr, values, nValues);
    return (fmi3Status)fw_set_integer(INSTANCE(instance), vr, nvr, (const int *)values);
}

/* fmi3Boolean is a C bool, the framework's booleans are ints: one value at a time. */
fmi3Status fmi3GetBoolean(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, fmi3Boolean values[],
                          size_t nValues)
{
    CHECK(instance);
    CHECK_ARRAYS(instance, "fmi3GetBoolean", vr, nvr, values, nValues);
    for (size_t i = 0; i < nvr; ++i) {
        int value;
        FwStatus status = fw_get_boolean(INSTANCE(instance), &vr[i], 1, &value);
        if (status != FW_OK) return (fmi3Status)status;
        values[i] = value != 0;
    }
    return fmi3OK;
}

fmi3Status fmi3SetBoolean(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                          const fmi3Boolean values[], size_t nValues)
{
    CHECK(instance);
    CHECK_ARRAYS(instance, "fmi3SetBoolean", vr, nvr, values, nValues);
    for (size_t i = 0; i < nvr; ++i) {
        int value = values[i] ? 1 : 0;
        FwStatus status = fw_set_boolean(INSTANCE(instance), &vr[i], 1, &value);
        if (status != FW_OK) return (fmi3Status)status;
    }
    return fmi3OK;
}

fmi3Status fmi3GetString(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, fmi3String values[],
                         size_t nValues)
{
    CHECK(instance);
    CHECK_ARRAYS(instance, "fmi3GetString", vr, nvr, values, nValues);
    return (fmi3Status)fw_get_string(INSTANCE(instance), vr, nvr, values);
}

fmi3Status fmi3SetString(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, const fmi3String values[],
                         size_t nValues)
{
    CHECK(instance);
    CHECK_ARRAYS(instance, "fmi3SetString", vr, nvr, values, nValues);
    return (fmi3Status)fw_set_string(INSTANCE(instance), vr, nvr, values);
}

/* --- stepping ------------------------------------------------------------------------------------ */

fmi3Status fmi3DoStep(fmi3Instance instance, fmi3Float64 currentCommunicationPoint, fmi3Float64 communicationStepSize,
                      fmi3Boolean noSetFMUStatePriorToCurrentPoint, fmi3Boolean *eventHandlingNeeded,
                      fmi3Boolean *terminateSimulation, fmi3Boolean *earlyReturn, fmi3Float64 *lastSuccessfulTime)
{
    (void)noSetFMUStatePriorToCurrentPoint;
    CHECK(instance);
    Instance *c = INSTANCE(instance);
    FwStatus status = fw_do_step(c, currentCommunicationPoint, communicationStepSize);
    /* a refused step kept the state: the host may retry (smaller step, other inputs) or roll back */
    if (eventHandlingNeeded) *eventHandlingNeeded = fmi3False;
    if (terminateSimulation) *terminateSimulation = fmi3False;
    if (earlyReturn) *earlyReturn = fmi3False;
    if (lastSuccessfulTime) *lastSuccessfulTime = c->time;
    return (fmi3Status)status;
}

/* --- FMU state ----------------------------------------------------------------------------------- */

fmi3Status fmi3GetFMUState(fmi3Instance instance, fmi3FMUState *FMUState)
{
    CHECK(instance);
    if (!FMUState) return (fmi3Status)fw_refuse(INSTANCE(instance), "fmi3GetFMUState: FMUState is NULL");
    return (fmi3Status)fw_get_state(INSTANCE(instance), (FwState **)FMUState);
}

fmi3Status fmi3SetFMUState(fmi3Instance instance, fmi3FMUState FMUState)
{
    CHECK(instance);
    return (fmi3Status)fw_set_state(INSTANCE(instance), (const FwState *)FMUState);
}

fmi3Status fmi3FreeFMUState(fmi3Instance instance, fmi3FMUState *FMUState)
{
    CHECK(instance);
    if (!FMUState) return fmi3OK; /* nothing to free */
    return (fmi3Status)fw_free_state(INSTANCE(instance), (FwState **)FMUState);
}

fmi3Status fmi3SerializedFMUStateSize(fmi3Instance instance, fmi3FMUState FMUState, size_t *size)
{
    CHECK(instance);
    return (fmi3Status)fw_serialized_size(INSTANCE(instance), (const FwState *)FMUState, size);
}

fmi3Status fmi3SerializeFMUState(fmi3Instance instance, fmi3FMUState FMUState, fmi3Byte serializedState[],
                                 size_t size)
{
    CHECK(instance);
    return (fmi3Status)fw_serialize(INSTANCE(instance), (const FwState *)FMUState, serializedState, size);
}

fmi3Status fmi3DeserializeFMUState(fmi3Instance instance, const fmi3Byte serializedState[], size_t size,
                                   fmi3FMUState *FMUState)
{
    CHECK(instance);
    if (!FMUState) return (fmi3Status)fw_refuse(INSTANCE(instance), "fmi3DeserializeFMUState: FMUState is NULL");
    return (fmi3Status)fw_deserialize(INSTANCE(instance), serializedState, size, (FwState **)FMUState);
}

/* --- not supported: fmi3Error with the reason logged ---------------------------------------------- */

static fmi3Status unsupported(fmi3Instance instance, const char *function, const char *why)
{
    CHECK(instance);
    return (fmi3Status)fw_refuse(INSTANCE(instance), "%s is not supported: %s", function, why);
}

#define NO_VARIABLES_OF(type) "this FMU has no " type " variables (only Float64, Int32, Boolean and String)"
#define NOT_CO_SIMULATION "it belongs to Model Exchange or Scheduled Execution; this is a co-simulation FMU"
#define NO_EVENTS "this FMU has no event mode and no clocks (hasEventMode=\"false\")"

/* Get and Set of a type the models do not have. */
#define UNSUPPORTED_TYPE(name, c_type, type_name)                                                          \
    fmi3Status fmi3Get##name(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, c_type values[], \
                             size_t nValues)                                                               \
    {                                                                                                      \
        (void)vr, (void)nvr, (void)values, (void)nValues;                                                  \
        return unsupported(instance, "fmi3Get" #name, NO_VARIABLES_OF(type_name));                         \
    }                                                                                                      \
    fmi3Status fmi3Set##name(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,              \
                             const c_type values[], size_t nValues)                                        \
    {                                                                                                      \
        (void)vr, (void)nvr, (void)values, (void)nValues;                                                  \
        return unsupported(instance, "fmi3Set" #name, NO_VARIABLES_OF(type_name));                         \
    }

UNSUPPORTED_TYPE(Float32, fmi3Float32, "Float32")
UNSUPPORTED_TYPE(Int8, fmi3Int8, "Int8")
UNSUPPORTED_TYPE(UInt8, fmi3UInt8, "UInt8")
UNSUPPORTED_TYPE(Int16, fmi3Int16, "Int16")
UNSUPPORTED_TYPE(UInt16, fmi3UInt16, "UInt16")
UNSUPPORTED_TYPE(UInt32, fmi3UInt32, "UInt32")
UNSUPPORTED_TYPE(Int64, fmi3Int64, "Int64")
UNSUPPORTED_TYPE(UInt64, fmi3UInt64, "UInt64")

fmi3Status fmi3GetBinary(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, size_t valueSizes[],
                         fmi3Binary values[], size_t nValues)
{
    (void)vr, (void)nvr, (void)valueSizes, (void)values, (void)nValues;
    return unsupported(instance, "fmi3GetBinary", NO_VARIABLES_OF("Binary"));
}

fmi3Status fmi3SetBinary(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, const size_t valueSizes[],
                         const fmi3Binary values[], size_t nValues)
{
    (void)vr, (void)nvr, (void)valueSizes, (void)values, (void)nValues;
    return unsupported(instance, "fmi3SetBinary", NO_VARIABLES_OF("Binary"));
}

fmi3Status fmi3GetClock(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, fmi3Clock values[])
{
    (void)vr, (void)nvr, (void)values;
    return unsupported(instance, "fmi3GetClock", NO_EVENTS);
}

fmi3Status fmi3SetClock(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, const fmi3Clock values[])
{
    (void)vr, (void)nvr, (void)values;
    return unsupported(instance, "fmi3SetClock", NO_EVENTS);
}

fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance instance, fmi3ValueReference valueReference,
                                               size_t *nDependencies)
{
    (void)valueReference, (void)nDependencies;
    return unsupported(instance, "fmi3GetNumberOfVariableDependencies",
                       "providesPerElementDependencies=\"false\"; the model description lists the dependencies");
}

fmi3Status fmi3GetVariableDependencies(fmi3Instance instance, fmi3ValueReference dependent,
                                       size_t elementIndicesOfDependent[], fmi3ValueReference independents[],
                                       size_t elementIndicesOfIndependents[], fmi3DependencyKind dependencyKinds[],
                                       size_t nDependencies)
{
    (void)dependent, (void)elementIndicesOfDependent, (void)independents, (void)elementIndicesOfIndependents;
    (void)dependencyKinds, (void)nDependencies;
    return unsupported(instance, "fmi3GetVariableDependencies",
                       "providesPerElementDependencies=\"false\"; the model description lists the dependencies");
}

#define DERIVATIVE_ARGUMENTS                                                                              \
    fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns,                        \
        const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[], size_t nSeed,       \
        fmi3Float64 sensitivity[], size_t nSensitivity
#define IGNORE_DERIVATIVE_ARGUMENTS                                                                       \
    (void)unknowns, (void)nUnknowns, (void)knowns, (void)nKnowns, (void)seed, (void)nSeed, (void)sensitivity, \
        (void)nSensitivity

fmi3Status fmi3GetDirectionalDerivative(DERIVATIVE_ARGUMENTS)
{
    IGNORE_DERIVATIVE_ARGUMENTS;
    return unsupported(instance, "fmi3GetDirectionalDerivative", "providesDirectionalDerivatives=\"false\"");
}

fmi3Status fmi3GetAdjointDerivative(DERIVATIVE_ARGUMENTS)
{
    IGNORE_DERIVATIVE_ARGUMENTS;
    return unsupported(instance, "fmi3GetAdjointDerivative", "providesAdjointDerivatives=\"false\"");
}

fmi3Status fmi3GetOutputDerivatives(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                    const fmi3Int32 orders[], fmi3Float64 values[], size_t nValues)
{
    (void)vr, (void)nvr, (void)orders, (void)values, (void)nValues;
    return unsupported(instance, "fmi3GetOutputDerivatives", "maxOutputDerivativeOrder=\"0\"");
}

fmi3Status fmi3EnterConfigurationMode(fmi3Instance instance)
{
    return unsupported(instance, "fmi3EnterConfigurationMode", "this FMU has no structural parameters");
}

fmi3Status fmi3ExitConfigurationMode(fmi3Instance instance)
{
    return unsupported(instance, "fmi3ExitConfigurationMode", "this FMU has no structural parameters");
}

fmi3Status fmi3EnterEventMode(fmi3Instance instance) { return unsupported(instance, "fmi3EnterEventMode", NO_EVENTS); }

fmi3Status fmi3EnterStepMode(fmi3Instance instance) { return unsupported(instance, "fmi3EnterStepMode", NO_EVENTS); }

fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance instance)
{
    return unsupported(instance, "fmi3EvaluateDiscreteStates", NO_EVENTS);
}

fmi3Status fmi3UpdateDiscreteStates(fmi3Instance instance, fmi3Boolean *discreteStatesNeedUpdate,
                                    fmi3Boolean *terminateSimulation, fmi3Boolean *nominalsOfContinuousStatesChanged,
                                    fmi3Boolean *valuesOfContinuousStatesChanged, fmi3Boolean *nextEventTimeDefined,
                                    fmi3Float64 *nextEventTime)
{
    (void)discreteStatesNeedUpdate, (void)terminateSimulation, (void)nominalsOfContinuousStatesChanged;
    (void)valuesOfContinuousStatesChanged, (void)nextEventTimeDefined, (void)nextEventTime;
    return unsupported(instance, "fmi3UpdateDiscreteStates", NO_EVENTS);
}

fmi3Status fmi3GetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                  fmi3Float64 intervals[], fmi3IntervalQualifier qualifiers[])
{
    (void)vr, (void)nvr, (void)intervals, (void)qualifiers;
    return unsupported(instance, "fmi3GetIntervalDecimal", NO_EVENTS);
}

fmi3Status fmi3GetIntervalFraction(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                   fmi3UInt64 counters[], fmi3UInt64 resolutions[], fmi3IntervalQualifier qualifiers[])
{
    (void)vr, (void)nvr, (void)counters, (void)resolutions, (void)qualifiers;
    return unsupported(instance, "fmi3GetIntervalFraction", NO_EVENTS);
}

fmi3Status fmi3GetShiftDecimal(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr, fmi3Float64 shifts[])
{
    (void)vr, (void)nvr, (void)shifts;
    return unsupported(instance, "fmi3GetShiftDecimal", NO_EVENTS);
}

fmi3Status fmi3GetShiftFraction(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                fmi3UInt64 counters[], fmi3UInt64 resolutions[])
{
    (void)vr, (void)nvr, (void)counters, (void)resolutions;
    return unsupported(instance, "fmi3GetShiftFraction", NO_EVENTS);
}

fmi3Status fmi3SetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                  const fmi3Float64 intervals[])
{
    (void)vr, (void)nvr, (void)intervals;
    return unsupported(instance, "fmi3SetIntervalDecimal", NO_EVENTS);
}

fmi3Status fmi3SetIntervalFraction(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                   const fmi3UInt64 counters[], const fmi3UInt64 resolutions[])
{
    (void)vr, (void)nvr, (void)counters, (void)resolutions;
    return unsupported(instance, "fmi3SetIntervalFraction", NO_EVENTS);
}

fmi3Status fmi3SetShiftDecimal(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                               const fmi3Float64 shifts[])
{
    (void)vr, (void)nvr, (void)shifts;
    return unsupported(instance, "fmi3SetShiftDecimal", NO_EVENTS);
}

fmi3Status fmi3SetShiftFraction(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                                const fmi3UInt64 counters[], const fmi3UInt64 resolutions[])
{
    (void)vr, (void)nvr, (void)counters, (void)resolutions;
    return unsupported(instance, "fmi3SetShiftFraction", NO_EVENTS);
}

fmi3Status fmi3ActivateModelPartition(fmi3Instance instance, fmi3ValueReference clockReference,
                                      fmi3Float64 activationTime)
{
    (void)clockReference, (void)activationTime;
    return unsupported(instance, "fmi3ActivateModelPartition", NOT_CO_SIMULATION);
}

fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance instance)
{
    return unsupported(instance, "fmi3EnterContinuousTimeMode", NOT_CO_SIMULATION);
}

fmi3Status fmi3CompletedIntegratorStep(fmi3Instance instance, fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi3Boolean *enterEventMode, fmi3Boolean *terminateSimulation)
{
    (void)noSetFMUStatePriorToCurrentPoint, (void)enterEventMode, (void)terminateSimulation;
    return unsupported(instance, "fmi3CompletedIntegratorStep", NOT_CO_SIMULATION);
}

fmi3Status fmi3SetTime(fmi3Instance instance, fmi3Float64 time)
{
    (void)time;
    return unsupported(instance, "fmi3SetTime", NOT_CO_SIMULATION);
}

fmi3Status fmi3SetContinuousStates(fmi3Instance instance, const fmi3Float64 continuousStates[],
                                   size_t nContinuousStates)
{
    (void)continuousStates, (void)nContinuousStates;
    return unsupported(instance, "fmi3SetContinuousStates", NOT_CO_SIMULATION);
}

fmi3Status fmi3GetContinuousStateDerivatives(fmi3Instance instance, fmi3Float64 derivatives[], size_t nContinuousStates)
{
    (void)derivatives, (void)nContinuousStates;
    return unsupported(instance, "fmi3GetContinuousStateDerivatives", NOT_CO_SIMULATION);
}

fmi3Status fmi3GetEventIndicators(fmi3Instance instance, fmi3Float64 eventIndicators[], size_t nEventIndicators)
{
    (void)eventIndicators, (void)nEventIndicators;
    return unsupported(instance, "fmi3GetEventIndicators", NOT_CO_SIMULATION);
}

fmi3Status fmi3GetContinuousStates(fmi3Instance instance, fmi3Float64 continuousStates[], size_t nContinuousStates)
{
    (void)continuousStates, (void)nContinuousStates;
    return unsupported(instance, "fmi3GetContinuousStates", NOT_CO_SIMULATION);
}

fmi3Status fmi3GetNominalsOfContinuousStates(fmi3Instance instance, fmi3Float64 nominals[], size_t nContinuousStates)
{
    (void)nominals, (void)nContinuousStates;
    return unsupported(instance, "fmi3GetNominalsOfContinuousStates", NOT_CO_SIMULATION);
}

fmi3Status fmi3GetNumberOfEventIndicators(fmi3Instance instance, size_t *nEventIndicators)
{
    (void)nEventIndicators;
    return unsupported(instance, "fmi3GetNumberOfEventIndicators", NOT_CO_SIMULATION);
}

fmi3Status fmi3GetNumberOfContinuousStates(fmi3Instance instance, size_t *nContinuousStates)
{
    (void)nContinuousStates;
    return unsupported(instance, "fmi3GetNumberOfContinuousStates", NOT_CO_SIMULATION);
}

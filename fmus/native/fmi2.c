/*
 * fmi2.c - the FMI 2.0 co-simulation entry points of a native platoon FMU.
 *
 * A thin layer: each fmi2 function checks its instance pointer and hands over to the framework
 * (framework.h), which knows no FMI version. The standard's headers come from FMPy's copy
 * (fmpy/c-code) at build time (fmus/native_build.py); they are not kept in this repository.
 * Functions of Model Exchange and the optional ones we do not support answer fmi2Error with a
 * logged reason, never crash.
 */
#include <stdarg.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "framework.h"

extern const ModelDef MODEL;

/* What the host gave fmi2Instantiate, kept for the logger. */
typedef struct {
    fmi2CallbackFunctions callbacks;
} Host;

static void log_to_host(Instance *instance, FwStatus status, const char *category, const char *message)
{
    const Host *host = (const Host *)instance->host;
    if (!host || !host->callbacks.logger) return;
    /* the message as an argument, never as the format: a '%' in it stays a '%' */
    host->callbacks.logger(host->callbacks.componentEnvironment, instance->name, (fmi2Status)status, category, "%s",
                           message);
}

/* The instance behind c; the calls below answer fmi2Error for NULL or anything that is not a live
 * instance (nobody to log to). */
#define INSTANCE(c) ((Instance *)(c))
#define CHECK(c)                                                                                        \
    do {                                                                                                \
        if (!fw_is_instance(c)) return fmi2Error;                                                       \
    } while (0)

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }

const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[])
{
    (void)nCategories;
    (void)categories;
    CHECK(c);
    INSTANCE(c)->logging_on = loggingOn != fmi2False;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean loggingOn)
{
    (void)fmuResourceLocation;
    (void)visible;
    const char *name = instanceName ? instanceName : "";
    if (!functions || !functions->logger) {
        /* FMI 2.0 requires the logger; without it there is nobody to tell why: refuse. */
        return NULL;
    }
    if (fmuType != fmi2CoSimulation) {
        functions->logger(functions->componentEnvironment, name, fmi2Error, "logStatusError",
                          "%s: %s is a co-simulation FMU; fmi2ModelExchange is not supported", name, MODEL.identifier);
        return NULL;
    }
    if (!fmuGUID || strcmp(fmuGUID, MODEL.guid) != 0) {
        functions->logger(functions->componentEnvironment, name, fmi2Error, "logStatusError",
                          "%s: GUID %s does not match this binary's %s (a model description from another build?)",
                          name, fmuGUID ? fmuGUID : "(NULL)", MODEL.guid);
        return NULL;
    }
    Host *host = malloc(sizeof *host);
    if (!host) return NULL;
    host->callbacks = *functions;
    Instance *instance = fw_instantiate(&MODEL, name, log_to_host, host, loggingOn != fmi2False);
    if (!instance) {
        functions->logger(functions->componentEnvironment, name, fmi2Error, "logStatusError", "%s: out of memory",
                          name);
        free(host);
        return NULL;
    }
    return instance;
}

void fmi2FreeInstance(fmi2Component c)
{
    if (!fw_is_instance(c)) return; /* NULL, or freed already */
    free(INSTANCE(c)->host);
    fw_free(INSTANCE(c));
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime)
{
    (void)toleranceDefined;
    (void)tolerance;
    (void)stopTimeDefined;
    (void)stopTime;
    CHECK(c);
    return (fmi2Status)fw_setup_experiment(INSTANCE(c), startTime);
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c)
{
    CHECK(c);
    return (fmi2Status)fw_enter_initialization(INSTANCE(c));
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c)
{
    CHECK(c);
    return (fmi2Status)fw_exit_initialization(INSTANCE(c));
}

fmi2Status fmi2Terminate(fmi2Component c)
{
    CHECK(c);
    return (fmi2Status)fw_terminate(INSTANCE(c));
}

fmi2Status fmi2Reset(fmi2Component c)
{
    CHECK(c);
    return (fmi2Status)fw_reset(INSTANCE(c));
}

/* --- variables --------------------------------------------------------------------------------- */

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[])
{
    CHECK(c);
    return (fmi2Status)fw_get_real(INSTANCE(c), vr, nvr, value);
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[])
{
    CHECK(c);
    return (fmi2Status)fw_get_integer(INSTANCE(c), vr, nvr, value);
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean value[])
{
    CHECK(c);
    return (fmi2Status)fw_get_boolean(INSTANCE(c), vr, nvr, value); /* fmi2Boolean is an int */
}

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2String value[])
{
    CHECK(c);
    return (fmi2Status)fw_get_string(INSTANCE(c), vr, nvr, value);
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[])
{
    CHECK(c);
    return (fmi2Status)fw_set_real(INSTANCE(c), vr, nvr, value);
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[])
{
    CHECK(c);
    return (fmi2Status)fw_set_integer(INSTANCE(c), vr, nvr, value);
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Boolean value[])
{
    CHECK(c);
    return (fmi2Status)fw_set_boolean(INSTANCE(c), vr, nvr, value);
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2String value[])
{
    CHECK(c);
    return (fmi2Status)fw_set_string(INSTANCE(c), vr, nvr, value);
}

/* --- FMU state ----------------------------------------------------------------------------------- */

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate)
{
    CHECK(c);
    return (fmi2Status)fw_get_state(INSTANCE(c), (FwState **)FMUstate);
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate)
{
    CHECK(c);
    return (fmi2Status)fw_set_state(INSTANCE(c), (const FwState *)FMUstate);
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate)
{
    CHECK(c);
    return (fmi2Status)fw_free_state(INSTANCE(c), (FwState **)FMUstate);
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size)
{
    CHECK(c);
    return (fmi2Status)fw_serialized_size(INSTANCE(c), (const FwState *)FMUstate, size);
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte serializedState[], size_t size)
{
    CHECK(c);
    return (fmi2Status)fw_serialize(INSTANCE(c), (const FwState *)FMUstate, (unsigned char *)serializedState, size);
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate)
{
    CHECK(c);
    return (fmi2Status)fw_deserialize(INSTANCE(c), (const unsigned char *)serializedState, size,
                                      (FwState **)FMUstate);
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[], size_t nUnknown,
                                        const fmi2ValueReference vKnown_ref[], size_t nKnown,
                                        const fmi2Real dvKnown[], fmi2Real dvUnknown[])
{
    (void)vUnknown_ref, (void)nUnknown, (void)vKnown_ref, (void)nKnown, (void)dvKnown, (void)dvUnknown;
    CHECK(c);
    return (fmi2Status)fw_refuse(INSTANCE(c), "fmi2GetDirectionalDerivative is not provided "
                                              "(providesDirectionalDerivative=\"false\")");
}

/* --- co-simulation ----------------------------------------------------------------------------------- */

fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[])
{
    (void)vr, (void)nvr, (void)order, (void)value;
    CHECK(c);
    return (fmi2Status)fw_refuse(INSTANCE(c), "fmi2SetRealInputDerivatives is not supported "
                                              "(canInterpolateInputs=\"false\")");
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[])
{
    (void)vr, (void)nvr, (void)order, (void)value;
    CHECK(c);
    return (fmi2Status)fw_refuse(INSTANCE(c), "fmi2GetRealOutputDerivatives is not supported "
                                              "(maxOutputDerivativeOrder=\"0\")");
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint, fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentPoint)
{
    (void)noSetFMUStatePriorToCurrentPoint;
    CHECK(c);
    return (fmi2Status)fw_do_step(INSTANCE(c), currentCommunicationPoint, communicationStepSize);
}

fmi2Status fmi2CancelStep(fmi2Component c)
{
    CHECK(c);
    return (fmi2Status)fw_refuse(INSTANCE(c), "fmi2CancelStep: steps are never asynchronous "
                                              "(canRunAsynchronuously=\"false\")");
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value)
{
    (void)s, (void)value;
    CHECK(c);
    return (fmi2Status)fw_refuse(INSTANCE(c), "fmi2GetStatus: no asynchronous step to ask about");
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value)
{
    CHECK(c);
    if (s == fmi2LastSuccessfulTime && value) {
        *value = INSTANCE(c)->time;
        return fmi2OK;
    }
    return (fmi2Status)fw_refuse(INSTANCE(c), "fmi2GetRealStatus: only fmi2LastSuccessfulTime is answered");
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value)
{
    (void)s, (void)value;
    CHECK(c);
    return (fmi2Status)fw_refuse(INSTANCE(c), "fmi2GetIntegerStatus: no integer status");
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value)
{
    (void)s, (void)value;
    CHECK(c);
    return (fmi2Status)fw_refuse(INSTANCE(c), "fmi2GetBooleanStatus: no boolean status");
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value)
{
    (void)s, (void)value;
    CHECK(c);
    return (fmi2Status)fw_refuse(INSTANCE(c), "fmi2GetStringStatus: no string status");
}

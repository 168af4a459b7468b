/*
 * minimal_host.c - a minimal FMI 2.0 co-simulation importer in plain C.
 *
 * It proves that our FMUs run in a host that is not Python: no FMI library, no FMI headers,
 * only dlopen()/dlsym() and the handful of fmi2 types declared below.
 *
 * Usage:
 *   minimal_host <unzipped_fmu_dir> <guid> <steps> <step_size> <vr_x> <vr_y> <vr_speed> <vr_gap>
 *                [<model_identifier>]
 *
 * Loads <dir>/binaries/<platform>/<model_identifier>.<so|dll|dylib> (default model identifier:
 * Vehicle; <platform> the folder of the platform it was compiled for, tests/c_host/loader.h),
 * instantiates it as a co-simulation slave with the resource location file://<dir>/resources,
 * initialises it at t = 0 and takes <steps> communication steps of <step_size>. The
 * communication points are t_n = n * step_size (no accumulated rounding; the step passed to
 * fmi2DoStep is t_{n+1} - t_n, as FMPy does). Prints the CSV header "t,x,y,speed,gap" and one
 * line per communication point, t_0 included, with 17 significant digits to stdout. Messages
 * from the FMU go to stderr.
 *
 * Exit status: 0 on success; 2 bad arguments; 3 the binary cannot be loaded (typically: the
 * Python symbols it needs are not available, see docs/fmus.md); 4 a function is missing;
 * 5 fmi2Instantiate returned NULL; 6 an FMI call returned a status other than fmi2OK.
 *
 * Build: cc -std=c99 -Wall -o minimal_host minimal_host.c -ldl
 */

#define _POSIX_C_SOURCE 200809L

#include <limits.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "loader.h"

/* --- The parts of fmi2FunctionTypes.h / fmi2TypesPlatform.h this host needs. --- */

typedef void *fmi2Component;
typedef void *fmi2ComponentEnvironment;
typedef const char *fmi2String;
typedef int fmi2Boolean;
typedef double fmi2Real;
typedef unsigned int fmi2ValueReference;

#define fmi2True 1
#define fmi2False 0

typedef enum { fmi2OK, fmi2Warning, fmi2Discard, fmi2Error, fmi2Fatal, fmi2Pending } fmi2Status;
typedef enum { fmi2ModelExchange, fmi2CoSimulation } fmi2Type;

typedef void (*fmi2CallbackLogger)(fmi2ComponentEnvironment, fmi2String, fmi2Status, fmi2String,
                                   fmi2String, ...);
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

typedef fmi2Component (*fmi2InstantiateTYPE)(fmi2String, fmi2Type, fmi2String, fmi2String,
                                              const fmi2CallbackFunctions *, fmi2Boolean,
                                              fmi2Boolean);
typedef fmi2Status (*fmi2SetupExperimentTYPE)(fmi2Component, fmi2Boolean, fmi2Real, fmi2Real,
                                              fmi2Boolean, fmi2Real);
typedef fmi2Status (*fmi2EnterInitializationModeTYPE)(fmi2Component);
typedef fmi2Status (*fmi2ExitInitializationModeTYPE)(fmi2Component);
typedef fmi2Status (*fmi2DoStepTYPE)(fmi2Component, fmi2Real, fmi2Real, fmi2Boolean);
typedef fmi2Status (*fmi2GetRealTYPE)(fmi2Component, const fmi2ValueReference[], size_t,
                                      fmi2Real[]);
typedef fmi2Status (*fmi2TerminateTYPE)(fmi2Component);
typedef void (*fmi2FreeInstanceTYPE)(fmi2Component);

/* --- Host. --- */

static const char *status_name(fmi2Status s)
{
    switch (s) {
    case fmi2OK: return "fmi2OK";
    case fmi2Warning: return "fmi2Warning";
    case fmi2Discard: return "fmi2Discard";
    case fmi2Error: return "fmi2Error";
    case fmi2Fatal: return "fmi2Fatal";
    case fmi2Pending: return "fmi2Pending";
    }
    return "unknown status";
}

static void logger(fmi2ComponentEnvironment env, fmi2String instance, fmi2Status status,
                   fmi2String category, fmi2String message, ...)
{
    va_list args;
    (void)env;
    fprintf(stderr, "[%s] %s (%s): ", instance ? instance : "?", status_name(status),
            category ? category : "");
    va_start(args, message);
    vfprintf(stderr, message ? message : "", args);
    va_end(args);
    fputc('\n', stderr);
}

static void *resolve(library_t lib, const char *name)
{
    void *f = library_symbol(lib, name);
    if (!f) {
        fprintf(stderr, "minimal_host: the FMU binary does not export %s: %s\n", name, library_error());
        exit(4);
    }
    return f;
}

static void check(fmi2Status status, const char *call)
{
    if (status != fmi2OK) {
        fprintf(stderr, "minimal_host: %s returned %s (%d), expected fmi2OK\n", call,
                status_name(status), (int)status);
        exit(6);
    }
}

static int parse_long(const char *text, long *out)
{
    char *end;
    *out = strtol(text, &end, 10);
    return *text != '\0' && *end == '\0';
}

static int parse_double(const char *text, double *out)
{
    char *end;
    *out = strtod(text, &end);
    return *text != '\0' && *end == '\0';
}

int main(int argc, char **argv)
{
    if (argc != 9 && argc != 10) {
        fprintf(stderr,
                "usage: %s <unzipped_fmu_dir> <guid> <steps> <step_size> <vr_x> <vr_y> "
                "<vr_speed> <vr_gap> [<model_identifier>]\n",
                argv[0]);
        return 2;
    }
    const char *dir = argv[1];
    const char *guid = argv[2];
    const char *model_identifier = argc == 10 ? argv[9] : "Vehicle";
    long steps;
    double h;
    fmi2ValueReference vrs[4];
    if (!parse_long(argv[3], &steps) || steps < 0) {
        fprintf(stderr, "minimal_host: <steps> must be a non-negative integer, got '%s'\n", argv[3]);
        return 2;
    }
    if (!parse_double(argv[4], &h) || !(h > 0.0)) {
        fprintf(stderr, "minimal_host: <step_size> must be a positive number, got '%s'\n", argv[4]);
        return 2;
    }
    for (int i = 0; i < 4; ++i) {
        long vr;
        if (!parse_long(argv[5 + i], &vr) || vr < 0 || (unsigned long)vr > UINT_MAX) {
            fprintf(stderr, "minimal_host: value reference '%s' is not valid\n", argv[5 + i]);
            return 2;
        }
        vrs[i] = (fmi2ValueReference)vr;
    }

    char library[PATH_MAX];
    char resources[PATH_MAX + 16];
    if (snprintf(library, sizeof library, "%s/binaries/" FMI2_PLATFORM "/%s" FMU_SUFFIX, dir, model_identifier) >=
            (int)sizeof library ||
        snprintf(resources, sizeof resources, "file://%s/resources", dir) >=
            (int)sizeof resources) {
        fprintf(stderr, "minimal_host: path too long\n");
        return 2;
    }

    library_t lib = library_open(library);
    if (!lib) {
        fprintf(stderr, "minimal_host: cannot load %s: %s\n", library, library_error());
        return 3;
    }

    fmi2InstantiateTYPE instantiate = (fmi2InstantiateTYPE)resolve(lib, "fmi2Instantiate");
    fmi2SetupExperimentTYPE setup_experiment =
        (fmi2SetupExperimentTYPE)resolve(lib, "fmi2SetupExperiment");
    fmi2EnterInitializationModeTYPE enter_init =
        (fmi2EnterInitializationModeTYPE)resolve(lib, "fmi2EnterInitializationMode");
    fmi2ExitInitializationModeTYPE exit_init =
        (fmi2ExitInitializationModeTYPE)resolve(lib, "fmi2ExitInitializationMode");
    fmi2DoStepTYPE do_step = (fmi2DoStepTYPE)resolve(lib, "fmi2DoStep");
    fmi2GetRealTYPE get_real = (fmi2GetRealTYPE)resolve(lib, "fmi2GetReal");
    fmi2TerminateTYPE terminate = (fmi2TerminateTYPE)resolve(lib, "fmi2Terminate");
    fmi2FreeInstanceTYPE free_instance = (fmi2FreeInstanceTYPE)resolve(lib, "fmi2FreeInstance");

    fmi2CallbackFunctions callbacks = {logger, calloc, free, NULL, NULL};
    fmi2Component c = instantiate("minimal_host", fmi2CoSimulation, guid, resources, &callbacks,
                                  fmi2False, fmi2False);
    if (!c) {
        fprintf(stderr, "minimal_host: fmi2Instantiate returned NULL (guid %s, resources %s)\n",
                guid, resources);
        return 5;
    }

    const double start = 0.0;
    const double stop = start + (double)steps * h;
    check(setup_experiment(c, fmi2False, 0.0, start, fmi2True, stop), "fmi2SetupExperiment");
    check(enter_init(c), "fmi2EnterInitializationMode");
    check(exit_init(c), "fmi2ExitInitializationMode");

    fmi2Real v[4];
    printf("t,x,y,speed,gap\n");
    check(get_real(c, vrs, 4, v), "fmi2GetReal");
    printf("%.17g,%.17g,%.17g,%.17g,%.17g\n", start, v[0], v[1], v[2], v[3]);
    for (long n = 0; n < steps; ++n) {
        double t = start + (double)n * h;
        double t_next = start + (double)(n + 1) * h;
        check(do_step(c, t, t_next - t, fmi2True), "fmi2DoStep");
        check(get_real(c, vrs, 4, v), "fmi2GetReal");
        printf("%.17g,%.17g,%.17g,%.17g,%.17g\n", t_next, v[0], v[1], v[2], v[3]);
    }

    check(terminate(c), "fmi2Terminate");
    free_instance(c);
    if (fflush(stdout) != 0) {
        perror("minimal_host: stdout");
        return 6;
    }
    /* The library is deliberately not dlclose()d: unloading an embedded interpreter is not
     * something every runtime supports, and the process ends here anyway. */
    return 0;
}

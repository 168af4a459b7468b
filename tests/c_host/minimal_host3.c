/*
 * minimal_host3.c - a minimal FMI 3.0 co-simulation importer in plain C.
 *
 * The FMI 3.0 twin of minimal_host.c: no FMI library, only dlopen()/dlsym() and the standard's
 * own headers (fmi3FunctionTypes.h and fmi3PlatformTypes.h, which FMPy ships in fmpy/c-code), so
 * every call is checked by the compiler against the FMI 3.0 signatures.
 *
 * Usage:
 *   minimal_host3 <unzipped_fmu_dir> <instantiation_token> <steps> <step_size>
 *                 <vr_1> <vr_2> <vr_3> <vr_4> [<model_identifier>]
 *
 * Loads <dir>/binaries/<platform>/<model_identifier>.<so|dll|dylib> (default model identifier:
 * Vehicle; <platform> the folder of the platform it was compiled for, tests/c_host/loader.h),
 * checks that fmi3GetVersion says "3.0", instantiates it for co-simulation with the resource
 * path <dir>/resources/ (FMI 3.0: a native path ending in a separator, no URI), initialises it
 * at t = 0 and takes <steps> communication steps of <step_size>. The communication points are
 * t_n = n * step_size, the step passed to fmi3DoStep is t_{n+1} - t_n (as in minimal_host.c and
 * FMPy). Prints the same CSV as minimal_host.c: the header "t,x,y,speed,gap" (the four value
 * references given, in that order) and one line per communication point, t_0 included, with 17
 * significant digits to stdout. Messages from the FMU go to stderr.
 *
 * Exit status: 0 on success; 2 bad arguments; 3 the binary cannot be loaded; 4 a function is
 * missing; 5 fmi3InstantiateCoSimulation returned NULL; 6 an FMI call returned a status other than
 * fmi3OK, or fmi3DoStep did not complete its step (terminateSimulation, earlyReturn, or a
 * lastSuccessfulTime short of the step's end), or the FMU is not FMI 3.0.
 *
 * Build: cc -std=c99 -Wall -I<site-packages>/fmpy/c-code -o minimal_host3 minimal_host3.c -ldl
 */

#define _POSIX_C_SOURCE 200809L

#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "loader.h"

#include "fmi3FunctionTypes.h"

static const char *status_name(fmi3Status s)
{
    switch (s) {
    case fmi3OK: return "fmi3OK";
    case fmi3Warning: return "fmi3Warning";
    case fmi3Discard: return "fmi3Discard";
    case fmi3Error: return "fmi3Error";
    case fmi3Fatal: return "fmi3Fatal";
    }
    return "unknown status";
}

static void log_message(fmi3InstanceEnvironment env, fmi3Status status, fmi3String category,
                        fmi3String message)
{
    (void)env;
    fprintf(stderr, "[minimal_host3] %s (%s): %s\n", status_name(status), category ? category : "",
            message ? message : "");
}

static void *resolve(library_t lib, const char *name)
{
    void *f = library_symbol(lib, name);
    if (!f) {
        fprintf(stderr, "minimal_host3: the FMU binary does not export %s: %s\n", name, library_error());
        exit(4);
    }
    return f;
}

static void check(fmi3Status status, const char *call)
{
    if (status != fmi3OK) {
        fprintf(stderr, "minimal_host3: %s returned %s (%d), expected fmi3OK\n", call,
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
                "usage: %s <unzipped_fmu_dir> <instantiation_token> <steps> <step_size> <vr_1> "
                "<vr_2> <vr_3> <vr_4> [<model_identifier>]\n",
                argv[0]);
        return 2;
    }
    const char *dir = argv[1];
    const char *token = argv[2];
    const char *model_identifier = argc == 10 ? argv[9] : "Vehicle";
    long steps;
    double h;
    fmi3ValueReference vrs[4];
    if (!parse_long(argv[3], &steps) || steps < 0) {
        fprintf(stderr, "minimal_host3: <steps> must be a non-negative integer, got '%s'\n", argv[3]);
        return 2;
    }
    if (!parse_double(argv[4], &h) || !(h > 0.0)) {
        fprintf(stderr, "minimal_host3: <step_size> must be a positive number, got '%s'\n", argv[4]);
        return 2;
    }
    for (int i = 0; i < 4; ++i) {
        long vr;
        if (!parse_long(argv[5 + i], &vr) || vr < 0 || (unsigned long)vr > UINT_MAX) {
            fprintf(stderr, "minimal_host3: value reference '%s' is not valid\n", argv[5 + i]);
            return 2;
        }
        vrs[i] = (fmi3ValueReference)vr;
    }

    char library[PATH_MAX];
    char resources[PATH_MAX];
    if (snprintf(library, sizeof library, "%s/binaries/" FMI3_PLATFORM "/%s" FMU_SUFFIX, dir,
                 model_identifier) >= (int)sizeof library ||
        snprintf(resources, sizeof resources, "%s/resources/", dir) >= (int)sizeof resources) {
        fprintf(stderr, "minimal_host3: path too long\n");
        return 2;
    }

    library_t lib = library_open(library);
    if (!lib) {
        fprintf(stderr, "minimal_host3: cannot load %s: %s\n", library, library_error());
        return 3;
    }

    fmi3GetVersionTYPE *get_version = (fmi3GetVersionTYPE *)resolve(lib, "fmi3GetVersion");
    fmi3InstantiateCoSimulationTYPE *instantiate =
        (fmi3InstantiateCoSimulationTYPE *)resolve(lib, "fmi3InstantiateCoSimulation");
    fmi3EnterInitializationModeTYPE *enter_init =
        (fmi3EnterInitializationModeTYPE *)resolve(lib, "fmi3EnterInitializationMode");
    fmi3ExitInitializationModeTYPE *exit_init =
        (fmi3ExitInitializationModeTYPE *)resolve(lib, "fmi3ExitInitializationMode");
    fmi3DoStepTYPE *do_step = (fmi3DoStepTYPE *)resolve(lib, "fmi3DoStep");
    fmi3GetFloat64TYPE *get_float64 = (fmi3GetFloat64TYPE *)resolve(lib, "fmi3GetFloat64");
    fmi3TerminateTYPE *terminate = (fmi3TerminateTYPE *)resolve(lib, "fmi3Terminate");
    fmi3FreeInstanceTYPE *free_instance = (fmi3FreeInstanceTYPE *)resolve(lib, "fmi3FreeInstance");

    const char *version = get_version();
    if (!version || strcmp(version, "3.0") != 0) {
        fprintf(stderr, "minimal_host3: fmi3GetVersion returned '%s', expected '%s'\n",
                version ? version : "(null)", "3.0");
        return 6;
    }

    fmi3Instance c = instantiate("minimal_host3", token, resources, fmi3False, fmi3False,
                                 fmi3False, fmi3False, NULL, 0, NULL, log_message, NULL);
    if (!c) {
        fprintf(stderr, "minimal_host3: fmi3InstantiateCoSimulation returned NULL (token %s, "
                        "resources %s)\n", token, resources);
        return 5;
    }

    const double start = 0.0;
    const double stop = start + (double)steps * h;
    check(enter_init(c, fmi3False, 0.0, start, fmi3True, stop), "fmi3EnterInitializationMode");
    check(exit_init(c), "fmi3ExitInitializationMode");

    fmi3Float64 v[4];
    printf("t,x,y,speed,gap\n");
    check(get_float64(c, vrs, 4, v, 4), "fmi3GetFloat64");
    printf("%.17g,%.17g,%.17g,%.17g,%.17g\n", start, v[0], v[1], v[2], v[3]);
    for (long n = 0; n < steps; ++n) {
        double t = start + (double)n * h;
        double t_next = start + (double)(n + 1) * h;
        fmi3Boolean event_handling_needed = fmi3False, terminate_simulation = fmi3False;
        fmi3Boolean early_return = fmi3False;
        fmi3Float64 last_successful_time = -1.0;
        check(do_step(c, t, t_next - t, fmi3False, &event_handling_needed, &terminate_simulation,
                      &early_return, &last_successful_time),
              "fmi3DoStep");
        if (terminate_simulation || early_return || last_successful_time != t + (t_next - t)) {
            fprintf(stderr, "minimal_host3: fmi3DoStep from t = %.17g did not complete its step "
                            "(terminateSimulation %d, earlyReturn %d, lastSuccessfulTime %.17g)\n",
                    t, (int)terminate_simulation, (int)early_return, last_successful_time);
            return 6;
        }
        check(get_float64(c, vrs, 4, v, 4), "fmi3GetFloat64");
        printf("%.17g,%.17g,%.17g,%.17g,%.17g\n", t_next, v[0], v[1], v[2], v[3]);
    }

    check(terminate(c), "fmi3Terminate");
    free_instance(c);
    if (fflush(stdout) != 0) {
        perror("minimal_host3: stdout");
        return 6;
    }
    library_close(lib);
    return 0;
}

/*
 * link.c - the Link FMU's model: fmus/model/link.py in C.
 *
 * One communication link: delay, jitter, beacons with sample and hold, independent or
 * Gilbert-Elliott loss, drawn from splitmix64 exactly as the Python model draws them, so the
 * native and the pythonfmu Link deliver the same messages at the same steps. Each function names
 * the Python function it mirrors, with its arithmetic in the same order.
 *
 * The messages the link holds (the one in use, then those in flight, oldest first) live in a ring
 * of LINK_CAPACITY slots in the instance's memory; the state vector holds everything else and the
 * ring's window (first slot, count). A step only writes a slot outside the window and moves the
 * window, so the framework's restoring of the state vector undoes a refused step.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "framework.h"
#include "variables.h"

#define LINK_CAPACITY 256      /* fmus.model.link.CAPACITY */
#define LINK_TOLERANCE 1e-9    /* fmus.model.link.TIME_TOLERANCE */
#define SIGNAL_COUNT 8         /* fmus.model.link.SIGNALS */
#define SLOT (2 + SIGNAL_COUNT) /* arrival, output_time, the signals */

/* the state vector */
enum { S_RNG, S_FIRST, S_COUNT, S_DELIVERED, S_LOST, S_NEXT_BEACON, S_LAST_SENT, S_BAD };

/* fmus.model.link.SIGNALS: input and output value references, in order */
static const int INPUTS[SIGNAL_COUNT] = {VR_IN_X, VR_IN_Y, VR_IN_HEADING, VR_IN_SPEED,
                                        VR_IN_SPEED_RATE, VR_IN_TURN_RATE, VR_IN_GAP, VR_IN_GAP_RATE};
static const int OUTPUTS[SIGNAL_COUNT] = {VR_X, VR_Y, VR_HEADING, VR_SPEED, VR_SPEED_RATE, VR_TURN_RATE, VR_GAP,
                                         VR_GAP_RATE};

/* fmus.model.link.LinkParameters, as fmus.model.factory.link_stepper reads them */
typedef struct {
    double delay, jitter, period, loss, burst;
} LinkConfig;

static const LinkConfig *config_of(const Instance *instance) { return (const LinkConfig *)instance->config; }

/* --- the generator: fmus.model.link.seed_state, splitmix64, unit_draw ---------------------------- */

static uint64_t rng_of(const Instance *instance)
{
    uint64_t bits;
    memcpy(&bits, &instance->state[S_RNG], sizeof bits);
    return bits;
}

static void set_rng(Instance *instance, uint64_t bits) { memcpy(&instance->state[S_RNG], &bits, sizeof bits); }

/* LinkStepper._draw */
static double draw(Instance *instance)
{
    uint64_t state = rng_of(instance) + 0x9E3779B97F4A7C15u;
    uint64_t z = state;
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9u;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBu;
    z = z ^ (z >> 31);
    set_rng(instance, state);
    return (double)(z >> 11) * 0x1.0p-53;
}

/* --- fmus.model.link.parameter_errors ------------------------------------------------------------ */

static void at_least_zero(const Instance *instance, int vr, FwText *reasons, int *errors)
{
    double value = instance->reals[vr];
    if (isfinite(value) && value >= 0.0) return;
    fw_text_append(reasons, "%s%s = ", (*errors)++ ? "; " : "", instance->model->variables[vr].name);
    fw_text_float(reasons, value);
    fw_text_append(reasons, ": must be a finite number >= 0");
}

static int link_parameter_errors(const Instance *instance, FwText *reasons)
{
    const double *r = instance->reals;
    int errors = 0;
    at_least_zero(instance, VR_DELAY, reasons, &errors);
    at_least_zero(instance, VR_JITTER, reasons, &errors);
    at_least_zero(instance, VR_PERIOD, reasons, &errors);
    double loss = r[VR_LOSS], burst = r[VR_BURST];
    int loss_valid = loss >= 0.0 && loss <= 1.0;
    if (!loss_valid) {
        fw_text_append(reasons, "%sloss = ", errors++ ? "; " : "");
        fw_text_float(reasons, loss);
        fw_text_append(reasons, ": must be a probability from 0 to 1");
    }
    if (!(isfinite(burst) && burst >= 1.0)) {
        fw_text_append(reasons, "%sburst = ", errors++ ? "; " : "");
        fw_text_float(reasons, burst);
        fw_text_append(reasons, ": must be a finite number >= 1 (messages)");
    } else if (burst > 1.0 && loss_valid && loss > burst / (burst + 1.0)) {
        fw_text_append(reasons, "%sloss = ", errors++ ? "; " : "");
        fw_text_float(reasons, loss);
        fw_text_append(reasons, ": with burst = ");
        fw_text_float(reasons, burst);
        fw_text_append(reasons, " at most burst / (burst + 1) = %.6g (bursts of that mean length need good spells "
                       "between them)", burst / (burst + 1.0));
    }
    const int integers[2] = {VR_SEED, VR_STREAM};
    for (int i = 0; i < 2; ++i) {
        int value = instance->integers[integers[i]];
        if (value < 0) {
            fw_text_append(reasons, "%s%s = %d: must be an integer from 0 to 2147483647", errors++ ? "; " : "",
                           instance->model->variables[integers[i]].name, value);
        }
    }
    return errors;
}

/* --- fmus.model.link.LinkStepper ------------------------------------------------------------------- */

static double *slot(Instance *instance, int index) { return instance->memory + (size_t)(index % LINK_CAPACITY) * SLOT; }

static const double *held(const Instance *instance)
{
    return instance->memory + (size_t)((int)instance->state[S_FIRST] % LINK_CAPACITY) * SLOT;
}

/* LinkStepper.message: [output_time, signals] of the sender, from the inputs */
static void message_of(const Instance *instance, double *message)
{
    message[0] = instance->reals[VR_IN_TIME];
    for (int i = 0; i < SIGNAL_COUNT; ++i) message[1 + i] = instance->reals[INPUTS[i]];
}

/* LinkStepper.__init__ and take_initial: the message at the end of initialization is in use */
static void link_configure(Instance *instance)
{
    LinkConfig *config = (LinkConfig *)instance->config;
    const double *r = instance->reals;
    config->delay = r[VR_DELAY];
    config->jitter = r[VR_JITTER];
    config->period = r[VR_PERIOD];
    config->loss = r[VR_LOSS];
    config->burst = r[VR_BURST];
    uint32_t seed = (uint32_t)instance->integers[VR_SEED], stream = (uint32_t)instance->integers[VR_STREAM];
    set_rng(instance, (uint64_t)seed << 32 | stream);
    double *first = slot(instance, 0);
    message_of(instance, first + 1);
    first[0] = first[1];
    instance->state[S_FIRST] = 0.0;
    instance->state[S_COUNT] = 1.0;
    instance->state[S_DELIVERED] = 0.0;
    instance->state[S_LOST] = 0.0;
    instance->state[S_NEXT_BEACON] = instance->start_time + config->period;
    instance->state[S_LAST_SENT] = first[1];
    instance->state[S_BAD] = 0.0;
}

static double link_max_substep(const Instance *instance)
{
    (void)instance;
    return INFINITY; /* no integration: any step is one step */
}

/* LinkStepper.sent */
static double sent(const Instance *instance)
{
    return instance->state[S_DELIVERED] + instance->state[S_LOST] + (instance->state[S_COUNT] - 1.0);
}

/* LinkStepper._is_lost (fmus.model.link.gilbert_elliott for the transition probabilities) */
static int is_lost(Instance *instance, double u)
{
    const LinkConfig *config = config_of(instance);
    if (config->burst <= 1.0) return u < config->loss;
    double recover = 1.0 / config->burst;
    double to_bad = config->loss * recover / (1.0 - config->loss);
    int bad = instance->state[S_BAD] != 0.0;
    if (sent(instance) == 0.0) {
        bad = u < config->loss;
    } else if (bad) {
        bad = !(u < recover);
    } else {
        bad = u < to_bad;
    }
    instance->state[S_BAD] = bad ? 1.0 : 0.0;
    return bad;
}

/* LinkStepper._beacon_due */
static int beacon_due(const Instance *instance, double output_time)
{
    if (!(output_time > instance->state[S_LAST_SENT] + LINK_TOLERANCE)) return 0;
    double period = config_of(instance)->period;
    return period == 0.0 || output_time >= instance->state[S_NEXT_BEACON] - LINK_TOLERANCE;
}

/* LinkStepper._send */
static int send(Instance *instance, const double *message, FwText *why)
{
    const LinkConfig *config = config_of(instance);
    double output_time = message[0];
    instance->state[S_LAST_SENT] = output_time;
    if (config->period > 0.0) {
        instance->state[S_NEXT_BEACON] = (floor((output_time + LINK_TOLERANCE) / config->period) + 1.0) * config->period;
    }
    int lost = is_lost(instance, draw(instance));
    double extra = config->jitter * draw(instance);
    if (lost) {
        instance->state[S_LOST] += 1.0;
        return 0;
    }
    int count = (int)instance->state[S_COUNT];
    if (count + 1 > LINK_CAPACITY) {
        fw_text_append(why, "ValueError: more than %d messages in flight (delay + jitter spans too many beacons)",
                       LINK_CAPACITY);
        return 1;
    }
    int first = (int)instance->state[S_FIRST];
    double arrival = output_time + config->delay + extra;
    double latest = slot(instance, first + count - 1)[0];
    if (arrival < latest) arrival = latest; /* FIFO: no overtaking */
    double *free_slot = slot(instance, first + count);
    free_slot[0] = arrival;
    memcpy(free_slot + 1, message, (1 + SIGNAL_COUNT) * sizeof *message);
    instance->state[S_COUNT] = (double)(count + 1);
    return 0;
}

/* LinkStepper.step */
static int link_step(Instance *instance, double t, double h, FwStepMemo *memo, FwText *why)
{
    (void)memo;
    double message[1 + SIGNAL_COUNT];
    message_of(instance, message);
    if (beacon_due(instance, message[0]) && send(instance, message, why) != 0) return 1;
    double now = t + h;
    int first = (int)instance->state[S_FIRST], count = (int)instance->state[S_COUNT];
    int arrived = 0;
    while (arrived < count - 1 && slot(instance, first + 1 + arrived)[0] <= now + LINK_TOLERANCE) ++arrived;
    if (arrived) {
        instance->state[S_FIRST] = (double)((first + arrived) % LINK_CAPACITY);
        instance->state[S_COUNT] = (double)(count - arrived);
        instance->state[S_DELIVERED] += (double)arrived;
    }
    instance->time = now;
    return 0;
}

/* LinkStepper.outputs */
static void link_outputs(const Instance *instance, const FwStepMemo *memo, double *values)
{
    (void)memo;
    const double *message = held(instance) + 1;
    for (int i = 0; i < SIGNAL_COUNT; ++i) values[OUTPUTS[i]] = message[1 + i];
    values[VR_OUTPUT_TIME] = message[0];
    values[VR_SENT] = sent(instance);
    values[VR_DELIVERED] = instance->state[S_DELIVERED];
    values[VR_LOST] = instance->state[S_LOST];
    values[VR_AGE] = instance->time - message[0];
}

const ModelDef MODEL = {
    MODEL_IDENTIFIER,   MODEL_GUID,            VARIABLE_COUNT, MODEL_VARIABLES,
    sizeof(LinkConfig), link_parameter_errors, link_configure, link_max_substep,
    link_outputs,       link_step,             LINK_CAPACITY * SLOT,
};

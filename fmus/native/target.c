/*
 * target.c - the VirtualTarget FMU's model: fmus/model/target.py on fmus/model/paths.py, in C.
 *
 * The point on the path (circle or line) the lead vehicle chases, moving at V_0 = V_1 d* / d_1
 * (paper eq. 3; acc, cacc: v_c), plus a speed push (disturbance.speed). Each function names the
 * Python function it mirrors, with its arithmetic in the same order. Variables and value references
 * come from the generated "variables.h".
 */
#include <math.h>
#include <string.h>

#include "framework.h"
#include "science.h"
#include "variables.h"

typedef enum { PATH_CIRCLE, PATH_LINE } PathKind; /* fmus.model.paths.PATH_KINDS */

/* fmus.model.paths.CirclePath / LinePath and fmus.model.target.VirtualTargetStepper's parameters,
 * as fmus.model.factory.target_stepper builds them. */
typedef struct {
    PathKind kind;
    double radius, x0, y0, heading; /* circle: centre, start angle; line: origin, direction */
    int direction;
    double d_star, max_substep;
    Coupling coupling;
    int constant_speed; /* VirtualTargetStepper.constant_speed: acc, cacc move at v_c */
    double speed_command;
} TargetConfig;

static const TargetConfig *config_of(const Instance *instance) { return (const TargetConfig *)instance->config; }

/* --- fmus.model.factory.target_parameter_errors --------------------------------------------------- */

static const char *const PATH_KINDS[] = {"circle", "line"};

static int target_parameter_errors(const Instance *instance, FwText *reasons)
{
    int errors = 0;
    int kind = fw_choice(instance, VR_PATH_KIND, PATH_KINDS, 2, reasons, &errors);
    fw_choice(instance, VR_COUPLING, COUPLING_MODES, 2, reasons, &errors);
    fw_choice(instance, VR_SPEED_LAW, SPEED_LAWS, 3, reasons, &errors);
    int direction = instance->integers[VR_PATH_DIRECTION];
    if (direction != 1 && direction != -1) {
        fw_text_append(reasons, "%spath.direction = %d: expected 1 or -1", errors++ ? "; " : "", direction);
    }
    fw_positive(instance, VR_D_STAR, reasons, &errors);
    fw_positive(instance, VR_MAX_SUBSTEP, reasons, &errors);
    fw_positive(instance, VR_V_C, reasons, &errors);
    if (kind == PATH_CIRCLE) {
        fw_positive(instance, VR_PATH_RADIUS, reasons, &errors);
        double d_star = instance->reals[VR_D_STAR], radius = instance->reals[VR_PATH_RADIUS];
        if (!errors && d_star > 2.0 * radius) {
            fw_text_append(reasons, "d_star = ");
            fw_text_float(reasons, d_star);
            fw_text_append(reasons, ": must be <= 2 R = ");
            fw_text_float(reasons, 2.0 * radius);
            fw_text_append(reasons, " (a chord of the circle)");
            ++errors;
        }
    }
    return errors;
}

/* fmus.model.factory.target_stepper and target_path (fmus.model.paths.make_path) */
static void target_configure(Instance *instance)
{
    TargetConfig *config = (TargetConfig *)instance->config;
    const double *r = instance->reals;
    config->kind = fw_chosen(instance, VR_PATH_KIND, PATH_KINDS, 2) == 1 ? PATH_LINE : PATH_CIRCLE;
    config->coupling = fw_chosen(instance, VR_COUPLING, COUPLING_MODES, 2) == 1 ? COUPLING_EXTRAPOLATE
                                                                                                 : COUPLING_HOLD;
    config->radius = r[VR_PATH_RADIUS];
    config->x0 = r[VR_PATH_X0];
    config->y0 = r[VR_PATH_Y0];
    config->heading = r[VR_PATH_HEADING];
    config->direction = instance->integers[VR_PATH_DIRECTION];
    config->d_star = r[VR_D_STAR];
    config->max_substep = r[VR_MAX_SUBSTEP];
    config->constant_speed = fw_chosen(instance, VR_SPEED_LAW, SPEED_LAWS, 3) != SPEED_LAW_PAPER;
    config->speed_command = r[VR_V_C];
    instance->state[0] = r[VR_INITIAL_ARC_LENGTH];
}

static double target_max_substep(const Instance *instance) { return config_of(instance)->max_substep; }

/* --- fmus.model.paths ------------------------------------------------------------------------------- */

/* CirclePath.pose_at / LinePath.pose_at */
static void pose_at(const TargetConfig *path, double s, double *x, double *y, double *heading)
{
    if (path->kind == PATH_LINE) {
        *x = path->x0 + s * cos(path->heading);
        *y = path->y0 + s * sin(path->heading);
        *heading = path->heading;
        return;
    }
    double direction = (double)path->direction;
    double angle = path->heading + direction * s / path->radius;
    *x = path->x0 + path->radius * cos(angle);
    *y = path->y0 + path->radius * sin(angle);
    *heading = angle + direction * 0.5 * SCIENCE_PI;
}

/* CirclePath.curvature / LinePath.curvature */
static double curvature(const TargetConfig *path)
{
    return path->kind == PATH_LINE ? 0.0 : (double)path->direction / path->radius;
}

/* --- fmus.model.target.VirtualTargetStepper ---------------------------------------------------------- */

/* VirtualTargetStepper.lead_at: lead speed, gap and their rates at time t */
static void lead_at(const Instance *instance, double t, double out[4])
{
    const double *r = instance->reals;
    if (config_of(instance)->coupling != COUPLING_EXTRAPOLATE) {
        out[0] = r[VR_LEAD_SPEED];
        out[1] = r[VR_LEAD_GAP];
    } else {
        double dt = t - r[VR_LEAD_TIME];
        out[0] = linear_extrapolate(r[VR_LEAD_SPEED], r[VR_LEAD_SPEED_RATE], dt);
        out[1] = linear_extrapolate(r[VR_LEAD_GAP], r[VR_LEAD_GAP_RATE], dt);
    }
    out[2] = r[VR_LEAD_SPEED_RATE];
    out[3] = r[VR_LEAD_GAP_RATE];
}

/* VirtualTargetStepper.speed_of: the law's speed plus the push (disturbance.speed) */
static double speed_of(const Instance *instance, double lead_speed, double lead_gap)
{
    const TargetConfig *config = config_of(instance);
    double law_speed = config->constant_speed ? config->speed_command : spacing_speed(lead_speed, lead_gap, config->d_star);
    return law_speed + instance->reals[VR_DISTURBANCE_SPEED];
}

/* VirtualTargetStepper.derivative (speed_at) */
static void derivative_of(void *context, double t, const double *state, double *derivative)
{
    const Instance *instance = (const Instance *)context;
    double lead[4];
    (void)state;
    if (config_of(instance)->constant_speed) { /* VirtualTargetStepper.speed_at */
        derivative[0] = speed_of(instance, 0.0, 0.0);
        return;
    }
    lead_at(instance, t, lead);
    derivative[0] = speed_of(instance, lead[0], lead[1]);
}

/* VirtualTargetStepper.step */
static int target_step(Instance *instance, double t, double h, FwStepMemo *memo, FwText *why)
{
    (void)memo;
    double arc_length[1] = {instance->state[0]};
    integrate(derivative_of, instance, t, arc_length, 1, h, config_of(instance)->max_substep);
    if (!isfinite(arc_length[0])) {
        fw_text_append(why, "the target's arc length became non-finite during the step from t = %.6g s", t);
        return 1;
    }
    instance->state[0] = arc_length[0];
    instance->time = t + h;
    return 0;
}

/* VirtualTargetStepper.outputs */
static void target_outputs(const Instance *instance, const FwStepMemo *memo, double *values)
{
    (void)memo;
    const TargetConfig *config = config_of(instance);
    double t = instance->time;
    double s = instance->state[0];
    double target_speed, target_speed_rate;
    if (config->constant_speed) {
        target_speed = speed_of(instance, 0.0, 0.0);
        target_speed_rate = 0.0;
    } else {
        double lead[4];
        lead_at(instance, t, lead);
        target_speed = speed_of(instance, lead[0], lead[1]);
        target_speed_rate = spacing_speed_rate(lead[0], lead[2], lead[1], lead[3], config->d_star);
    }
    double x, y, heading;
    pose_at(config, s, &x, &y, &heading);
    double k = curvature(config);
    values[VR_X] = x;
    values[VR_Y] = y;
    values[VR_HEADING] = heading;
    values[VR_SPEED] = target_speed;
    values[VR_SPEED_RATE] = target_speed_rate;
    values[VR_TURN_RATE] = target_speed * k;
    values[VR_CURVATURE] = k;
    values[VR_ARC_LENGTH] = s;
    values[VR_OUTPUT_TIME] = t;
}

const ModelDef MODEL = {
    MODEL_IDENTIFIER,      MODEL_GUID,      VARIABLE_COUNT,     MODEL_VARIABLES,
    sizeof(TargetConfig),  target_parameter_errors, target_configure, target_max_substep,
    target_outputs,        target_step,
};

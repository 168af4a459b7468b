/*
 * vehicle.c - the Vehicle FMU's model: fmus/model/vehicle.py on fmus/model/dynamics.py, in C.
 *
 * Guidance (regular or sine law) on kinematic or m3pi dynamics, the speed chain, hold or
 * extrapolate coupling of the inputs, RK4 with equal substeps: each function names the Python
 * function it mirrors, and keeps its arithmetic in the same order (science.h, pymath.h).
 * Variables and value references come from the generated "variables.h" (fmus/native_build.py).
 */
#include <math.h>
#include <string.h>

#include "framework.h"
#include "science.h"
#include "variables.h"

#define LATENCY_MAX 1.0        /* fmus.model.robot_loop.LATENCY_MAX */
#define COMMAND_CAPACITY 256   /* fmus.model.robot_loop.COMMAND_CAPACITY */
#define COMMAND_FIELDS 3       /* fmus.model.robot_loop.COMMAND_FIELDS: lands at, right, left */

/* The state vector: the controller's (m3pi: x, y, heading, v_right, v_left, V_s), then, in the sampled loop of
 * a robot with latencies (fmus.model.robot_loop.RobotLoopStepper), the robot and the command acting; the commands
 * in flight live in a ring of COMMAND_CAPACITY in the instance's memory, whose window is in the state vector. A
 * step only writes a slot outside the window and moves the window, so restoring the state vector undoes it. */
enum { S_ROBOT = 6, S_HELD_KNOWN = 11, S_HELD_RIGHT, S_HELD_LEFT, S_FIRST, S_COUNT };
#define ROBOT_SIZE 5

typedef enum { DYNAMICS_KINEMATIC, DYNAMICS_M3PI } DynamicsKind; /* fmus.model.dynamics.DYNAMICS_KINDS */

/* fmus.model.vehicle.VehicleModel with its dynamics (fmus.model.dynamics.*Dynamics), as
 * fmus.model.factory.vehicle_stepper builds them from the parameters. */
typedef struct {
    Law law;
    SpeedLaw speed_law;
    DynamicsKind dynamics;
    Coupling coupling;
    int is_last;
    double d_star, k_v, v_c, max_substep;
    double track, wheel_speed_max, motor_time_constant;
    double wheel_gain_right, wheel_gain_left, wheel_deadband;
    double speed_max; /* KinematicDynamics.speed_max: 0, no limit */
    int sampled;  /* fmus.model.factory.samples_its_robot */
    double delay; /* RobotLoopStepper.delay: command_latency + pose_latency */
    double time_gap, standstill_gap, cacc_gain; /* fmus.model.vehicle.SpeedLaw */
    int state_size;
} VehicleConfig;

static const VehicleConfig *config_of(const Instance *instance) { return (const VehicleConfig *)instance->config; }

/* --- fmus.model.factory.vehicle_parameter_errors ------------------------------------------------- */

static const char *const LAWS[] = {"regular", "sine"};
static const char *const DYNAMICS_KINDS[] = {"kinematic", "m3pi"};

/* fmus.model.factory._non_negative: Real variable vr must be a finite number >= 0. */
static void non_negative(const Instance *instance, int vr, FwText *reasons, int *errors)
{
    double value = instance->reals[vr];
    if (isfinite(value) && value >= 0.0) return;
    fw_text_append(reasons, "%s%s = ", (*errors)++ ? "; " : "", instance->model->variables[vr].name);
    fw_text_float(reasons, value);
    fw_text_append(reasons, ": must be a finite number >= 0");
}

/* fmus.model.factory._at_most: Real variable vr must be a finite number in [0, limit]. */
static void at_most(const Instance *instance, int vr, double limit, FwText *reasons, int *errors)
{
    double value = instance->reals[vr];
    if (isfinite(value) && 0.0 <= value && value <= limit) return;
    fw_text_append(reasons, "%s%s = ", (*errors)++ ? "; " : "", instance->model->variables[vr].name);
    fw_text_float(reasons, value);
    fw_text_append(reasons, ": must be a finite number >= 0 and <= %g", limit);
}

/* fmus.model.factory._robot_errors */
static void robot_errors(const Instance *instance, FwText *reasons, int *errors)
{
    int before = *errors;
    fw_positive(instance, VR_M3PI_WHEEL_GAIN_RIGHT, reasons, errors);
    fw_positive(instance, VR_M3PI_WHEEL_GAIN_LEFT, reasons, errors);
    non_negative(instance, VR_M3PI_WHEEL_DEADBAND, reasons, errors);
    at_most(instance, VR_M3PI_COMMAND_LATENCY, LATENCY_MAX, reasons, errors);
    at_most(instance, VR_M3PI_POSE_LATENCY, LATENCY_MAX, reasons, errors);
    double deadband = instance->reals[VR_M3PI_WHEEL_DEADBAND], limit = instance->reals[VR_M3PI_WHEEL_SPEED_MAX];
    if (*errors == before && isfinite(limit) && deadband >= limit) {
        fw_text_append(reasons, "%sm3pi.wheel_deadband = ", (*errors)++ ? "; " : "");
        fw_text_float(reasons, deadband);
        fw_text_append(reasons, ": must be below m3pi.wheel_speed_max = ");
        fw_text_float(reasons, limit);
        fw_text_append(reasons, " (no command would turn the wheels)");
    }
}

static int vehicle_parameter_errors(const Instance *instance, FwText *reasons)
{
    int errors = 0;
    fw_choice(instance, VR_LAW, LAWS, 2, reasons, &errors);
    fw_choice(instance, VR_SPEED_LAW, SPEED_LAWS, 3, reasons, &errors);
    fw_choice(instance, VR_DYNAMICS, DYNAMICS_KINDS, 2, reasons, &errors);
    fw_choice(instance, VR_COUPLING, COUPLING_MODES, 2, reasons, &errors);
    static const int POSITIVE[] = {VR_D_STAR, VR_K_V, VR_V_C, VR_MAX_SUBSTEP, VR_INITIAL_SPEED, VR_M3PI_TRACK,
                                   VR_M3PI_WHEEL_SPEED_MAX, VR_M3PI_MOTOR_TIME_CONSTANT, VR_TIME_GAP, VR_CACC_GAIN};
    for (size_t i = 0; i < sizeof POSITIVE / sizeof POSITIVE[0]; ++i) fw_positive(instance, POSITIVE[i], reasons, &errors);
    non_negative(instance, VR_STANDSTILL_GAP, reasons, &errors);
    non_negative(instance, VR_SPEED_MAX, reasons, &errors);
    robot_errors(instance, reasons, &errors);
    return errors;
}

/* fmus.model.factory.vehicle_stepper, with fmus.model.dynamics.*Dynamics.initial_state */
static void vehicle_configure(Instance *instance)
{
    VehicleConfig *config = (VehicleConfig *)instance->config;
    const double *r = instance->reals;
    config->law = fw_chosen(instance, VR_LAW, LAWS, 2) == 1 ? LAW_SINE : LAW_REGULAR;
    config->speed_law = (SpeedLaw)fw_chosen(instance, VR_SPEED_LAW, SPEED_LAWS, 3); /* same order as the enum */
    config->time_gap = r[VR_TIME_GAP];
    config->standstill_gap = r[VR_STANDSTILL_GAP];
    config->cacc_gain = r[VR_CACC_GAIN];
    config->dynamics = fw_chosen(instance, VR_DYNAMICS, DYNAMICS_KINDS, 2) == 1 ? DYNAMICS_M3PI
                                                                                               : DYNAMICS_KINEMATIC;
    config->coupling = fw_chosen(instance, VR_COUPLING, COUPLING_MODES, 2) == 1 ? COUPLING_EXTRAPOLATE
                                                                                                 : COUPLING_HOLD;
    config->is_last = instance->integers[VR_IS_LAST] != 0;
    config->d_star = r[VR_D_STAR];
    config->k_v = r[VR_K_V];
    config->v_c = r[VR_V_C];
    config->max_substep = r[VR_MAX_SUBSTEP];
    config->track = r[VR_M3PI_TRACK];
    config->wheel_speed_max = r[VR_M3PI_WHEEL_SPEED_MAX];
    config->motor_time_constant = r[VR_M3PI_MOTOR_TIME_CONSTANT];
    config->wheel_gain_right = r[VR_M3PI_WHEEL_GAIN_RIGHT];
    config->wheel_gain_left = r[VR_M3PI_WHEEL_GAIN_LEFT];
    config->wheel_deadband = r[VR_M3PI_WHEEL_DEADBAND];
    config->speed_max = r[VR_SPEED_MAX];
    double *state = instance->state;
    state[0] = r[VR_INITIAL_X];
    state[1] = r[VR_INITIAL_Y];
    state[2] = r[VR_INITIAL_HEADING];
    state[3] = r[VR_INITIAL_SPEED];
    if (config->dynamics == DYNAMICS_M3PI) { /* M3piDynamics.initial_state: (x, y, heading, V, V, V) */
        state[4] = r[VR_INITIAL_SPEED];
        state[5] = r[VR_INITIAL_SPEED];
        config->state_size = 6;
        /* fmus.model.factory.samples_its_robot, RobotLoopStepper.__init__ */
        config->sampled = r[VR_M3PI_COMMAND_LATENCY] > 0.0 || r[VR_M3PI_POSE_LATENCY] > 0.0;
        config->delay = r[VR_M3PI_COMMAND_LATENCY] + r[VR_M3PI_POSE_LATENCY];
        memcpy(&state[S_ROBOT], state, ROBOT_SIZE * sizeof *state);
        state[S_HELD_KNOWN] = state[S_HELD_RIGHT] = state[S_HELD_LEFT] = state[S_FIRST] = state[S_COUNT] = 0.0;
    } else {
        config->state_size = 4;
        config->sampled = 0;
        config->delay = 0.0;
    }
}

static double vehicle_max_substep(const Instance *instance) { return config_of(instance)->max_substep; }

/* --- fmus.model.dynamics ----------------------------------------------------------------------------- */

/* fmus.model.dynamics.differential_wheel_speeds */
static void differential_wheel_speeds(double speed, double lateral_acceleration, double track, double *right,
                                      double *left)
{
    double half_difference = 0.5 * track * lateral_acceleration / speed;
    *right = speed + half_difference;
    *left = speed - half_difference;
}

/* KinematicDynamics.speed / M3piDynamics.speed */
static double dynamics_speed(const VehicleConfig *config, const double *state, double speed_offset)
{
    if (config->dynamics == DYNAMICS_M3PI) return 0.5 * (state[3] + state[4]) + speed_offset;
    return state[3] + speed_offset;
}

/* KinematicDynamics.loop_speed / M3piDynamics.loop_speed */
static double dynamics_loop_speed(const VehicleConfig *config, const double *state)
{
    return config->dynamics == DYNAMICS_M3PI ? state[5] : state[3];
}

/* M3piDynamics.wheel_target: none inside the dead-band, else the gain times the command, within the limit */
static double m3pi_wheel_target(const VehicleConfig *config, double command, double gain)
{
    if (fabs(command) < config->wheel_deadband) return 0.0;
    double limit = config->wheel_speed_max;
    return py_min(py_max(gain * command, -limit), limit);
}

/* M3piDynamics.drive: the derivative of (x, y, heading, v_right, v_left) under wheel commands */
static void m3pi_drive(const VehicleConfig *config, double heading, double right, double left, double right_cmd,
                       double left_cmd, double speed_offset, double *derivative)
{
    double v = 0.5 * (right + left) + speed_offset;
    double lag = 1.0 / config->motor_time_constant;
    double right_target = m3pi_wheel_target(config, right_cmd, config->wheel_gain_right);
    double left_target = m3pi_wheel_target(config, left_cmd, config->wheel_gain_left);
    derivative[0] = v * cos(heading);
    derivative[1] = v * sin(heading);
    derivative[2] = (right - left) / config->track;
    derivative[3] = (right_target - right) * lag;
    derivative[4] = (left_target - left) * lag;
}

/* KinematicDynamics.limit_command: the speed command clipped to +-speed_max, as it is without a limit */
static double kinematic_limit_command(const VehicleConfig *config, double commanded_speed)
{
    double limit = config->speed_max;
    if (limit <= 0.0) return commanded_speed;
    return py_min(py_max(commanded_speed, -limit), limit);
}

/* KinematicDynamics.derivative / M3piDynamics.derivative (with wheel_commands, limit_wheels, drive) */
static void dynamics_derivative(const VehicleConfig *config, const double *state, double lateral_acceleration,
                                double commanded_speed, double speed_offset, double *derivative)
{
    if (config->dynamics == DYNAMICS_KINEMATIC) {
        double heading = state[2];
        double v = state[3] + speed_offset;
        derivative[0] = v * cos(heading);
        derivative[1] = v * sin(heading);
        derivative[2] = lateral_acceleration / v;
        derivative[3] = speed_loop(config->k_v, kinematic_limit_command(config, commanded_speed), state[3]);
        return;
    }
    double setpoint = state[5];
    double right_cmd, left_cmd; /* M3piDynamics.wheel_commands */
    differential_wheel_speeds(setpoint, lateral_acceleration, config->track, &right_cmd, &left_cmd);
    double limit = config->wheel_speed_max; /* M3piDynamics.limit_wheels */
    right_cmd = py_min(py_max(right_cmd, -limit), limit);
    left_cmd = py_min(py_max(left_cmd, -limit), limit);
    m3pi_drive(config, state[2], state[3], state[4], right_cmd, left_cmd, speed_offset, derivative);
    derivative[5] = speed_loop(config->k_v, commanded_speed, setpoint);
}

/* KinematicDynamics.speed_rate / M3piDynamics.speed_rate (heading_rate is derivative[2] for both) */
static double dynamics_speed_rate(const VehicleConfig *config, const double *derivative)
{
    if (config->dynamics == DYNAMICS_M3PI) return 0.5 * (derivative[3] + derivative[4]);
    return derivative[3];
}

/* KinematicDynamics.wheel_speeds / M3piDynamics.wheel_speeds */
static void dynamics_wheel_speeds(const VehicleConfig *config, const double *state, double lateral_acceleration,
                                  double speed_offset, double *right, double *left)
{
    if (config->dynamics == DYNAMICS_M3PI) {
        *right = state[3] + speed_offset;
        *left = state[4] + speed_offset;
        return;
    }
    differential_wheel_speeds(state[3] + speed_offset, lateral_acceleration, config->track, right, left);
}

/* --- fmus.model.vehicle.VehicleStepper --------------------------------------------------------------- */

/* VehicleStepper.target_at: the target's (x, y, heading, speed) at time t as this vehicle sees it */
static void target_at(const Instance *instance, double t, double out[4])
{
    const double *r = instance->reals;
    if (config_of(instance)->coupling != COUPLING_EXTRAPOLATE) {
        out[0] = r[VR_TARGET_X];
        out[1] = r[VR_TARGET_Y];
        out[2] = r[VR_TARGET_HEADING];
        out[3] = r[VR_TARGET_SPEED];
        return;
    }
    arc_extrapolate(r[VR_TARGET_X], r[VR_TARGET_Y], r[VR_TARGET_HEADING], r[VR_TARGET_SPEED], r[VR_TARGET_SPEED_RATE],
                    r[VR_TARGET_TURN_RATE], t - r[VR_TARGET_TIME], out);
}

/* VehicleStepper.sensor_at: the position of the vehicle ahead at time t as the on-board sensor sees it */
static void sensor_at(const Instance *instance, double t, double *x, double *y)
{
    const double *r = instance->reals;
    if (config_of(instance)->coupling != COUPLING_EXTRAPOLATE) {
        *x = r[VR_SENSOR_X];
        *y = r[VR_SENSOR_Y];
        return;
    }
    double out[4];
    arc_extrapolate(r[VR_SENSOR_X], r[VR_SENSOR_Y], r[VR_SENSOR_HEADING], r[VR_SENSOR_SPEED], r[VR_SENSOR_SPEED_RATE],
                    r[VR_SENSOR_TURN_RATE], t - r[VR_SENSOR_TIME], out);
    *x = out[0];
    *y = out[1];
}

/* fmus.model.vehicle.VehicleModel.evaluate's speed command, with VehicleModel.sensing_speed */
static double commanded_speed(const VehicleConfig *config, const double *state, double speed, double sensed_gap,
                              double predecessor_speed, double follower_speed, double follower_gap)
{
    if (config->speed_law == SPEED_LAW_ACC) {
        return time_gap_speed(sensed_gap, config->standstill_gap, config->time_gap);
    }
    if (config->speed_law == SPEED_LAW_CACC) {
        double error = spacing_error(sensed_gap, config->standstill_gap, config->time_gap, speed);
        double acceleration =
            cacc_acceleration(predecessor_speed, speed, error, config->time_gap, config->cacc_gain);
        return speed_for_acceleration(dynamics_loop_speed(config, state), acceleration, config->k_v);
    }
    if (config->is_last) return config->v_c;
    return spacing_speed(follower_speed, follower_gap, config->d_star);
}

/* VehicleStepper.follower_at */
static void follower_at(const Instance *instance, double t, double *speed, double *gap)
{
    const double *r = instance->reals;
    if (config_of(instance)->coupling != COUPLING_EXTRAPOLATE) {
        *speed = r[VR_FOLLOWER_SPEED];
        *gap = r[VR_FOLLOWER_GAP];
        return;
    }
    double dt = t - r[VR_FOLLOWER_TIME];
    *speed = linear_extrapolate(r[VR_FOLLOWER_SPEED], r[VR_FOLLOWER_SPEED_RATE], dt);
    *gap = linear_extrapolate(r[VR_FOLLOWER_GAP], r[VR_FOLLOWER_GAP_RATE], dt);
}

/* The target as one step and its outputs see it: target_at is a pure function of t (the inputs do
 * not change between a step and its outputs), and RK4's second and third stages ask for the same
 * instant, the outputs for the step's end, which its last stage used, so each instant is
 * extrapolated once (same numbers: the same function, called once instead of twice). Not in the
 * Python model, where the saving would not be worth a cache: it only saves time. */
typedef struct {
    const Instance *instance;
    int known;
    double t;
    double target[4];
} TargetSight;

static TargetSight target_sight(const Instance *instance)
{
    TargetSight sight = {instance, 0, 0.0, {0.0, 0.0, 0.0, 0.0}};
    return sight;
}

/* The last instant a step saw, kept for its outputs: memo.values = (t, x, y, heading, speed). */
static void remember_sight(const TargetSight *sight, FwStepMemo *memo)
{
    memo->known = sight->known;
    memo->values[0] = sight->t;
    memcpy(&memo->values[1], sight->target, sizeof sight->target);
}

/* The sight of the outputs: what the step just taken saw, if they follow one (memo not NULL). */
static TargetSight recalled_sight(const Instance *instance, const FwStepMemo *memo)
{
    TargetSight sight = target_sight(instance);
    if (memo && memo->known) {
        sight.known = 1;
        sight.t = memo->values[0];
        memcpy(sight.target, &memo->values[1], sizeof sight.target);
    }
    return sight;
}

static const double *target_seen(TargetSight *sight, double t)
{
    if (!sight->known || sight->t != t) {
        target_at(sight->instance, t, sight->target);
        sight->t = t;
        sight->known = 1;
    }
    return sight->target;
}

/* VehicleStepper.evaluate with fmus.model.vehicle.VehicleModel.evaluate: the state derivative, the
 * acting lateral acceleration and the distance to the target. */
static void evaluate(TargetSight *sight, double t, const double *state, double *derivative,
                     double *acceleration, double *distance)
{
    const Instance *instance = sight->instance;
    const VehicleConfig *config = config_of(instance);
    const double *r = instance->reals;
    const double *target = target_seen(sight, t);
    double follower_speed, follower_gap;
    follower_at(instance, t, &follower_speed, &follower_gap);
    double added_acceleration = r[VR_DISTURBANCE_LATERAL_ACCELERATION];
    double added_speed = r[VR_DISTURBANCE_SPEED];
    /* VehicleModel.evaluate */
    double x = state[0], y = state[1], heading = state[2];
    double speed = dynamics_speed(config, state, added_speed);
    double los;
    line_of_sight(x, y, target[0], target[1], distance, &los);
    *acceleration =
        lateral_acceleration(config->law, speed, *distance, los, heading, target[2]) + added_acceleration;
    double sensed_gap = 0.0;
    if (config->speed_law != SPEED_LAW_PAPER) { /* SpeedLaw.senses */
        double sensor_x, sensor_y;
        sensor_at(instance, t, &sensor_x, &sensor_y);
        sensed_gap = point_distance(x, y, sensor_x, sensor_y);
    }
    double commanded =
        commanded_speed(config, state, speed, sensed_gap, target[3], follower_speed, follower_gap);
    dynamics_derivative(config, state, *acceleration, commanded, added_speed, derivative);
}

/* VehicleStepper.derivative */
static void derivative_of(void *context, double t, const double *state, double *derivative)
{
    double acceleration, distance;
    evaluate((TargetSight *)context, t, state, derivative, &acceleration, &distance);
}

/* --- fmus.model.robot_loop.RobotLoopStepper ----------------------------------------------------------- */

/* M3piDynamics.radio_command */
static void radio_command(const VehicleConfig *config, double setpoint, double lateral_acceleration,
                          double added_speed, double *right, double *left)
{
    differential_wheel_speeds(setpoint, lateral_acceleration, config->track, right, left);
    double limit = config->wheel_speed_max; /* wheel_commands' limit_wheels, then limit_wheels with the push */
    *right = py_min(py_max(*right, -limit), limit);
    *left = py_min(py_max(*left, -limit), limit);
    *right = py_min(py_max(*right + added_speed, -limit), limit);
    *left = py_min(py_max(*left + added_speed, -limit), limit);
}

/* RobotLoopStepper.robot_derivative: the robot's physics under the command acting */
typedef struct {
    const VehicleConfig *config;
    double right_cmd, left_cmd;
} RobotDrive;

static void robot_derivative(void *context, double t, const double *state, double *derivative)
{
    (void)t;
    const RobotDrive *drive = (const RobotDrive *)context;
    m3pi_drive(drive->config, state[2], state[3], state[4], drive->right_cmd, drive->left_cmd, 0.0, derivative);
}

static double *command_slot(Instance *instance, int index)
{
    return instance->memory + (size_t)(index % COMMAND_CAPACITY) * COMMAND_FIELDS;
}

/* RobotLoopStepper.move_robot on state (the instance's, copied), after the command sent at t joined the ring */
static void move_robot(Instance *instance, double t, double h, double *state)
{
    const VehicleConfig *config = config_of(instance);
    double now = t, end = t + h;
    for (;;) {
        int count = (int)state[S_COUNT], first = (int)state[S_FIRST];
        double lands = count > 0 ? command_slot(instance, first)[0] : INFINITY;
        double until = py_min(lands, end);
        if (state[S_HELD_KNOWN] != 0.0 && until > now) {
            RobotDrive drive = {config, state[S_HELD_RIGHT], state[S_HELD_LEFT]};
            integrate(robot_derivative, &drive, now, &state[S_ROBOT], ROBOT_SIZE, until - now, config->max_substep);
        }
        now = py_max(now, until);
        if (lands > end) return;
        const double *landed = command_slot(instance, first);
        state[S_HELD_KNOWN] = 1.0;
        state[S_HELD_RIGHT] = landed[1];
        state[S_HELD_LEFT] = landed[2];
        state[S_FIRST] = (double)((first + 1) % COMMAND_CAPACITY);
        state[S_COUNT] = (double)(count - 1);
    }
}

/* RobotLoopStepper.step's command: sent at t from the controller's state, into the ring (0, or 1 when full) */
static int send_command(Instance *instance, TargetSight *sight, double t, double *state, FwText *why)
{
    const VehicleConfig *config = config_of(instance);
    double derivative[FW_MAX_STATE], acceleration, distance, right, left;
    evaluate(sight, t, state, derivative, &acceleration, &distance);
    radio_command(config, state[5], acceleration, instance->reals[VR_DISTURBANCE_SPEED], &right, &left);
    int count = (int)state[S_COUNT];
    if (count + 1 > COMMAND_CAPACITY) {
        fw_text_append(why, "ValueError: more than %d commands in flight (the latencies span too many steps)",
                       COMMAND_CAPACITY);
        return 1;
    }
    double *slot = command_slot(instance, (int)state[S_FIRST] + count);
    slot[0] = t + config->delay;
    slot[1] = right;
    slot[2] = left;
    state[S_COUNT] = (double)(count + 1);
    return 0;
}

/* The robot after the step (RobotLoopStepper.step): finite, and measured: the controller sees its pose */
static int measure_robot(double *state, double time, FwText *why)
{
    for (int i = 0; i < ROBOT_SIZE; ++i) {
        if (!isfinite(state[S_ROBOT + i])) {
            fw_text_append(why, "the robot's state became non-finite before t = %.6g s", time);
            return 1;
        }
    }
    memcpy(state, &state[S_ROBOT], 3 * sizeof *state);
    return 0;
}

/* VehicleStepper.step with VehicleStepper.check; RobotLoopStepper.step in the sampled loop */
static int vehicle_step(Instance *instance, double t, double h, FwStepMemo *memo, FwText *why)
{
    const VehicleConfig *config = config_of(instance);
    double state[FW_MAX_STATE];
    memcpy(state, instance->state, sizeof state);
    TargetSight sight = target_sight(instance);
    if (config->sampled && send_command(instance, &sight, t, state, why) != 0) return 1;
    integrate(derivative_of, &sight, t, state, config->state_size, h, config->max_substep);
    double time = t + h;
    for (int i = 0; i < config->state_size; ++i) {
        if (!isfinite(state[i])) {
            fw_text_append(why, "the state became non-finite before t = %.6g s", time);
            return 1;
        }
    }
    double speed = dynamics_speed(config, state, instance->reals[VR_DISTURBANCE_SPEED]);
    if (speed <= 0.0) {
        fw_text_append(why, "speed fell to %.6g m/s at t = %.6g s; guidance needs V > 0", speed, time);
        return 1;
    }
    if (config->sampled) {
        move_robot(instance, t, h, state);
        if (measure_robot(state, time, why) != 0) return 1;
    }
    memcpy(instance->state, state, sizeof state);
    instance->time = time;
    remember_sight(&sight, memo);
    return 0;
}

/* VehicleStepper.outputs */
static void vehicle_outputs(const Instance *instance, const FwStepMemo *memo, double *values)
{
    const VehicleConfig *config = config_of(instance);
    double t = instance->time;
    const double *state = instance->state;
    double added_speed = instance->reals[VR_DISTURBANCE_SPEED];
    double derivative[FW_MAX_STATE], acceleration, gap;
    TargetSight sight = recalled_sight(instance, memo);
    evaluate(&sight, t, state, derivative, &acceleration, &gap);
    double x = state[0], y = state[1], heading = state[2];
    double speed = dynamics_speed(config, state, added_speed);
    const double *target = target_seen(&sight, t);
    double dx = target[0] - x, dy = target[1] - y;
    /* speed * cos(heading) and speed * sin(heading) are the position derivative evaluate just
     * computed, as the same product of the same numbers (v = speed in both dynamics) */
    double relative_vx = target[3] * cos(target[2]) - derivative[0];
    double relative_vy = target[3] * sin(target[2]) - derivative[1];
    double wheel_right, wheel_left;
    dynamics_wheel_speeds(config, state, acceleration, added_speed, &wheel_right, &wheel_left);
    values[VR_X] = x;
    values[VR_Y] = y;
    values[VR_HEADING] = heading;
    values[VR_SPEED] = speed;
    values[VR_SPEED_RATE] = dynamics_speed_rate(config, derivative);
    values[VR_TURN_RATE] = derivative[2];
    values[VR_LATERAL_ACCELERATION] = acceleration;
    values[VR_GAP] = gap;
    values[VR_GAP_RATE] = (dx * relative_vx + dy * relative_vy) / gap;
    values[VR_WHEEL_RIGHT] = wheel_right;
    values[VR_WHEEL_LEFT] = wheel_left;
    values[VR_OUTPUT_TIME] = t;
}

const ModelDef MODEL = {
    MODEL_IDENTIFIER,         MODEL_GUID,    VARIABLE_COUNT,      MODEL_VARIABLES,
    sizeof(VehicleConfig),    vehicle_parameter_errors, vehicle_configure, vehicle_max_substep,
    vehicle_outputs,          vehicle_step,  COMMAND_CAPACITY * COMMAND_FIELDS,
};

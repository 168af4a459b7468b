/*
 * science.h - the parts of fmus/model both native models use: angles, guidance, RK4, coupling.
 *
 * Each function mirrors one Python function, named in its comment, with the arithmetic in the
 * same order (Python evaluates a + b + c as (a + b) + c, a * b / c as (a * b) / c), so results
 * agree to the last bit (pymath.h says where C and Python would otherwise differ).
 * fmus/model stays the reference: change the Python first, then this.
 */
#ifndef PLATOON_SCIENCE_H
#define PLATOON_SCIENCE_H

#include <math.h>

#include "pymath.h"

#define SCIENCE_PI 3.141592653589793      /* math.pi */
#define SCIENCE_TWO_PI (2.0 * SCIENCE_PI) /* fmus.model.angles.TWO_PI */

/* fmus.model.angles.wrap_angle */
static inline double wrap_angle(double angle)
{
    /* fmod(x, y) is x itself when |x| < |y| (fmod is exact), so the library call is needed only
     * for angles of a turn or more: most guidance errors are small */
    double wrapped = fabs(angle) < SCIENCE_TWO_PI ? angle : fmod(angle, SCIENCE_TWO_PI);
    if (wrapped > SCIENCE_PI) {
        wrapped -= SCIENCE_TWO_PI;
    } else if (wrapped <= -SCIENCE_PI) {
        wrapped += SCIENCE_TWO_PI;
    }
    return wrapped;
}

/* --- fmus.model.guidance ------------------------------------------------------------------------ */

typedef enum { LAW_REGULAR, LAW_SINE } Law; /* fmus.model.guidance.LAWS */

/* fmus.model.guidance.line_of_sight */
static inline void line_of_sight(double x, double y, double target_x, double target_y, double *distance,
                                 double *los)
{
    double dx = target_x - x;
    double dy = target_y - y;
    *distance = py_hypot(dx, dy);
    *los = atan2(dy, dx);
}

/* fmus.model.guidance.lateral_acceleration */
static inline double lateral_acceleration(Law law, double speed, double distance, double los, double heading,
                                          double target_heading)
{
    double vehicle_error = wrap_angle(los - heading);
    double target_error = wrap_angle(los - target_heading);
    double gain = speed * speed / distance;
    if (law == LAW_SINE) {
        return gain * (4.0 * sin(vehicle_error) + 2.0 * sin(target_error));
    }
    return gain * (4.0 * vehicle_error + 2.0 * target_error);
}

/* fmus.model.guidance.SPEED_LAWS */
typedef enum { SPEED_LAW_PAPER, SPEED_LAW_ACC, SPEED_LAW_CACC } SpeedLaw;
static const char *const SPEED_LAWS[] = {"paper", "acc", "cacc"};

/* fmus.model.guidance.distance (named apart from the distance variables of vehicle.c) */
static inline double point_distance(double x, double y, double target_x, double target_y)
{
    return py_hypot(target_x - x, target_y - y);
}

/* fmus.model.guidance.time_gap_speed */
static inline double time_gap_speed(double gap, double standstill_gap, double time_gap)
{
    return (gap - standstill_gap) / time_gap;
}

/* fmus.model.guidance.spacing_error */
static inline double spacing_error(double gap, double standstill_gap, double time_gap, double speed)
{
    return gap - standstill_gap - time_gap * speed;
}

/* fmus.model.guidance.cacc_acceleration */
static inline double cacc_acceleration(double predecessor_speed, double speed, double error, double time_gap,
                                       double gain)
{
    return (predecessor_speed - speed + gain * error) / time_gap;
}

/* fmus.model.guidance.speed_for_acceleration */
static inline double speed_for_acceleration(double speed, double acceleration, double k_v)
{
    return speed + acceleration / k_v;
}

/* fmus.model.guidance.spacing_speed */
static inline double spacing_speed(double speed, double gap, double d_star) { return speed * d_star / gap; }

/* fmus.model.guidance.spacing_speed_rate */
static inline double spacing_speed_rate(double speed, double speed_rate, double gap, double gap_rate, double d_star)
{
    return d_star * (speed_rate * gap - speed * gap_rate) / (gap * gap);
}

/* fmus.model.guidance.speed_loop */
static inline double speed_loop(double k_v, double commanded_speed, double speed)
{
    return k_v * (commanded_speed - speed);
}

/* --- fmus.model.integrate ----------------------------------------------------------------------- */

/* dy/dt = f(t, y) into derivative; context is the model's. */
typedef void (*Derivative)(void *context, double t, const double *y, double *derivative);

/* fmus.model.integrate.rk4_step (y is replaced by the new value) */
static inline void rk4_step(Derivative f, void *context, double t, double *y, int size, double h)
{
    double k1[8], k2[8], k3[8], k4[8], stage[8];
    double half = 0.5 * h;
    f(context, t, y, k1);
    for (int i = 0; i < size; ++i) stage[i] = y[i] + half * k1[i];
    f(context, t + half, stage, k2);
    for (int i = 0; i < size; ++i) stage[i] = y[i] + half * k2[i];
    f(context, t + half, stage, k3);
    for (int i = 0; i < size; ++i) stage[i] = y[i] + h * k3[i];
    f(context, t + h, stage, k4);
    double sixth = h / 6.0;
    for (int i = 0; i < size; ++i) y[i] = y[i] + sixth * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
}

/* fmus.model.integrate.substep_count, as a double (the caller checks it against its limit before
 * it becomes a loop count: 1e9 / 0.01 substeps must be refused, not attempted). */
static inline double substep_count(double step, double max_substep)
{
    double count = ceil(step / max_substep - 1e-9);
    return py_max(1.0, count);
}

/* fmus.model.integrate.integrate */
static inline void integrate(Derivative f, void *context, double t, double *y, int size, double step,
                             double max_substep)
{
    long n = (long)substep_count(step, max_substep);
    double h = step / (double)n;
    for (long k = 0; k < n; ++k) rk4_step(f, context, t + (double)k * h, y, size, h);
}

/* --- fmus.model.coupling ------------------------------------------------------------------------ */

typedef enum { COUPLING_HOLD, COUPLING_EXTRAPOLATE } Coupling;
static const char *const COUPLING_MODES[] = {"hold", "extrapolate"}; /* fmus.model.coupling.COUPLING_MODES */

#define ARC_SERIES_LIMIT 1e-3 /* fmus.model.coupling._SERIES_LIMIT */

/* fmus.model.coupling._arc_factors */
static inline void arc_factors(double turn, double *along, double *across)
{
    if (fabs(turn) < ARC_SERIES_LIMIT) {
        double u2 = turn * turn;
        *along = 1.0 - u2 / 6.0 + u2 * u2 / 120.0;
        *across = turn * (0.5 - u2 / 24.0 + u2 * u2 / 720.0);
        return;
    }
    *along = sin(turn) / turn;
    *across = (1.0 - cos(turn)) / turn;
}

/* fmus.model.coupling.arc_extrapolate: out = (x, y, heading, speed) dt after the sample */
static inline void arc_extrapolate(double x, double y, double heading, double speed, double speed_rate,
                                   double turn_rate, double dt, double out[4])
{
    double arc_length = dt * (speed + 0.5 * speed_rate * dt);
    double curvature = speed != 0.0 ? turn_rate / speed : 0.0;
    double turn = curvature * arc_length;
    if (arc_length == 0.0 && turn == 0.0 && isfinite(heading) && x != 0.0 && y != 0.0) {
        /* No way travelled (the sample is for this very instant, as at each step's start): the
         * factors are along = 1 and across = +-0, so both offsets are +-0 and x + +-0 is x for any
         * x but a zero, whose sign the sum could change. The same numbers without the cos and sin. */
        out[0] = x;
        out[1] = y;
    } else {
        double along, across;
        arc_factors(turn, &along, &across);
        double c = cos(heading);
        double s = sin(heading);
        out[0] = x + arc_length * (along * c - across * s);
        out[1] = y + arc_length * (along * s + across * c);
    }
    out[2] = heading + turn;
    out[3] = speed + speed_rate * dt;
}

/* fmus.model.coupling.linear_extrapolate */
static inline double linear_extrapolate(double value, double rate, double dt) { return value + rate * dt; }

#endif

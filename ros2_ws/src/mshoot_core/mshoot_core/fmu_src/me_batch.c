/* Batched Model Exchange intervals for mshoot: one C loop over many intervals of one
 * FMU instance, integrated with an adaptive explicit Runge-Kutta method (Dormand-Prince
 * 5(4), FSAL) instead of fmpy's CVode with a Python right-hand side.
 *
 * Each interval repeats what mshoot_core.models.fmi.FmiModel._start_interval does:
 * either restore the snapshot taken after the first initialisation (fmi2SetFMUstate),
 * write the start states, then enter event mode, set the inputs, iterate
 * fmi2NewDiscreteStates and enter continuous-time mode; or, for FMUs without FMU
 * states, reset, set parameters and start values, initialise with the inputs, iterate
 * the discrete states and write the start states. Then the states are integrated over
 * [t0, t0 + dt] (fmi2SetTime / fmi2SetContinuousStates / fmi2GetDerivatives at every stage,
 * fmi2CompletedIntegratorStep after accepted steps when the FMU needs it), and the
 * states and outputs are read at t0 + dt. The start time t0 of interval b is t_start[b]
 * (NULL: 0): set after restoring the snapshot (fmi2SetTime, before the event iteration),
 * or the experiment's start time on the reset path.
 *
 * Optionally the forward sensitivities S = [Sx | Su] (n x (k + m), row-major after x)
 * are integrated along with the states, S_j' = J_x S_j (+ J_u e_j), the products from
 * fmi2GetDirectionalDerivative, and the output partials d y / d (x, u) are evaluated at
 * the end of each interval: the same system as the Python class _Sensitivities.
 *
 * Only valid for FMUs without event indicators; an interval that would need event
 * handling (a time event inside the interval, a step event) returns a negative code
 * and the caller falls back to CVode. The FMU's functions come in as pointers from the
 * instance fmpy already loaded. */
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include "fmi2Functions.h"

typedef struct {
    fmi2ResetTYPE *reset;
    fmi2SetRealTYPE *set_real;
    fmi2GetRealTYPE *get_real;
    fmi2SetupExperimentTYPE *setup_experiment;
    fmi2EnterInitializationModeTYPE *enter_initialization;
    fmi2ExitInitializationModeTYPE *exit_initialization;
    fmi2SetFMUstateTYPE *set_fmu_state;
    fmi2EnterEventModeTYPE *enter_event_mode;
    fmi2NewDiscreteStatesTYPE *new_discrete_states;
    fmi2EnterContinuousTimeModeTYPE *enter_continuous_time_mode;
    fmi2CompletedIntegratorStepTYPE *completed_integrator_step;
    fmi2SetTimeTYPE *set_time;
    fmi2SetContinuousStatesTYPE *set_continuous_states;
    fmi2GetDerivativesTYPE *get_derivatives;
    fmi2GetContinuousStatesTYPE *get_continuous_states;
    fmi2GetNominalsOfContinuousStatesTYPE *get_nominals;
    fmi2GetDirectionalDerivativeTYPE *get_directional_derivative;
} mshoot_me_api;

/* Everything that is the same for all intervals of a batch. */
typedef struct {
    fmi2FMUstate snapshot;          /* NULL: reset and initialise every interval */
    int needs_completed_step;       /* call fmi2CompletedIntegratorStep after accepted steps */
    double tolerance;               /* relative tolerance (also passed to fmi2SetupExperiment) */
    double dt;                      /* interval length [s] */
    size_t max_steps;               /* attempted steps per interval before giving up */
    size_t n;                       /* number of continuous states */
    const fmi2ValueReference *cstate_vr;      /* (n) continuous states */
    const fmi2ValueReference *derivative_vr;  /* (n) their derivatives */
    size_t nx;                      /* model states */
    const size_t *x_pos;            /* (nx) their positions in the continuous-state vector */
    const fmi2ValueReference *x_vr; /* (nx) read at the end */
    size_t ny;
    const fmi2ValueReference *y_vr; /* (ny) outputs read at the end */
    size_t n_in;
    const fmi2ValueReference *in_vr;
    size_t n_par;                   /* Real parameters (reset path only) */
    const fmi2ValueReference *par_vr;
    const double *par_val;
    size_t n_start;                 /* start values of model states (reset path only) */
    const fmi2ValueReference *start_vr;
    const size_t *start_idx;        /* (n_start) indices into the model state vector */
    /* sensitivities: 0 columns = states only */
    size_t n_su;                    /* input columns (the state columns are the nx states) */
    const fmi2ValueReference *su_vr;
    const double *su_nominal;       /* (n_su) nominals of those inputs */
    double sensitivity_factor;      /* abs. tolerance of S_ij: factor * x_nom_i / nom_j */
    int sensitivities;              /* integrate S and evaluate output partials */
    size_t n_yo;                    /* outputs that are FMU outputs (output partials) */
    const fmi2ValueReference *yo_vr;
    /* chains: 0, the intervals are independent; C > 0, interval b >= C starts from the end
     * states of interval b - C (C trajectories of consecutive intervals, interleaved) */
    size_t chain;
} mshoot_me_problem;

/* Return codes besides 0 (success): > 0 an FMI call failed, 16 * interval + stage + 1;
 * < 0 the interval needs what this driver does not do (the caller falls back):  */
#define ME_TIME_EVENT (-1)   /* a time event at or before the end of the interval */
#define ME_STEP_EVENT (-2)   /* fmi2CompletedIntegratorStep requested event mode */
#define ME_MAX_STEPS (-3)    /* more than max_steps steps (stiff?) */
#define ME_STEP_SIZE (-4)    /* step size underflow */
#define ME_NO_MEMORY (-5)
#define ME_TERMINATE (-6)    /* the FMU requested termination */
#define ME_MISSING (-7)      /* an FMI function this batch needs is not exported */

/* stages of the FMI calls, for the error code */
enum { S_RESTORE, S_PARAMETERS, S_START, S_SETUP, S_ENTER_INIT, S_INPUTS, S_EXIT_INIT,
       S_EVENTS, S_CONTINUOUS, S_STATES, S_DERIVATIVES, S_DIRECTIONAL, S_STEP, S_READ };

#define CHECK(call, stage) do { if ((call) > fmi2Warning) { \
    code = (long)(b * 16 + (stage) + 1); goto done; } } while (0)
#define FAIL(value) do { code = (value); goto done; } while (0)

typedef struct {
    const mshoot_me_api *api;
    fmi2Component c;
    const mshoot_me_problem *p;
    size_t size;          /* n * (1 + columns) */
    size_t columns;       /* nx + n_su when sensitivities, else 0 */
    fmi2ValueReference *knowns;  /* (n + 1): continuous states and one input */
    double *seed;         /* (n + 1) */
    long evaluations;
} rhs_context;

/* dy/dt of the (augmented) system at (t, y); stage of a failing call or -1. */
static int rhs(rhs_context *ctx, double t, const double *y, double *dy)
{
    const mshoot_me_api *api = ctx->api;
    const mshoot_me_problem *p = ctx->p;
    size_t n = p->n, cols = ctx->columns, i, j;
    ctx->evaluations++;
    if (api->set_time(ctx->c, t) > fmi2Warning) return S_STATES;
    if (api->set_continuous_states(ctx->c, y, n) > fmi2Warning) return S_STATES;
    if (api->get_derivatives(ctx->c, dy, n) > fmi2Warning) return S_DERIVATIVES;
    for (j = 0; j < cols; j++) {
        size_t n_known = n;
        for (i = 0; i < n; i++) ctx->seed[i] = y[n + i * cols + j];
        if (j >= p->nx) {
            ctx->knowns[n] = p->su_vr[j - p->nx];
            ctx->seed[n] = 1.0;
            n_known = n + 1;
        }
        /* the column of J S_j goes to the scratch after the seed, then into dy */
        if (api->get_directional_derivative(ctx->c, p->derivative_vr, n, ctx->knowns, n_known,
                                            ctx->seed, ctx->seed + n + 1) > fmi2Warning)
            return S_DIRECTIONAL;
        for (i = 0; i < n; i++) dy[n + i * cols + j] = ctx->seed[n + 1 + i];
    }
    return -1;
}

/* Weighted RMS norm as CVode's: sqrt(mean((v_i / (rtol |y_i| + atol_i))^2)). */
static double wrms(const double *v, const double *y, const double *y2, const double *atol,
                   double rtol, size_t size)
{
    double sum = 0.0;
    size_t i;
    for (i = 0; i < size; i++) {
        double scale = fabs(y[i]);
        if (y2 && fabs(y2[i]) > scale) scale = fabs(y2[i]);
        double w = v[i] / (rtol * scale + atol[i]);
        sum += w * w;
    }
    return sqrt(sum / (double)size);
}

/* Dormand-Prince 5(4) tableau */
static const double C2 = 1.0 / 5, C3 = 3.0 / 10, C4 = 4.0 / 5, C5 = 8.0 / 9;
static const double A21 = 1.0 / 5;
static const double A31 = 3.0 / 40, A32 = 9.0 / 40;
static const double A41 = 44.0 / 45, A42 = -56.0 / 15, A43 = 32.0 / 9;
static const double A51 = 19372.0 / 6561, A52 = -25360.0 / 2187, A53 = 64448.0 / 6561,
                    A54 = -212.0 / 729;
static const double A61 = 9017.0 / 3168, A62 = -355.0 / 33, A63 = 46732.0 / 5247,
                    A64 = 49.0 / 176, A65 = -5103.0 / 18656;
static const double B1 = 35.0 / 384, B3 = 500.0 / 1113, B4 = 125.0 / 192, B5 = -2187.0 / 6784,
                    B6 = 11.0 / 84;
static const double E1 = 71.0 / 57600, E3 = -71.0 / 16695, E4 = 71.0 / 1920,
                    E5 = -17253.0 / 339200, E6 = 22.0 / 525, E7 = -1.0 / 40;

__attribute__((visibility("default")))
long mshoot_me_batch(const mshoot_me_api *api, fmi2Component c, const mshoot_me_problem *p,
                     size_t n_batch, const double *x0, const double *u,
                     double *x_end, double *y_end, double *s_end, double *dyo, long *stats,
                     const double *t_start)
{
    size_t n = p->n, nx = p->nx, b = 0, i, j;
    size_t columns = p->sensitivities ? nx + p->n_su : 0;
    size_t size = n * (1 + columns);
    long code = 0, accepted = 0, rejected = 0;
    double dt = p->dt, rtol = p->tolerance;
    double *work = calloc(12 * size + 4 * n + 1 + p->n_yo, sizeof(double));
    fmi2ValueReference *knowns = calloc(n + 1, sizeof(fmi2ValueReference));
    double *k1, *k2, *k3, *k4, *k5, *k6, *k7, *y, *ynew, *tmp, *err, *atol, *xfull, *nominal, *column;
    rhs_context ctx;
    fmi2EventInfo info;
    if (!api->set_real || !api->get_real || !api->new_discrete_states
        || !api->enter_continuous_time_mode || !api->set_time || !api->set_continuous_states
        || !api->get_derivatives || !api->get_continuous_states || !api->get_nominals
        || (p->snapshot && (!api->set_fmu_state || !api->enter_event_mode))
        || (!p->snapshot && (!api->reset || !api->setup_experiment
                             || !api->enter_initialization || !api->exit_initialization))
        || (p->needs_completed_step && !api->completed_integrator_step)
        || (p->sensitivities && !api->get_directional_derivative)) {
        free(work); free(knowns);
        if (stats) stats[0] = stats[1] = stats[2] = stats[3] = 0;
        return ME_MISSING;
    }
    if (!work || !knowns) {
        free(work); free(knowns);
        if (stats) stats[0] = stats[1] = stats[2] = stats[3] = 0;
        return ME_NO_MEMORY;
    }
    k1 = work; k2 = k1 + size; k3 = k2 + size; k4 = k3 + size; k5 = k4 + size;
    k6 = k5 + size; k7 = k6 + size; y = k7 + size; ynew = y + size; tmp = ynew + size;
    err = tmp + size; atol = err + size; xfull = atol + size; nominal = xfull + n;
    ctx.api = api; ctx.c = c; ctx.p = p; ctx.size = size; ctx.columns = columns;
    ctx.knowns = knowns; ctx.seed = nominal + n;  /* (n + 1) seed, then (n) column */
    column = ctx.seed + 2 * n + 1;                /* (n_yo) output partials */
    ctx.evaluations = 0;
    memcpy(knowns, p->cstate_vr, n * sizeof(fmi2ValueReference));

    for (b = 0; b < n_batch; b++) {
        const double *xb = (p->chain && b >= p->chain) ? x_end + (b - p->chain) * nx
                                                       : x0 + b * nx;
        const double *ub = u + b * p->n_in;
        /* t runs over [0, dt]; the FMU sees t0 + t (t0 = 0: the same numbers as before) */
        const double t0 = t_start ? t_start[b] : 0.0;
        double t = 0.0, h, e, eps = 1e-12 * (dt > 1.0 ? dt : 1.0);
        double eps_event = 1e-12 * (fabs(t0) + dt > 1.0 ? fabs(t0) + dt : 1.0);
        size_t steps = 0;
        int stage, last_rejected = 0;
        /* -- start the interval, as FmiModel._start_interval ------------------------------ */
        if (p->snapshot) {
            CHECK(api->set_fmu_state(c, p->snapshot), S_RESTORE);
            if (t_start) CHECK(api->set_time(c, t0), S_RESTORE);
            CHECK(api->get_continuous_states(c, xfull, n), S_STATES);
            for (i = 0; i < nx; i++) xfull[p->x_pos[i]] = xb[i];
            CHECK(api->set_continuous_states(c, xfull, n), S_STATES);
            CHECK(api->enter_event_mode(c), S_EVENTS);
            if (p->n_in) CHECK(api->set_real(c, p->in_vr, p->n_in, ub), S_INPUTS);
        } else {
            CHECK(api->reset(c), S_RESTORE);
            if (p->n_par) CHECK(api->set_real(c, p->par_vr, p->n_par, p->par_val), S_PARAMETERS);
            for (i = 0; i < p->n_start; i++) tmp[i] = xb[p->start_idx[i]];
            if (p->n_start) CHECK(api->set_real(c, p->start_vr, p->n_start, tmp), S_START);
            CHECK(api->setup_experiment(c, fmi2True, rtol, t0, fmi2False, 0.0), S_SETUP);
            CHECK(api->enter_initialization(c), S_ENTER_INIT);
            if (p->n_in) CHECK(api->set_real(c, p->in_vr, p->n_in, ub), S_INPUTS);
            CHECK(api->exit_initialization(c), S_EXIT_INIT);
        }
        info.newDiscreteStatesNeeded = fmi2True;
        while (info.newDiscreteStatesNeeded) {
            CHECK(api->new_discrete_states(c, &info), S_EVENTS);
            if (info.terminateSimulation) FAIL(ME_TERMINATE);
        }
        if (info.nextEventTimeDefined && info.nextEventTime <= t0 + dt + eps_event)
            FAIL(ME_TIME_EVENT);
        CHECK(api->enter_continuous_time_mode(c), S_CONTINUOUS);
        if (!p->snapshot) {
            CHECK(api->get_continuous_states(c, xfull, n), S_STATES);
            for (i = 0; i < nx; i++) xfull[p->x_pos[i]] = xb[i];
            CHECK(api->set_continuous_states(c, xfull, n), S_STATES);
        }
        /* -- y = [x, S(0) = (unit columns of the model states | 0)], tolerances ------------ */
        memset(y, 0, size * sizeof(double));
        CHECK(api->get_continuous_states(c, y, n), S_STATES);
        for (j = 0; j < columns && j < nx; j++) y[n + p->x_pos[j] * columns + j] = 1.0;
        CHECK(api->get_nominals(c, nominal, n), S_STATES);
        for (i = 0; i < n; i++) {
            double x_nom = fabs(nominal[i]);
            atol[i] = rtol * nominal[i];
            for (j = 0; j < columns; j++) {
                double scale = j < nx ? fabs(nominal[p->x_pos[j]]) : p->su_nominal[j - nx];
                atol[n + i * columns + j] = rtol * p->sensitivity_factor * x_nom / scale;
            }
        }
        for (i = 0; i < size; i++) if (!(atol[i] > 0.0)) atol[i] = rtol;
        /* -- initial step, after Hairer, Norsett & Wanner (II.4): h0 changes y by ~1 % of
         * its tolerance-weighted size in an Euler step; d2 = ||y''|| from that step gives
         * the rate lam = d2 / d1, and h1 ~ (0.01 / ||y^(5)||)^(1/5) with
         * ||y^(5)|| ~ lam^4 ||y'|| (their (0.01 / max(d1, d2))^(1/5) mixes units and
         * starts slow building models with seconds-long steps) --------------------------- */
        if ((stage = rhs(&ctx, t0, y, k1)) >= 0) CHECK(fmi2Error, stage);
        {
            double d0 = wrms(y, y, NULL, atol, rtol, size), d1 = wrms(k1, y, NULL, atol, rtol, size);
            double h0 = (d0 < 1e-5 || d1 < 1e-5) ? 1e-6 * dt : 0.01 * d0 / d1, d2, h1 = dt;
            if (h0 > dt) h0 = dt;
            for (i = 0; i < size; i++) ynew[i] = y[i] + h0 * k1[i];
            if ((stage = rhs(&ctx, t0 + h0, ynew, k2)) >= 0) CHECK(fmi2Error, stage);
            for (i = 0; i < size; i++) err[i] = (k2[i] - k1[i]) / h0;
            d2 = wrms(err, y, NULL, atol, rtol, size);
            if (d1 >= 1e-5 && d2 > 0.0)
                h1 = exp(0.2 * (log(0.01) + 3.0 * log(d1) - 4.0 * log(d2)));
            else if (d2 > 1e-15)
                h1 = pow(0.01 / d2, 0.2);
            h = fmin(100.0 * h0, h1);
            if (!(h > 0.0)) h = h0;
        }
        /* -- Dormand-Prince 5(4) with FSAL ------------------------------------------------- */
        while (dt - t > eps) {
            int final = 0;
            if (++steps > p->max_steps) FAIL(ME_MAX_STEPS);
            if (h >= dt - t || t + 1.01 * h >= dt) { h = dt - t; final = 1; }
            if (h <= eps * 1e-3) FAIL(ME_STEP_SIZE);
            for (i = 0; i < size; i++) tmp[i] = y[i] + h * A21 * k1[i];
            if ((stage = rhs(&ctx, t0 + t + C2 * h, tmp, k2)) >= 0) CHECK(fmi2Error, stage);
            for (i = 0; i < size; i++) tmp[i] = y[i] + h * (A31 * k1[i] + A32 * k2[i]);
            if ((stage = rhs(&ctx, t0 + t + C3 * h, tmp, k3)) >= 0) CHECK(fmi2Error, stage);
            for (i = 0; i < size; i++)
                tmp[i] = y[i] + h * (A41 * k1[i] + A42 * k2[i] + A43 * k3[i]);
            if ((stage = rhs(&ctx, t0 + t + C4 * h, tmp, k4)) >= 0) CHECK(fmi2Error, stage);
            for (i = 0; i < size; i++)
                tmp[i] = y[i] + h * (A51 * k1[i] + A52 * k2[i] + A53 * k3[i] + A54 * k4[i]);
            if ((stage = rhs(&ctx, t0 + t + C5 * h, tmp, k5)) >= 0) CHECK(fmi2Error, stage);
            for (i = 0; i < size; i++)
                tmp[i] = y[i] + h * (A61 * k1[i] + A62 * k2[i] + A63 * k3[i] + A64 * k4[i]
                                     + A65 * k5[i]);
            if ((stage = rhs(&ctx, t0 + (final ? dt : t + h), tmp, k6)) >= 0)
                CHECK(fmi2Error, stage);
            for (i = 0; i < size; i++)
                ynew[i] = y[i] + h * (B1 * k1[i] + B3 * k3[i] + B4 * k4[i] + B5 * k5[i]
                                      + B6 * k6[i]);
            if ((stage = rhs(&ctx, t0 + (final ? dt : t + h), ynew, k7)) >= 0)
                CHECK(fmi2Error, stage);
            for (i = 0; i < size; i++)
                err[i] = h * (E1 * k1[i] + E3 * k3[i] + E4 * k4[i] + E5 * k5[i] + E6 * k6[i]
                              + E7 * k7[i]);
            e = wrms(err, y, ynew, atol, rtol, size);
            if (e <= 1.0) {  /* accept; k7 = f(t + h, ynew) is the next step's k1 */
                double factor = e > 0.0 ? 0.9 * pow(e, -0.2) : 5.0;
                if (factor > 5.0) factor = 5.0;
                if (last_rejected && factor > 1.0) factor = 1.0;
                t = final ? dt : t + h;
                memcpy(y, ynew, size * sizeof(double));
                memcpy(k1, k7, size * sizeof(double));
                accepted++;
                last_rejected = 0;
                if (p->needs_completed_step) {
                    fmi2Boolean enter_event = fmi2False, terminate = fmi2False;
                    CHECK(api->set_time(c, t0 + t), S_STATES);
                    CHECK(api->set_continuous_states(c, y, n), S_STATES);
                    CHECK(api->completed_integrator_step(c, fmi2True, &enter_event, &terminate),
                          S_STEP);
                    if (terminate) FAIL(ME_TERMINATE);
                    if (enter_event) FAIL(ME_STEP_EVENT);
                }
                h *= factor;
            } else {
                double factor = isfinite(e) ? 0.9 * pow(e, -0.2) : 0.2;
                if (factor < 0.2) factor = 0.2;
                h *= factor;
                rejected++;
                last_rejected = 1;
            }
        }
        /* -- the end of the interval: states, outputs, sensitivities ---------------------- */
        CHECK(api->set_time(c, t0 + dt), S_STATES);
        CHECK(api->set_continuous_states(c, y, n), S_STATES);
        if (nx) CHECK(api->get_real(c, p->x_vr, nx, x_end + b * nx), S_READ);
        if (p->ny) CHECK(api->get_real(c, p->y_vr, p->ny, y_end + b * p->ny), S_READ);
        if (columns) {
            size_t nk = n + p->n_su;
            double one = 1.0;
            memcpy(s_end + b * n * columns, y + n, n * columns * sizeof(double));
            for (j = 0; j < nk && p->n_yo; j++) {
                fmi2ValueReference known = j < n ? p->cstate_vr[j] : p->su_vr[j - n];
                CHECK(api->get_directional_derivative(c, p->yo_vr, p->n_yo, &known, 1, &one, column),
                      S_DIRECTIONAL);
                for (i = 0; i < p->n_yo; i++) dyo[(b * p->n_yo + i) * nk + j] = column[i];
            }
        }
    }
done:
    if (stats) {
        stats[0] = accepted;
        stats[1] = rejected;
        stats[2] = ctx.evaluations;
        stats[3] = (long)b;  /* the interval that failed, or n_batch */
    }
    free(work);
    free(knowns);
    return code;
}

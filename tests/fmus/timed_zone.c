/*
 * A time-dependent test FMU (FMI 2.0, Model Exchange and Co-Simulation in one binary): a
 * one-node zone whose internal heat gains follow a schedule on FMU time, so that results
 * depend on when an interval is simulated, not only on its start state and inputs.
 *
 *   C dT/dt = UA (Tout + 273.15 - T) + q + Pint(t)      T: zone.T [K]
 *   dEint/dt = Pint(t)                                  Eint: energy of the gains [J]
 *   schedule = 0: Pint = gain between 08:00 and 17:00 of every day of FMU time, else 0
 *                 (Model Exchange: time events at the switches, a discrete state "on");
 *   schedule = 1: Pint = gain (1 - cos(2 pi t / 1 d)) / 2 (smooth, no events).
 *   Past FMU time nan_after [s] the model computes NaN (a broken FMU, for the tests).
 *
 * Co-Simulation: fmi2DoStep is exact for schedule 0 (split at the switches) and classic
 * Runge-Kutta with steps <= 10 s for schedule 1. FMU state get/set/serialise works (the
 * modelDescription may or may not declare it: the tests build both variants).
 *
 * The FMI boilerplate is that of every mshoot FMU (fmi2_model.h, in mshoot_core/fmu_src).
 * Built by the tests (tests/timed_fmu.py) with -DMODEL_GUID="{...}"; value references
 * must match timed_zone.xml.
 */
enum {
    VR_C = 0, VR_UA = 1, VR_GAIN = 2, VR_SCHEDULE = 3, VR_NAN_AFTER = 4,
    VR_TOUT = 10, VR_Q = 11,
    VR_T_K = 20, VR_DER_T_K = 21, VR_EINT = 22, VR_DER_EINT = 23, VR_T_DEGC = 24, VR_PINT = 25
};

#define KELVIN 273.15
#define DAY 86400.0
#define ON_S (8.0 * 3600.0)
#define OFF_S (17.0 * 3600.0)
#define TWO_PI 6.283185307179586

#define MODEL_NAME "TimedZone"
#define MODEL_NX 2
#define MODEL_EXCHANGE 1
#define MODEL_CO_SIMULATION 1
#define MODEL_PARTIALS 1
#define MODEL_STATE_MAGIC 0x54494d45u /* "TIME" */
#define MODEL_TIME_EVENTS

typedef struct {
    double C, UA, gain, schedule, nan_after;
    double Tout, q;
    double T, Eint;
    double time;
    int on;      /* discrete state of schedule 0 (Model Exchange: updated at events) */
    int phase;
} ModelData;

#include "fmi2_model.h"

static void model_defaults(ModelData *d) {
    d->C = 1.0e7; d->UA = 250.0; d->gain = 3000.0; d->schedule = 0.0; d->nan_after = 1e300;
    d->Tout = 0.0; d->q = 0.0; d->T = 293.15; d->Eint = 0.0; d->on = 0;
}

static int occupied(double t) {
    double tod = t - floor(t / DAY) * DAY;
    return tod >= ON_S && tod < OFF_S;
}

/* The next switch of schedule 0 strictly after t. */
static double next_switch(double t) {
    double day = floor(t / DAY) * DAY, tod = t - day;
    if (tod < ON_S) return day + ON_S;
    if (tod < OFF_S) return day + OFF_S;
    return day + DAY + ON_S;
}

static double gains(const ModelData *d, double t, int on) {
    if (d->schedule != 0.0) return d->gain * 0.5 * (1.0 - cos(TWO_PI * t / DAY));
    return on ? d->gain : 0.0;
}

static void rates(const ModelData *d, double t, int on, double T, double *dT, double *dE) {
    double p = gains(d, t, on);
    *dT = (d->UA * (d->Tout + KELVIN - T) + d->q + p) / d->C;
    *dE = p;
    if (t >= d->nan_after) *dT = NAN;
}

static fmi2Status model_initialize(Instance *inst) {
    inst->d.on = occupied(inst->d.time);
    return fmi2OK;
}

static double output(const ModelData *d, fmi2ValueReference vr, int *ok) {
    double dT, dE;
    *ok = 1;
    switch (vr) {
    case VR_C: return d->C;
    case VR_UA: return d->UA;
    case VR_GAIN: return d->gain;
    case VR_SCHEDULE: return d->schedule;
    case VR_NAN_AFTER: return d->nan_after;
    case VR_TOUT: return d->Tout;
    case VR_Q: return d->q;
    case VR_T_K: return d->T;
    case VR_EINT: return d->Eint;
    case VR_T_DEGC: return d->time >= d->nan_after ? NAN : d->T - KELVIN;
    case VR_PINT: return gains(d, d->time, d->on);
    case VR_DER_T_K: rates(d, d->time, d->on, d->T, &dT, &dE); return dT;
    case VR_DER_EINT: rates(d, d->time, d->on, d->T, &dT, &dE); return dE;
    default: *ok = 0; return 0.0;
    }
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                       fmi2Real value[]) {
    Instance *inst = (Instance *)c;
    size_t i;
    int ok;
    if (!inst) return fmi2Error;
    for (i = 0; i < n; i++) {
        value[i] = output(&inst->d, vr[i], &ok);
        if (!ok) return fail(inst, "getReal: unknown value reference %u", vr[i]);
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                       const fmi2Real value[]) {
    Instance *inst = (Instance *)c;
    ModelData *d;
    size_t i;
    if (!inst) return fmi2Error;
    d = &inst->d;
    for (i = 0; i < n; i++) {
        int start = vr[i] <= VR_NAN_AFTER || vr[i] == VR_T_K || vr[i] == VR_EINT;
        if (start && !before_initialization(d))
            return fail(inst, "setReal: %u is settable only before initialisation", vr[i]);
        switch (vr[i]) {
        case VR_C: d->C = value[i]; break;
        case VR_UA: d->UA = value[i]; break;
        case VR_GAIN: d->gain = value[i]; break;
        case VR_SCHEDULE: d->schedule = value[i]; break;
        case VR_NAN_AFTER: d->nan_after = value[i]; break;
        case VR_TOUT: d->Tout = value[i]; break;
        case VR_Q: d->q = value[i]; break;
        case VR_T_K: d->T = value[i]; break;
        case VR_EINT: d->Eint = value[i]; break;
        default: return fail(inst, "setReal: %u is not settable", vr[i]);
        }
    }
    return fmi2OK;
}

/* d(unknown)/d(known): 0 for the pairs not listed, -1 for another unknown. */
static int model_partial(const ModelData *d, fmi2ValueReference u, fmi2ValueReference k,
                         double *p) {
    *p = 0.0;
    if (u == VR_DER_T_K) {
        if (k == VR_T_K) *p = -d->UA / d->C;
        else if (k == VR_TOUT) *p = d->UA / d->C;
        else if (k == VR_Q) *p = 1.0 / d->C;
    } else if (u == VR_T_DEGC) {
        if (k == VR_T_K) *p = 1.0;
    } else if (u == VR_EINT) {
        if (k == VR_EINT) *p = 1.0;
    } else if (u != VR_DER_EINT && u != VR_PINT) {
        return -1;
    }
    return 0;
}

/* ---- Model Exchange ------------------------------------------------------------------ */
static void model_events(ModelData *d, fmi2EventInfo *info) {
    d->on = occupied(d->time);
    info->nextEventTimeDefined = d->schedule == 0.0;
    info->nextEventTime = d->schedule == 0.0 ? next_switch(d->time) : 0.0;
}

static void model_get_states(const ModelData *d, double x[]) {
    x[0] = d->T;
    x[1] = d->Eint;
}

static void model_set_states(ModelData *d, const double x[]) {
    d->T = x[0];
    d->Eint = x[1];
}

static void model_derivatives(ModelData *d, double dx[]) {
    rates(d, d->time, d->on, d->T, &dx[0], &dx[1]);
}

static void model_nominals(const ModelData *d, double x[]) {
    (void)d;
    x[0] = 300.0;
    x[1] = 1.0e7;
}

/* ---- Co-Simulation ------------------------------------------------------------------- */
/* Exact over [t, t + h] with the gains constant (schedule 0). */
static void exact(ModelData *d, double h, double p) {
    double t_inf = d->Tout + KELVIN + (d->q + p) / d->UA;
    d->T = t_inf + (d->T - t_inf) * exp(-d->UA * h / d->C);
    d->Eint += p * h;
}

static void rk4(ModelData *d, double t, double h) {
    double k1, k2, k3, k4, e1, e2, e3, e4;
    rates(d, t, d->on, d->T, &k1, &e1);
    rates(d, t + h / 2, d->on, d->T + h / 2 * k1, &k2, &e2);
    rates(d, t + h / 2, d->on, d->T + h / 2 * k2, &k3, &e3);
    rates(d, t + h, d->on, d->T + h * k3, &k4, &e4);
    d->T += h / 6 * (k1 + 2 * k2 + 2 * k3 + k4);
    d->Eint += h / 6 * (e1 + 2 * e2 + 2 * e3 + e4);
}

static fmi2Status model_do_step(Instance *inst, double t, double h) {
    ModelData *d = &inst->d;
    const double end = t + h;
    if (d->schedule == 0.0) {
        while (d->time < end) {
            double stop = next_switch(d->time);
            if (stop > end) stop = end;
            d->on = occupied(d->time);
            exact(d, stop - d->time, gains(d, d->time, d->on));
            d->time = stop;
        }
        d->on = occupied(end);
    } else {
        int i, n = (int)ceil(h / 10.0);
        for (i = 0; i < n; i++) rk4(d, t + i * (h / n), h / n);
    }
    if (end > d->nan_after) d->T = NAN;
    return fmi2OK;
}

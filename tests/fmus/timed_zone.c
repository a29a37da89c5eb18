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
 * Built by the tests (tests/timed_fmu.py) with -DMODEL_GUID="{...}"; value references
 * must match timed_zone.xml.
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>

#include "fmi2Functions.h"

#ifndef MODEL_GUID
#error "MODEL_GUID must be defined"
#endif

enum {
    VR_C = 0, VR_UA = 1, VR_GAIN = 2, VR_SCHEDULE = 3, VR_NAN_AFTER = 4,
    VR_TOUT = 10, VR_Q = 11,
    VR_T_K = 20, VR_DER_T_K = 21, VR_EINT = 22, VR_DER_EINT = 23, VR_T_DEGC = 24, VR_PINT = 25
};

#define NX 2
#define KELVIN 273.15
#define DAY 86400.0
#define ON_S (8.0 * 3600.0)
#define OFF_S (17.0 * 3600.0)
#define MAGIC 0x54494d45u  /* "TIME" */
#define TWO_PI 6.283185307179586

typedef enum { PH_INSTANTIATED, PH_INIT, PH_EVENT, PH_CONT, PH_STEP, PH_TERMINATED } Phase;

typedef struct {
    double C, UA, gain, schedule, nan_after;
    double Tout, q;
    double T, Eint;
    double time;
    int on;      /* discrete state of schedule 0 (Model Exchange: updated at events) */
    int phase;
} ModelData;

typedef struct {
    ModelData d;
    fmi2Type type;
    char *name;
    fmi2CallbackFunctions cb;
} Instance;

static fmi2Status fail(Instance *inst, const char *fmt, ...) {
    char buf[256];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof(buf), fmt, ap);
    va_end(ap);
    if (inst && inst->cb.logger)
        inst->cb.logger(inst->cb.componentEnvironment, inst->name, fmi2Error, "logStatusError",
                        "%s", buf);
    return fmi2Error;
}

static void defaults(ModelData *d) {
    d->C = 1.0e7; d->UA = 250.0; d->gain = 3000.0; d->schedule = 0.0; d->nan_after = 1e300;
    d->Tout = 0.0; d->q = 0.0; d->T = 293.15; d->Eint = 0.0; d->time = 0.0; d->on = 0;
    d->phase = PH_INSTANTIATED;
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

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String k[]) {
    (void)on; (void)n; (void)k;
    return c ? fmi2OK : fmi2Error;
}

fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid,
                              fmi2String location, const fmi2CallbackFunctions *cb,
                              fmi2Boolean visible, fmi2Boolean logging) {
    Instance *inst;
    (void)location; (void)visible; (void)logging;
    if (!cb || !cb->allocateMemory || !cb->freeMemory || !name || !guid) return NULL;
    if (strcmp(guid, MODEL_GUID) != 0) return NULL;
    inst = (Instance *)cb->allocateMemory(1, sizeof(Instance));
    if (!inst) return NULL;
    inst->name = (char *)cb->allocateMemory(strlen(name) + 1, 1);
    if (!inst->name) { cb->freeMemory(inst); return NULL; }
    strcpy(inst->name, name);
    inst->cb = *cb;
    inst->type = type;
    defaults(&inst->d);
    return inst;
}

void fmi2FreeInstance(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (!inst) return;
    inst->cb.freeMemory(inst->name);
    inst->cb.freeMemory(inst);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean tol_defined, fmi2Real tol,
                               fmi2Real start, fmi2Boolean stop_defined, fmi2Real stop) {
    Instance *inst = (Instance *)c;
    (void)tol_defined; (void)tol; (void)stop_defined; (void)stop;
    if (!inst) return fmi2Error;
    if (inst->d.phase != PH_INSTANTIATED) return fail(inst, "setupExperiment after init");
    inst->d.time = start;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (!inst) return fmi2Error;
    if (inst->d.phase != PH_INSTANTIATED) return fail(inst, "enterInitializationMode twice");
    inst->d.phase = PH_INIT;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (!inst) return fmi2Error;
    if (inst->d.phase != PH_INIT) return fail(inst, "exitInitializationMode outside init");
    inst->d.on = occupied(inst->d.time);
    inst->d.phase = inst->type == fmi2ModelExchange ? PH_EVENT : PH_STEP;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) {
    if (!c) return fmi2Error;
    ((Instance *)c)->d.phase = PH_TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c) {
    if (!c) return fmi2Error;
    defaults(&((Instance *)c)->d);
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
        if (start && d->phase != PH_INSTANTIATED && d->phase != PH_INIT)
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

static fmi2Status none(fmi2Component c, size_t n) {
    if (!c) return fmi2Error;
    return n ? fail((Instance *)c, "no variables of this type") : fmi2OK;
}
fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference v[], size_t n,
                          fmi2Integer x[]) { (void)v; (void)x; return none(c, n); }
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference v[], size_t n,
                          fmi2Boolean x[]) { (void)v; (void)x; return none(c, n); }
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference v[], size_t n,
                         fmi2String x[]) { (void)v; (void)x; return none(c, n); }
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference v[], size_t n,
                          const fmi2Integer x[]) { (void)v; (void)x; return none(c, n); }
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference v[], size_t n,
                          const fmi2Boolean x[]) { (void)v; (void)x; return none(c, n); }
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference v[], size_t n,
                         const fmi2String x[]) { (void)v; (void)x; return none(c, n); }

/* ---- FMU state ----------------------------------------------------------------------- */
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s) {
    Instance *inst = (Instance *)c;
    if (!inst || !s) return fmi2Error;
    if (!*s) *s = inst->cb.allocateMemory(1, sizeof(ModelData));
    if (!*s) return fail(inst, "out of memory");
    memcpy(*s, &inst->d, sizeof(ModelData));
    return fmi2OK;
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) {
    if (!c || !s) return fmi2Error;
    memcpy(&((Instance *)c)->d, s, sizeof(ModelData));
    return fmi2OK;
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s) {
    if (!c || !s) return fmi2Error;
    if (*s) ((Instance *)c)->cb.freeMemory(*s);
    *s = NULL;
    return fmi2OK;
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t *size) {
    (void)s;
    if (!c || !size) return fmi2Error;
    *size = sizeof(unsigned) + sizeof(ModelData);
    return fmi2OK;
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte data[], size_t n) {
    unsigned magic = MAGIC;
    if (!c || !s || n < sizeof(magic) + sizeof(ModelData)) return fmi2Error;
    memcpy(data, &magic, sizeof(magic));
    memcpy(data + sizeof(magic), s, sizeof(ModelData));
    return fmi2OK;
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte data[], size_t n,
                                   fmi2FMUstate *s) {
    Instance *inst = (Instance *)c;
    unsigned magic;
    if (!inst || !s || n != sizeof(magic) + sizeof(ModelData)) return fmi2Error;
    memcpy(&magic, data, sizeof(magic));
    if (magic != MAGIC) return fail(inst, "not a state of this FMU");
    if (!*s) *s = inst->cb.allocateMemory(1, sizeof(ModelData));
    if (!*s) return fail(inst, "out of memory");
    memcpy(*s, data + sizeof(magic), sizeof(ModelData));
    return fmi2OK;
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[],
                                        size_t nu, const fmi2ValueReference k[], size_t nk,
                                        const fmi2Real dk[], fmi2Real du[]) {
    Instance *inst = (Instance *)c;
    const ModelData *d;
    size_t i, j;
    if (!inst) return fmi2Error;
    d = &inst->d;
    for (i = 0; i < nu; i++) {
        double sum = 0.0;
        for (j = 0; j < nk; j++) {
            double p = 0.0;
            if (u[i] == VR_DER_T_K) {
                if (k[j] == VR_T_K) p = -d->UA / d->C;
                else if (k[j] == VR_TOUT) p = d->UA / d->C;
                else if (k[j] == VR_Q) p = 1.0 / d->C;
            } else if (u[i] == VR_T_DEGC) {
                if (k[j] == VR_T_K) p = 1.0;
            } else if (u[i] == VR_EINT) {
                if (k[j] == VR_EINT) p = 1.0;
            } else if (u[i] != VR_DER_EINT && u[i] != VR_PINT) {
                return fail(inst, "no directional derivative of %u", u[i]);
            }
            sum += p * dk[j];
        }
        du[i] = sum;
    }
    return fmi2OK;
}

/* ---- Model Exchange ------------------------------------------------------------------ */
fmi2Status fmi2EnterEventMode(fmi2Component c) {
    if (!c) return fmi2Error;
    ((Instance *)c)->d.phase = PH_EVENT;
    return fmi2OK;
}

fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *info) {
    Instance *inst = (Instance *)c;
    if (!inst || !info) return fmi2Error;
    inst->d.on = occupied(inst->d.time);
    info->newDiscreteStatesNeeded = fmi2False;
    info->terminateSimulation = fmi2False;
    info->nominalsOfContinuousStatesChanged = fmi2False;
    info->valuesOfContinuousStatesChanged = fmi2False;
    info->nextEventTimeDefined = inst->d.schedule == 0.0;
    info->nextEventTime = inst->d.schedule == 0.0 ? next_switch(inst->d.time) : 0.0;
    return fmi2OK;
}

fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) {
    if (!c) return fmi2Error;
    ((Instance *)c)->d.phase = PH_CONT;
    return fmi2OK;
}

fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean no_set, fmi2Boolean *event,
                                       fmi2Boolean *terminate) {
    (void)no_set;
    if (!c || !event || !terminate) return fmi2Error;
    *event = fmi2False;
    *terminate = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2SetTime(fmi2Component c, fmi2Real time) {
    if (!c) return fmi2Error;
    ((Instance *)c)->d.time = time;
    return fmi2OK;
}

fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t n) {
    Instance *inst = (Instance *)c;
    if (!inst || n != NX) return fmi2Error;
    inst->d.T = x[0];
    inst->d.Eint = x[1];
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real dx[], size_t n) {
    Instance *inst = (Instance *)c;
    if (!inst || n != NX) return fmi2Error;
    rates(&inst->d, inst->d.time, inst->d.on, inst->d.T, &dx[0], &dx[1]);
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real z[], size_t n) {
    (void)z;
    return c && n == 0 ? fmi2OK : fmi2Error;
}

fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t n) {
    Instance *inst = (Instance *)c;
    if (!inst || n != NX) return fmi2Error;
    x[0] = inst->d.T;
    x[1] = inst->d.Eint;
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x[], size_t n) {
    if (!c || n != NX) return fmi2Error;
    x[0] = 300.0;
    x[1] = 1.0e7;
    return fmi2OK;
}

/* ---- Co-Simulation ------------------------------------------------------------------- */
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference v[], size_t n,
                                       const fmi2Integer o[], const fmi2Real x[]) {
    (void)v; (void)o; (void)x;
    return none(c, n);
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference v[],
                                        size_t n, const fmi2Integer o[], fmi2Real x[]) {
    (void)v; (void)o; (void)x;
    return none(c, n);
}

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

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean no_set) {
    Instance *inst = (Instance *)c;
    ModelData *d;
    double end;
    (void)no_set;
    if (!inst) return fmi2Error;
    d = &inst->d;
    if (inst->type != fmi2CoSimulation || d->phase != PH_STEP)
        return fail(inst, "doStep: not an initialised Co-Simulation slave");
    if (fabs(t - d->time) > 1e-9 * (1.0 + fabs(d->time)))
        return fail(inst, "doStep: communication point %.17g differs from FMU time %.17g", t,
                    d->time);
    end = t + h;
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
    d->time = end;
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) {
    (void)c;
    return fmi2Error;
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *v) {
    (void)s; (void)v;
    return c ? fmi2Discard : fmi2Error;
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *v) {
    if (!c || !v) return fmi2Error;
    if (s != fmi2LastSuccessfulTime) return fmi2Discard;
    *v = ((Instance *)c)->d.time;
    return fmi2OK;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *v) {
    (void)s; (void)v;
    return c ? fmi2Discard : fmi2Error;
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *v) {
    if (!c || !v) return fmi2Error;
    if (s != fmi2Terminated) return fmi2Discard;
    *v = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *v) {
    (void)s; (void)v;
    return c ? fmi2Discard : fmi2Error;
}

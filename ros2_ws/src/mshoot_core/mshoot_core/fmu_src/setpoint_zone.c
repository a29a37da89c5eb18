/*
 * A zone of our own for mshoot: FMI 2.0 Model Exchange, two nodes (air + envelope) whose air
 * state is its internal energy U [J], not a temperature, heated by a local proportional loop
 * on a zone temperature setpoint, with a BOPTEST-style setpoint override (oveTSet_u [K] and
 * its switch oveTSet_activate).
 *
 *   T      = U / Cair                                             zone air temperature [K]
 *   TSet   = oveTSet_activate ? oveTSet_u : TSetDefault           the loop's setpoint [K]
 *   Qheat  = min(max(Kp (TSet - T), 0), Qmax)                     heat delivered [W]
 *   dU/dt  = (wall.T - T)/Raw + (Tout + 273.15 - T)/Rwin + (1 - fsun) shgc solrad
 *            + occ_w occ + Qheat
 *   Cwall d(wall.T)/dt = (T - wall.T)/Raw + (Tout + 273.15 - wall.T)/Rwa + fsun shgc solrad
 *
 * The air and the envelope start at T_start. Outputs: T [K], Qheat [W], TSet_applied [K]
 * (the setpoint the loop follows), Qheat_total [J] (heat delivered since the start, a state).
 * No directional derivatives, no FMU state: a plant as many exported FMUs are. Real value
 * references are the positions in setpoint_zone.xml; the switch is Boolean 0.
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>

#include "fmi2Functions.h"

#ifndef MODEL_GUID
#error "MODEL_GUID must be defined"
#endif

#define CAIR 0
#define CWALL 1
#define RAW 2
#define RWA 3
#define RWIN 4
#define SHGC 5
#define FSUN 6
#define OCC_W 7
#define KP 8
#define QMAX 9
#define TSET_DEFAULT 10
#define T_START 11
#define TOUT 12
#define SOLRAD 13
#define OCC 14
#define OVE_TSET 15
#define AIR_U 16
#define DER_AIR_U 17
#define WALL_T 18
#define DER_WALL_T 19
#define QTOTAL 20
#define DER_QTOTAL 21
#define T_ZONE 22
#define QHEAT 23
#define TSET_APPLIED 24
#define NVARS 25
#define NPARAMS 12
#define NSTATES 3
#define ACTIVATE 0 /* the Boolean */

static const double start_values[NVARS] = {
    2.0e6, 4.0e7, 0.002, 0.008, 0.01, 2.0, 0.7, 40.0, 3000.0, 6000.0, 294.65, 294.15,
    0.0, 0.0, 0.0, 294.65,                  /* inputs */
    0.0, 0.0, 294.15, 0.0, 0.0, 0.0,        /* states and derivatives (set at init) */
    0.0, 0.0, 0.0                           /* outputs */
};

enum { INSTANTIATED, INITIALIZATION, EVENT, CONTINUOUS, TERMINATED };

typedef struct {
    double r[NVARS];
    int activate;
    int mode;
    fmi2CallbackFunctions cb;
    char name[128];
} Comp;

static fmi2Status fail(Comp *m, const char *fmt, ...) {
    char msg[400];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(msg, sizeof msg, fmt, ap);
    va_end(ap);
    if (m != NULL && m->cb.logger != NULL)
        m->cb.logger(m->cb.componentEnvironment, m->name, fmi2Error, "logStatusError", "%s",
                     msg);
    return fmi2Error;
}

static void evaluate(Comp *m) {
    double *r = m->r;
    const double t = r[AIR_U] / r[CAIR];
    const double tout = r[TOUT] + 273.15;
    const double sun = r[SHGC] * r[SOLRAD];
    const double tset = m->activate ? r[OVE_TSET] : r[TSET_DEFAULT];
    double q = r[KP] * (tset - t);
    q = q < 0.0 ? 0.0 : (q > r[QMAX] ? r[QMAX] : q);
    r[T_ZONE] = t;
    r[TSET_APPLIED] = tset;
    r[QHEAT] = q;
    r[DER_AIR_U] = (r[WALL_T] - t) / r[RAW] + (tout - t) / r[RWIN] + (1.0 - r[FSUN]) * sun
                   + r[OCC_W] * r[OCC] + q;
    r[DER_WALL_T] = ((t - r[WALL_T]) / r[RAW] + (tout - r[WALL_T]) / r[RWA]
                     + r[FSUN] * sun) / r[CWALL];
    r[DER_QTOTAL] = q;
}

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String cat[]) {
    (void)on; (void)n; (void)cat;
    return c ? fmi2OK : fmi2Error;
}

fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid,
                              fmi2String location, const fmi2CallbackFunctions *cb,
                              fmi2Boolean visible, fmi2Boolean logging) {
    Comp *m;
    (void)location; (void)visible; (void)logging;
    if (cb == NULL || cb->allocateMemory == NULL || name == NULL) return NULL;
    if (type != fmi2ModelExchange || guid == NULL || strcmp(guid, MODEL_GUID) != 0) {
        if (cb->logger)
            cb->logger(cb->componentEnvironment, name, fmi2Error, "logStatusError", "%s",
                       "SetpointZone: Model Exchange only, or wrong GUID");
        return NULL;
    }
    m = (Comp *)cb->allocateMemory(1, sizeof(Comp));
    if (m == NULL) return NULL;
    m->cb = *cb;
    snprintf(m->name, sizeof m->name, "%s", name);
    memcpy(m->r, start_values, sizeof m->r);
    m->activate = 0;
    m->mode = INSTANTIATED;
    return m;
}

void fmi2FreeInstance(fmi2Component c) {
    Comp *m = (Comp *)c;
    if (m) m->cb.freeMemory(m);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean tolDef, fmi2Real tol,
                               fmi2Real start, fmi2Boolean stopDef, fmi2Real stop) {
    (void)tolDef; (void)tol; (void)start; (void)stopDef; (void)stop;
    return c ? fmi2OK : fmi2Error;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    Comp *m = (Comp *)c;
    if (m == NULL || m->mode != INSTANTIATED) return fail(m, "EnterInitializationMode: bad mode");
    m->mode = INITIALIZATION;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Comp *m = (Comp *)c;
    int i;
    if (m == NULL || m->mode != INITIALIZATION)
        return fail(m, "ExitInitializationMode: bad mode");
    for (i = CAIR; i <= RWIN; i++)
        if (!(m->r[i] > 0.0)) return fail(m, "parameter %d must be > 0, got %g", i, m->r[i]);
    if (!(m->r[QMAX] >= 0.0 && m->r[KP] >= 0.0 && m->r[T_START] > 0.0))
        return fail(m, "Kp, Qmax must be >= 0 and T_start > 0 K");
    m->r[AIR_U] = m->r[CAIR] * m->r[T_START];
    m->r[WALL_T] = m->r[T_START];
    m->r[QTOTAL] = 0.0;
    m->mode = EVENT;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) {
    Comp *m = (Comp *)c;
    if (m == NULL) return fmi2Error;
    m->mode = TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c) {
    Comp *m = (Comp *)c;
    if (m == NULL) return fmi2Error;
    memcpy(m->r, start_values, sizeof m->r);
    m->activate = 0;
    m->mode = INSTANTIATED;
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Real v[]) {
    Comp *m = (Comp *)c;
    size_t i;
    if (m == NULL) return fmi2Error;
    evaluate(m);
    for (i = 0; i < n; i++) {
        if (vr[i] >= NVARS) return fail(m, "GetReal: no value reference %u", vr[i]);
        v[i] = m->r[vr[i]];
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                       const fmi2Real v[]) {
    Comp *m = (Comp *)c;
    size_t i;
    if (m == NULL) return fmi2Error;
    for (i = 0; i < n; i++) {
        const unsigned int k = vr[i];
        const int before_init = m->mode == INSTANTIATED || m->mode == INITIALIZATION;
        if (k < NPARAMS) {
            if (!before_init) return fail(m, "SetReal: parameter %u is settable before init only", k);
        } else if (!(k >= TOUT && k <= OVE_TSET)) {
            return fail(m, "SetReal: vr %u is not settable", k);
        }
        m->r[k] = v[i];
    }
    return fmi2OK;
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                          fmi2Boolean v[]) {
    Comp *m = (Comp *)c;
    size_t i;
    if (m == NULL) return fmi2Error;
    for (i = 0; i < n; i++) {
        if (vr[i] != ACTIVATE) return fail(m, "GetBoolean: no value reference %u", vr[i]);
        v[i] = m->activate ? fmi2True : fmi2False;
    }
    return fmi2OK;
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                          const fmi2Boolean v[]) {
    Comp *m = (Comp *)c;
    size_t i;
    if (m == NULL) return fmi2Error;
    for (i = 0; i < n; i++) {
        if (vr[i] != ACTIVATE) return fail(m, "SetBoolean: no value reference %u", vr[i]);
        m->activate = v[i] ? 1 : 0;
    }
    return fmi2OK;
}

#define NO_VARS(fn, T, CONST)                                                              \
    fmi2Status fn(fmi2Component c, const fmi2ValueReference vr[], size_t n, CONST T v[]) {  \
        (void)vr; (void)v;                                                                  \
        if (c == NULL) return fmi2Error;                                                    \
        return n == 0 ? fmi2OK : fail((Comp *)c, #fn ": no such variables");                \
    }
NO_VARS(fmi2GetInteger, fmi2Integer, )
NO_VARS(fmi2GetString, fmi2String, )
NO_VARS(fmi2SetInteger, fmi2Integer, const)
NO_VARS(fmi2SetString, fmi2String, const)

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s) {
    (void)s;
    return fail((Comp *)c, "GetFMUstate is not supported");
}
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) {
    (void)s;
    return fail((Comp *)c, "SetFMUstate is not supported");
}
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s) {
    (void)s;
    return fail((Comp *)c, "FreeFMUstate is not supported");
}
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t *n) {
    (void)s; (void)n;
    return fail((Comp *)c, "SerializedFMUstateSize is not supported");
}
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte b[], size_t n) {
    (void)s; (void)b; (void)n;
    return fail((Comp *)c, "SerializeFMUstate is not supported");
}
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n,
                                   fmi2FMUstate *s) {
    (void)b; (void)n; (void)s;
    return fail((Comp *)c, "DeSerializeFMUstate is not supported");
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference unk[],
                                        size_t nu, const fmi2ValueReference kn[], size_t nk,
                                        const fmi2Real dk[], fmi2Real du[]) {
    (void)unk; (void)nu; (void)kn; (void)nk; (void)dk; (void)du;
    return fail((Comp *)c, "GetDirectionalDerivative is not supported");
}

fmi2Status fmi2EnterEventMode(fmi2Component c) {
    Comp *m = (Comp *)c;
    if (m == NULL) return fmi2Error;
    m->mode = EVENT;
    return fmi2OK;
}

fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *info) {
    if (c == NULL || info == NULL) return fmi2Error;
    memset(info, 0, sizeof *info);
    return fmi2OK;
}

fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) {
    Comp *m = (Comp *)c;
    if (m == NULL || m->mode != EVENT) return fail(m, "EnterContinuousTimeMode: bad mode");
    m->mode = CONTINUOUS;
    return fmi2OK;
}

fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean noPrior,
                                       fmi2Boolean *enterEvent, fmi2Boolean *terminate) {
    (void)noPrior;
    if (c == NULL) return fmi2Error;
    *enterEvent = fmi2False;
    *terminate = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2SetTime(fmi2Component c, fmi2Real t) {
    (void)t;
    return c ? fmi2OK : fmi2Error;
}

fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t nx) {
    Comp *m = (Comp *)c;
    if (m == NULL || nx != NSTATES) return fail(m, "SetContinuousStates: nx must be 3");
    m->r[AIR_U] = x[0];
    m->r[WALL_T] = x[1];
    m->r[QTOTAL] = x[2];
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real dx[], size_t nx) {
    Comp *m = (Comp *)c;
    if (m == NULL || nx != NSTATES) return fail(m, "GetDerivatives: nx must be 3");
    evaluate(m);
    dx[0] = m->r[DER_AIR_U];
    dx[1] = m->r[DER_WALL_T];
    dx[2] = m->r[DER_QTOTAL];
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real z[], size_t nz) {
    (void)z;
    if (c == NULL) return fmi2Error;
    return nz == 0 ? fmi2OK : fail((Comp *)c, "GetEventIndicators: none");
}

fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    Comp *m = (Comp *)c;
    if (m == NULL || nx != NSTATES) return fail(m, "GetContinuousStates: nx must be 3");
    x[0] = m->r[AIR_U];
    x[1] = m->r[WALL_T];
    x[2] = m->r[QTOTAL];
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    Comp *m = (Comp *)c;
    if (m == NULL || nx != NSTATES) return fail(m, "GetNominals: nx must be 3");
    x[0] = m->r[CAIR] * 293.15;
    x[1] = 293.15;
    x[2] = 1.0e6;
    return fmi2OK;
}

/*
 * "Third-party-style" test FMU for mshoot: a two-node (air + wall) R2C2 zone, FMI 2.0
 * Model Exchange only, written independently of r1c1.c and deliberately different from it:
 * states in degC with dotted names, other inputs, a direct-feedthrough output, a flat
 * value array indexed by value reference, no FMU state get/set, directional derivatives.
 *
 *   Cair  d(air.T)/dt  = (wall.T - air.T)/Raw + (Tamb - air.T)/Rwin + Qhvac + (1 - fsun) Qsun
 *   Cwall d(wall.T)/dt = (air.T - wall.T)/Raw + (Tamb - wall.T)/Rwa + fsun Qsun
 *   Tair = air.T,   Pwin = (air.T - Tamb)/Rwin   (heat lost through the windows [W])
 *
 * Value references are the 0-based positions in r2c2.xml.
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
#define FSUN 5
#define TAMB 6
#define QHVAC 7
#define QSUN 8
#define AIR_T 9
#define DER_AIR_T 10
#define WALL_T 11
#define DER_WALL_T 12
#define TAIR 13
#define PWIN 14
#define NVARS 15
#define NSTATES 2

static const double start_values[NVARS] = {
    5.0e6, 5.0e7, 0.002, 0.01, 0.05, 0.6,   /* parameters */
    0.0, 0.0, 0.0,                          /* inputs */
    20.0, 0.0, 18.0, 0.0,                   /* states and derivatives */
    0.0, 0.0                                /* outputs */
};

enum { INSTANTIATED, INITIALIZATION, EVENT, CONTINUOUS, TERMINATED };

typedef struct {
    double r[NVARS];
    int mode;
    fmi2CallbackFunctions cb;
    const char *name;
    char name_buf[128];
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

static void evaluate(double *r) {
    const double q_aw = (r[WALL_T] - r[AIR_T]) / r[RAW];
    r[DER_AIR_T] = (q_aw + (r[TAMB] - r[AIR_T]) / r[RWIN] + r[QHVAC]
                    + (1.0 - r[FSUN]) * r[QSUN]) / r[CAIR];
    r[DER_WALL_T] = (-q_aw + (r[TAMB] - r[WALL_T]) / r[RWA] + r[FSUN] * r[QSUN]) / r[CWALL];
    r[TAIR] = r[AIR_T];
    r[PWIN] = (r[AIR_T] - r[TAMB]) / r[RWIN];
}

/* Jacobian entry d r[unknown] / d r[known]; -1 if not an (unknown, known) pair. */
static int jac(const double *r, int unknown, int known, double *out) {
    if (!(known == AIR_T || known == WALL_T || known == TAMB || known == QHVAC || known == QSUN))
        return -1;
    *out = 0.0;
    if (unknown == DER_AIR_T) {
        if (known == AIR_T) *out = -(1.0 / r[RAW] + 1.0 / r[RWIN]) / r[CAIR];
        if (known == WALL_T) *out = 1.0 / (r[RAW] * r[CAIR]);
        if (known == TAMB) *out = 1.0 / (r[RWIN] * r[CAIR]);
        if (known == QHVAC) *out = 1.0 / r[CAIR];
        if (known == QSUN) *out = (1.0 - r[FSUN]) / r[CAIR];
    } else if (unknown == DER_WALL_T) {
        if (known == AIR_T) *out = 1.0 / (r[RAW] * r[CWALL]);
        if (known == WALL_T) *out = -(1.0 / r[RAW] + 1.0 / r[RWA]) / r[CWALL];
        if (known == TAMB) *out = 1.0 / (r[RWA] * r[CWALL]);
        if (known == QSUN) *out = r[FSUN] / r[CWALL];
    } else if (unknown == TAIR) {
        if (known == AIR_T) *out = 1.0;
    } else if (unknown == PWIN) {
        if (known == AIR_T) *out = 1.0 / r[RWIN];
        if (known == TAMB) *out = -1.0 / r[RWIN];
    } else {
        return -1;
    }
    return 0;
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
                       "R2C2: Model Exchange only, or wrong GUID");
        return NULL;
    }
    m = (Comp *)cb->allocateMemory(1, sizeof(Comp));
    if (m == NULL) return NULL;
    m->cb = *cb;
    snprintf(m->name_buf, sizeof m->name_buf, "%s", name);
    m->name = m->name_buf;
    memcpy(m->r, start_values, sizeof m->r);
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
    m->mode = INSTANTIATED;
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Real v[]) {
    Comp *m = (Comp *)c;
    size_t i;
    if (m == NULL) return fmi2Error;
    evaluate(m->r);
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
        if (k <= FSUN || k == AIR_T || k == WALL_T) {
            if (!before_init) return fail(m, "SetReal: vr %u is settable before init only", k);
        } else if (!(k == TAMB || k == QHVAC || k == QSUN)) {
            return fail(m, "SetReal: vr %u is not settable", k);
        }
        m->r[k] = v[i];
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
NO_VARS(fmi2GetBoolean, fmi2Boolean, )
NO_VARS(fmi2GetString, fmi2String, )
NO_VARS(fmi2SetInteger, fmi2Integer, const)
NO_VARS(fmi2SetBoolean, fmi2Boolean, const)
NO_VARS(fmi2SetString, fmi2String, const)

/* No FMU state support (canGetAndSetFMUstate="false"), as in many exported FMUs. */
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
    Comp *m = (Comp *)c;
    size_t i, j;
    if (m == NULL) return fmi2Error;
    for (i = 0; i < nu; i++) {
        du[i] = 0.0;
        for (j = 0; j < nk; j++) {
            double d;
            if (unk[i] >= NVARS || kn[j] >= NVARS || jac(m->r, (int)unk[i], (int)kn[j], &d))
                return fail(m, "GetDirectionalDerivative: no d(%u)/d(%u)", unk[i], kn[j]);
            du[i] += d * dk[j];
        }
    }
    return fmi2OK;
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
    if (m == NULL || nx != NSTATES) return fail(m, "SetContinuousStates: nx must be 2");
    m->r[AIR_T] = x[0];
    m->r[WALL_T] = x[1];
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real dx[], size_t nx) {
    Comp *m = (Comp *)c;
    if (m == NULL || nx != NSTATES) return fail(m, "GetDerivatives: nx must be 2");
    evaluate(m->r);
    dx[0] = m->r[DER_AIR_T];
    dx[1] = m->r[DER_WALL_T];
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real z[], size_t nz) {
    (void)z;
    if (c == NULL) return fmi2Error;
    return nz == 0 ? fmi2OK : fail((Comp *)c, "GetEventIndicators: none");
}

fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    Comp *m = (Comp *)c;
    if (m == NULL || nx != NSTATES) return fail(m, "GetContinuousStates: nx must be 2");
    x[0] = m->r[AIR_T];
    x[1] = m->r[WALL_T];
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    Comp *m = (Comp *)c;
    if (m == NULL || nx != NSTATES) return fail(m, "GetNominals: nx must be 2");
    x[0] = 1.0;
    x[1] = 1.0;
    return fmi2OK;
}

/*
 * R1C1 zone model of the OU44 classroom as an FMI 2.0 FMU.
 *
 * One binary serves both interfaces:
 *   - Model Exchange: continuous states T [K] (heatCapacitor.T) and Qr [J], derivatives,
 *     directional derivatives of derivatives/outputs w.r.t. states and inputs;
 *   - Co-Simulation: fmi2DoStep applies the exact closed-form solution over the step
 *     (inputs held constant within a step), so it is exact to rounding.
 *
 *   C dT/dt = (Tout + 273.15 - T)/R + shgc*solrad + occheff*occ*M(T) + qv + q
 *   C = tmass*1.2*1005*Vi,  R = RExt/(3*Vi^(2/3)),  M(T) = 84*(325.15 - T)/32
 *   qv = (1206/3600)*(maxVent*dpos/100)*(max(Tout, Tve) + 273.15 - T)
 *   dQr/dt = q
 *
 * With inputs constant the right-hand side is affine in T: C dT/dt = f - g*T.
 *
 * Value references must match r1c1.xml. The builder (mshoot_core/fmu_build.py) compiles
 * this file with -DMODEL_GUID="{...}" (a hash of the sources, also written into the
 * modelDescription.xml).
 */
#include <float.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>

#include "fmi2Functions.h"

#ifndef MODEL_GUID
#error "MODEL_GUID must be defined, e.g. -DMODEL_GUID=\"{...}\" (see fmu_build.py)"
#endif

/* ---- value references (r1c1.xml) ------------------------------------------------------- */
enum {
    VR_TMASS = 0, VR_SHGC = 1, VR_OCCHEFF = 2, VR_REXT = 3, VR_TVE = 4, VR_VI = 5,
    VR_MAXVENT = 6,
    VR_SOLRAD = 10, VR_TOUT = 11, VR_OCC = 12, VR_DPOS = 13, VR_Q = 14,
    VR_T_K = 20, VR_DER_T_K = 21, VR_QR = 22, VR_DER_QR = 23, VR_T_DEGC = 24
};

#define NX 2                          /* continuous states: T [K], Qr [J] */
#define KELVIN 273.15
#define OCC_HEAT_W 84.0               /* W per occupant at 293.15 K */
#define OCC_HEAT_ZERO_K 325.15        /* ... falling linearly to 0 W here */
#define OCC_HEAT_SPAN_K 32.0
#define AIR_HEAT_PER_M3H (1206.0 / 3600.0)
#define NOMINAL_T_K 300.0
#define NOMINAL_QR_J 1.0e6
#define SNAPSHOT_MAGIC 0x52314331u    /* "R1C1" */

typedef enum {
    PH_INSTANTIATED, PH_INIT, PH_EVENT, PH_CONT, PH_STEP, PH_TERMINATED
} Phase;

/* Everything an FMU state holds: plain data, copied with memcpy. */
typedef struct {
    double tmass, shgc, occheff, RExt, Tve, Vi, maxVent;   /* parameters */
    double solrad, Tout, occ, dpos, q;                      /* inputs */
    double T, Qr;                                           /* continuous states [K], [J] */
    double time;                                            /* [s] */
    int phase;
} ModelData;

typedef struct {
    ModelData d;
    fmi2Type type;
    char *instanceName;
    fmi2CallbackFunctions cb;
    fmi2Boolean loggingOn;
} Instance;

typedef struct {
    unsigned int magic;
    unsigned int size;
} SnapshotHeader;

/* ---- helpers ----------------------------------------------------------------------------- */
static void log_msg(Instance *inst, fmi2Status status, const char *category, const char *fmt,
                    ...) {
    char buf[512];
    va_list ap;
    if (inst == NULL || inst->cb.logger == NULL) return;
    if (status == fmi2OK && !inst->loggingOn) return;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof(buf), fmt, ap);
    va_end(ap);
    inst->cb.logger(inst->cb.componentEnvironment, inst->instanceName, status, category, "%s",
                    buf);
}

#define ERR(inst, ...) (log_msg((inst), fmi2Error, "logStatusError", __VA_ARGS__), fmi2Error)

static void set_defaults(ModelData *d) {
    d->tmass = 50.0;
    d->shgc = 4.608961327935981;
    d->occheff = 2.0836995296486704;
    d->RExt = 4.0;
    d->Tve = 21.0;
    d->Vi = 486.5;
    d->maxVent = 4800.0;
    d->solrad = 0.0;
    d->Tout = 0.0;
    d->occ = 0.0;
    d->dpos = 0.0;
    d->q = 0.0;
    d->T = 293.15;
    d->Qr = 0.0;
    d->time = 0.0;
    d->phase = PH_INSTANTIATED;
}

static double capacity(const ModelData *d) { return d->tmass * 1.2 * 1005.0 * d->Vi; }

static double resistance(const ModelData *d) {
    return d->RExt / (3.0 * pow(d->Vi, 2.0 / 3.0));
}

/* C dT/dt = f - g*T with the current inputs. */
static void affine(const ModelData *d, double *f, double *g) {
    const double r = resistance(d);
    const double occ_slope = d->occheff * d->occ * OCC_HEAT_W / OCC_HEAT_SPAN_K;
    const double vent = AIR_HEAT_PER_M3H * d->maxVent * d->dpos / 100.0;
    const double tsup = (d->Tout > d->Tve ? d->Tout : d->Tve) + KELVIN;
    *g = 1.0 / r + occ_slope + vent;
    *f = (d->Tout + KELVIN) / r + d->shgc * d->solrad + occ_slope * OCC_HEAT_ZERO_K
         + vent * tsup + d->q;
}

static double der_T(const ModelData *d) {
    double f, g;
    affine(d, &f, &g);
    return (f - g * d->T) / capacity(d);
}

/* Partial derivative d(unknown)/d(known); returns 0 on success, -1 if the pair is invalid. */
static int partial(const ModelData *d, fmi2ValueReference unknown, fmi2ValueReference known,
                   double *value) {
    const double c = capacity(d);
    const double vent_per_dpos = AIR_HEAT_PER_M3H * d->maxVent / 100.0;
    const double tsup = (d->Tout > d->Tve ? d->Tout : d->Tve) + KELVIN;
    double f, g;
    int known_ok = (known == VR_T_K || known == VR_QR || (known >= VR_SOLRAD && known <= VR_Q));
    if (!known_ok) return -1;
    *value = 0.0;
    switch (unknown) {
    case VR_DER_T_K:
        affine(d, &f, &g);
        switch (known) {
        case VR_T_K: *value = -g / c; break;
        case VR_SOLRAD: *value = d->shgc / c; break;
        case VR_TOUT:
            *value = (1.0 / resistance(d) + (d->Tout > d->Tve ? vent_per_dpos * d->dpos : 0.0))
                     / c;
            break;
        case VR_OCC:
            *value = d->occheff * OCC_HEAT_W / OCC_HEAT_SPAN_K * (OCC_HEAT_ZERO_K - d->T) / c;
            break;
        case VR_DPOS: *value = vent_per_dpos * (tsup - d->T) / c; break;
        case VR_Q: *value = 1.0 / c; break;
        default: break;
        }
        return 0;
    case VR_DER_QR:
        if (known == VR_Q) *value = 1.0;
        return 0;
    case VR_T_DEGC:
        if (known == VR_T_K) *value = 1.0;
        return 0;
    case VR_QR:
        if (known == VR_QR) *value = 1.0;
        return 0;
    default:
        return -1;
    }
}

static int settable_start(int phase) { return phase == PH_INSTANTIATED || phase == PH_INIT; }

static fmi2Status check_parameter(Instance *inst, const char *name, double value, int positive) {
    if (!isfinite(value)) return ERR(inst, "parameter %s must be finite, got %g", name, value);
    if (positive && value <= 0.0)
        return ERR(inst, "parameter %s must be > 0, got %g", name, value);
    return fmi2OK;
}

/* ---- common functions -------------------------------------------------------------------- */
const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }

const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[]) {
    Instance *inst = (Instance *)c;
    (void)nCategories;
    (void)categories;
    if (inst == NULL) return fmi2Error;
    inst->loggingOn = loggingOn;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation,
                              const fmi2CallbackFunctions *functions, fmi2Boolean visible,
                              fmi2Boolean loggingOn) {
    Instance *inst;
    size_t n;
    (void)fmuResourceLocation;
    (void)visible;
    if (functions == NULL || functions->allocateMemory == NULL || functions->freeMemory == NULL)
        return NULL;
    if (instanceName == NULL || instanceName[0] == '\0') {
        if (functions->logger)
            functions->logger(functions->componentEnvironment, "R1C1", fmi2Error,
                              "logStatusError", "%s", "missing instance name");
        return NULL;
    }
    if (fmuGUID == NULL || strcmp(fmuGUID, MODEL_GUID) != 0) {
        if (functions->logger)
            functions->logger(functions->componentEnvironment, instanceName, fmi2Error,
                              "logStatusError", "wrong GUID %s, expected %s",
                              fmuGUID ? fmuGUID : "(null)", MODEL_GUID);
        return NULL;
    }
    if (fmuType != fmi2ModelExchange && fmuType != fmi2CoSimulation) return NULL;
    inst = (Instance *)functions->allocateMemory(1, sizeof(Instance));
    if (inst == NULL) return NULL;
    n = strlen(instanceName) + 1;
    inst->instanceName = (char *)functions->allocateMemory(n, sizeof(char));
    if (inst->instanceName == NULL) {
        functions->freeMemory(inst);
        return NULL;
    }
    memcpy(inst->instanceName, instanceName, n);
    inst->cb = *functions;
    inst->type = fmuType;
    inst->loggingOn = loggingOn;
    set_defaults(&inst->d);
    log_msg(inst, fmi2OK, "logAll", "instantiated (%s)",
            fmuType == fmi2ModelExchange ? "ModelExchange" : "CoSimulation");
    return inst;
}

void fmi2FreeInstance(fmi2Component c) {
    Instance *inst = (Instance *)c;
    fmi2CallbackFreeMemory free_memory;
    if (inst == NULL) return;
    free_memory = inst->cb.freeMemory;
    free_memory(inst->instanceName);
    free_memory(inst);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined,
                               fmi2Real tolerance, fmi2Real startTime,
                               fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    Instance *inst = (Instance *)c;
    (void)toleranceDefined;
    (void)tolerance;
    (void)stopTimeDefined;
    (void)stopTime;
    if (inst == NULL) return fmi2Error;
    if (inst->d.phase != PH_INSTANTIATED)
        return ERR(inst, "fmi2SetupExperiment is only allowed after instantiation or reset");
    inst->d.time = startTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    if (inst->d.phase != PH_INSTANTIATED)
        return ERR(inst, "fmi2EnterInitializationMode is only allowed after instantiation");
    inst->d.phase = PH_INIT;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    if (inst->d.phase != PH_INIT)
        return ERR(inst, "fmi2ExitInitializationMode is only allowed in initialization mode");
    inst->d.phase = inst->type == fmi2ModelExchange ? PH_EVENT : PH_STEP;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    inst->d.phase = PH_TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    set_defaults(&inst->d);
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       fmi2Real value[]) {
    Instance *inst = (Instance *)c;
    const ModelData *d;
    size_t i;
    if (inst == NULL) return fmi2Error;
    if (nvr > 0 && (vr == NULL || value == NULL)) return ERR(inst, "fmi2GetReal: NULL array");
    d = &inst->d;
    for (i = 0; i < nvr; i++) {
        switch (vr[i]) {
        case VR_TMASS: value[i] = d->tmass; break;
        case VR_SHGC: value[i] = d->shgc; break;
        case VR_OCCHEFF: value[i] = d->occheff; break;
        case VR_REXT: value[i] = d->RExt; break;
        case VR_TVE: value[i] = d->Tve; break;
        case VR_VI: value[i] = d->Vi; break;
        case VR_MAXVENT: value[i] = d->maxVent; break;
        case VR_SOLRAD: value[i] = d->solrad; break;
        case VR_TOUT: value[i] = d->Tout; break;
        case VR_OCC: value[i] = d->occ; break;
        case VR_DPOS: value[i] = d->dpos; break;
        case VR_Q: value[i] = d->q; break;
        case VR_T_K: value[i] = d->T; break;
        case VR_DER_T_K: value[i] = der_T(d); break;
        case VR_QR: value[i] = d->Qr; break;
        case VR_DER_QR: value[i] = d->q; break;
        case VR_T_DEGC: value[i] = d->T - KELVIN; break;
        default: return ERR(inst, "fmi2GetReal: unknown value reference %u", vr[i]);
        }
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       const fmi2Real value[]) {
    Instance *inst = (Instance *)c;
    ModelData *d;
    size_t i;
    if (inst == NULL) return fmi2Error;
    if (nvr > 0 && (vr == NULL || value == NULL)) return ERR(inst, "fmi2SetReal: NULL array");
    d = &inst->d;
    if (d->phase == PH_TERMINATED) return ERR(inst, "fmi2SetReal: the instance is terminated");
    for (i = 0; i < nvr; i++) {
        const double v = value[i];
        if (vr[i] <= VR_MAXVENT || vr[i] == VR_T_K || vr[i] == VR_QR) {
            if (!settable_start(d->phase))
                return ERR(inst, "fmi2SetReal: value reference %u is a parameter or start value,"
                                 " settable only before fmi2ExitInitializationMode", vr[i]);
        }
        switch (vr[i]) {
        case VR_TMASS:
            if (check_parameter(inst, "tmass", v, 1) != fmi2OK) return fmi2Error;
            d->tmass = v;
            break;
        case VR_SHGC:
            if (check_parameter(inst, "shgc", v, 0) != fmi2OK) return fmi2Error;
            d->shgc = v;
            break;
        case VR_OCCHEFF:
            if (check_parameter(inst, "occheff", v, 0) != fmi2OK) return fmi2Error;
            d->occheff = v;
            break;
        case VR_REXT:
            if (check_parameter(inst, "RExt", v, 1) != fmi2OK) return fmi2Error;
            d->RExt = v;
            break;
        case VR_TVE:
            if (check_parameter(inst, "Tve", v, 0) != fmi2OK) return fmi2Error;
            d->Tve = v;
            break;
        case VR_VI:
            if (check_parameter(inst, "Vi", v, 1) != fmi2OK) return fmi2Error;
            d->Vi = v;
            break;
        case VR_MAXVENT:
            if (check_parameter(inst, "maxVent", v, 0) != fmi2OK) return fmi2Error;
            d->maxVent = v;
            break;
        case VR_SOLRAD: d->solrad = v; break;
        case VR_TOUT: d->Tout = v; break;
        case VR_OCC: d->occ = v; break;
        case VR_DPOS: d->dpos = v; break;
        case VR_Q: d->q = v; break;
        case VR_T_K: d->T = v; break;
        case VR_QR: d->Qr = v; break;
        default: return ERR(inst, "fmi2SetReal: value reference %u is not settable", vr[i]);
        }
    }
    return fmi2OK;
}

static fmi2Status no_variables(Instance *inst, const char *function, size_t nvr) {
    if (inst == NULL) return fmi2Error;
    if (nvr > 0) return ERR(inst, "%s: the model has no variables of this type", function);
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          fmi2Integer value[]) {
    (void)vr;
    (void)value;
    return no_variables((Instance *)c, "fmi2GetInteger", nvr);
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          fmi2Boolean value[]) {
    (void)vr;
    (void)value;
    return no_variables((Instance *)c, "fmi2GetBoolean", nvr);
}

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                         fmi2String value[]) {
    (void)vr;
    (void)value;
    return no_variables((Instance *)c, "fmi2GetString", nvr);
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          const fmi2Integer value[]) {
    (void)vr;
    (void)value;
    return no_variables((Instance *)c, "fmi2SetInteger", nvr);
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          const fmi2Boolean value[]) {
    (void)vr;
    (void)value;
    return no_variables((Instance *)c, "fmi2SetBoolean", nvr);
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                         const fmi2String value[]) {
    (void)vr;
    (void)value;
    return no_variables((Instance *)c, "fmi2SetString", nvr);
}

/* ---- FMU state ------------------------------------------------------------------------- */
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    Instance *inst = (Instance *)c;
    ModelData *snapshot;
    if (inst == NULL || FMUstate == NULL) return fmi2Error;
    snapshot = (ModelData *)*FMUstate;
    if (snapshot == NULL) {
        snapshot = (ModelData *)inst->cb.allocateMemory(1, sizeof(ModelData));
        if (snapshot == NULL) return ERR(inst, "fmi2GetFMUstate: out of memory");
    }
    memcpy(snapshot, &inst->d, sizeof(ModelData));
    *FMUstate = snapshot;
    return fmi2OK;
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    if (FMUstate == NULL) return ERR(inst, "fmi2SetFMUstate: NULL state");
    memcpy(&inst->d, FMUstate, sizeof(ModelData));
    return fmi2OK;
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    Instance *inst = (Instance *)c;
    if (inst == NULL || FMUstate == NULL) return fmi2Error;
    if (*FMUstate != NULL) inst->cb.freeMemory(*FMUstate);
    *FMUstate = NULL;
    return fmi2OK;
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size) {
    (void)FMUstate;
    if (c == NULL || size == NULL) return fmi2Error;
    *size = sizeof(SnapshotHeader) + sizeof(ModelData);
    return fmi2OK;
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte data[],
                                 size_t size) {
    Instance *inst = (Instance *)c;
    SnapshotHeader header;
    if (inst == NULL) return fmi2Error;
    if (FMUstate == NULL || data == NULL) return ERR(inst, "fmi2SerializeFMUstate: NULL");
    if (size < sizeof(SnapshotHeader) + sizeof(ModelData))
        return ERR(inst, "fmi2SerializeFMUstate: buffer of %zu bytes is too small", size);
    header.magic = SNAPSHOT_MAGIC;
    header.size = (unsigned int)sizeof(ModelData);
    memcpy(data, &header, sizeof(header));
    memcpy(data + sizeof(header), FMUstate, sizeof(ModelData));
    return fmi2OK;
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[],
                                   size_t size, fmi2FMUstate *FMUstate) {
    Instance *inst = (Instance *)c;
    SnapshotHeader header;
    if (inst == NULL) return fmi2Error;
    if (serializedState == NULL || FMUstate == NULL)
        return ERR(inst, "fmi2DeSerializeFMUstate: NULL");
    if (size != sizeof(SnapshotHeader) + sizeof(ModelData))
        return ERR(inst, "fmi2DeSerializeFMUstate: %zu bytes, expected %zu", size,
                   sizeof(SnapshotHeader) + sizeof(ModelData));
    memcpy(&header, serializedState, sizeof(header));
    if (header.magic != SNAPSHOT_MAGIC || header.size != sizeof(ModelData))
        return ERR(inst, "fmi2DeSerializeFMUstate: not an R1C1 state");
    if (*FMUstate == NULL) {
        *FMUstate = inst->cb.allocateMemory(1, sizeof(ModelData));
        if (*FMUstate == NULL) return ERR(inst, "fmi2DeSerializeFMUstate: out of memory");
    }
    memcpy(*FMUstate, serializedState + sizeof(header), sizeof(ModelData));
    return fmi2OK;
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[],
                                        size_t nUnknown, const fmi2ValueReference vKnown_ref[],
                                        size_t nKnown, const fmi2Real dvKnown[],
                                        fmi2Real dvUnknown[]) {
    Instance *inst = (Instance *)c;
    size_t i, j;
    if (inst == NULL) return fmi2Error;
    for (i = 0; i < nUnknown; i++) {
        double sum = 0.0;
        for (j = 0; j < nKnown; j++) {
            double p;
            if (partial(&inst->d, vUnknown_ref[i], vKnown_ref[j], &p) != 0)
                return ERR(inst, "fmi2GetDirectionalDerivative: d(vr %u)/d(vr %u) is not "
                                 "available (unknowns: derivatives and outputs; knowns: states "
                                 "and inputs)", vUnknown_ref[i], vKnown_ref[j]);
            sum += p * dvKnown[j];
        }
        dvUnknown[i] = sum;
    }
    return fmi2OK;
}

/* ---- Model Exchange -------------------------------------------------------------------- */
fmi2Status fmi2EnterEventMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    if (inst->d.phase != PH_CONT && inst->d.phase != PH_EVENT)
        return ERR(inst, "fmi2EnterEventMode is only allowed in continuous-time mode");
    inst->d.phase = PH_EVENT;
    return fmi2OK;
}

fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *eventInfo) {
    Instance *inst = (Instance *)c;
    if (inst == NULL || eventInfo == NULL) return fmi2Error;
    if (inst->d.phase != PH_EVENT)
        return ERR(inst, "fmi2NewDiscreteStates is only allowed in event mode");
    eventInfo->newDiscreteStatesNeeded = fmi2False;
    eventInfo->terminateSimulation = fmi2False;
    eventInfo->nominalsOfContinuousStatesChanged = fmi2False;
    eventInfo->valuesOfContinuousStatesChanged = fmi2False;
    eventInfo->nextEventTimeDefined = fmi2False;
    eventInfo->nextEventTime = 0.0;
    return fmi2OK;
}

fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    if (inst->d.phase != PH_EVENT)
        return ERR(inst, "fmi2EnterContinuousTimeMode is only allowed in event mode");
    inst->d.phase = PH_CONT;
    return fmi2OK;
}

fmi2Status fmi2CompletedIntegratorStep(fmi2Component c,
                                       fmi2Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi2Boolean *enterEventMode,
                                       fmi2Boolean *terminateSimulation) {
    (void)noSetFMUStatePriorToCurrentPoint;
    if (c == NULL || enterEventMode == NULL || terminateSimulation == NULL) return fmi2Error;
    *enterEventMode = fmi2False;
    *terminateSimulation = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2SetTime(fmi2Component c, fmi2Real time) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    inst->d.time = time;
    return fmi2OK;
}

fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t nx) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    if (nx != NX || x == NULL)
        return ERR(inst, "fmi2SetContinuousStates: %zu states, expected %d", nx, NX);
    inst->d.T = x[0];
    inst->d.Qr = x[1];
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real derivatives[], size_t nx) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    if (nx != NX || derivatives == NULL)
        return ERR(inst, "fmi2GetDerivatives: %zu states, expected %d", nx, NX);
    derivatives[0] = der_T(&inst->d);
    derivatives[1] = inst->d.q;
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real eventIndicators[], size_t ni) {
    (void)eventIndicators;
    if (c == NULL) return fmi2Error;
    if (ni != 0) return ERR((Instance *)c, "fmi2GetEventIndicators: the model has none");
    return fmi2OK;
}

fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    if (nx != NX || x == NULL)
        return ERR(inst, "fmi2GetContinuousStates: %zu states, expected %d", nx, NX);
    x[0] = inst->d.T;
    x[1] = inst->d.Qr;
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x_nominal[], size_t nx) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    if (nx != NX || x_nominal == NULL)
        return ERR(inst, "fmi2GetNominalsOfContinuousStates: %zu states, expected %d", nx, NX);
    x_nominal[0] = NOMINAL_T_K;
    x_nominal[1] = NOMINAL_QR_J;
    return fmi2OK;
}

/* ---- Co-Simulation --------------------------------------------------------------------- */
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[],
                                       size_t nvr, const fmi2Integer order[],
                                       const fmi2Real value[]) {
    (void)vr;
    (void)order;
    (void)value;
    if (c == NULL) return fmi2Error;
    if (nvr == 0) return fmi2OK;
    return ERR((Instance *)c, "fmi2SetRealInputDerivatives: inputs are held constant per step "
                              "(canInterpolateInputs=false)");
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[],
                                        size_t nvr, const fmi2Integer order[],
                                        fmi2Real value[]) {
    (void)vr;
    (void)order;
    (void)value;
    if (c == NULL) return fmi2Error;
    if (nvr == 0) return fmi2OK;
    return ERR((Instance *)c, "fmi2GetRealOutputDerivatives: maxOutputDerivativeOrder is 0");
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint,
                      fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentCommunicationPoint) {
    Instance *inst = (Instance *)c;
    ModelData *d;
    double f, g, cap, a, h;
    (void)noSetFMUStatePriorToCurrentCommunicationPoint;
    if (inst == NULL) return fmi2Error;
    d = &inst->d;
    h = communicationStepSize;
    if (inst->type != fmi2CoSimulation || d->phase != PH_STEP)
        return ERR(inst, "fmi2DoStep: the instance is not an initialized Co-Simulation slave");
    if (!(h >= 0.0) || !isfinite(h))
        return ERR(inst, "fmi2DoStep: step size must be >= 0, got %g", h);
    if (fabs(currentCommunicationPoint - d->time) > 1e-9 * (1.0 + fabs(d->time)))
        return ERR(inst, "fmi2DoStep: communication point %.17g differs from the FMU time %.17g",
                   currentCommunicationPoint, d->time);
    affine(d, &f, &g);
    cap = capacity(d);
    /* Exact solution of C dT/dt = f - g*T over h: T + (f - g T)/g * (1 - exp(-g h / C)). */
    a = g * h / cap;
    if (fabs(a) > 1e-300) {
        const double t_inf = f / g;
        d->T = t_inf + (d->T - t_inf) * exp(-a);
    } else {
        d->T += (f - g * d->T) * h / cap;
    }
    d->Qr += d->q * h;
    d->time = currentCommunicationPoint + h;
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) {
    if (c == NULL) return fmi2Error;
    return ERR((Instance *)c, "fmi2CancelStep: fmi2DoStep never runs asynchronously");
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    (void)s;
    (void)value;
    if (c == NULL) return fmi2Error;
    return fmi2Discard;
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    Instance *inst = (Instance *)c;
    if (inst == NULL || value == NULL) return fmi2Error;
    if (s == fmi2LastSuccessfulTime) {
        *value = inst->d.time;
        return fmi2OK;
    }
    return fmi2Discard;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value) {
    (void)s;
    (void)value;
    if (c == NULL) return fmi2Error;
    return fmi2Discard;
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    (void)s;
    if (c == NULL || value == NULL) return fmi2Error;
    if (s == fmi2Terminated) {
        *value = fmi2False;
        return fmi2OK;
    }
    return fmi2Discard;
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    (void)s;
    (void)value;
    if (c == NULL) return fmi2Error;
    return fmi2Discard;
}

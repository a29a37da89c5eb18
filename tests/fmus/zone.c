/*
 * Test FMU for model cards: a one-zone RC model with names of its own (FMI 2.0, Model
 * Exchange and Co-Simulation in one binary). It is the R1C1 zone of the OU44 case without
 * ventilation, written with other variable names:
 *
 *   parameters  tmass, shgc, occheff, RExt, Vi            (as the built-in R1C1)
 *   inputs      solrad [W/m2], Tout [degC], occ [1], q [W] (no dpos)
 *   states      cair.T [K] (zone air), Qr [J] (integral of q)
 *   outputs     T [degC], Qr [J]
 *
 *   C dT/dt = (Tout + 273.15 - T)/R + shgc*solrad + occheff*occ*M(T) + q - Pc
 *   C = tmass*1.2*1005*Vi,  R = RExt/(3*Vi^(2/3)),  M(T) = 84*(325.15 - T)/32
 *
 * Built with -DTWO_CONTROLS it has a second control, a cooler given in kW with an
 * overwrite switch (as BOPTEST's oveX_u + oveX_activate pairs):
 *
 *   inputs      Pcool [kW] (cooling power, >= 0), Pcool_activate (Boolean, start false)
 *   Pc = 1000*Pcool when Pcool_activate, else 0 (the local loop keeps the cooler off)
 *
 * Model Exchange offers directional derivatives and FMU states; Co-Simulation steps with the
 * exact solution of the affine ODE (inputs held over the step). The tests build this file
 * with -DMODEL_GUID="{...}" into an FMU (tests/card_fmus.py); value references must match
 * zone.xml / zone2.xml.
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
    R_TMASS = 0, R_SHGC = 1, R_OCCHEFF = 2, R_REXT = 3, R_VI = 4,
    R_SOLRAD = 10, R_TOUT = 11, R_OCC = 12, R_Q = 13, R_PCOOL = 14,
    R_TAIR = 20, R_DER_TAIR = 21, R_QR = 22, R_DER_QR = 23, R_T_C = 24,
    B_PCOOL_ACTIVATE = 0
};

#define N_STATES 2
#define ZERO_C 273.15

enum { INSTANTIATED, INITIALIZING, EVENT_MODE, CONTINUOUS, STEPPING, TERMINATED };

typedef struct {
    double tmass, shgc, occheff, RExt, Vi;
    double solrad, Tout, occ, q, Pcool;
    int cooler_on;
    double Tair, Qr, time;
    int mode;
} Zone;

typedef struct {
    Zone z;
    fmi2Type kind;
    char name[128];
    fmi2CallbackFunctions cb;
} Component;

static fmi2Status fail(Component *comp, const char *fmt, ...) {
    char text[256];
    va_list args;
    if (comp == NULL || comp->cb.logger == NULL) return fmi2Error;
    va_start(args, fmt);
    vsnprintf(text, sizeof(text), fmt, args);
    va_end(args);
    comp->cb.logger(comp->cb.componentEnvironment, comp->name, fmi2Error, "logStatusError",
                    "%s", text);
    return fmi2Error;
}

static void defaults(Zone *z) {
    memset(z, 0, sizeof(*z));
    z->tmass = 50.0;
    z->shgc = 4.608961327935981;
    z->occheff = 2.0836995296486704;
    z->RExt = 4.0;
    z->Vi = 486.5;
    z->Tair = 293.15;
    z->mode = INSTANTIATED;
}

static double heat_capacity(const Zone *z) { return z->tmass * 1.2 * 1005.0 * z->Vi; }

static double conductance_out(const Zone *z) {
    return 3.0 * pow(z->Vi, 2.0 / 3.0) / z->RExt;
}

static double cooling_w(const Zone *z) {
#ifdef TWO_CONTROLS
    return z->cooler_on ? 1000.0 * z->Pcool : 0.0;
#else
    (void)z;
    return 0.0;
#endif
}

/* C dT/dt = gain - loss*T */
static void balance(const Zone *z, double *gain, double *loss) {
    const double people = z->occheff * z->occ * 84.0 / 32.0;
    const double ua = conductance_out(z);
    *loss = ua + people;
    *gain = ua * (z->Tout + ZERO_C) + z->shgc * z->solrad + people * 325.15 + z->q
            - cooling_w(z);
}

static double dTair(const Zone *z) {
    double gain, loss;
    balance(z, &gain, &loss);
    return (gain - loss * z->Tair) / heat_capacity(z);
}

static int is_parameter(fmi2ValueReference vr) { return vr <= R_VI; }

static int is_input(fmi2ValueReference vr) {
#ifdef TWO_CONTROLS
    return vr >= R_SOLRAD && vr <= R_PCOOL;
#else
    return vr >= R_SOLRAD && vr <= R_Q;
#endif
}

/* d(unknown)/d(known) for derivatives and outputs w.r.t. states and inputs. */
static int partial(const Zone *z, fmi2ValueReference unknown, fmi2ValueReference known,
                   double *out) {
    const double c = heat_capacity(z);
    if (!(known == R_TAIR || known == R_QR || is_input(known))) return -1;
    *out = 0.0;
    if (unknown == R_DER_TAIR) {
        double gain, loss;
        balance(z, &gain, &loss);
        if (known == R_TAIR) *out = -loss / c;
        else if (known == R_SOLRAD) *out = z->shgc / c;
        else if (known == R_TOUT) *out = conductance_out(z) / c;
        else if (known == R_OCC) *out = z->occheff * 84.0 / 32.0 * (325.15 - z->Tair) / c;
        else if (known == R_Q) *out = 1.0 / c;
        else if (known == R_PCOOL) *out = z->cooler_on ? -1000.0 / c : 0.0;
        return 0;
    }
    if (unknown == R_DER_QR) { if (known == R_Q) *out = 1.0; return 0; }
    if (unknown == R_T_C) { if (known == R_TAIR) *out = 1.0; return 0; }
    if (unknown == R_QR) { if (known == R_QR) *out = 1.0; return 0; }
    return -1;
}

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n,
                               const fmi2String categories[]) {
    (void)on; (void)n; (void)categories;
    return c ? fmi2OK : fmi2Error;
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String guid,
                              fmi2String resources, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean loggingOn) {
    Component *comp;
    (void)resources; (void)visible; (void)loggingOn;
    if (functions == NULL || functions->allocateMemory == NULL || instanceName == NULL)
        return NULL;
    if (guid == NULL || strcmp(guid, MODEL_GUID) != 0) return NULL;
    comp = (Component *)functions->allocateMemory(1, sizeof(Component));
    if (comp == NULL) return NULL;
    comp->kind = fmuType;
    comp->cb = *functions;
    strncpy(comp->name, instanceName, sizeof(comp->name) - 1);
    defaults(&comp->z);
    return comp;
}

void fmi2FreeInstance(fmi2Component c) {
    Component *comp = (Component *)c;
    if (comp != NULL) comp->cb.freeMemory(comp);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean tolDefined, fmi2Real tol,
                               fmi2Real start, fmi2Boolean stopDefined, fmi2Real stop) {
    Component *comp = (Component *)c;
    (void)tolDefined; (void)tol; (void)stopDefined; (void)stop;
    if (comp == NULL) return fmi2Error;
    comp->z.time = start;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    Component *comp = (Component *)c;
    if (comp == NULL || comp->z.mode != INSTANTIATED) return fail(comp, "not instantiated");
    comp->z.mode = INITIALIZING;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Component *comp = (Component *)c;
    if (comp == NULL || comp->z.mode != INITIALIZING) return fail(comp, "not initializing");
    comp->z.mode = comp->kind == fmi2ModelExchange ? EVENT_MODE : STEPPING;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) {
    Component *comp = (Component *)c;
    if (comp == NULL) return fmi2Error;
    comp->z.mode = TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c) {
    Component *comp = (Component *)c;
    if (comp == NULL) return fmi2Error;
    defaults(&comp->z);
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       fmi2Real value[]) {
    Component *comp = (Component *)c;
    const Zone *z;
    size_t i;
    if (comp == NULL) return fmi2Error;
    z = &comp->z;
    for (i = 0; i < nvr; i++) {
        switch (vr[i]) {
        case R_TMASS: value[i] = z->tmass; break;
        case R_SHGC: value[i] = z->shgc; break;
        case R_OCCHEFF: value[i] = z->occheff; break;
        case R_REXT: value[i] = z->RExt; break;
        case R_VI: value[i] = z->Vi; break;
        case R_SOLRAD: value[i] = z->solrad; break;
        case R_TOUT: value[i] = z->Tout; break;
        case R_OCC: value[i] = z->occ; break;
        case R_Q: value[i] = z->q; break;
#ifdef TWO_CONTROLS
        case R_PCOOL: value[i] = z->Pcool; break;
#endif
        case R_TAIR: value[i] = z->Tair; break;
        case R_DER_TAIR: value[i] = dTair(z); break;
        case R_QR: value[i] = z->Qr; break;
        case R_DER_QR: value[i] = z->q; break;
        case R_T_C: value[i] = z->Tair - ZERO_C; break;
        default: return fail(comp, "fmi2GetReal: no variable %u", vr[i]);
        }
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       const fmi2Real value[]) {
    Component *comp = (Component *)c;
    Zone *z;
    size_t i;
    if (comp == NULL) return fmi2Error;
    z = &comp->z;
    for (i = 0; i < nvr; i++) {
        if ((is_parameter(vr[i]) || vr[i] == R_TAIR || vr[i] == R_QR)
            && z->mode != INSTANTIATED && z->mode != INITIALIZING)
            return fail(comp, "fmi2SetReal: %u is settable before initialisation only", vr[i]);
        if (is_parameter(vr[i]) && !isfinite(value[i]))
            return fail(comp, "fmi2SetReal: parameter %u must be finite", vr[i]);
        switch (vr[i]) {
        case R_TMASS: z->tmass = value[i]; break;
        case R_SHGC: z->shgc = value[i]; break;
        case R_OCCHEFF: z->occheff = value[i]; break;
        case R_REXT: z->RExt = value[i]; break;
        case R_VI: z->Vi = value[i]; break;
        case R_SOLRAD: z->solrad = value[i]; break;
        case R_TOUT: z->Tout = value[i]; break;
        case R_OCC: z->occ = value[i]; break;
        case R_Q: z->q = value[i]; break;
#ifdef TWO_CONTROLS
        case R_PCOOL: z->Pcool = value[i]; break;
#endif
        case R_TAIR: z->Tair = value[i]; break;
        case R_QR: z->Qr = value[i]; break;
        default: return fail(comp, "fmi2SetReal: %u is not settable", vr[i]);
        }
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          fmi2Integer value[]) {
    (void)vr; (void)value;
    return c && nvr == 0 ? fmi2OK : fail((Component *)c, "no Integer variables");
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          const fmi2Integer value[]) {
    (void)vr; (void)value;
    return c && nvr == 0 ? fmi2OK : fail((Component *)c, "no Integer variables");
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          fmi2Boolean value[]) {
    Component *comp = (Component *)c;
    size_t i;
    if (comp == NULL) return fmi2Error;
    for (i = 0; i < nvr; i++) {
#ifdef TWO_CONTROLS
        if (vr[i] == B_PCOOL_ACTIVATE) { value[i] = comp->z.cooler_on; continue; }
#endif
        (void)value;
        return fail(comp, "fmi2GetBoolean: no variable %u", vr[i]);
    }
    return fmi2OK;
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          const fmi2Boolean value[]) {
    Component *comp = (Component *)c;
    size_t i;
    if (comp == NULL) return fmi2Error;
    for (i = 0; i < nvr; i++) {
#ifdef TWO_CONTROLS
        if (vr[i] == B_PCOOL_ACTIVATE) { comp->z.cooler_on = value[i] ? 1 : 0; continue; }
#endif
        (void)value;
        return fail(comp, "fmi2SetBoolean: no variable %u", vr[i]);
    }
    return fmi2OK;
}

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                         fmi2String value[]) {
    (void)vr; (void)value;
    return c && nvr == 0 ? fmi2OK : fail((Component *)c, "no String variables");
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                         const fmi2String value[]) {
    (void)vr; (void)value;
    return c && nvr == 0 ? fmi2OK : fail((Component *)c, "no String variables");
}

/* FMU states: plain copies of the zone. */
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *state) {
    Component *comp = (Component *)c;
    if (comp == NULL || state == NULL) return fmi2Error;
    if (*state == NULL) *state = comp->cb.allocateMemory(1, sizeof(Zone));
    if (*state == NULL) return fail(comp, "out of memory");
    memcpy(*state, &comp->z, sizeof(Zone));
    return fmi2OK;
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate state) {
    Component *comp = (Component *)c;
    if (comp == NULL || state == NULL) return fmi2Error;
    memcpy(&comp->z, state, sizeof(Zone));
    return fmi2OK;
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *state) {
    Component *comp = (Component *)c;
    if (comp == NULL || state == NULL) return fmi2Error;
    if (*state != NULL) comp->cb.freeMemory(*state);
    *state = NULL;
    return fmi2OK;
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate state, size_t *size) {
    (void)state;
    if (c == NULL || size == NULL) return fmi2Error;
    *size = sizeof(Zone);
    return fmi2OK;
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate state, fmi2Byte data[],
                                 size_t size) {
    if (c == NULL || state == NULL || size < sizeof(Zone)) return fmi2Error;
    memcpy(data, state, sizeof(Zone));
    return fmi2OK;
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte data[], size_t size,
                                   fmi2FMUstate *state) {
    Component *comp = (Component *)c;
    if (comp == NULL || state == NULL || size != sizeof(Zone)) return fmi2Error;
    if (*state == NULL) *state = comp->cb.allocateMemory(1, sizeof(Zone));
    if (*state == NULL) return fail(comp, "out of memory");
    memcpy(*state, data, sizeof(Zone));
    return fmi2OK;
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference unknowns[],
                                        size_t nu, const fmi2ValueReference knowns[],
                                        size_t nk, const fmi2Real dknown[],
                                        fmi2Real dunknown[]) {
    Component *comp = (Component *)c;
    size_t i, j;
    if (comp == NULL) return fmi2Error;
    for (i = 0; i < nu; i++) {
        double sum = 0.0, p;
        for (j = 0; j < nk; j++) {
            if (partial(&comp->z, unknowns[i], knowns[j], &p) != 0)
                return fail(comp, "no partial d(%u)/d(%u)", unknowns[i], knowns[j]);
            sum += p * dknown[j];
        }
        dunknown[i] = sum;
    }
    return fmi2OK;
}

/* Model Exchange */
fmi2Status fmi2EnterEventMode(fmi2Component c) {
    Component *comp = (Component *)c;
    if (comp == NULL) return fmi2Error;
    comp->z.mode = EVENT_MODE;
    return fmi2OK;
}

fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *info) {
    if (c == NULL || info == NULL) return fmi2Error;
    memset(info, 0, sizeof(*info));
    return fmi2OK;
}

fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) {
    Component *comp = (Component *)c;
    if (comp == NULL) return fmi2Error;
    comp->z.mode = CONTINUOUS;
    return fmi2OK;
}

fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean noSetPrior,
                                       fmi2Boolean *enterEventMode, fmi2Boolean *terminate) {
    (void)noSetPrior;
    if (c == NULL || enterEventMode == NULL || terminate == NULL) return fmi2Error;
    *enterEventMode = fmi2False;
    *terminate = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2SetTime(fmi2Component c, fmi2Real time) {
    Component *comp = (Component *)c;
    if (comp == NULL) return fmi2Error;
    comp->z.time = time;
    return fmi2OK;
}

fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t nx) {
    Component *comp = (Component *)c;
    if (comp == NULL || nx != N_STATES) return fmi2Error;
    comp->z.Tair = x[0];
    comp->z.Qr = x[1];
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real dx[], size_t nx) {
    Component *comp = (Component *)c;
    if (comp == NULL || nx != N_STATES) return fmi2Error;
    dx[0] = dTair(&comp->z);
    dx[1] = comp->z.q;
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real indicators[], size_t ni) {
    (void)indicators;
    return c && ni == 0 ? fmi2OK : fmi2Error;
}

fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    Component *comp = (Component *)c;
    if (comp == NULL || nx != N_STATES) return fmi2Error;
    x[0] = comp->z.Tair;
    x[1] = comp->z.Qr;
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real nominal[], size_t nx) {
    if (c == NULL || nx != N_STATES) return fmi2Error;
    nominal[0] = 300.0;
    nominal[1] = 1.0e6;
    return fmi2OK;
}

/* Co-Simulation: the exact solution of the affine ODE over the step. */
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[],
                                       size_t nvr, const fmi2Integer order[],
                                       const fmi2Real value[]) {
    (void)vr; (void)order; (void)value;
    return c && nvr == 0 ? fmi2OK : fmi2Error;
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[],
                                        size_t nvr, const fmi2Integer order[],
                                        fmi2Real value[]) {
    (void)vr; (void)order; (void)value;
    return c && nvr == 0 ? fmi2OK : fmi2Error;
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean noSetPrior) {
    Component *comp = (Component *)c;
    Zone *z;
    double gain, loss, rate;
    (void)noSetPrior;
    if (comp == NULL) return fmi2Error;
    z = &comp->z;
    if (z->mode != STEPPING) return fail(comp, "fmi2DoStep: not initialized");
    balance(z, &gain, &loss);
    rate = loss * h / heat_capacity(z);
    if (fabs(rate) > 1e-300) {
        const double steady = gain / loss;
        z->Tair = steady + (z->Tair - steady) * exp(-rate);
    } else {
        z->Tair += (gain - loss * z->Tair) * h / heat_capacity(z);
    }
    z->Qr += z->q * h;
    z->time = t + h;
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) { (void)c; return fmi2Error; }

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    (void)c; (void)s; (void)value;
    return fmi2Discard;
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    Component *comp = (Component *)c;
    if (comp == NULL || value == NULL || s != fmi2LastSuccessfulTime) return fmi2Discard;
    *value = comp->z.time;
    return fmi2OK;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value) {
    (void)c; (void)s; (void)value;
    return fmi2Discard;
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    (void)c;
    if (value == NULL || s != fmi2Terminated) return fmi2Discard;
    *value = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    (void)c; (void)s; (void)value;
    return fmi2Discard;
}

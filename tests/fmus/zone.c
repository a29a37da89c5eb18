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
 * exact solution of the affine ODE (inputs held over the step); the FMI boilerplate is that of
 * every mshoot FMU (fmi2_model.h, in mshoot_core/fmu_src). The tests build this file
 * with -DMODEL_GUID="{...}" into an FMU (tests/card_fmus.py); value references must match
 * zone.xml / zone2.xml.
 */
enum {
    R_TMASS = 0, R_SHGC = 1, R_OCCHEFF = 2, R_REXT = 3, R_VI = 4,
    R_SOLRAD = 10, R_TOUT = 11, R_OCC = 12, R_Q = 13, R_PCOOL = 14,
    R_TAIR = 20, R_DER_TAIR = 21, R_QR = 22, R_DER_QR = 23, R_T_C = 24,
    B_PCOOL_ACTIVATE = 0
};

#define ZERO_C 273.15

#define MODEL_NAME "Zone"
#define MODEL_NX 2
#define MODEL_EXCHANGE 1
#define MODEL_CO_SIMULATION 1
#define MODEL_PARTIALS 1
#define MODEL_STATE_MAGIC 0x5a4f4e45u /* "ZONE" */
#ifdef TWO_CONTROLS
#define MODEL_BOOLEANS
#endif

/* Everything an FMU state holds. */
typedef struct {
    double tmass, shgc, occheff, RExt, Vi;
    double solrad, Tout, occ, q, Pcool;
    int cooler_on;
    double Tair, Qr, time;
    int phase;
} ModelData;

#include "fmi2_model.h"

static void model_defaults(ModelData *z) {
    z->tmass = 50.0;
    z->shgc = 4.608961327935981;
    z->occheff = 2.0836995296486704;
    z->RExt = 4.0;
    z->Vi = 486.5;
    z->Tair = 293.15;
}

static fmi2Status model_initialize(Instance *inst) {
    (void)inst;
    return fmi2OK;
}

static double heat_capacity(const ModelData *z) { return z->tmass * 1.2 * 1005.0 * z->Vi; }

static double conductance_out(const ModelData *z) {
    return 3.0 * pow(z->Vi, 2.0 / 3.0) / z->RExt;
}

static double cooling_w(const ModelData *z) {
#ifdef TWO_CONTROLS
    return z->cooler_on ? 1000.0 * z->Pcool : 0.0;
#else
    (void)z;
    return 0.0;
#endif
}

/* C dT/dt = gain - loss*T */
static void balance(const ModelData *z, double *gain, double *loss) {
    const double people = z->occheff * z->occ * 84.0 / 32.0;
    const double ua = conductance_out(z);
    *loss = ua + people;
    *gain = ua * (z->Tout + ZERO_C) + z->shgc * z->solrad + people * 325.15 + z->q
            - cooling_w(z);
}

static double dTair(const ModelData *z) {
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
static int model_partial(const ModelData *z, fmi2ValueReference unknown,
                         fmi2ValueReference known, double *out) {
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

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       fmi2Real value[]) {
    Instance *comp = (Instance *)c;
    const ModelData *z;
    size_t i;
    if (comp == NULL) return fmi2Error;
    z = &comp->d;
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
    Instance *comp = (Instance *)c;
    ModelData *z;
    size_t i;
    if (comp == NULL) return fmi2Error;
    z = &comp->d;
    for (i = 0; i < nvr; i++) {
        if ((is_parameter(vr[i]) || vr[i] == R_TAIR || vr[i] == R_QR)
            && !before_initialization(z))
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

#ifdef TWO_CONTROLS  /* the cooler's overwrite switch */
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          fmi2Boolean value[]) {
    Instance *comp = (Instance *)c;
    size_t i;
    if (comp == NULL) return fmi2Error;
    for (i = 0; i < nvr; i++) {
        if (vr[i] == B_PCOOL_ACTIVATE) { value[i] = comp->d.cooler_on; continue; }
        return fail(comp, "fmi2GetBoolean: no variable %u", vr[i]);
    }
    return fmi2OK;
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          const fmi2Boolean value[]) {
    Instance *comp = (Instance *)c;
    size_t i;
    if (comp == NULL) return fmi2Error;
    for (i = 0; i < nvr; i++) {
        if (vr[i] == B_PCOOL_ACTIVATE) { comp->d.cooler_on = value[i] ? 1 : 0; continue; }
        return fail(comp, "fmi2SetBoolean: no variable %u", vr[i]);
    }
    return fmi2OK;
}
#endif

/* Model Exchange */
static void model_get_states(const ModelData *z, double x[]) {
    x[0] = z->Tair;
    x[1] = z->Qr;
}

static void model_set_states(ModelData *z, const double x[]) {
    z->Tair = x[0];
    z->Qr = x[1];
}

static void model_derivatives(ModelData *z, double dx[]) {
    dx[0] = dTair(z);
    dx[1] = z->q;
}

static void model_nominals(const ModelData *z, double nominal[]) {
    (void)z;
    nominal[0] = 300.0;
    nominal[1] = 1.0e6;
}

/* Co-Simulation: the exact solution of the affine ODE over the step. */
static fmi2Status model_do_step(Instance *comp, double t, double h) {
    ModelData *z = &comp->d;
    double gain, loss, rate;
    (void)t;
    balance(z, &gain, &loss);
    rate = loss * h / heat_capacity(z);
    if (fabs(rate) > 1e-300) {
        const double steady = gain / loss;
        z->Tair = steady + (z->Tair - steady) * exp(-rate);
    } else {
        z->Tair += (gain - loss * z->Tair) * h / heat_capacity(z);
    }
    z->Qr += z->q * h;
    return fmi2OK;
}

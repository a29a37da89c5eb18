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
 * The FMI boilerplate is that of every mshoot FMU (fmi2_model.h).
 *
 * Value references must match r1c1.xml. The builder (mshoot_core/fmu_build.py) compiles
 * this file with -DMODEL_GUID="{...}" (a hash of the sources, also written into the
 * modelDescription.xml).
 */
#define MODEL_NAME "R1C1"
#define MODEL_NX 2                    /* continuous states: T [K], Qr [J] */
#define MODEL_EXCHANGE 1
#define MODEL_CO_SIMULATION 1
#define MODEL_PARTIALS 1
#define MODEL_STATE_MAGIC 0x52314331u /* "R1C1" */

/* ---- value references (r1c1.xml) ------------------------------------------------------- */
enum {
    VR_TMASS = 0, VR_SHGC = 1, VR_OCCHEFF = 2, VR_REXT = 3, VR_TVE = 4, VR_VI = 5,
    VR_MAXVENT = 6,
    VR_SOLRAD = 10, VR_TOUT = 11, VR_OCC = 12, VR_DPOS = 13, VR_Q = 14,
    VR_T_K = 20, VR_DER_T_K = 21, VR_QR = 22, VR_DER_QR = 23, VR_T_DEGC = 24
};

#define KELVIN 273.15
#define OCC_HEAT_W 84.0               /* W per occupant at 293.15 K */
#define OCC_HEAT_ZERO_K 325.15        /* ... falling linearly to 0 W here */
#define OCC_HEAT_SPAN_K 32.0
#define AIR_HEAT_PER_M3H (1206.0 / 3600.0)
#define NOMINAL_T_K 300.0
#define NOMINAL_QR_J 1.0e6

/* Everything an FMU state holds: plain data, copied with memcpy. */
typedef struct {
    double tmass, shgc, occheff, RExt, Tve, Vi, maxVent;   /* parameters */
    double solrad, Tout, occ, dpos, q;                      /* inputs */
    double T, Qr;                                           /* continuous states [K], [J] */
    double time;                                            /* [s] */
    int phase;
} ModelData;

#include "fmi2_model.h"

/* ---- the model --------------------------------------------------------------------------- */
static void model_defaults(ModelData *d) {
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

/* Partial derivative d(unknown)/d(known): unknowns derivatives and outputs, knowns states and
 * inputs; returns 0 on success, -1 if the pair is invalid. */
static int model_partial(const ModelData *d, fmi2ValueReference unknown,
                         fmi2ValueReference known, double *value) {
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

static fmi2Status check_parameter(Instance *inst, const char *name, double value, int positive) {
    if (!isfinite(value)) return fail(inst, "parameter %s must be finite, got %g", name, value);
    if (positive && value <= 0.0)
        return fail(inst, "parameter %s must be > 0, got %g", name, value);
    return fmi2OK;
}

static fmi2Status model_initialize(Instance *inst) {
    (void)inst;  /* the parameters are checked as they are set */
    return fmi2OK;
}

/* ---- variables ----------------------------------------------------------------------- */
fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       fmi2Real value[]) {
    Instance *inst = (Instance *)c;
    const ModelData *d;
    size_t i;
    if (inst == NULL) return fmi2Error;
    if (nvr > 0 && (vr == NULL || value == NULL)) return fail(inst, "fmi2GetReal: NULL array");
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
        default: return fail(inst, "fmi2GetReal: unknown value reference %u", vr[i]);
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
    if (nvr > 0 && (vr == NULL || value == NULL)) return fail(inst, "fmi2SetReal: NULL array");
    d = &inst->d;
    if (d->phase == PH_TERMINATED) return fail(inst, "fmi2SetReal: the instance is terminated");
    for (i = 0; i < nvr; i++) {
        const double v = value[i];
        if (vr[i] <= VR_MAXVENT || vr[i] == VR_T_K || vr[i] == VR_QR) {
            if (!before_initialization(d))
                return fail(inst, "fmi2SetReal: value reference %u is a parameter or start value,"
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
        default: return fail(inst, "fmi2SetReal: value reference %u is not settable", vr[i]);
        }
    }
    return fmi2OK;
}

/* ---- Model Exchange -------------------------------------------------------------------- */
static void model_get_states(const ModelData *d, double x[]) {
    x[0] = d->T;
    x[1] = d->Qr;
}

static void model_set_states(ModelData *d, const double x[]) {
    d->T = x[0];
    d->Qr = x[1];
}

static void model_derivatives(ModelData *d, double dx[]) {
    dx[0] = der_T(d);
    dx[1] = d->q;
}

static void model_nominals(const ModelData *d, double x[]) {
    (void)d;
    x[0] = NOMINAL_T_K;
    x[1] = NOMINAL_QR_J;
}

/* ---- Co-Simulation --------------------------------------------------------------------- */
static fmi2Status model_do_step(Instance *inst, double t, double h) {
    ModelData *d = &inst->d;
    double f, g, cap, a;
    (void)t;
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
    return fmi2OK;
}

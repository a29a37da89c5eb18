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
 * references are the positions in setpoint_zone.xml; the switch is Boolean 0. The FMI
 * boilerplate is that of every mshoot FMU (fmi2_model.h).
 */
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

#define MODEL_NAME "SetpointZone"
#define MODEL_NX NSTATES
#define MODEL_NVARS NVARS
#define MODEL_EXCHANGE 1
#define MODEL_CO_SIMULATION 0
#define MODEL_PARTIALS 0
#define MODEL_BOOLEANS

typedef struct {
    double r[NVARS];
    int activate;
    double time;
    int phase;
} ModelData;

#include "fmi2_model.h"

static void evaluate(ModelData *m) {
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

static void model_defaults(ModelData *d) {
    memcpy(d->r, start_values, sizeof d->r);
    d->activate = 0;
}

static fmi2Status model_initialize(Instance *inst) {
    double *r = inst->d.r;
    int i;
    for (i = CAIR; i <= RWIN; i++)
        if (!(r[i] > 0.0)) return fail(inst, "parameter %d must be > 0, got %g", i, r[i]);
    if (!(r[QMAX] >= 0.0 && r[KP] >= 0.0 && r[T_START] > 0.0))
        return fail(inst, "Kp, Qmax must be >= 0 and T_start > 0 K");
    r[AIR_U] = r[CAIR] * r[T_START];
    r[WALL_T] = r[T_START];
    r[QTOTAL] = 0.0;
    return fmi2OK;
}

static void model_evaluate(ModelData *d) { evaluate(d); }

static int model_settable(fmi2ValueReference k) {
    if (k < NPARAMS) return REAL_START;
    return k >= TOUT && k <= OVE_TSET ? REAL_INPUT : REAL_FIXED;
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                          fmi2Boolean v[]) {
    Instance *m = (Instance *)c;
    size_t i;
    if (m == NULL) return fmi2Error;
    for (i = 0; i < n; i++) {
        if (vr[i] != ACTIVATE) return fail(m, "GetBoolean: no value reference %u", vr[i]);
        v[i] = m->d.activate ? fmi2True : fmi2False;
    }
    return fmi2OK;
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                          const fmi2Boolean v[]) {
    Instance *m = (Instance *)c;
    size_t i;
    if (m == NULL) return fmi2Error;
    for (i = 0; i < n; i++) {
        if (vr[i] != ACTIVATE) return fail(m, "SetBoolean: no value reference %u", vr[i]);
        m->d.activate = v[i] ? 1 : 0;
    }
    return fmi2OK;
}

static void model_get_states(const ModelData *d, double x[]) {
    x[0] = d->r[AIR_U];
    x[1] = d->r[WALL_T];
    x[2] = d->r[QTOTAL];
}

static void model_set_states(ModelData *d, const double x[]) {
    d->r[AIR_U] = x[0];
    d->r[WALL_T] = x[1];
    d->r[QTOTAL] = x[2];
}

static void model_derivatives(ModelData *d, double dx[]) {
    evaluate(d);
    dx[0] = d->r[DER_AIR_U];
    dx[1] = d->r[DER_WALL_T];
    dx[2] = d->r[DER_QTOTAL];
}

static void model_nominals(const ModelData *d, double x[]) {
    x[0] = d->r[CAIR] * 293.15;
    x[1] = 293.15;
    x[2] = 1.0e6;
}

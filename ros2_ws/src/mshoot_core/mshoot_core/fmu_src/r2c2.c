/*
 * "Third-party-style" test FMU for mshoot: a two-node (air + wall) R2C2 zone, FMI 2.0
 * Model Exchange only, deliberately different from r1c1.c where a model can differ: states in
 * degC with dotted names, other inputs, a direct-feedthrough output, a flat value array
 * indexed by value reference, no FMU state get/set, directional derivatives. The FMI
 * boilerplate is that of every mshoot FMU (fmi2_model.h).
 *
 *   Cair  d(air.T)/dt  = (wall.T - air.T)/Raw + (Tamb - air.T)/Rwin + Qhvac + (1 - fsun) Qsun
 *   Cwall d(wall.T)/dt = (air.T - wall.T)/Raw + (Tamb - wall.T)/Rwa + fsun Qsun
 *   Tair = air.T,   Pwin = (air.T - Tamb)/Rwin   (heat lost through the windows [W])
 *
 * Value references are the 0-based positions in r2c2.xml.
 */
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

#define MODEL_NAME "R2C2"
#define MODEL_NX NSTATES
#define MODEL_NVARS NVARS
#define MODEL_EXCHANGE 1
#define MODEL_CO_SIMULATION 0
#define MODEL_PARTIALS 1

typedef struct {
    double r[NVARS];
    double time;
    int phase;
} ModelData;

#include "fmi2_model.h"

static void evaluate(double *r) {
    const double q_aw = (r[WALL_T] - r[AIR_T]) / r[RAW];
    r[DER_AIR_T] = (q_aw + (r[TAMB] - r[AIR_T]) / r[RWIN] + r[QHVAC]
                    + (1.0 - r[FSUN]) * r[QSUN]) / r[CAIR];
    r[DER_WALL_T] = (-q_aw + (r[TAMB] - r[WALL_T]) / r[RWA] + r[FSUN] * r[QSUN]) / r[CWALL];
    r[TAIR] = r[AIR_T];
    r[PWIN] = (r[AIR_T] - r[TAMB]) / r[RWIN];
}

/* Jacobian entry d r[unknown] / d r[known]; -1 if not an (unknown, known) pair. */
static int jac(const double *r, unsigned int unknown, unsigned int known, double *out) {
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

static void model_defaults(ModelData *d) { memcpy(d->r, start_values, sizeof d->r); }

static fmi2Status model_initialize(Instance *inst) {
    int i;
    for (i = CAIR; i <= RWIN; i++)
        if (!(inst->d.r[i] > 0.0))
            return fail(inst, "parameter %d must be > 0, got %g", i, inst->d.r[i]);
    return fmi2OK;
}

static int model_partial(const ModelData *d, fmi2ValueReference unknown,
                         fmi2ValueReference known, double *value) {
    if (unknown >= NVARS || known >= NVARS) return -1;
    return jac(d->r, unknown, known, value);
}

static void model_evaluate(ModelData *d) { evaluate(d->r); }

static int model_settable(fmi2ValueReference k) {
    if (k <= FSUN || k == AIR_T || k == WALL_T) return REAL_START;
    return k == TAMB || k == QHVAC || k == QSUN ? REAL_INPUT : REAL_FIXED;
}

static void model_get_states(const ModelData *d, double x[]) {
    x[0] = d->r[AIR_T];
    x[1] = d->r[WALL_T];
}

static void model_set_states(ModelData *d, const double x[]) {
    d->r[AIR_T] = x[0];
    d->r[WALL_T] = x[1];
}

static void model_derivatives(ModelData *d, double dx[]) {
    evaluate(d->r);
    dx[0] = d->r[DER_AIR_T];
    dx[1] = d->r[DER_WALL_T];
}

static void model_nominals(const ModelData *d, double x[]) {
    (void)d;
    x[0] = 1.0;
    x[1] = 1.0;
}

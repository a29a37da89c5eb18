/*
 * The FMI 2.0 functions every mshoot FMU shares: instance, life cycle, logging, the variable
 * types it has none of, FMU state, the Model Exchange calls around the model's states, and
 * the Co-Simulation checks and status queries. A model's C file defines what is its own, then
 * includes this file once (it defines the exported FMI functions: one model per binary):
 *
 *   MODEL_NAME            its name in messages, e.g. "R1C1"
 *   MODEL_NX              number of continuous states
 *   MODEL_EXCHANGE        1: offers Model Exchange (fmi2Instantiate refuses it otherwise)
 *   MODEL_CO_SIMULATION   1: offers Co-Simulation (fmi2DoStep calls model_do_step)
 *   MODEL_STATE_MAGIC     defined: FMU state get/set/serialise (a copy of ModelData, the
 *                         serialised form headed by this number); else they fail
 *   MODEL_PARTIALS        1: directional derivatives from model_partial; 0: they fail
 *   MODEL_TIME_EVENTS     defined: fmi2NewDiscreteStates calls model_events
 *   MODEL_BOOLEANS        defined: the model writes fmi2GetBoolean/fmi2SetBoolean itself
 *   MODEL_NVARS           defined: the Real variables are ModelData's `double r[MODEL_NVARS]`
 *                         by value reference; fmi2GetReal and fmi2SetReal are written here
 *                         (from model_evaluate and model_settable), not by the model
 *   ModelData             plain data copied as the FMU state, with the fields
 *                         `double time` [s] and `int phase` (a Phase)
 *
 * and the functions declared below (model_*), then fmi2GetReal and fmi2SetReal. The builder
 * (mshoot_core/fmu_build.py) compiles with -DMODEL_GUID="{...}", checked at instantiation.
 */
#ifndef MSHOOT_FMI2_MODEL_H
#define MSHOOT_FMI2_MODEL_H

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>

#include "fmi2Functions.h"

#ifndef MODEL_GUID
#error "MODEL_GUID must be defined, e.g. -DMODEL_GUID=\"{...}\" (see fmu_build.py)"
#endif
#if !defined(MODEL_NAME) || !defined(MODEL_NX) || !defined(MODEL_EXCHANGE) \
    || !defined(MODEL_CO_SIMULATION) || !defined(MODEL_PARTIALS)
#error "define MODEL_NAME, MODEL_NX, MODEL_EXCHANGE, MODEL_CO_SIMULATION and MODEL_PARTIALS"
#endif

/* Where an instance is in the FMI life cycle (ModelData's phase). */
typedef enum { PH_INSTANTIATED, PH_INIT, PH_EVENT, PH_CONT, PH_STEP, PH_TERMINATED } Phase;

typedef struct {
    ModelData d;
    fmi2Type type;
    char *name;
    fmi2CallbackFunctions cb;
    fmi2Boolean logging;
} Instance;

/* ---- what the model defines ------------------------------------------------------------ */
/* Parameters, inputs and start values of a new or reset instance (d is zeroed before). */
static void model_defaults(ModelData *d);
/* At fmi2ExitInitializationMode: check the parameters, set what follows from the starts. */
static fmi2Status model_initialize(Instance *inst);
#if MODEL_EXCHANGE
static void model_get_states(const ModelData *d, double x[]);
static void model_set_states(ModelData *d, const double x[]);
static void model_derivatives(ModelData *d, double dx[]);
static void model_nominals(const ModelData *d, double x[]);
#endif
#ifdef MODEL_TIME_EVENTS
/* At fmi2NewDiscreteStates (info zeroed): update the discrete states, say the next event. */
static void model_events(ModelData *d, fmi2EventInfo *info);
#endif
#if MODEL_PARTIALS
/* d(unknown)/d(known) at the current values; 0, or -1 if the pair is not offered. */
static int model_partial(const ModelData *d, fmi2ValueReference unknown,
                         fmi2ValueReference known, double *value);
#endif
#ifdef MODEL_NVARS
/* Compute the values of d->r that follow from the others (derivatives, outputs). */
static void model_evaluate(ModelData *d);
/* How a Real variable is set: REAL_FIXED (not), REAL_START (before initialization only: a
 * parameter or start value) or REAL_INPUT (any time). */
enum { REAL_FIXED, REAL_START, REAL_INPUT };
static int model_settable(fmi2ValueReference vr);
#endif
#if MODEL_CO_SIMULATION
/* Advance d from the communication point t (d->time) by h >= 0 [s]; the caller then sets
 * d->time to t + h. */
static fmi2Status model_do_step(Instance *inst, double t, double h);
#endif

/* ---- logging --------------------------------------------------------------------------- */
static void log_message(Instance *inst, fmi2Status status, const char *category,
                        const char *fmt, ...) {
    char text[512];
    va_list ap;
    if (inst == NULL || inst->cb.logger == NULL) return;
    if (status == fmi2OK && !inst->logging) return;
    va_start(ap, fmt);
    vsnprintf(text, sizeof(text), fmt, ap);
    va_end(ap);
    inst->cb.logger(inst->cb.componentEnvironment, inst->name, status, category, "%s", text);
}

/* Log an error (category logStatusError) and return fmi2Error. */
#define fail(inst, ...) (log_message((inst), fmi2Error, "logStatusError", __VA_ARGS__), fmi2Error)

/* Parameters and start values are settable only before fmi2ExitInitializationMode. */
static inline int before_initialization(const ModelData *d) {
    return d->phase == PH_INSTANTIATED || d->phase == PH_INIT;
}

static void reset_data(ModelData *d) {
    memset(d, 0, sizeof(*d));
    model_defaults(d);
    d->time = 0.0;
    d->phase = PH_INSTANTIATED;
}

/* ---- common functions ------------------------------------------------------------------ */
const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }

const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[]) {
    Instance *inst = (Instance *)c;
    (void)nCategories;
    (void)categories;
    if (inst == NULL) return fmi2Error;
    inst->logging = loggingOn;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation,
                              const fmi2CallbackFunctions *functions, fmi2Boolean visible,
                              fmi2Boolean loggingOn) {
    Instance *inst;
    size_t n;
    const int offered = fmuType == fmi2ModelExchange ? MODEL_EXCHANGE
                        : fmuType == fmi2CoSimulation ? MODEL_CO_SIMULATION : 0;
    (void)fmuResourceLocation;
    (void)visible;
    if (functions == NULL || functions->allocateMemory == NULL || functions->freeMemory == NULL)
        return NULL;
    if (instanceName == NULL || instanceName[0] == '\0') {
        if (functions->logger)
            functions->logger(functions->componentEnvironment, MODEL_NAME, fmi2Error,
                              "logStatusError", "%s", "missing instance name");
        return NULL;
    }
    if (fmuGUID == NULL || strcmp(fmuGUID, MODEL_GUID) != 0 || !offered) {
        if (functions->logger)
            functions->logger(functions->componentEnvironment, instanceName, fmi2Error,
                              "logStatusError", "%s: %s", MODEL_NAME,
                              offered ? "wrong GUID" : "this FMU type is not offered");
        return NULL;
    }
    inst = (Instance *)functions->allocateMemory(1, sizeof(Instance));
    if (inst == NULL) return NULL;
    n = strlen(instanceName) + 1;
    inst->name = (char *)functions->allocateMemory(n, sizeof(char));
    if (inst->name == NULL) {
        functions->freeMemory(inst);
        return NULL;
    }
    memcpy(inst->name, instanceName, n);
    inst->cb = *functions;
    inst->type = fmuType;
    inst->logging = loggingOn;
    reset_data(&inst->d);
    log_message(inst, fmi2OK, "logAll", "instantiated (%s)",
                fmuType == fmi2ModelExchange ? "ModelExchange" : "CoSimulation");
    return inst;
}

void fmi2FreeInstance(fmi2Component c) {
    Instance *inst = (Instance *)c;
    fmi2CallbackFreeMemory free_memory;
    if (inst == NULL) return;
    free_memory = inst->cb.freeMemory;
    free_memory(inst->name);
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
        return fail(inst, "fmi2SetupExperiment is only allowed after instantiation or reset");
    inst->d.time = startTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    if (inst->d.phase != PH_INSTANTIATED)
        return fail(inst, "fmi2EnterInitializationMode is only allowed after instantiation");
    inst->d.phase = PH_INIT;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    if (inst->d.phase != PH_INIT)
        return fail(inst, "fmi2ExitInitializationMode is only allowed in initialization mode");
    if (model_initialize(inst) != fmi2OK) return fmi2Error;
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
    reset_data(&inst->d);
    return fmi2OK;
}

#ifdef MODEL_NVARS
fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       fmi2Real value[]) {
    Instance *inst = (Instance *)c;
    size_t i;
    if (inst == NULL) return fmi2Error;
    model_evaluate(&inst->d);
    for (i = 0; i < nvr; i++) {
        if (vr[i] >= MODEL_NVARS) return fail(inst, "fmi2GetReal: no value reference %u", vr[i]);
        value[i] = inst->d.r[vr[i]];
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       const fmi2Real value[]) {
    Instance *inst = (Instance *)c;
    size_t i;
    if (inst == NULL) return fmi2Error;
    for (i = 0; i < nvr; i++) {
        const int how = vr[i] < MODEL_NVARS ? model_settable(vr[i]) : REAL_FIXED;
        if (how == REAL_FIXED) return fail(inst, "fmi2SetReal: vr %u is not settable", vr[i]);
        if (how == REAL_START && !before_initialization(&inst->d))
            return fail(inst, "fmi2SetReal: vr %u is settable before initialization only",
                        vr[i]);
        inst->d.r[vr[i]] = value[i];
    }
    return fmi2OK;
}
#endif

/* The variable types a model has none of: only empty calls succeed. */
#define NO_VARIABLES(function, type, constness)                                              \
    fmi2Status function(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,            \
                        constness type value[]) {                                              \
        (void)vr;                                                                              \
        (void)value;                                                                           \
        if (c == NULL) return fmi2Error;                                                       \
        if (nvr > 0) return fail((Instance *)c, "%s: the model has no variables of this type", \
                                 #function);                                                   \
        return fmi2OK;                                                                         \
    }
NO_VARIABLES(fmi2GetInteger, fmi2Integer, )
NO_VARIABLES(fmi2SetInteger, fmi2Integer, const)
NO_VARIABLES(fmi2GetString, fmi2String, )
NO_VARIABLES(fmi2SetString, fmi2String, const)
#ifndef MODEL_BOOLEANS
NO_VARIABLES(fmi2GetBoolean, fmi2Boolean, )
NO_VARIABLES(fmi2SetBoolean, fmi2Boolean, const)
#endif

/* ---- FMU state ------------------------------------------------------------------------- */
#ifdef MODEL_STATE_MAGIC
typedef struct {
    unsigned int magic;
    unsigned int size;
} SnapshotHeader;

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    Instance *inst = (Instance *)c;
    ModelData *snapshot;
    if (inst == NULL || FMUstate == NULL) return fmi2Error;
    snapshot = (ModelData *)*FMUstate;
    if (snapshot == NULL) {
        snapshot = (ModelData *)inst->cb.allocateMemory(1, sizeof(ModelData));
        if (snapshot == NULL) return fail(inst, "fmi2GetFMUstate: out of memory");
    }
    memcpy(snapshot, &inst->d, sizeof(ModelData));
    *FMUstate = snapshot;
    return fmi2OK;
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    if (FMUstate == NULL) return fail(inst, "fmi2SetFMUstate: NULL state");
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
    if (FMUstate == NULL || data == NULL) return fail(inst, "fmi2SerializeFMUstate: NULL");
    if (size < sizeof(SnapshotHeader) + sizeof(ModelData))
        return fail(inst, "fmi2SerializeFMUstate: buffer of %zu bytes is too small", size);
    header.magic = MODEL_STATE_MAGIC;
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
        return fail(inst, "fmi2DeSerializeFMUstate: NULL");
    if (size != sizeof(SnapshotHeader) + sizeof(ModelData))
        return fail(inst, "fmi2DeSerializeFMUstate: %zu bytes, expected %zu", size,
                    sizeof(SnapshotHeader) + sizeof(ModelData));
    memcpy(&header, serializedState, sizeof(header));
    if (header.magic != MODEL_STATE_MAGIC || header.size != sizeof(ModelData))
        return fail(inst, "fmi2DeSerializeFMUstate: not a state of %s", MODEL_NAME);
    if (*FMUstate == NULL) {
        *FMUstate = inst->cb.allocateMemory(1, sizeof(ModelData));
        if (*FMUstate == NULL) return fail(inst, "fmi2DeSerializeFMUstate: out of memory");
    }
    memcpy(*FMUstate, serializedState + sizeof(header), sizeof(ModelData));
    return fmi2OK;
}
#else  /* canGetAndSetFMUstate="false", as in many exported FMUs */
#define NO_FMU_STATE(c) fail((Instance *)(c), "%s is not supported", __func__)

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s) {
    (void)s;
    return NO_FMU_STATE(c);
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) {
    (void)s;
    return NO_FMU_STATE(c);
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s) {
    (void)s;
    return NO_FMU_STATE(c);
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t *n) {
    (void)s;
    (void)n;
    return NO_FMU_STATE(c);
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte b[], size_t n) {
    (void)s;
    (void)b;
    (void)n;
    return NO_FMU_STATE(c);
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n,
                                   fmi2FMUstate *s) {
    (void)b;
    (void)n;
    (void)s;
    return NO_FMU_STATE(c);
}
#endif

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[],
                                        size_t nUnknown, const fmi2ValueReference vKnown_ref[],
                                        size_t nKnown, const fmi2Real dvKnown[],
                                        fmi2Real dvUnknown[]) {
    Instance *inst = (Instance *)c;
#if MODEL_PARTIALS
    size_t i, j;
    if (inst == NULL) return fmi2Error;
    for (i = 0; i < nUnknown; i++) {
        double sum = 0.0;
        for (j = 0; j < nKnown; j++) {
            double p;
            if (model_partial(&inst->d, vUnknown_ref[i], vKnown_ref[j], &p) != 0)
                return fail(inst, "fmi2GetDirectionalDerivative: d(vr %u)/d(vr %u) is not "
                                  "available", vUnknown_ref[i], vKnown_ref[j]);
            sum += p * dvKnown[j];
        }
        dvUnknown[i] = sum;
    }
    return fmi2OK;
#else
    (void)vUnknown_ref;
    (void)nUnknown;
    (void)vKnown_ref;
    (void)nKnown;
    (void)dvKnown;
    (void)dvUnknown;
    return fail(inst, "fmi2GetDirectionalDerivative is not supported");
#endif
}

/* ---- Model Exchange -------------------------------------------------------------------- */
#if MODEL_EXCHANGE
fmi2Status fmi2EnterEventMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    if (inst->d.phase != PH_CONT && inst->d.phase != PH_EVENT)
        return fail(inst, "fmi2EnterEventMode is only allowed in continuous-time mode");
    inst->d.phase = PH_EVENT;
    return fmi2OK;
}

fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *eventInfo) {
    Instance *inst = (Instance *)c;
    if (inst == NULL || eventInfo == NULL) return fmi2Error;
    if (inst->d.phase != PH_EVENT)
        return fail(inst, "fmi2NewDiscreteStates is only allowed in event mode");
    memset(eventInfo, 0, sizeof(*eventInfo));
#ifdef MODEL_TIME_EVENTS
    model_events(&inst->d, eventInfo);
#endif
    return fmi2OK;
}

fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (inst == NULL) return fmi2Error;
    if (inst->d.phase != PH_EVENT)
        return fail(inst, "fmi2EnterContinuousTimeMode is only allowed in event mode");
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

/* The state vector calls: nx must be MODEL_NX. */
#define CHECK_STATES(function, array)                                                         \
    do {                                                                                       \
        if (inst == NULL) return fmi2Error;                                                    \
        if (nx != MODEL_NX || (array) == NULL)                                                 \
            return fail(inst, "%s: %zu states, expected %d", function, nx, MODEL_NX);          \
    } while (0)

fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t nx) {
    Instance *inst = (Instance *)c;
    CHECK_STATES("fmi2SetContinuousStates", x);
    model_set_states(&inst->d, x);
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real derivatives[], size_t nx) {
    Instance *inst = (Instance *)c;
    CHECK_STATES("fmi2GetDerivatives", derivatives);
    model_derivatives(&inst->d, derivatives);
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real eventIndicators[], size_t ni) {
    (void)eventIndicators;
    if (c == NULL) return fmi2Error;
    if (ni != 0) return fail((Instance *)c, "fmi2GetEventIndicators: the model has none");
    return fmi2OK;
}

fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    Instance *inst = (Instance *)c;
    CHECK_STATES("fmi2GetContinuousStates", x);
    model_get_states(&inst->d, x);
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x_nominal[], size_t nx) {
    Instance *inst = (Instance *)c;
    CHECK_STATES("fmi2GetNominalsOfContinuousStates", x_nominal);
    model_nominals(&inst->d, x_nominal);
    return fmi2OK;
}
#endif

/* ---- Co-Simulation --------------------------------------------------------------------- */
#if MODEL_CO_SIMULATION
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[],
                                       size_t nvr, const fmi2Integer order[],
                                       const fmi2Real value[]) {
    (void)vr;
    (void)order;
    (void)value;
    if (c == NULL) return fmi2Error;
    if (nvr == 0) return fmi2OK;
    return fail((Instance *)c, "fmi2SetRealInputDerivatives: inputs are held constant per step "
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
    return fail((Instance *)c, "fmi2GetRealOutputDerivatives: maxOutputDerivativeOrder is 0");
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint,
                      fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentCommunicationPoint) {
    Instance *inst = (Instance *)c;
    ModelData *d;
    const double h = communicationStepSize;
    (void)noSetFMUStatePriorToCurrentCommunicationPoint;
    if (inst == NULL) return fmi2Error;
    d = &inst->d;
    if (inst->type != fmi2CoSimulation || d->phase != PH_STEP)
        return fail(inst, "fmi2DoStep: the instance is not an initialized Co-Simulation slave");
    if (!(h >= 0.0) || !isfinite(h))
        return fail(inst, "fmi2DoStep: step size must be >= 0, got %g", h);
    if (fabs(currentCommunicationPoint - d->time) > 1e-9 * (1.0 + fabs(d->time)))
        return fail(inst, "fmi2DoStep: communication point %.17g differs from the FMU time "
                          "%.17g", currentCommunicationPoint, d->time);
    if (model_do_step(inst, currentCommunicationPoint, h) != fmi2OK) return fmi2Error;
    d->time = currentCommunicationPoint + h;
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) {
    if (c == NULL) return fmi2Error;
    return fail((Instance *)c, "fmi2CancelStep: fmi2DoStep never runs asynchronously");
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
    if (s != fmi2LastSuccessfulTime) return fmi2Discard;
    *value = inst->d.time;
    return fmi2OK;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value) {
    (void)s;
    (void)value;
    if (c == NULL) return fmi2Error;
    return fmi2Discard;
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    if (c == NULL || value == NULL) return fmi2Error;
    if (s != fmi2Terminated) return fmi2Discard;
    *value = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    (void)s;
    (void)value;
    if (c == NULL) return fmi2Error;
    return fmi2Discard;
}
#endif

#endif /* MSHOOT_FMI2_MODEL_H */

/* Batched Co-Simulation intervals for mshoot: one C loop over many intervals of one
 * FMU instance, so the per-interval cost is the FMU's own work instead of ~10 Python
 * ctypes round trips. Each interval: reset, set parameters and start states, set up the
 * experiment at the interval's start time (t_start[b], or 0 when t_start is NULL),
 * initialise with the interval's inputs, one doStep of dt from there, read states and
 * outputs. The FMU's functions come in as pointers from the instance fmpy already loaded. */
#include <stddef.h>
#include "fmi2Functions.h"

typedef struct {
    fmi2ResetTYPE *reset;
    fmi2SetRealTYPE *set_real;
    fmi2GetRealTYPE *get_real;
    fmi2SetupExperimentTYPE *setup_experiment;
    fmi2EnterInitializationModeTYPE *enter_initialization;
    fmi2ExitInitializationModeTYPE *exit_initialization;
    fmi2DoStepTYPE *do_step;
} mshoot_cs_api;

#define CHECK(call, stage) do { if ((call) > fmi2Warning) return (long)(b * 16 + (stage) + 1); } while (0)

/* Returns 0 on success, else 16*interval + stage + 1 of the first failing call. */
__attribute__((visibility("default")))
long mshoot_cs_batch(const mshoot_cs_api *api, fmi2Component c, size_t n_batch, double dt,
                     int tolerance_defined, double tolerance,
                     size_t n_par, const fmi2ValueReference *par_vr, const double *par_val,
                     size_t n_start, const fmi2ValueReference *start_vr, const double *start,
                     size_t n_in, const fmi2ValueReference *in_vr, const double *in,
                     size_t nx, const fmi2ValueReference *x_vr, double *x_end,
                     size_t ny, const fmi2ValueReference *y_vr, double *y_end,
                     const double *t_start)
{
    size_t b;
    for (b = 0; b < n_batch; b++) {
        const double t0 = t_start ? t_start[b] : 0.0;
        CHECK(api->reset(c), 0);
        if (n_par) CHECK(api->set_real(c, par_vr, n_par, par_val), 1);
        if (n_start) CHECK(api->set_real(c, start_vr, n_start, start + b * n_start), 2);
        CHECK(api->setup_experiment(c, tolerance_defined, tolerance, t0, fmi2False, 0.0), 3);
        CHECK(api->enter_initialization(c), 4);
        if (n_in) CHECK(api->set_real(c, in_vr, n_in, in + b * n_in), 5);
        CHECK(api->exit_initialization(c), 6);
        CHECK(api->do_step(c, t0, dt, fmi2True), 7);
        if (nx) CHECK(api->get_real(c, x_vr, nx, x_end + b * nx), 8);
        if (ny) CHECK(api->get_real(c, y_vr, ny, y_end + b * ny), 9);
    }
    return 0;
}

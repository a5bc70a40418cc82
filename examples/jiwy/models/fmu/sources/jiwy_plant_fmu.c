/* jiwy_plant_fmu.c - JIWY pan/tilt plant as an FMI 2.0 co-simulation FMU.
 * rtloop test fixture (MIT). doStep follows 20-sim's Euler order: integrate the
 * states with the rates of the previous evaluation, advance time, evaluate the rates
 * and outputs with the current inputs. The expressions and their order are those of
 * examples/jiwy/models/Plant/Plant.cpp, so the trajectories agree to rounding error.
 *
 * Value references: 0 SteeringPan, 1 SteeringTilt (inputs), 2 AnglePan, 3 AngleTilt
 * (outputs), 4 pan.p, 5 tilt.p (motor momenta). */
#include <stdlib.h>
#include <string.h>
#include "fmi2_minimal.h"

#define GUID "{6f1b6a52-3c0e-4d8e-9a51-7e2b1c0f9a11}"
#define N_VR 6

typedef struct {
	double r, j_mot, d_mot, g, b, j_cam, d_cam;
} Axis;

static const Axis PAN = {0.018, 2.06e-7, 1.77e-6, 1.0 / 19.0, 1.0, 3e-4, 2e-4};
static const Axis TILT = {0.00701, 5.28e-8, 4e-7, 1.0 / 19.0, 0.25, 4.5e-5, 1e-4};

typedef struct {
	double u[2];	/* SteeringPan, SteeringTilt */
	double s[4];	/* pan.p, pan.theta, tilt.p, tilt.theta */
	double R[4];	/* their rates at the last evaluation */
	double time;
	int initialized;
} Instance;

static void axis_rates(const Axis *a, double p, double u, double *dp, double *dtheta)
{
	double gb = a->g * a->b;
	double j_eq = a->j_mot + gb * gb * a->j_cam;
	double omega = p / j_eq;
	double omega_cam = gb * omega;
	double tau_cam = a->d_cam * omega_cam;
	*dp = a->r * u - a->d_mot * omega - gb * tau_cam;
	*dtheta = omega_cam;
}

static void evaluate(Instance *m)
{
	axis_rates(&PAN, m->s[0], m->u[0], &m->R[0], &m->R[1]);
	axis_rates(&TILT, m->s[2], m->u[1], &m->R[2], &m->R[3]);
}

static double get_vr(const Instance *m, fmi2ValueReference vr)
{
	switch (vr) {
	case 0: return m->u[0];
	case 1: return m->u[1];
	case 2: return m->s[1];
	case 3: return m->s[3];
	case 4: return m->s[0];
	default: return m->s[2];
	}
}

/* ---- common functions ---------------------------------------------------- */

FMI2_EXPORT const char *fmi2GetTypesPlatform(void) { return "default"; }
FMI2_EXPORT const char *fmi2GetVersion(void) { return "2.0"; }

FMI2_EXPORT fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n,
	const fmi2String categories[])
{
	(void)c; (void)on; (void)n; (void)categories;
	return fmi2OK;
}

FMI2_EXPORT fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType,
	fmi2String guid, fmi2String resourceLocation, const fmi2CallbackFunctions *functions,
	fmi2Boolean visible, fmi2Boolean loggingOn)
{
	(void)instanceName; (void)resourceLocation; (void)functions; (void)visible; (void)loggingOn;
	if (fmuType != fmi2CoSimulation || guid == NULL || strcmp(guid, GUID) != 0)
		return NULL;
	return calloc(1, sizeof(Instance));
}

FMI2_EXPORT void fmi2FreeInstance(fmi2Component c) { free(c); }

FMI2_EXPORT fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined,
	fmi2Real tolerance, fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime)
{
	(void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
	((Instance *)c)->time = startTime;
	return fmi2OK;
}

FMI2_EXPORT fmi2Status fmi2EnterInitializationMode(fmi2Component c) { (void)c; return fmi2OK; }

FMI2_EXPORT fmi2Status fmi2ExitInitializationMode(fmi2Component c)
{
	Instance *m = c;
	evaluate(m);	/* 20-sim's Initialize: rates from the initial states */
	m->initialized = 1;
	return fmi2OK;
}

FMI2_EXPORT fmi2Status fmi2Terminate(fmi2Component c) { (void)c; return fmi2OK; }

FMI2_EXPORT fmi2Status fmi2Reset(fmi2Component c)
{
	memset(c, 0, sizeof(Instance));
	return fmi2OK;
}

FMI2_EXPORT fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
	fmi2Real value[])
{
	size_t i;
	for (i = 0; i < nvr; i++) {
		if (vr[i] >= N_VR) return fmi2Error;
		value[i] = get_vr(c, vr[i]);
	}
	return fmi2OK;
}

FMI2_EXPORT fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
	const fmi2Real value[])
{
	Instance *m = c;
	size_t i;
	for (i = 0; i < nvr; i++) {
		if (vr[i] == 0 || vr[i] == 1) m->u[vr[i]] = value[i];
		else if (vr[i] == 4 && !m->initialized) m->s[0] = value[i];
		else if (vr[i] == 5 && !m->initialized) m->s[2] = value[i];
		else return fmi2Error;
	}
	return fmi2OK;
}


FMI2_EXPORT fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
	fmi2Integer value[]) { (void)c; (void)vr; (void)value; return nvr ? fmi2Error : fmi2OK; }
FMI2_EXPORT fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
	fmi2Boolean value[]) { (void)c; (void)vr; (void)value; return nvr ? fmi2Error : fmi2OK; }
FMI2_EXPORT fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
	fmi2String value[]) { (void)c; (void)vr; (void)value; return nvr ? fmi2Error : fmi2OK; }
FMI2_EXPORT fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
	const fmi2Integer value[]) { (void)c; (void)vr; (void)value; return nvr ? fmi2Error : fmi2OK; }
FMI2_EXPORT fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
	const fmi2Boolean value[]) { (void)c; (void)vr; (void)value; return nvr ? fmi2Error : fmi2OK; }
FMI2_EXPORT fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
	const fmi2String value[]) { (void)c; (void)vr; (void)value; return nvr ? fmi2Error : fmi2OK; }

/* FMU state: a copy of the instance (plain numbers), serialised as its bytes */
FMI2_EXPORT fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s)
{
	Instance *copy = *s != NULL ? *s : malloc(sizeof(Instance));
	if (copy == NULL)
		return fmi2Error;
	memcpy(copy, c, sizeof(Instance));
	*s = copy;
	return fmi2OK;
}
FMI2_EXPORT fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s)
{
	if (s == NULL)
		return fmi2Error;
	memcpy(c, s, sizeof(Instance));
	return fmi2OK;
}
FMI2_EXPORT fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s)
{
	(void)c;
	free(*s);
	*s = NULL;
	return fmi2OK;
}
FMI2_EXPORT fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t *n)
{
	(void)c; (void)s;
	*n = sizeof(Instance);
	return fmi2OK;
}
FMI2_EXPORT fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte b[], size_t n)
{
	(void)c;
	if (s == NULL || n != sizeof(Instance))
		return fmi2Error;
	memcpy(b, s, n);
	return fmi2OK;
}
FMI2_EXPORT fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n,
	fmi2FMUstate *s)
{
	Instance *copy;
	(void)c;
	if (n != sizeof(Instance) || (copy = malloc(sizeof(Instance))) == NULL)
		return fmi2Error;
	memcpy(copy, b, n);
	*s = copy;
	return fmi2OK;
}
/* directional derivatives: not supported (capability flags say so) */
FMI2_EXPORT fmi2Status fmi2GetDirectionalDerivative(fmi2Component c,
	const fmi2ValueReference vu[], size_t nu, const fmi2ValueReference vk[], size_t nk,
	const fmi2Real dvk[], fmi2Real dvu[])
{ (void)c; (void)vu; (void)nu; (void)vk; (void)nk; (void)dvk; (void)dvu; return fmi2Error; }

/* ---- co-simulation ------------------------------------------------------- */

FMI2_EXPORT fmi2Status fmi2SetRealInputDerivatives(fmi2Component c,
	const fmi2ValueReference vr[], size_t nvr, const fmi2Integer order[], const fmi2Real value[])
{ (void)c; (void)vr; (void)nvr; (void)order; (void)value; return fmi2Error; }
FMI2_EXPORT fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c,
	const fmi2ValueReference vr[], size_t nvr, const fmi2Integer order[], fmi2Real value[])
{ (void)c; (void)vr; (void)nvr; (void)order; (void)value; return fmi2Error; }

FMI2_EXPORT fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint,
	fmi2Real communicationStepSize, fmi2Boolean noSetFMUStatePriorToCurrentPoint)
{
	Instance *m = c;
	int i;
	(void)currentCommunicationPoint; (void)noSetFMUStatePriorToCurrentPoint;
	for (i = 0; i < 4; i++)
		m->s[i] = m->s[i] + m->R[i] * communicationStepSize;
	m->time = m->time + communicationStepSize;
	evaluate(m);
	return fmi2OK;
}

FMI2_EXPORT fmi2Status fmi2CancelStep(fmi2Component c) { (void)c; return fmi2Error; }

FMI2_EXPORT fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *v)
{ (void)c; (void)s; (void)v; return fmi2Discard; }
FMI2_EXPORT fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *v)
{
	if (s != fmi2LastSuccessfulTime) return fmi2Discard;
	*v = ((Instance *)c)->time;
	return fmi2OK;
}
FMI2_EXPORT fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s,
	fmi2Integer *v) { (void)c; (void)s; (void)v; return fmi2Discard; }
FMI2_EXPORT fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s,
	fmi2Boolean *v) { (void)c; (void)s; (void)v; return fmi2Discard; }
FMI2_EXPORT fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s,
	fmi2String *v) { (void)c; (void)s; (void)v; return fmi2Discard; }

/* jiwy_plant_fmu3.c - JIWY pan/tilt plant as an FMI 3.0 co-simulation FMU.
 * rtloop test fixture (MIT), written from the FMI 3.0 specification's function list;
 * not the official headers. Same Euler order as the FMI 2.0 fixture: doStep integrates
 * with the rates of the previous evaluation, then evaluates with the current inputs.
 *
 * Value references: 0 time, 1 SteeringPan, 2 SteeringTilt, 3 AnglePan, 4 AngleTilt. */
#include <stdbool.h>
#include <stddef.h>
#include <stdlib.h>
#include <string.h>

#define EXPORT __attribute__((visibility("default")))
#define TOKEN "{0c7d9f3e-51a2-4b8c-8e44-2d6a90b3f7c5}"

typedef enum { fmi3OK, fmi3Warning, fmi3Discard, fmi3Error, fmi3Fatal } fmi3Status;
typedef unsigned int fmi3ValueReference;

typedef struct {
	double r, j_mot, d_mot, g, b, j_cam, d_cam;
} Axis;

static const Axis PAN = {0.018, 2.06e-7, 1.77e-6, 1.0 / 19.0, 1.0, 3e-4, 2e-4};
static const Axis TILT = {0.00701, 5.28e-8, 4e-7, 1.0 / 19.0, 0.25, 4.5e-5, 1e-4};

typedef struct {
	double u[2];	/* SteeringPan, SteeringTilt */
	double s[4];	/* pan.p, pan.theta, tilt.p, tilt.theta */
	double R[4];	/* rates at the last evaluation */
	double time;
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

EXPORT const char *fmi3GetVersion(void) { return "3.0"; }

EXPORT void *fmi3InstantiateCoSimulation(const char *instanceName, const char *token,
	const char *resourcePath, bool visible, bool loggingOn, bool eventModeUsed,
	bool earlyReturnAllowed, const fmi3ValueReference required[], size_t nRequired,
	void *environment, void *logMessage, void *intermediateUpdate)
{
	(void)instanceName; (void)resourcePath; (void)visible; (void)loggingOn;
	(void)eventModeUsed; (void)earlyReturnAllowed; (void)required; (void)nRequired;
	(void)environment; (void)logMessage; (void)intermediateUpdate;
	if (token == NULL || strcmp(token, TOKEN) != 0)
		return NULL;
	return calloc(1, sizeof(Instance));
}

EXPORT void fmi3FreeInstance(void *instance) { free(instance); }

EXPORT fmi3Status fmi3EnterInitializationMode(void *instance, bool toleranceDefined,
	double tolerance, double startTime, bool stopTimeDefined, double stopTime)
{
	(void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
	((Instance *)instance)->time = startTime;
	return fmi3OK;
}

EXPORT fmi3Status fmi3ExitInitializationMode(void *instance)
{
	evaluate(instance);
	return fmi3OK;
}

EXPORT fmi3Status fmi3Terminate(void *instance) { (void)instance; return fmi3OK; }

EXPORT fmi3Status fmi3Reset(void *instance)
{
	memset(instance, 0, sizeof(Instance));
	return fmi3OK;
}

EXPORT fmi3Status fmi3GetFloat64(void *instance, const fmi3ValueReference vr[], size_t nvr,
	double values[], size_t nValues)
{
	Instance *m = instance;
	size_t i;
	if (nValues < nvr) return fmi3Error;
	for (i = 0; i < nvr; i++) {
		switch (vr[i]) {
		case 0: values[i] = m->time; break;
		case 1: values[i] = m->u[0]; break;
		case 2: values[i] = m->u[1]; break;
		case 3: values[i] = m->s[1]; break;
		case 4: values[i] = m->s[3]; break;
		default: return fmi3Error;
		}
	}
	return fmi3OK;
}

EXPORT fmi3Status fmi3SetFloat64(void *instance, const fmi3ValueReference vr[], size_t nvr,
	const double values[], size_t nValues)
{
	Instance *m = instance;
	size_t i;
	if (nValues < nvr) return fmi3Error;
	for (i = 0; i < nvr; i++) {
		if (vr[i] == 1 || vr[i] == 2) m->u[vr[i] - 1] = values[i];
		else return fmi3Error;
	}
	return fmi3OK;
}

EXPORT fmi3Status fmi3DoStep(void *instance, double currentCommunicationPoint,
	double communicationStepSize, bool noSetFMUStatePriorToCurrentPoint,
	bool *eventHandlingNeeded, bool *terminateSimulation, bool *earlyReturn,
	double *lastSuccessfulTime)
{
	Instance *m = instance;
	int i;
	(void)currentCommunicationPoint; (void)noSetFMUStatePriorToCurrentPoint;
	for (i = 0; i < 4; i++)
		m->s[i] = m->s[i] + m->R[i] * communicationStepSize;
	m->time = m->time + communicationStepSize;
	evaluate(m);
	*eventHandlingNeeded = false;
	*terminateSimulation = false;
	*earlyReturn = false;
	*lastSuccessfulTime = m->time;
	return fmi3OK;
}

EXPORT fmi3Status fmi3SetDebugLogging(void *instance, bool on, size_t n, const char *const c[])
{
	(void)instance; (void)on; (void)n; (void)c;
	return fmi3OK;
}

/* The rest of the FMI 3.0 API exists so that loaders find every symbol; none is
 * used by this co-simulation fixture, and each answers fmi3Error if called. */
#define UNSUPPORTED(name) EXPORT fmi3Status name(void) { return fmi3Error; }
UNSUPPORTED(fmi3InstantiateModelExchange)
UNSUPPORTED(fmi3InstantiateScheduledExecution)
UNSUPPORTED(fmi3EnterEventMode)
UNSUPPORTED(fmi3EnterConfigurationMode)
UNSUPPORTED(fmi3ExitConfigurationMode)
UNSUPPORTED(fmi3EnterContinuousTimeMode)
UNSUPPORTED(fmi3EnterStepMode)
UNSUPPORTED(fmi3CompletedIntegratorStep)
UNSUPPORTED(fmi3EvaluateDiscreteStates)
UNSUPPORTED(fmi3UpdateDiscreteStates)
UNSUPPORTED(fmi3ActivateModelPartition)
UNSUPPORTED(fmi3GetFloat32)
UNSUPPORTED(fmi3SetFloat32)
UNSUPPORTED(fmi3GetInt8)
UNSUPPORTED(fmi3SetInt8)
UNSUPPORTED(fmi3GetUInt8)
UNSUPPORTED(fmi3SetUInt8)
UNSUPPORTED(fmi3GetInt16)
UNSUPPORTED(fmi3SetInt16)
UNSUPPORTED(fmi3GetUInt16)
UNSUPPORTED(fmi3SetUInt16)
UNSUPPORTED(fmi3GetInt32)
UNSUPPORTED(fmi3SetInt32)
UNSUPPORTED(fmi3GetUInt32)
UNSUPPORTED(fmi3SetUInt32)
UNSUPPORTED(fmi3GetInt64)
UNSUPPORTED(fmi3SetInt64)
UNSUPPORTED(fmi3GetUInt64)
UNSUPPORTED(fmi3SetUInt64)
UNSUPPORTED(fmi3GetBoolean)
UNSUPPORTED(fmi3SetBoolean)
UNSUPPORTED(fmi3GetString)
UNSUPPORTED(fmi3SetString)
UNSUPPORTED(fmi3GetBinary)
UNSUPPORTED(fmi3SetBinary)
UNSUPPORTED(fmi3GetClock)
UNSUPPORTED(fmi3SetClock)
UNSUPPORTED(fmi3GetFMUState)
UNSUPPORTED(fmi3SetFMUState)
UNSUPPORTED(fmi3FreeFMUState)
UNSUPPORTED(fmi3SerializedFMUStateSize)
UNSUPPORTED(fmi3SerializeFMUState)
UNSUPPORTED(fmi3DeserializeFMUState)
UNSUPPORTED(fmi3GetDirectionalDerivative)
UNSUPPORTED(fmi3GetAdjointDerivative)
UNSUPPORTED(fmi3GetOutputDerivatives)
UNSUPPORTED(fmi3GetNumberOfVariableDependencies)
UNSUPPORTED(fmi3GetVariableDependencies)
UNSUPPORTED(fmi3GetIntervalDecimal)
UNSUPPORTED(fmi3GetIntervalFraction)
UNSUPPORTED(fmi3SetIntervalDecimal)
UNSUPPORTED(fmi3SetIntervalFraction)
UNSUPPORTED(fmi3GetShiftDecimal)
UNSUPPORTED(fmi3GetShiftFraction)
UNSUPPORTED(fmi3SetShiftDecimal)
UNSUPPORTED(fmi3SetShiftFraction)
UNSUPPORTED(fmi3SetTime)
UNSUPPORTED(fmi3SetContinuousStates)
UNSUPPORTED(fmi3GetContinuousStateDerivatives)
UNSUPPORTED(fmi3GetEventIndicators)
UNSUPPORTED(fmi3GetContinuousStates)
UNSUPPORTED(fmi3GetNominalsOfContinuousStates)
UNSUPPORTED(fmi3GetNumberOfEventIndicators)
UNSUPPORTED(fmi3GetNumberOfContinuousStates)

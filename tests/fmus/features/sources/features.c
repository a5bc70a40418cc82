/* features.c - rtloop test FMU (FMI 3.0 co-simulation, MIT).
 * x' = gain * u (Euler, from x0); count = steps taken; positive = x > 0; half = x / 2 as
 * Float32; multiples = [x, 2x, 3x]; an event is signalled after event_at steps (events
 * counts event-mode visits); the simulation terminates once time >= stop_at.
 * It keeps the FMI 3 co-simulation modes as strictly as the Modelica Reference FMUs do:
 * after fmi3ExitInitializationMode it is in Event Mode when instantiated with
 * eventModeUsed, else in Step Mode; fmi3EnterEventMode is an error unless in Step Mode. */
#include <stdbool.h>
#include <stddef.h>
#include <stdlib.h>
#include <string.h>

#define EXPORT __attribute__((visibility("default")))

typedef enum { fmi3OK, fmi3Warning, fmi3Discard, fmi3Error, fmi3Fatal } fmi3Status;
typedef unsigned int fmi3ValueReference;
typedef void (*LogMessage)(void *env, fmi3Status status, const char *category, const char *message);

enum Mode { INSTANTIATED, INITIALIZATION, EVENT, STEP };

typedef struct {
	double time, u, gain, x0, stop_at, x;
	int event_at, count, events;
	bool event_mode_used;
	enum Mode mode;
	LogMessage log;
	void *env;
} Instance;

EXPORT const char *fmi3GetVersion(void) { return "3.0"; }

EXPORT void *fmi3InstantiateCoSimulation(const char *instanceName, const char *token,
	const char *resourcePath, bool visible, bool loggingOn, bool eventModeUsed,
	bool earlyReturnAllowed, const fmi3ValueReference required[], size_t nRequired,
	void *environment, void *logMessage, void *intermediateUpdate)
{
	Instance *m;
	(void)instanceName; (void)resourcePath; (void)visible; (void)loggingOn;
	(void)earlyReturnAllowed; (void)required; (void)nRequired; (void)intermediateUpdate;
	if (token == NULL || strcmp(token, "{rtloop-features-1}") != 0) return NULL;
	m = calloc(1, sizeof(Instance));
	m->gain = 2.0; m->x0 = 0.5; m->event_at = 5; m->stop_at = 1000.0;
	m->log = (LogMessage)logMessage; m->env = environment;
	m->event_mode_used = eventModeUsed; m->mode = INSTANTIATED;
	return m;
}

EXPORT void fmi3FreeInstance(void *instance) { free(instance); }

EXPORT fmi3Status fmi3EnterInitializationMode(void *instance, bool toleranceDefined,
	double tolerance, double startTime, bool stopTimeDefined, double stopTime)
{
	Instance *m = instance;
	(void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
	m->time = startTime;
	m->mode = INITIALIZATION;
	return fmi3OK;
}

EXPORT fmi3Status fmi3ExitInitializationMode(void *instance)
{
	Instance *m = instance;
	if (m->mode != INITIALIZATION) return fmi3Error;
	m->x = m->x0;
	m->mode = m->event_mode_used ? EVENT : STEP;
	return fmi3OK;
}

EXPORT fmi3Status fmi3EnterEventMode(void *instance)
{
	Instance *m = instance;
	if (m->mode != STEP || !m->event_mode_used) return fmi3Error;
	m->mode = EVENT;
	return fmi3OK;
}

EXPORT fmi3Status fmi3EnterStepMode(void *instance)
{
	Instance *m = instance;
	if (m->mode != EVENT) return fmi3Error;
	m->mode = STEP;
	return fmi3OK;
}

EXPORT fmi3Status fmi3UpdateDiscreteStates(void *instance, bool *needUpdate, bool *terminate,
	bool *nominalsChanged, bool *valuesChanged, bool *nextEventTimeDefined, double *nextEventTime)
{
	Instance *m = instance;
	if (m->mode != EVENT) return fmi3Error;
	if (m->count > 0) m->events += 1;	/* the first call ends initialisation */
	*needUpdate = false; *terminate = false; *nominalsChanged = false; *valuesChanged = false;
	*nextEventTimeDefined = false; *nextEventTime = 0.0;
	return fmi3OK;
}

EXPORT fmi3Status fmi3Terminate(void *instance) { (void)instance; return fmi3OK; }
EXPORT fmi3Status fmi3Reset(void *instance) { (void)instance; return fmi3OK; }
EXPORT fmi3Status fmi3SetDebugLogging(void *instance, bool on, size_t n, const char *const c[])
{ (void)instance; (void)on; (void)n; (void)c; return fmi3OK; }

EXPORT fmi3Status fmi3GetFloat64(void *instance, const fmi3ValueReference vr[], size_t nvr,
	double values[], size_t nValues)
{
	Instance *m = instance;
	size_t i, k = 0;
	for (i = 0; i < nvr; i++) {
		switch (vr[i]) {
		case 0: if (k >= nValues) return fmi3Error; values[k++] = m->time; break;
		case 1: if (k >= nValues) return fmi3Error; values[k++] = m->u; break;
		case 2: if (k >= nValues) return fmi3Error; values[k++] = m->gain; break;
		case 3: if (k >= nValues) return fmi3Error; values[k++] = m->x0; break;
		case 5: if (k >= nValues) return fmi3Error; values[k++] = m->stop_at; break;
		case 10: if (k >= nValues) return fmi3Error; values[k++] = m->x; break;
		case 14:
			if (k + 3 > nValues) return fmi3Error;
			values[k++] = m->x; values[k++] = 2.0 * m->x; values[k++] = 3.0 * m->x;
			break;
		default: return fmi3Error;
		}
	}
	return k == nValues ? fmi3OK : fmi3Error;
}

EXPORT fmi3Status fmi3SetFloat64(void *instance, const fmi3ValueReference vr[], size_t nvr,
	const double values[], size_t nValues)
{
	Instance *m = instance;
	size_t i;
	if (nValues != nvr) return fmi3Error;
	for (i = 0; i < nvr; i++) {
		switch (vr[i]) {
		case 1: m->u = values[i]; break;
		case 2: m->gain = values[i]; break;
		case 3: m->x0 = values[i]; break;
		case 5: m->stop_at = values[i]; break;
		default: return fmi3Error;
		}
	}
	return fmi3OK;
}

EXPORT fmi3Status fmi3GetFloat32(void *instance, const fmi3ValueReference vr[], size_t nvr,
	float values[], size_t nValues)
{
	Instance *m = instance;
	if (nvr != 1 || nValues != 1 || vr[0] != 13) return fmi3Error;
	values[0] = (float)(m->x / 2.0);
	return fmi3OK;
}

EXPORT fmi3Status fmi3GetInt32(void *instance, const fmi3ValueReference vr[], size_t nvr,
	int values[], size_t nValues)
{
	Instance *m = instance;
	size_t i;
	if (nValues != nvr) return fmi3Error;
	for (i = 0; i < nvr; i++) {
		if (vr[i] == 4) values[i] = m->event_at;
		else if (vr[i] == 11) values[i] = m->count;
		else if (vr[i] == 15) values[i] = m->events;
		else return fmi3Error;
	}
	return fmi3OK;
}

EXPORT fmi3Status fmi3SetInt32(void *instance, const fmi3ValueReference vr[], size_t nvr,
	const int values[], size_t nValues)
{
	Instance *m = instance;
	if (nvr != 1 || nValues != 1 || vr[0] != 4) return fmi3Error;
	m->event_at = values[0];
	return fmi3OK;
}

EXPORT fmi3Status fmi3GetBoolean(void *instance, const fmi3ValueReference vr[], size_t nvr,
	bool values[], size_t nValues)
{
	Instance *m = instance;
	if (nvr != 1 || nValues != 1 || vr[0] != 12) return fmi3Error;
	values[0] = m->x > 0.0;
	return fmi3OK;
}

EXPORT fmi3Status fmi3DoStep(void *instance, double currentCommunicationPoint,
	double communicationStepSize, bool noSetFMUStatePriorToCurrentPoint,
	bool *eventHandlingNeeded, bool *terminateSimulation, bool *earlyReturn,
	double *lastSuccessfulTime)
{
	Instance *m = instance;
	(void)noSetFMUStatePriorToCurrentPoint;
	if (m->mode != STEP) return fmi3Error;
	m->time = currentCommunicationPoint + communicationStepSize;
	m->x += m->gain * m->u * communicationStepSize;
	m->count += 1;
	*eventHandlingNeeded = m->count == m->event_at;
	*terminateSimulation = false;
	*earlyReturn = false;
	*lastSuccessfulTime = m->time;
	if (m->time >= m->stop_at - 1e-12) {
		if (m->log) m->log(m->env, fmi3OK, "logStatusInfo", "stop_at reached: the experiment is over");
		*terminateSimulation = true;
	}
	return fmi3OK;
}

/* The rest of the FMI 3.0 API, so that loaders find every symbol; each answers fmi3Error. */
#define UNSUPPORTED(name) EXPORT fmi3Status name(void) { return fmi3Error; }
UNSUPPORTED(fmi3InstantiateModelExchange)
UNSUPPORTED(fmi3InstantiateScheduledExecution)
UNSUPPORTED(fmi3EnterConfigurationMode)
UNSUPPORTED(fmi3ExitConfigurationMode)
UNSUPPORTED(fmi3EnterContinuousTimeMode)
UNSUPPORTED(fmi3CompletedIntegratorStep)
UNSUPPORTED(fmi3EvaluateDiscreteStates)
UNSUPPORTED(fmi3ActivateModelPartition)
UNSUPPORTED(fmi3SetFloat32)
UNSUPPORTED(fmi3GetInt8)
UNSUPPORTED(fmi3SetInt8)
UNSUPPORTED(fmi3GetUInt8)
UNSUPPORTED(fmi3SetUInt8)
UNSUPPORTED(fmi3GetInt16)
UNSUPPORTED(fmi3SetInt16)
UNSUPPORTED(fmi3GetUInt16)
UNSUPPORTED(fmi3SetUInt16)
UNSUPPORTED(fmi3GetUInt32)
UNSUPPORTED(fmi3SetUInt32)
UNSUPPORTED(fmi3GetInt64)
UNSUPPORTED(fmi3SetInt64)
UNSUPPORTED(fmi3GetUInt64)
UNSUPPORTED(fmi3SetUInt64)
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

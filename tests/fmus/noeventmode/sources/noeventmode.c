/* noeventmode.c - rtloop test FMU (FMI 3.0 co-simulation, MIT): y' = k * u (Euler).
 * Its modelDescription.xml declares hasEventMode="true", yet fmi3InstantiateCoSimulation refuses
 * eventModeUsed = true (it logs "Event Mode is not supported" and returns NULL), as some exporters'
 * FMUs do; FMI 3.0 lets the importer instantiate it without Event Mode instead. A k <= 0 is refused
 * by fmi3EnterInitializationMode with a message of the FMU's own: a model that cannot start. */
#include <stdbool.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define EXPORT __attribute__((visibility("default")))

typedef enum { fmi3OK, fmi3Warning, fmi3Discard, fmi3Error, fmi3Fatal } fmi3Status;
typedef unsigned int fmi3ValueReference;
typedef void (*LogMessage)(void *env, fmi3Status status, const char *category, const char *message);

typedef struct {
	double time, u, k, y;
	bool stepping;
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
	if (token == NULL || strcmp(token, "{rtloop-noeventmode-1}") != 0) return NULL;
	if (eventModeUsed) {
		if (logMessage) ((LogMessage)logMessage)(environment, fmi3Error, "logStatusError",
			"Event Mode is not supported");
		return NULL;
	}
	m = calloc(1, sizeof(Instance));
	m->u = 1.0; m->k = 2.0;
	m->log = (LogMessage)logMessage; m->env = environment;
	return m;
}

EXPORT void fmi3FreeInstance(void *instance) { free(instance); }

EXPORT fmi3Status fmi3EnterInitializationMode(void *instance, bool toleranceDefined,
	double tolerance, double startTime, bool stopTimeDefined, double stopTime)
{
	Instance *m = instance;
	char text[80];
	(void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
	if (m->k <= 0.0) {
		snprintf(text, sizeof text, "k must be positive, got %g", m->k);
		if (m->log) m->log(m->env, fmi3Error, "logStatusError", text);
		return fmi3Error;
	}
	m->time = startTime;
	return fmi3OK;
}

EXPORT fmi3Status fmi3ExitInitializationMode(void *instance)
{
	Instance *m = instance;
	m->stepping = true;
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
	size_t i;
	if (nValues != nvr) return fmi3Error;
	for (i = 0; i < nvr; i++) {
		switch (vr[i]) {
		case 0: values[i] = m->time; break;
		case 1: values[i] = m->u; break;
		case 2: values[i] = m->k; break;
		case 3: values[i] = m->y; break;
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
	if (nValues != nvr) return fmi3Error;
	for (i = 0; i < nvr; i++) {
		if (vr[i] == 1) m->u = values[i];
		else if (vr[i] == 2) m->k = values[i];
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
	(void)noSetFMUStatePriorToCurrentPoint;
	if (!m->stepping) return fmi3Error;
	m->time = currentCommunicationPoint + communicationStepSize;
	m->y += m->k * m->u * communicationStepSize;
	*eventHandlingNeeded = false;
	*terminateSimulation = false;
	*earlyReturn = false;
	*lastSuccessfulTime = m->time;
	return fmi3OK;
}

/* The rest of the FMI 3.0 API, so that loaders find every symbol; each answers fmi3Error. */
#define UNSUPPORTED(name) EXPORT fmi3Status name(void) { return fmi3Error; }
UNSUPPORTED(fmi3EnterEventMode)
UNSUPPORTED(fmi3EnterStepMode)
UNSUPPORTED(fmi3UpdateDiscreteStates)
UNSUPPORTED(fmi3GetFloat32)
UNSUPPORTED(fmi3GetInt32)
UNSUPPORTED(fmi3SetInt32)
UNSUPPORTED(fmi3GetBoolean)
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

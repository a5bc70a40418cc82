/* xxmodel.h - base class of the rtloop 20-sim-shaped test fixtures.
 * Written for rtloop (MIT); same shape as a 20-sim C++ export, not a copy of it. */
#ifndef XXMODEL_H
#define XXMODEL_H

#include "xxtypes.h"

class Submodel20sim
{
public:
	enum stateflags_Submodel20sim { initialize, mainrun, finished };

	Submodel20sim(void) : m_step_size(0.0), m_time(0.0), m_start_time(0.0),
		m_finish_time(0.0), m_state(initialize) {}
	virtual ~Submodel20sim(void) {}

	virtual void Initialize(XXDouble *u, XXDouble *y, XXDouble t) = 0;
	virtual void Calculate(XXDouble *u, XXDouble *y) = 0;
	virtual void Terminate(XXDouble *u, XXDouble *y) = 0;
	virtual void Reset(XXDouble starttime) = 0;

	/* 0.0 means: run forever */
	bool SetFinishTime(XXDouble newtime)
	{
		if (newtime > 0.0 && newtime <= m_time)
			return false;
		m_finish_time = newtime;
		return true;
	}
	bool IsFinished(void) { return m_state == finished; }
	XXDouble GetTime(void) { return m_time; }

protected:
	XXDouble m_step_size;
	XXDouble m_time;
	XXDouble m_start_time;
	XXDouble m_finish_time;
	stateflags_Submodel20sim m_state;

	/* finished once time has reached the finish time (within half a step) */
	void CheckFinished(void)
	{
		if (m_finish_time > 0.0 && m_time >= m_finish_time - 0.5 * m_step_size)
			m_state = finished;
	}
};

#endif

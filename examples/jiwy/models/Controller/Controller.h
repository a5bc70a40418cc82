/* Controller.h - JIWY PID controller (Euler, 1 ms).
 * rtloop test fixture in the shape of a 20-sim 4.8 C++ export (written for rtloop, MIT). */
#ifndef CONTROLLER_H
#define CONTROLLER_H

#include "common/xxmodel.h"

class Controller : virtual public Submodel20sim
{
public:
	Controller(void);
	virtual ~Controller(void);

	void Initialize(XXDouble *u, XXDouble *y, XXDouble t);
	void Calculate(XXDouble *u, XXDouble *y);
	void Terminate(XXDouble *u, XXDouble *y);
	void Reset(XXDouble starttime);

protected:
	void CalculateInitial(void);
	void CalculateStatic(void);
	void CalculateInput(void);
	void CalculateDynamic(void);
	void CalculateOutput(void);
	void CalculateFinal(void);
	void CopyInputsToVariables(XXDouble *u);
	void CopyVariablesToOutputs(XXDouble *y);
	void EulerStep(void);

	int m_number_parameters;
	int m_number_variables;
	int m_number_states;
	int m_number_inputs;
	int m_number_outputs;

	XXDouble *m_P;	/* parameters */
	XXDouble *m_V;	/* variables */
	XXDouble *m_s;	/* states */
	XXDouble *m_R;	/* rates */
};

#endif

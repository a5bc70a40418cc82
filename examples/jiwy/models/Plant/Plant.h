/* Plant.h - JIWY pan/tilt gimbal plant (Euler, 1 ms).
 * rtloop test fixture in the shape of a 20-sim 4.8 C++ export (written for rtloop, MIT). */
#ifndef PLANT_H
#define PLANT_H

#include "common/xxmodel.h"

class Plant : virtual public Submodel20sim
{
public:
	Plant(void);
	virtual ~Plant(void);

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

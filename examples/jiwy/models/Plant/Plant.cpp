/* Plant.cpp - JIWY pan/tilt gimbal plant (Euler, 1 ms).
 * rtloop test fixture in the shape of a 20-sim 4.8 C++ export (written for rtloop, MIT).
 * Per axis: states p (motor momentum) and theta (camera angle). */
#include "Plant.h"

Plant::Plant(void)
{
	m_number_parameters = 14;
	m_number_variables = 16;
	m_number_states = 4;
	m_number_inputs = 2;
	m_number_outputs = 2;

	m_P = new XXDouble[m_number_parameters + 1];
	m_V = new XXDouble[m_number_variables + 1];
	m_s = new XXDouble[m_number_states + 1];
	m_R = new XXDouble[m_number_states + 1];

	m_step_size = 0.001;
	Reset(0.0);
	m_finish_time = 100.0;
}

Plant::~Plant(void)
{
	/* generated code of this vintage relies on NULL without including <cstddef> */
	if (m_P != NULL) delete[] m_P;
	if (m_V != NULL) delete[] m_V;
	if (m_s != NULL) delete[] m_s;
	if (m_R != NULL) delete[] m_R;
}

void Plant::Reset(XXDouble starttime)
{
	m_start_time = starttime;
	m_time = starttime;
	m_state = initialize;
	for (int i = 0; i <= m_number_variables; i++) m_V[i] = 0.0;
	for (int i = 0; i <= m_number_states; i++) { m_s[i] = 0.0; m_R[i] = 0.0; }
}

void Plant::Initialize(XXDouble *u, XXDouble *y, XXDouble t)
{
	m_time = t;
	CopyInputsToVariables(u);
	CalculateInitial();
	CalculateStatic();
	CalculateInput();
	CalculateDynamic();
	CalculateOutput();
	CopyVariablesToOutputs(y);
	m_state = mainrun;
}

void Plant::Calculate(XXDouble *u, XXDouble *y)
{
	switch (m_state)
	{
	case initialize:
		Initialize(u, y, m_start_time);
		break;
	case mainrun:
		CopyInputsToVariables(u);
		EulerStep();	/* states with the rates of the previous evaluation */
		CalculateInput();
		CalculateDynamic();
		CalculateOutput();
		CopyVariablesToOutputs(y);
		CheckFinished();
		break;
	case finished:
		CopyVariablesToOutputs(y);
		break;
	}
}

void Plant::Terminate(XXDouble *u, XXDouble *y)
{
	CopyInputsToVariables(u);
	CalculateFinal();
	CopyVariablesToOutputs(y);
	m_state = finished;
}

void Plant::EulerStep(void)
{
	for (int i = 0; i < m_number_states; i++)
		m_s[i] = m_s[i] + m_R[i] * m_step_size;
	m_time = m_time + m_step_size;
}

void Plant::CalculateInitial(void)
{
	/* pan: r, Jmot, Dmot, g, b, Jcam, Dcam */
	m_P[0] = 0.018;	/* pan\r */
	m_P[1] = 2.06e-7;	/* pan\Jmot */
	m_P[2] = 1.77e-6;	/* pan\Dmot */
	m_P[3] = 1.0 / 19.0;	/* pan\g */
	m_P[4] = 1.0;	/* pan\b */
	m_P[5] = 3e-4;	/* pan\Jcam */
	m_P[6] = 2e-4;	/* pan\Dcam */
	/* tilt */
	m_P[7] = 0.00701;	/* tilt\r */
	m_P[8] = 5.28e-8;	/* tilt\Jmot */
	m_P[9] = 4e-7;	/* tilt\Dmot */
	m_P[10] = 1.0 / 19.0;	/* tilt\g */
	m_P[11] = 0.25;	/* tilt\b */
	m_P[12] = 4.5e-5;	/* tilt\Jcam */
	m_P[13] = 1e-4;	/* tilt\Dcam */

	m_s[0] = 0.0;	/* pan.p */
	m_s[1] = 0.0;	/* pan.theta */
	m_s[2] = 0.0;	/* tilt.p */
	m_s[3] = 0.0;	/* tilt.theta */
}

void Plant::CalculateStatic(void)
{
}

void Plant::CalculateInput(void)
{
}

void Plant::CalculateDynamic(void)
{
	/* pan */
	m_V[2] = m_P[3] * m_P[4];			/* gb */
	m_V[3] = m_P[1] + m_V[2] * m_V[2] * m_P[5];	/* Jeq */
	m_V[4] = m_s[0] / m_V[3];			/* omega */
	m_V[5] = m_V[2] * m_V[4];			/* omega_cam */
	m_V[6] = m_P[6] * m_V[5];			/* tau_cam */
	m_R[0] = m_P[0] * m_V[0] - m_P[2] * m_V[4] - m_V[2] * m_V[6];
	m_R[1] = m_V[5];

	/* tilt */
	m_V[7] = m_P[10] * m_P[11];
	m_V[8] = m_P[8] + m_V[7] * m_V[7] * m_P[12];
	m_V[9] = m_s[2] / m_V[8];
	m_V[10] = m_V[7] * m_V[9];
	m_V[11] = m_P[13] * m_V[10];
	m_R[2] = m_P[7] * m_V[1] - m_P[9] * m_V[9] - m_V[7] * m_V[11];
	m_R[3] = m_V[10];
}

void Plant::CalculateOutput(void)
{
	m_V[14] = m_s[1];	/* AnglePan */
	m_V[15] = m_s[3];	/* AngleTilt */
}

void Plant::CalculateFinal(void)
{
}

void Plant::CopyInputsToVariables(XXDouble *u)
{
	m_V[0] = u[0];	/* SteeringPan */
	m_V[1] = u[1];	/* SteeringTilt */
}

void Plant::CopyVariablesToOutputs(XXDouble *y)
{
	y[0] = m_V[14];	/* AnglePan */
	y[1] = m_V[15];	/* AngleTilt */
}

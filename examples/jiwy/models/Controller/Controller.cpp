/* Controller.cpp - JIWY PID controller (Euler, 1 ms).
 * rtloop test fixture in the shape of a 20-sim 4.8 C++ export (written for rtloop, MIT).
 * Per axis 20-sim's PID kp*(1 + tauD*s)/(1 + beta*tauD*s)*(1 + 1/(tauI*s)),
 * states pdstate and pistate. */
#include "Controller.h"

Controller::Controller(void)
{
	m_number_parameters = 8;
	m_number_variables = 12;
	m_number_states = 4;
	m_number_inputs = 4;
	m_number_outputs = 2;

	m_P = new XXDouble[m_number_parameters + 1];
	m_V = new XXDouble[m_number_variables + 1];
	m_s = new XXDouble[m_number_states + 1];
	m_R = new XXDouble[m_number_states + 1];

	m_step_size = 0.001;
	Reset(0.0);
	m_finish_time = 100.0;
}

Controller::~Controller(void)
{
	if (m_P != NULL) delete[] m_P;
	if (m_V != NULL) delete[] m_V;
	if (m_s != NULL) delete[] m_s;
	if (m_R != NULL) delete[] m_R;
}

void Controller::Reset(XXDouble starttime)
{
	m_start_time = starttime;
	m_time = starttime;
	m_state = initialize;
	for (int i = 0; i <= m_number_variables; i++) m_V[i] = 0.0;
	for (int i = 0; i <= m_number_states; i++) { m_s[i] = 0.0; m_R[i] = 0.0; }
}

void Controller::Initialize(XXDouble *u, XXDouble *y, XXDouble t)
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

void Controller::Calculate(XXDouble *u, XXDouble *y)
{
	switch (m_state)
	{
	case initialize:
		Initialize(u, y, m_start_time);
		break;
	case mainrun:
		CopyInputsToVariables(u);
		EulerStep();
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

void Controller::Terminate(XXDouble *u, XXDouble *y)
{
	CopyInputsToVariables(u);
	CalculateFinal();
	CopyVariablesToOutputs(y);
	m_state = finished;
}

void Controller::EulerStep(void)
{
	for (int i = 0; i < m_number_states; i++)
		m_s[i] = m_s[i] + m_R[i] * m_step_size;
	m_time = m_time + m_step_size;
}

void Controller::CalculateInitial(void)
{
	/* pan: kp, tauD, beta, tauI */
	m_P[0] = 0.3;
	m_P[1] = 0.1;
	m_P[2] = 0.1;
	m_P[3] = 1000.0;
	/* tilt */
	m_P[4] = 0.2;
	m_P[5] = 0.2;
	m_P[6] = 0.1;
	m_P[7] = 1000.0;

	m_s[0] = 0.0;	/* PID_pan.pdstate */
	m_s[1] = 0.0;	/* PID_pan.pistate */
	m_s[2] = 0.0;	/* PID_tilt.pdstate */
	m_s[3] = 0.0;	/* PID_tilt.pistate */
}

void Controller::CalculateStatic(void)
{
}

void Controller::CalculateInput(void)
{
}

void Controller::CalculateDynamic(void)
{
	/* pan */
	m_V[4] = m_V[2] - m_V[0];			/* error */
	m_V[5] = m_s[0] + m_P[0] * m_V[4] / m_P[2];	/* pdout */
	m_R[0] = (m_P[0] * m_V[4] - m_V[5]) / (m_P[2] * m_P[1]);
	m_R[1] = m_V[5] / m_P[3];
	m_V[6] = m_s[1] + m_V[5];			/* output */

	/* tilt */
	m_V[7] = m_V[3] - m_V[1];
	m_V[8] = m_s[2] + m_P[4] * m_V[7] / m_P[6];
	m_R[2] = (m_P[4] * m_V[7] - m_V[8]) / (m_P[6] * m_P[5]);
	m_R[3] = m_V[8] / m_P[7];
	m_V[9] = m_s[3] + m_V[8];
}

void Controller::CalculateOutput(void)
{
	m_V[10] = m_V[6];	/* SteeringPan */
	m_V[11] = m_V[9];	/* SteeringTilt */
}

void Controller::CalculateFinal(void)
{
}

void Controller::CopyInputsToVariables(XXDouble *u)
{
	m_V[0] = u[0];	/* MeasuredPan */
	m_V[1] = u[1];	/* MeasuredTilt */
	m_V[2] = u[2];	/* SetPointPan */
	m_V[3] = u[3];	/* SetPointTilt */
}

void Controller::CopyVariablesToOutputs(XXDouble *y)
{
	y[0] = m_V[10];	/* SteeringPan */
	y[1] = m_V[11];	/* SteeringTilt */
}
